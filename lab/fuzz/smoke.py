"""Fuzzed frames over real sockets: a relay subprocess, TCP and WebSocket clients.

The relay runs as ``python -m lab.cli relay`` on free loopback ports. Each fuzz connection
(alternately TCP and WebSocket) sends, with or without a valid hello first, a few mutants of
real messages (framed for TCP; binary, sometimes text, WebSocket messages), sometimes raw
garbage, reads what the relay answers for a moment and closes. Afterwards a good session (a
local station over TCP and a remote over WebSocket) must still work: welcome, a forwarded
``platform_state``, and ``GET /status``. The relay's log must show no traceback and no
``ERROR`` line: an exception escaping a connection handler is a crash.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import random
import signal
import socket
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
from websockets.asyncio.client import connect

from lab.child import module_argv
from lab.fuzz.mutate import mutate_bytes, mutate_message
from lab.fuzz.seeds import FUZZ_SECRET, hello_for, seed_messages
from shared.protocol import Hello, PlatformState, ProtocolConnection, Welcome, decode, encode, frame

__all__ = ["SmokeResult", "run_smoke"]

_REPO = Path(__file__).resolve().parents[2]


@dataclass
class SmokeResult:
    """What the real-socket run saw."""

    connections: int = 0
    frames_sent: int = 0
    answers: int = 0  # messages the relay wrote back to fuzz connections
    error_codes: dict[str, int] = field(default_factory=dict)
    relay_alive: bool = False
    good_session: bool = False
    status_ok: bool = False
    relay_log_errors: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def passed(self) -> bool:
        return (self.relay_alive and self.good_session and self.status_ok
                and not self.relay_log_errors)


def _known_bad() -> list[list[bytes | str]]:
    """Inputs that crashed a connection handler before their fix (one connection each, both
    transports): a hop whose clock is a list, a v2 token with non-ASCII digits; and a first
    message over the hello limit, whose ``oversize`` must reach the TCP client (the issue
    found it lost on TCP in 10 of 20 tries)."""
    state = msgpack.packb({"v": 1, "type": "platform_state", "seq": 1, "ts": 2,
                           "hops": [[[1], "capture", 1]], "position_mm": [0, 0, 0],
                           "velocity_mm_s": [0, 0, 0]})
    token = encode(Hello(role="local", session="fz0", token="v2.local.²³.AAAA"))
    hello = encode(hello_for("local", "fzk"))
    big = bytes(70_000)
    return [[hello, state], [hello, state], [token], [token], [big], [big]]


_KNOWN_BAD = _known_bad()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def _wait_ready(port: int, deadline_s: float) -> None:
    end = time.monotonic() + deadline_s
    while True:
        try:
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.close()
            return
        except OSError:
            if time.monotonic() > end:
                raise
            await asyncio.sleep(0.1)


def _note(result: SmokeResult, data: bytes, transport: str) -> None:
    with contextlib.suppress(Exception):
        msg = decode(data, max_message_bytes=2**31)
        result.answers += 1
        code = getattr(msg, "code", None)
        if code is not None:
            key = f"{transport}:{code}"
            result.error_codes[key] = result.error_codes.get(key, 0) + 1


async def _fuzz_tcp(port: int, payloads: list[bytes | str], result: SmokeResult,
                    rng: random.Random, read_s: float) -> None:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    conn = ProtocolConnection("tcp", 2**31)
    try:
        for p in payloads:
            raw = p.encode() if isinstance(p, str) else p
            writer.write(raw if rng.random() < 0.1 else frame(raw))
            result.frames_sent += 1
        with contextlib.suppress(OSError):
            await writer.drain()
        with contextlib.suppress(TimeoutError, OSError):
            async with asyncio.timeout(read_s):
                while chunk := await reader.read(65536):
                    conn.receive_data(chunk)
                    for ev in conn.events_received():
                        msg = getattr(ev, "message", None)
                        if msg is not None:
                            _note(result, encode(msg, validate=False, max_message_bytes=2**31),
                                  "tcp")
    finally:
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()


async def _fuzz_ws(port: int, payloads: list[bytes | str], result: SmokeResult,
                   read_s: float) -> None:
    async with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None,
                       open_timeout=10) as ws:
        with contextlib.suppress(Exception):  # the relay may close at any point
            for p in payloads:
                await ws.send(p)
                result.frames_sent += 1
        with contextlib.suppress(Exception):
            async with asyncio.timeout(read_s):
                while True:
                    data = await ws.recv(decode=False)
                    _note(result, data if isinstance(data, bytes) else data.encode(), "ws")


async def _good_session(ws_port: int, tcp_port: int) -> bool:
    """A local station over TCP and a remote over WebSocket exchange a platform_state."""
    reader, writer = await asyncio.open_connection("127.0.0.1", tcp_port)
    tcp = ProtocolConnection("tcp")
    session = f"good{os.getpid()}"
    try:
        async with connect(f"ws://127.0.0.1:{ws_port}", compression=None) as ws:
            writer.write(tcp.encode(hello_for("local", session)))
            await ws.send(encode(hello_for("remote", session, v2=True)))
            got_welcome = False
            async with asyncio.timeout(10):
                while not got_welcome:
                    tcp.receive_data(await reader.read(65536))
                    got_welcome = any(isinstance(getattr(e, "message", None), Welcome)
                                      for e in tcp.events_received())
                while not isinstance(decode(await ws.recv(decode=False)), Welcome):
                    pass
                sent = PlatformState(seq=77, ts_us=1, position_mm=(1.0, 2.0, 3.0))
                writer.write(tcp.encode(sent))
                while True:
                    msg = decode(await ws.recv(decode=False))
                    if isinstance(msg, PlatformState):
                        return msg.seq == 77 and msg.position_mm == sent.position_mm
    except (TimeoutError, OSError):
        return False
    finally:
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()


async def _status_ok(port: int) -> bool:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        async with asyncio.timeout(10):
            head = await reader.readline()
        return head.startswith(b"HTTP/1.1 200")
    finally:
        writer.close()


async def _run(connections: int, seed: int, result: SmokeResult, log_path: Path) -> None:
    ws_port, tcp_port = _free_port(), _free_port()
    cmd = [*module_argv(), "--log-level", "WARNING", "relay", "--host",
           "127.0.0.1", "--port", str(ws_port), "--tcp-port", str(tcp_port), "--secret",
           FUZZ_SECRET, "--hello-timeout-s", "2"]
    rng = random.Random(seed)
    seeds = seed_messages()
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=_REPO)
        try:
            await _wait_ready(ws_port, 30.0)
            await _wait_ready(tcp_port, 30.0)
            for i in range(connections):
                payloads: list[bytes | str] = []
                if i < len(_KNOWN_BAD):  # what the fuzzers found, over real sockets too
                    payloads = list(_KNOWN_BAD[i])
                elif rng.random() < 0.7:
                    payloads.append(encode(hello_for(rng.choice(("local", "remote", "observer")),
                                                     f"fz{i % 5}")))
                for _ in range(rng.randrange(1, 6)):
                    p = rng.choice(seeds)
                    for _ in range(rng.randrange(1, 4)):
                        p = (mutate_message(rng, p) if rng.random() < 0.7
                             else mutate_bytes(rng, p))
                    payloads.append(p)
                if rng.random() < 0.1:
                    payloads.append("text " + str(i))
                if rng.random() < 0.05:
                    payloads.append(bytes(rng.randrange(256) for _ in range(70_000)))
                result.connections += 1
                if i % 2:
                    with contextlib.suppress(Exception):
                        await _fuzz_ws(ws_port, payloads, result, 0.05)
                else:
                    await _fuzz_tcp(tcp_port, payloads, result, rng, 0.05)
            result.relay_alive = proc.poll() is None
            result.good_session = await _good_session(ws_port, tcp_port)
            result.status_ok = await _status_ok(ws_port)
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()


def run_smoke(connections: int = 200, seed: int = 0) -> SmokeResult:
    """Fuzz a real relay process over TCP and WebSocket, then check it still serves."""
    result = SmokeResult()
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        log_path = Path(tmp) / "relay.log"
        asyncio.run(_run(connections, seed, result, log_path))
        for line in log_path.read_text(errors="replace").splitlines():
            if "Traceback" in line or " ERROR " in line or "Exception" in line:
                result.relay_log_errors.append(line[:300])
    result.seconds = time.perf_counter() - start
    return result
