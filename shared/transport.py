"""The two byte transports of Tele-Touch, for the stations and the relay alike.

A :class:`Transport` moves whole protocol units: over WebSocket one binary message per
Tele-Touch message (``websockets`` asyncio API, client or server connection), over raw TCP
the length-prefixed byte stream in chunks (asyncio streams; framing is the sans-I/O
core's job). Both turn every way a connection can end into :class:`TransportClosed`, with
the WebSocket close code when there is one, so the glue above handles one error.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import ssl
from typing import Any, Protocol

from websockets.asyncio.connection import Connection
from websockets.exceptions import ConnectionClosed
from websockets.protocol import Protocol as WsProtocol
from websockets.protocol import State

from shared.errors import TlsCertificateError
from shared.protocol.connection import Framing

__all__ = [
    "TcpTransport",
    "Transport",
    "TransportClosed",
    "WsTransport",
    "open_client_transport",
    "set_nodelay",
]

#: websockets' asyncio connection has what :meth:`WsTransport.write_nowait` uses
_WS_DIRECT_WRITE = callable(getattr(Connection, "send_data", None)) and \
    callable(getattr(WsProtocol, "send_binary", None))

_CLOSE_TIMEOUT_S = 2.0
_TCP_READ_BYTES = 64 * 1024
#: WebSocket close codes of a clean close (bye, shutdown): no lingering needed
_CLEAN_CLOSE_CODES = frozenset({1000, 1001})


class TransportClosed(ConnectionError):
    """The connection ended; ``close_code`` is the WebSocket close code, if any."""

    def __init__(self, message: str, close_code: int | None = None) -> None:
        super().__init__(message)
        self.close_code = close_code


class Transport(Protocol):
    """One open connection carrying Tele-Touch messages."""

    framing: Framing

    async def write(self, frames: list[bytes]) -> None:
        """Write framed messages and wait for the transport to take them.

        Raises:
            TransportClosed: the connection is gone.
        """

    def ready(self) -> bool:
        """True when :meth:`write_nowait` may be used: the connection is open and nothing of
        earlier writes waits in its buffer (the socket took everything so far)."""

    def write_nowait(self, frames: list[bytes]) -> None:
        """Hand framed messages to the socket at once, without waiting (only after
        :meth:`ready`; the relay's fast path: no task switch per forwarded message)."""

    def buffered(self) -> bool:
        """True when :meth:`recv` may return without waiting (received input is buffered;
        also when that cannot be told)."""

    async def recv(self) -> bytes | str:
        """Return the next WebSocket message or TCP chunk.

        Raises:
            TransportClosed: the connection ended.
        """

    async def close(self, code: int = 1000, reason: str = "") -> None:
        """Close (``code`` is a WebSocket close code; TCP ignores it); never raises."""

    def abort(self) -> None:
        """Drop the connection at once: no close handshake, no flush of what is buffered
        (for a dead or blackholed peer, which would never answer a graceful close); never
        raises."""


def set_nodelay(transport: Any) -> None:
    """Turn Nagle's algorithm off on an asyncio transport's TCP socket (if it has one)."""
    sock = transport.get_extra_info("socket") if transport is not None else None
    if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


class TcpTransport:
    """Length-prefixed TCP over asyncio streams.

    Args:
        reader: the stream reader.
        writer: the stream writer.
        write_buffer_bytes: high-water mark of the write buffer (None: asyncio's default).
        linger_s: on an error close (any code but 1000/1001), half-close and read and
            discard what the peer still sends for up to this long before closing. Closing
            a socket with unread input makes the kernel send a reset, and a reset destroys
            the data in flight to the peer: the fatal ``error`` just written (the relay's
            ``oversize`` was lost 10 times in 20 without this). 0 = close at once.
    """

    framing: Framing = "tcp"

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                 write_buffer_bytes: int | None = None, linger_s: float = 0.0) -> None:
        self._reader, self._writer = reader, writer
        self._linger_s = linger_s
        self._close_lock = asyncio.Lock()
        set_nodelay(writer.transport)
        if write_buffer_bytes is not None:
            writer.transport.set_write_buffer_limits(high=write_buffer_bytes)

    async def write(self, frames: list[bytes]) -> None:
        try:
            self._writer.write(frames[0] if len(frames) == 1 else b"".join(frames))
            await self._writer.drain()
        except (OSError, RuntimeError) as err:
            raise TransportClosed(f"TCP send failed: {err}") from err

    def ready(self) -> bool:
        return not self._writer.is_closing() and \
            self._writer.transport.get_write_buffer_size() == 0

    def write_nowait(self, frames: list[bytes]) -> None:
        self._writer.write(frames[0] if len(frames) == 1 else b"".join(frames))

    def buffered(self) -> bool:
        buffer = getattr(self._reader, "_buffer", None)  # asyncio.StreamReader's
        return buffer is None or len(buffer) > 0

    async def recv(self) -> bytes:
        try:
            data = await self._reader.read(_TCP_READ_BYTES)
        except OSError as err:
            raise TransportClosed(f"TCP receive failed: {err}") from err
        if not data:
            raise TransportClosed("the peer closed the TCP connection")
        return data

    async def close(self, code: int = 1000, reason: str = "") -> None:
        async with self._close_lock:  # a second closer waits for the first one's linger
            if not self._writer.is_closing():
                if self._linger_s > 0 and code not in _CLEAN_CLOSE_CODES:
                    await self._linger()
                self._writer.close()
            with contextlib.suppress(OSError, asyncio.TimeoutError):
                await asyncio.wait_for(self._writer.wait_closed(), _CLOSE_TIMEOUT_S)

    def abort(self) -> None:
        with contextlib.suppress(Exception):
            self._writer.transport.abort()

    async def _linger(self) -> None:
        with contextlib.suppress(OSError, RuntimeError, asyncio.TimeoutError):
            await asyncio.wait_for(self._writer.drain(), self._linger_s)
            if self._writer.can_write_eof():
                self._writer.write_eof()  # our side is done: the peer reads to EOF
            async with asyncio.timeout(self._linger_s):
                while await self._reader.read(_TCP_READ_BYTES):
                    pass  # discard: only so the close is a FIN, not a reset


