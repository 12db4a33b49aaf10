"""The floor under the NATS hop: one 19 kB message from one process to another, three ways.

``teletouch bench nats-hop`` measures what a second relay worker adds. This module measures
what the path costs with no relay code on it, in the same rounds, so the hop can be read
against what the machine allows:

* ``direct``: a plain TCP socket from the benchmark process to a receiver process (what the
  same-worker path pays for its second socket hop);
* ``nats_raw``: through the ``nats-server`` with a minimal client speaking the NATS wire
  protocol (``CONNECT``, ``SUB``, ``PUB``, ``MSG``, ``PING``/``PONG``) straight from asyncio
  protocol callbacks: no client library, no task or queue between the socket and the
  callback. Nothing cheaper can talk to that server, so this is the server's floor;
* ``nats_py``: the same through ``nats-py``, the client the relay workers use.

Each message carries its send time (``time.time_ns``, one host, one clock) in its first
eight bytes and a warm-up flag in the ninth; the receiver process subtracts on arrival. The
minimal client is measurement tooling only: the relay uses ``nats-py``.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

__all__ = ["PATHS", "FloorSender", "start_receiver"]

#: the paths measured, in the order of each round
PATHS = ("direct", "nats_raw", "nats_py")
_SUBJECT = {"nats_raw": "floor.raw", "nats_py": "floor.py"}


def _stamp(size: int, measured: bool) -> bytes:
    return time.time_ns().to_bytes(8, "little") + (b"\x01" if measured else b"\x00") + \
        b"x" * (size - 9)


def _latency_us(payload: bytes | bytearray | memoryview) -> int | None:
    """Arrival minus the stamped send time (us); None for a warm-up message."""
    if payload[8] != 1:
        return None
    return (time.time_ns() - int.from_bytes(payload[:8], "little")) // 1000


class _RawNats(asyncio.Protocol):
    """A minimal NATS connection: publishes and delivers from the protocol callbacks."""

    def __init__(self, on_msg: Callable[[bytes], None] | None = None) -> None:
        self.on_msg = on_msg
        self.buf = bytearray()
        self.transport: asyncio.Transport | None = None
        self.ready: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        transport.write(b'CONNECT {"verbose":false,"pedantic":false,"name":"floor"}\r\n'
                        b"PING\r\n")

    def data_received(self, data: bytes) -> None:
        buf = self.buf
        buf += data
        while True:
            end = buf.find(b"\r\n")
            if end < 0:
                return
            line = bytes(buf[:end])
            if line.startswith(b"MSG "):
                size = int(line.rsplit(b" ", 1)[1])
                if len(buf) < end + 2 + size + 2:
                    return
                payload = bytes(buf[end + 2:end + 2 + size])
                del buf[:end + 2 + size + 2]
                if self.on_msg is not None:
                    self.on_msg(payload)
                continue
            del buf[:end + 2]
            if line == b"PING":
                assert self.transport is not None
                self.transport.write(b"PONG\r\n")
            elif line == b"PONG" and not self.ready.done():
                self.ready.set_result(None)
            elif line.startswith(b"-ERR") and not self.ready.done():
                self.ready.set_exception(
                    RuntimeError(f"nats-server: {line.decode(errors='replace')}"))

    def publish(self, subject: str, payload: bytes) -> None:
        assert self.transport is not None
        self.transport.write(b"PUB %s %d\r\n%s\r\n" % (subject.encode(), len(payload), payload))

    async def subscribe(self, subject: str) -> None:
        """Subscribe; return once the server has answered the PING after it."""
        assert self.transport is not None
        self.ready = asyncio.get_running_loop().create_future()
        self.transport.write(b"SUB %s 1\r\nPING\r\n" % subject.encode())
        await self.ready


async def _raw_connect(url: str, on_msg: Callable[[bytes], None] | None = None) -> _RawNats:
    host, port = url.removeprefix("nats://").rsplit(":", 1)
    loop = asyncio.get_running_loop()
    _, proto = await loop.create_connection(lambda: _RawNats(on_msg), host, int(port))
    await proto.ready
    return proto


class _Framed(asyncio.Protocol):
    """Fixed-size messages on a TCP stream."""

    def __init__(self, size: int, on_msg: Callable[[bytes], None]) -> None:
        self.size, self.on_msg, self.buf = size, on_msg, bytearray()

    def data_received(self, data: bytes) -> None:
        self.buf += data
        while len(self.buf) >= self.size:
            self.on_msg(bytes(self.buf[:self.size]))
            del self.buf[:self.size]


async def _receive(url: str, size: int, conn: Connection) -> None:
    import nats

    got: dict[str, list[int]] = {p: [] for p in PATHS}

    def note(path: str) -> Callable[[bytes], None]:
        def on_msg(payload: bytes) -> None:
            latency = _latency_us(payload)
            if latency is not None:
                got[path].append(latency)
        return on_msg

    loop = asyncio.get_running_loop()
    server = await loop.create_server(lambda: _Framed(size, note("direct")), "127.0.0.1", 0)
    raw = await _raw_connect(url, note("nats_raw"))
    await raw.subscribe(_SUBJECT["nats_raw"])
    nc = await nats.connect(url, name="floor-receiver")
    on_py = note("nats_py")

    async def cb(msg: Any) -> None:
        on_py(msg.data)

    await nc.subscribe(_SUBJECT["nats_py"], cb=cb)
    await nc.flush()
    conn.send(server.sockets[0].getsockname()[1])
    await asyncio.to_thread(conn.recv)  # the sender is done
    conn.send(got)
    await nc.close()
    server.close()


def _receiver_main(url: str, size: int, conn: Connection) -> None:
    asyncio.run(_receive(url, size, conn))


def start_receiver(url: str, size: int) -> tuple[multiprocessing.process.BaseProcess,
                                                  Connection, int]:
    """Start the receiver process; return (process, its pipe, its TCP port)."""
    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_receiver_main, args=(url, size, child), daemon=True,
                       name="nats-floor-receiver")
    proc.start()
    if not parent.poll(30.0):
        proc.kill()
        raise RuntimeError("the NATS floor receiver did not start")
    return proc, parent, int(parent.recv())


class FloorSender:
    """The sending side of the three paths (one connection each, opened by :meth:`open`)."""

    def __init__(self, url: str, port: int, size: int) -> None:
        self.url, self.port, self.size = url, port, size
        self._writer: asyncio.StreamWriter | None = None
        self._raw: _RawNats | None = None
        self._nc: Any = None

    async def open(self) -> None:
        import nats

        from shared.transport import set_nodelay

        _, self._writer = await asyncio.open_connection("127.0.0.1", self.port)
        set_nodelay(self._writer.transport)
        self._raw = await _raw_connect(self.url)
        self._nc = await nats.connect(self.url, name="floor-sender")

    async def phase(self, path: str, rate_hz: float, seconds: float, warmup_s: float) -> int:
        """Send on ``path`` at ``rate_hz`` for ``warmup_s + seconds``; the measured count."""
        assert self._writer is not None and self._raw is not None
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        n = measured = 0
        while loop.time() - t0 < warmup_s + seconds:
            n += 1
            is_measured = loop.time() - t0 >= warmup_s
            payload = _stamp(self.size, is_measured)
            if path == "direct":
                self._writer.write(payload)
            elif path == "nats_raw":
                self._raw.publish(_SUBJECT["nats_raw"], payload)
            else:
                await self._nc.publish(_SUBJECT["nats_py"], payload)
            measured += is_measured
            await asyncio.sleep(max(0.0, t0 + n / rate_hz - loop.time()))
        await asyncio.sleep(0.2)  # the last messages arrive
        return measured

    async def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
        if self._raw is not None and self._raw.transport is not None:
            self._raw.transport.close()
        if self._nc is not None:
            with contextlib.suppress(Exception):
                await self._nc.close()
