"""Minimal station clients for the relay tests (WebSocket and length-prefixed TCP)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from typing import Any

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from relay_server.config import RelayConfig
from relay_server.server import RelayServer
from shared.protocol import ClockPing, ClockPong, Hello, Message, ProtocolConnection, decode
from shared.timebase import now_us
from tests.support import scaled

SECRET = "test-secret-0123456789abcdef0123456789"


class Closed(Exception):
    """The relay closed the connection."""


class Client:
    """One test station. ``clock_offset_us`` simulates a station clock ahead of the relay."""

    def __init__(self, kind: str, clock_offset_us: int = 0) -> None:
        self.kind = kind
        self.clock_offset_us = clock_offset_us
        self.conn = ProtocolConnection("ws" if kind == "ws" else "tcp")
        self.ws: ClientConnection | None = None
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None
        self.inbox: list[Message] = []
        self.close_code: int | None = None

    async def connect(self, relay: RelayServer) -> Client:
        if self.kind == "ws":
            self.ws = await connect(f"ws://127.0.0.1:{relay.ws_port}", compression=None,
                                    max_size=None)
        else:
            self.reader, self.writer = await asyncio.open_connection("127.0.0.1",
                                                                     relay.tcp_port)
        return self

    def now(self) -> int:
        return now_us() + self.clock_offset_us

    async def send_raw(self, payload: bytes) -> None:
        """Send one message body (framed for TCP)."""
        if self.ws is not None:
            await self.ws.send(payload)
        else:
            assert self.writer is not None
            self.writer.write(payload)
            await self.writer.drain()

    async def send(self, msg: Message, validate: bool = True) -> None:
        await self.send_raw(self.conn.encode(msg, validate=validate))

    async def hello(self, role: str, session: str, token: str | None = None,
                    secret: str = SECRET) -> Message:
        from relay_server.auth import derive_token

        tok = derive_token(secret, session) if token is None else token
        await self.send(Hello(role=role, session=session, token=tok, name=f"test-{role}"))
        return await self.expect("welcome")

    async def _read_once(self) -> list[Message]:
        if self.ws is not None:
            try:
                data = await self.ws.recv(decode=False)
            except ConnectionClosed as err:
                self.close_code = err.rcvd.code if err.rcvd is not None else None
                raise Closed(str(err)) from err
            return [decode(data, max_message_bytes=2**30)]
        assert self.reader is not None
        try:
            chunk = await self.reader.read(65536)
        except ConnectionResetError as err:  # the relay closed with our reply in flight
            raise Closed(f"reset: {err}") from err
        if not chunk:
            raise Closed("eof")
        self.conn.receive_data(chunk)
        out = []
        for ev in self.conn.events_received():
            out.append(ev.message)  # type: ignore[union-attr]
        return out

    async def recv(self, timeout_s: float = 2.0) -> Message:
        """Next message; clock pings are answered (and still returned)."""
        async with asyncio.timeout(scaled(timeout_s)):
            while not self.inbox:
                for msg in await self._read_once():
                    if isinstance(msg, ClockPing):
                        t1 = self.now()
                        with contextlib.suppress(ConnectionClosed, ConnectionError):
                            await self.send(ClockPong(ping_id=msg.ping_id, t0_us=msg.t0_us,
                                                      t1_us=t1, t2_us=self.now()))
                    self.inbox.append(msg)
        return self.inbox.pop(0)

    async def expect(self, msg_type: str, timeout_s: float = 2.0,
                     skip: tuple[str, ...] = ("clock_ping", "stats")) -> Any:
        """Next message of ``msg_type``, skipping ``skip`` types; fail on anything else."""
        async with asyncio.timeout(scaled(timeout_s)):
            while True:
                msg = await self.recv(timeout_s)
                if msg_type == msg.TYPE:
                    return msg
                if msg.TYPE not in skip:
                    raise AssertionError(f"expected {msg_type}, got {msg}")

    async def expect_closed(self, timeout_s: float = 2.0) -> int | None:
        """Read until the relay closes; return the WebSocket close code."""
        with contextlib.suppress(Closed):
            async with asyncio.timeout(scaled(timeout_s)):
                while True:
                    await self.recv(timeout_s)
        return self.close_code

    async def close(self) -> None:
        if self.ws is not None:
            # read and drop what the relay still sends (as the station's transport does): an
            # unread queue above websockets' high-water mark stops reading, the relay's close
            # frame stays unread and the handshake waits out its 10 s close timeout
            discard = asyncio.ensure_future(self._discard_incoming(self.ws))
            try:
                await self.ws.close()
            finally:
                discard.cancel()
                await asyncio.gather(discard, return_exceptions=True)
        if self.writer is not None:
            self.writer.close()
            with contextlib.suppress(OSError, ConnectionError):
                await self.writer.wait_closed()

    @staticmethod
    async def _discard_incoming(ws: ClientConnection) -> None:
        with contextlib.suppress(ConnectionClosed, RuntimeError):  # RuntimeError: a reader
            while True:  # is already receiving
                await ws.recv(decode=False)


@contextlib.asynccontextmanager
async def running_relay(**overrides: Any) -> AsyncIterator[RelayServer]:
    """A relay on free ports of 127.0.0.1 with test-friendly timings."""
    settings: dict[str, Any] = dict(host="127.0.0.1", port=0, tcp_port=0, secret=SECRET,
                                    hello_timeout_s=scaled(2.0), ping_burst_spacing_s=0.005,
                                    stats_interval_s=0.2, ping_interval_s=0.2)
    settings.update(overrides)
    relay = RelayServer(RelayConfig(**settings))
    await relay.start()
    try:
        yield relay
    finally:
        await relay.close()


@contextlib.asynccontextmanager
async def clients(*specs: tuple[str, int]) -> AsyncIterator[list[Client]]:
    """Open clients (kind, clock_offset_us) and close them all afterwards."""
    opened: list[Client] = []
    try:
        for kind, offset in specs:
            opened.append(Client(kind, offset))
        yield opened
    finally:
        for c in opened:
            with contextlib.suppress(Exception):
                await c.close()
