"""Per-peer outgoing queue with per-stream policy, and the writer task that drains it.

Two kinds of entries wait for a peer:

* **latest-wins slots** for state streams (``platform_state``, ``arm_state``,
  ``tactile_frame``): one slot per stream key; a newer message replaces an unsent one
  and the replaced one is counted as a drop. Memory is bounded by the number of streams.
* **latest-wins control slots** for the relay's own periodic messages (``stats``,
  ``clock_ping``): an unsent one is stale, so a fresh one replaces it.
* an **ordered queue** for commands and control (``arm_command``, ``error``, ``welcome``,
  ``bye``, ...), bounded: :meth:`Outbox.put_ordered` returns False when full and the caller
  reports the overflow (never a silent loss).

A stalled peer therefore holds at most one entry per state stream and per periodic control
message, plus whatever ordered messages it was sent.

One writer task per peer drains the outbox in arrival order, encodes each message just
before writing it (``relay_out`` hop stamped then) and writes the batch. A peer whose
socket is slow only fills its own outbox: nobody else awaits it.
"""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Protocol

import msgpack

from shared.protocol import PROTOCOL_VERSION, DataMessage, Message, frame
from shared.protocol.messages import MAX_HOPS

__all__ = ["Link", "Outbox", "Pending", "encode_forwarded", "run_writer"]

log = logging.getLogger(__name__)


class Link(Protocol):
    """The transport under one peer (WebSocket or length-prefixed TCP)."""

    framing: str

    async def write(self, frames: list[bytes]) -> None:
        """Write already framed messages, waiting for the transport to drain."""

    async def close(self, code: int, reason: str) -> None:
        """Close the connection (``code`` is a WebSocket close code; TCP ignores it)."""


#: called just before a data message is encoded: (pending entry, relay_out time) -> None
OnSend = Callable[["Pending", int], None]


@dataclass(slots=True)
class Pending:
    """One message waiting for a peer.

    Attributes:
        order: arrival counter (keeps the writer in arrival order across slots and queue).
        message: the message.
        forwarded: a data message relayed from a station (already validated on receipt:
            gets a ``relay_out`` hop and is encoded without re-validation).
        on_send: accounting callback for forwarded messages, or None.
        build: for messages that must carry the time they are written (``clock_ping``):
            called with that time, returns the message to send instead of ``message``.
        t_in_us: relay clock when a forwarded message arrived (its ``relay_in`` hop).
    """

    order: int
    message: Message
    forwarded: bool = False
    on_send: OnSend | None = None
    build: Callable[[int], Message] | None = None
    t_in_us: int = 0


def encode_forwarded(msg: DataMessage, t_in_us: int, t_out_us: int, tcp: bool) -> bytes:
    """Encode a relayed message with its ``relay_in``/``relay_out`` hops appended.

    The message was validated when it arrived, so this skips re-validation and builds the
    wire map once (no intermediate message copies): the hot path of the relay.
    """
    wire = msg.to_wire()
    hops = wire["hops"]
    hops.append(["relay", "relay_in", t_in_us])
    hops.append(["relay", "relay_out", t_out_us])
    if len(hops) > MAX_HOPS:
        wire["hops"] = hops[-MAX_HOPS:]
    data: bytes = msgpack.packb({"v": PROTOCOL_VERSION, "type": msg.TYPE, **wire},
                                use_bin_type=True)
    return frame(data) if tcp else data