class WsTransport:
    """One Tele-Touch message per binary WebSocket message (client or server side).

    Args:
        ws: a ``websockets`` asyncio connection.
    """

    framing: Framing = "ws"

    def __init__(self, ws: Any) -> None:
        self.ws = ws

    @staticmethod
    def _closed(err: ConnectionClosed) -> TransportClosed:
        rcvd = err.rcvd
        code = rcvd.code if rcvd is not None else None
        reason = f" ({rcvd.reason})" if rcvd is not None and rcvd.reason else ""
        return TransportClosed(f"WebSocket closed with code {code}{reason}", close_code=code)

    async def write(self, frames: list[bytes]) -> None:
        try:
            for data in frames:
                await self.ws.send(data)
        except ConnectionClosed as err:
            raise self._closed(err) from err

    def ready(self) -> bool:
        ws = self.ws
        # the direct write drives websockets' connection below its ``send`` (its protocol
        # object and ``send_data``, websockets 13-17): a release without them gets the
        # writer task's ordinary ``send`` instead of a failed write
        return _WS_DIRECT_WRITE and ws.protocol.state is State.OPEN \
            and not ws.transport.is_closing() and ws.transport.get_write_buffer_size() == 0

    def write_nowait(self, frames: list[bytes]) -> None:
        # what ``send`` does inside its send context, for all frames at once: the frames
        # into the protocol, its output to the socket (flow control: see ready())
        ws = self.ws
        for data in frames:
            ws.protocol.send_binary(data)
        ws.send_data()

    def buffered(self) -> bool:
        frames = getattr(getattr(self.ws, "recv_messages", None), "frames", None)
        return frames is None or len(frames) > 0  # websockets' queue of received frames

    async def recv(self) -> bytes | str:
        try:
            data: bytes | str = await self.ws.recv()
        except ConnectionClosed as err:
            raise self._closed(err) from err
        return data

    async def close(self, code: int = 1000, reason: str = "") -> None:
        # read and discard what the peer still sends, else a receive queue full of its
        # unread messages hides its close frame and the close handshake never completes
        discard = asyncio.ensure_future(self._discard_incoming())
        try:
            await asyncio.wait_for(self.ws.close(code, reason[:120]), _CLOSE_TIMEOUT_S)
        except Exception:
            with contextlib.suppress(Exception):  # no handshake in time: drop the socket
                self.ws.transport.abort()
        finally:
            discard.cancel()
            await asyncio.gather(discard, return_exceptions=True)

    def abort(self) -> None:
        with contextlib.suppress(Exception):
            self.ws.transport.abort()

    async def _discard_incoming(self) -> None:
        with contextlib.suppress(Exception):  # closed, or a reader is already receiving
            while True:
                await self.ws.recv(decode=False)


async def open_client_transport(scheme: str, host: str, port: int, url: str, *,
                                max_message_bytes: int, open_timeout_s: float,
                                write_buffer_bytes: int,
                                ssl_context: ssl.SSLContext | None = None) -> Transport:
    """Connect to a relay: ``tcp`` (``tls``: inside TLS) to ``host:port``, ``ws``/``wss``
    to ``url``. TLS verifies the relay's certificate and host name with ``ssl_context``
    (the system's trust store when None).

    Raises:
        TlsCertificateError: the relay's certificate failed verification.
        OSError: the connection failed.
        websockets.exceptions.WebSocketException: the WebSocket handshake failed.
    """
    tls = scheme in ("tls", "wss")
    if tls and ssl_context is None:
        ssl_context = ssl.create_default_context()
    try:
        if scheme in ("tcp", "tls"):
            reader, writer = await asyncio.open_connection(
                host, port, ssl=ssl_context if tls else None,
                server_hostname=host if tls else None)
            return TcpTransport(reader, writer, write_buffer_bytes)
        from websockets.asyncio.client import connect

        kwargs: dict[str, Any] = {"ssl": ssl_context} if tls else {}
        ws = await connect(url, compression=None, max_size=max_message_bytes,
                           ping_interval=None, open_timeout=open_timeout_s,
                           write_limit=write_buffer_bytes, proxy=None, **kwargs)
    except ssl.SSLCertVerificationError as err:
        raise TlsCertificateError(
            f"TLS certificate of the relay {host}:{port} not trusted: {err.verify_message} "
            "(give the relay's CA with ca_file / --ca-file; docs/security.md)") from err
    return WsTransport(ws)
