"""Sans-I/O Tele-Touch connection: bytes in, events out; messages in, bytes out.

The session state machines (:mod:`~shared.protocol.station_session`,
:mod:`~shared.protocol.peer_session`) are built on this class::

    conn = ProtocolConnection("tcp")
    conn.receive_data(chunk)            # whatever the socket gave
    for event in conn.events_received():
        ...                              # MessageReceived / MessageRejected / ConnectionFailed
    conn.send(PlatformState(...))
    for data in conn.data_to_send():
        writer.write(data)

With ``"ws"`` framing each ``receive_data`` call is one whole WebSocket message and each
item of ``data_to_send`` is one WebSocket binary message.
A rejected message (bad field, unknown type, NaN, ...) leaves the stream usable: the
caller decides whether to answer with an ``error`` and carry on. A broken frame header
(oversize or empty on TCP) ends parsing: everything after it is ignored.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from shared.errors import RemoteProtocolError
from shared.protocol.codec import (
    DEFAULT_MAX_MESSAGE_BYTES,
    decode,
    decode_map,
    encode,
    message_from_map,
)
from shared.protocol.forward import WireMessage, locate_hops
from shared.protocol.framing import LengthPrefixDecoder, frame
from shared.protocol.messages import DataMessage, Message

__all__ = ["ConnectionFailed", "Event", "MessageReceived", "MessageRejected",
           "ProtocolConnection"]

Framing = Literal["tcp", "ws"]


@dataclass(frozen=True, slots=True)
class MessageReceived:
    """A valid message arrived; ``size`` is its encoded length in bytes; ``wire``: its bytes
    and the place of its ``hops`` (a data message, when the connection keeps them)."""

    message: Message
    size: int
    wire: WireMessage | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True, slots=True)
class MessageRejected:
    """One message was invalid; the connection can go on."""

    error: RemoteProtocolError


@dataclass(frozen=True, slots=True)
class ConnectionFailed:
    """The byte stream is broken beyond recovery; the connection must be closed."""

    error: RemoteProtocolError


Event = MessageReceived | MessageRejected | ConnectionFailed


class ProtocolConnection:
    """Protocol state of one connection, without any I/O.

    Args:
        framing: ``"tcp"`` (length prefix) or ``"ws"`` (one message per WebSocket message).
        max_message_bytes: size limit for received and sent messages.
        keep_wire: keep each received data message's bytes in its event
            (``MessageReceived.wire``), for forwarding them as they are (the relay).
    """

    def __init__(self, framing: Framing,
                 max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES, *,
                 keep_wire: bool = False) -> None:
        if framing not in ("tcp", "ws"):
            raise ValueError(f"framing must be 'tcp' or 'ws', got {framing!r}")
        self.framing: Framing = framing
        self.max_message_bytes = max_message_bytes
        self._receive_limit = max_message_bytes
        self._keep_wire = keep_wire
        self._decoder = LengthPrefixDecoder(max_message_bytes) if framing == "tcp" else None
        self._events: list[Event] = []
        self._outgoing: list[bytes] = []
        self.failed = False

    def set_receive_limit(self, max_bytes: int) -> None:
        """Change the size limit of received messages (e.g. small until the hello)."""
        self._receive_limit = max_bytes
        if self._decoder is not None:
            self._decoder.max_message_bytes = max_bytes

    def receive_data(self, data: bytes | bytearray | memoryview) -> None:
        """Take received bytes (TCP: any chunk; WebSocket: one whole message)."""
        if self.failed:
            return
        failure: RemoteProtocolError | None = None
        if self._decoder is None:
            payloads = [bytes(data)]
        else:
            payloads = []
            try:
                payloads = self._decoder.feed(data)
                if payloads:  # a broken header right behind them raises now
                    self._decoder.feed(b"")
            except RemoteProtocolError as err:
                failure = err
        for payload in payloads:  # the messages before a broken header count
            try:
                if self._keep_wire:
                    obj = decode_map(payload, max_message_bytes=self._receive_limit)
                    message = message_from_map(obj)
                    wire = locate_hops(payload, obj) if isinstance(message, DataMessage) \
                        else None
                    self._events.append(MessageReceived(message, len(payload), wire))
                else:
                    self._events.append(MessageReceived(
                        decode(payload, max_message_bytes=self._receive_limit), len(payload)))
            except RemoteProtocolError as err:
                self._events.append(MessageRejected(err))
        if failure is not None:
            self.failed = True
            self._events.append(ConnectionFailed(failure))

    def events_received(self) -> list[Event]:
        """Return and clear the events produced by :meth:`receive_data`."""
        events, self._events = self._events, []
        return events

    def send(self, message: Message, *, validate: bool = True) -> None:
        """Queue ``message`` for sending (see :meth:`data_to_send`).

        Raises:
            LocalProtocolError: the message is invalid or too large.
        """
        self._outgoing.append(self.encode(message, validate=validate))

    def encode(self, message: Message, *, validate: bool = True) -> bytes:
        """Encode and frame ``message`` without queueing it."""
        payload = encode(message, validate=validate, max_message_bytes=self.max_message_bytes)
        return frame(payload) if self._decoder is not None else payload

    def data_to_send(self) -> list[bytes]:
        """Return and clear the queued outgoing data."""
        out, self._outgoing = self._outgoing, []
        return out