class Outbox:
    """Bounded outgoing state of one peer (no I/O).

    Args:
        ordered_limit: maximum entries of the ordered queue.
    """

    def __init__(self, ordered_limit: int) -> None:
        self._ordered: deque[Pending] = deque()
        self._slots: dict[str, Pending] = {}
        self._limit = ordered_limit
        self._counter = 0
        self.wakeup = asyncio.Event()
        self.closed = False

    def __len__(self) -> int:
        return len(self._ordered) + len(self._slots)

    def put_latest(self, key: str, message: DataMessage, t_in_us: int,
                   on_send: OnSend | None = None) -> Pending | None:
        """Put a forwarded ``message`` in slot ``key``; return the unsent entry it replaced."""
        self._counter += 1
        old = self._slots.get(key)
        self._slots[key] = Pending(self._counter, message, True, on_send, None, t_in_us)
        self.wakeup.set()
        return old

    def put_control_latest(self, key: str, message: Message,
                           build: Callable[[int], Message] | None = None) -> bool:
        """Put the relay's own periodic control message (``stats``, ``clock_ping``) in slot
        ``key``: a fresh one replaces an unsent one, so a stalled peer never accumulates them.

        Returns:
            True when an unsent message was replaced.
        """
        self._counter += 1
        replaced = key in self._slots
        self._slots[key] = Pending(self._counter, message, False, None, build, 0)
        self.wakeup.set()
        return replaced

    def put_ordered(self, message: Message, on_send: OnSend | None = None, *,
                    forwarded: bool = False, force: bool = False,
                    build: Callable[[int], Message] | None = None, t_in_us: int = 0) -> bool:
        """Append to the ordered queue; False (nothing queued) when full.

        Args:
            message: the message.
            on_send: accounting callback.
            forwarded: a relayed data message (see :class:`Pending`).
            build: late-bound message factory (see :class:`Pending`).
            t_in_us: arrival time of a forwarded message.
            force: queue even when full (for the relay's own rare control messages, such
                as a fatal ``error`` before closing).
        """
        if len(self._ordered) >= self._limit and not force:
            return False
        self._counter += 1
        self._ordered.append(Pending(self._counter, message, forwarded, on_send, build,
                                     t_in_us))
        self.wakeup.set()
        return True

    def take(self) -> list[Pending]:
        """Remove and return everything waiting, in arrival order."""
        if not self._slots:
            out = list(self._ordered)
        else:
            out = sorted((*self._ordered, *self._slots.values()), key=lambda p: p.order)
            self._slots.clear()
        self._ordered.clear()
        self.wakeup.clear()
        return out


async def run_writer(outbox: Outbox, link: Link, encode: Callable[[Message, bool], bytes],
                     max_message_bytes: int,
                     stamp: Callable[[], int],
                     on_error: Callable[[BaseException], Awaitable[None]]) -> None:
    """Drain ``outbox`` to ``link`` until the outbox is closed and empty.

    Args:
        outbox: the peer's outbox.
        link: its transport.
        encode: (message, validate) -> framed bytes, for the relay's own messages;
            forwarded ones go through :func:`encode_forwarded`.
        max_message_bytes: a forwarded message that grew past this (two more hops) is
            not sent (counted by ``on_send`` never being called; logged at debug).
        stamp: the relay clock (``now_us``).
        on_error: awaited once if writing fails (the peer is then dropped).
    """
    try:
        while True:
            await outbox.wakeup.wait()
            batch = outbox.take()
            if not batch:
                if outbox.closed:
                    return
                continue
            frames = []
            tcp = link.framing == "tcp"
            for pending in batch:
                msg = pending.message
                if pending.forwarded and isinstance(msg, DataMessage):
                    t_out = stamp()
                    data = encode_forwarded(msg, pending.t_in_us, t_out, tcp)
                    if len(data) > max_message_bytes + 4:
                        if log.isEnabledFor(logging.DEBUG):
                            log.debug("forwarded %s too large after hops", msg.TYPE)
                        continue
                    if pending.on_send is not None:
                        pending.on_send(pending, t_out)
                    frames.append(data)
                elif pending.build is not None:
                    frames.append(encode(pending.build(stamp()), True))
                else:
                    frames.append(encode(msg, True))
            if frames:
                await link.write(frames)
            if outbox.closed and not len(outbox):
                return
    except asyncio.CancelledError:
        raise
    except Exception as err:  # transport failures of any kind end this peer only
        await on_error(err)
