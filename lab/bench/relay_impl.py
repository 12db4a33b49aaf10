"""Implementation of ``teletouch bench relay`` (see :mod:`lab.bench.relay`)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import platform
import socket
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.server import ServerConnection, serve

from lab.bench.results import publish
from lab.child import module_argv
from shared.protocol import (
    ArmCommand,
    ArmState,
    ClockPong,
    Hello,
    LengthPrefixDecoder,
    PlatformState,
    encode,
    frame,
)
from shared.report import format_table
from shared.timebase import now_us

__all__ = ["report", "run_benchmark_async"]

log = logging.getLogger(__name__)
_WARMUP_S = 0.5


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.asynccontextmanager
async def relay_process(**settings: Any) -> AsyncIterator[tuple[int, int, int]]:
    """Run ``teletouch relay`` in a child process; yield (ws_port, tcp_port, pid)."""
    port, tcp_port = _free_port(), _free_port()
    env = dict(os.environ)
    for key, value in settings.items():
        env[f"TELETOUCH_RELAY_{key.upper()}"] = str(value)
    proc = await asyncio.create_subprocess_exec(
        *module_argv(), "--log-level", "WARNING", "relay",
        "--host", "127.0.0.1", "--port", str(port), "--tcp-port", str(tcp_port),
        "--allow-any-token", env=env, stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 20.0
        while True:
            try:
                _, w = await asyncio.open_connection("127.0.0.1", tcp_port)
                w.close()
                await w.wait_closed()
                break
            except OSError:
                if time.monotonic() > deadline or proc.returncode is not None:
                    raise RuntimeError("relay process did not start") from None
                await asyncio.sleep(0.05)
        yield port, tcp_port, proc.pid
    finally:
        if proc.returncode is None:
            proc.terminate()
            try:
                await asyncio.wait_for(proc.wait(), 10.0)
            except TimeoutError:
                proc.kill()
                await proc.wait()


async def _relay_status(port: int) -> dict[str, Any]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(b"GET /status HTTP/1.1\r\nHost: x\r\n\r\n")
    data = await reader.read()
    writer.close()
    await writer.wait_closed()
    return dict(json.loads(data.partition(b"\r\n\r\n")[2]))


class _Sink:
    """Collects one-way latencies of data messages after the warm-up."""

    def __init__(self, start_after_us: int) -> None:
        self.start_after_us = start_after_us
        self.latencies_us: list[int] = []

    def take(self, data: bytes) -> dict[str, Any]:
        obj: dict[str, Any] = msgpack.unpackb(data, raw=False)
        ts = obj.get("ts")
        if ts is not None and ts >= self.start_after_us:
            self.latencies_us.append(now_us() - ts)
        return obj


async def _drain_ws(ws: ClientConnection | ServerConnection, sink: _Sink) -> None:
    with contextlib.suppress(Exception):
        async for data in ws:
            obj = sink.take(data)  # type: ignore[arg-type]
            if obj.get("type") == "clock_ping":
                t = now_us()
                await ws.send(encode(ClockPong(ping_id=obj["ping_id"], t0_us=obj["t0_us"],
                                               t1_us=t, t2_us=t), validate=False))


async def _pace(senders: list[tuple[ClientConnection | ServerConnection, str]],
                rate_hz: float, duration_s: float) -> int:
    """Send one message per stream per period on a drift-free schedule; return ticks sent."""
    period = 1.0 / rate_hz
    loop = asyncio.get_running_loop()
    start = loop.time()
    next_t = start
    seq = 0
    while loop.time() - start < duration_s:
        seq += 1
        ts = now_us()
        for ws, kind in senders:
            if kind == "platform_state":
                msg: Any = PlatformState(seq=seq, ts_us=ts, position_mm=(1.0, 2.0, 3.0),
                                         velocity_mm_s=(0.0, 0.0, 0.0))
            else:
                msg = ArmState(seq=seq, ts_us=ts, position_mm=(1.0, 2.0, 3.0), force_n=0.5)
            await ws.send(encode(msg, validate=False))
        next_t += period
        delay = next_t - loop.time()
        if delay > 0:
            await asyncio.sleep(delay)
        elif delay < -0.02:  # far behind: skip ahead instead of bursting
            next_t = loop.time()
    return seq


async def _latency_relay(ws_port: int, sessions: int, rate_hz: float, duration_s: float
                         ) -> tuple[list[int], int, dict[str, Any]]:
    url = f"ws://127.0.0.1:{ws_port}"
    conns: list[ClientConnection] = []
    senders: list[tuple[ClientConnection | ServerConnection, str]] = []
    sink = _Sink(now_us() + int(_WARMUP_S * 1e6))
    try:
        for i in range(sessions):
            for role, kind in (("local", "platform_state"), ("remote", "arm_state")):
                ws = await connect(url, compression=None, max_size=None)
                conns.append(ws)
                await ws.send(encode(Hello(role=role, session=f"bench{i}", token="x")))
                await ws.recv()  # welcome
                senders.append((ws, kind))
        drains = [asyncio.create_task(_drain_ws(ws, sink)) for ws in conns]
        await asyncio.sleep(0.2)  # clock burst
        sink.start_after_us = now_us() + int(_WARMUP_S * 1e6)
        ticks = await _pace(senders, rate_hz, duration_s + _WARMUP_S)
        await asyncio.sleep(0.05)
        status = await _relay_status(ws_port)  # while the sessions exist
    finally:
        for ws in conns:
            await ws.close()
    for t in drains:
        t.cancel()
    await asyncio.gather(*drains, return_exceptions=True)
    return sink.latencies_us, ticks, status


async def _latency_direct(sessions: int, rate_hz: float, duration_s: float
                          ) -> tuple[list[int], int]:
    sink = _Sink(0)
    server_side: list[ServerConnection] = []
    ready = asyncio.Event()
    done = asyncio.Event()

    async def handler(ws: ServerConnection) -> None:
        server_side.append(ws)
        if len(server_side) == sessions:
            ready.set()
        drain = asyncio.create_task(_drain_ws(ws, sink))
        await done.wait()
        drain.cancel()
        await asyncio.gather(drain, return_exceptions=True)

    async with serve(handler, "127.0.0.1", 0, compression=None, max_size=None) as server:
        port = next(iter(server.sockets)).getsockname()[1]
        clients = [await connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None)
                   for _ in range(sessions)]
        await ready.wait()
        drains = [asyncio.create_task(_drain_ws(ws, sink)) for ws in clients]
        senders: list[tuple[ClientConnection | ServerConnection, str]] = [
            (ws, "platform_state") for ws in clients]
        senders += [(ws, "arm_state") for ws in server_side]
        sink.start_after_us = now_us() + int(_WARMUP_S * 1e6)
        ticks = await _pace(senders, rate_hz, duration_s + _WARMUP_S)
        await asyncio.sleep(0.05)
        done.set()
        for ws in clients:
            await ws.close()
        for t in drains:
            t.cancel()
        await asyncio.gather(*drains, return_exceptions=True)
    return sink.latencies_us, ticks


def _cpu_s(pid: int | None) -> float:
    """CPU seconds (user + system) used so far by process ``pid`` (Linux), or NaN."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return float("nan")


async def _throughput(tcp_port: int, sessions: int, duration_s: float, window: int,
                      pid: int | None = None) -> dict[str, float]:
    """Closed-loop saturation over TCP with ``arm_command`` (ordered, never dropped)."""
    pre = [frame(encode(ArmCommand(seq=i, ts_us=now_us(), action="stop"), validate=False))
           for i in range(window)]
    half_batches = (b"".join(pre[: window // 2]), b"".join(pre[window // 2:]))
    received = [0] * sessions
    sent = [0] * sessions
    stop = asyncio.Event()
    conns: list[asyncio.StreamWriter] = []

    async def join(role: str, i: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        r, w = await asyncio.open_connection("127.0.0.1", tcp_port)
        conns.append(w)
        w.write(frame(encode(Hello(role=role, session=f"tput{i}", token="x"))))
        await w.drain()
        return r, w

    async def receiver(i: int, r: asyncio.StreamReader, w: asyncio.StreamWriter,
                       credit: asyncio.Event) -> None:
        dec = LengthPrefixDecoder(2**24)
        while not stop.is_set():
            chunk = await r.read(2**18)
            if not chunk:
                return
            for payload in dec.feed(chunk):
                if b"arm_command" in payload:
                    received[i] += 1
                elif b"clock_ping" in payload:
                    obj = msgpack.unpackb(payload)
                    t = now_us()
                    w.write(frame(encode(ClockPong(ping_id=obj["ping_id"],
                                                   t0_us=obj["t0_us"], t1_us=t, t2_us=t))))
            if sent[i] - received[i] <= window // 2:
                credit.set()

    async def sender(i: int, w: asyncio.StreamWriter, credit: asyncio.Event) -> None:
        while not stop.is_set():
            if sent[i] - received[i] > window // 2:
                credit.clear()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(credit.wait(), 0.5)
                continue
            w.write(half_batches[(sent[i] // (window // 2)) % 2])  # half a window per write
            sent[i] += window // 2
            await w.drain()

    tasks: list[asyncio.Task[None]] = []
    try:
        pairs = []
        for i in range(sessions):
            lr, lw = await join("local", i)
            rr, rw = await join("remote", i)
            pairs.append((lr, lw, rr, rw))
        await asyncio.sleep(0.2)
        for i, (lr, lw, rr, rw) in enumerate(pairs):
            credit = asyncio.Event()
            credit.set()
            tasks.append(asyncio.create_task(receiver(i, rr, rw, credit)))
            tasks.append(asyncio.create_task(sender(i, lw, credit)))
            tasks.append(asyncio.create_task(_discard(lr)))
        await asyncio.sleep(0.5)  # warm-up
        r0, t0, c0 = sum(received), time.perf_counter(), _cpu_s(pid)
        await asyncio.sleep(duration_s)
        r1, t1, c1 = sum(received), time.perf_counter(), _cpu_s(pid)
    finally:
        stop.set()
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for w in conns:
            w.close()
    n = max(r1 - r0, 1)
    return {"sessions": sessions, "window": window,
            "throughput_msgs_per_s": (r1 - r0) / (t1 - t0),
            "relay_cpu_us_per_msg": (c1 - c0) * 1e6 / n,
            "relay_cpu_share": (c1 - c0) / (t1 - t0)}


async def _discard(r: asyncio.StreamReader) -> None:
    while await r.read(2**18):
        pass


def _diff(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else a - b


def _pcts(lat: list[int]) -> dict[str, float | None]:
    if not lat:
        return {"p50": None, "p99": None, "max": None}
    a = np.asarray(lat, dtype=np.float64)
    p50, p99 = np.percentile(a, [50, 99])
    return {"p50": float(p50), "p99": float(p99), "max": float(a.max())}


async def run_benchmark_async(*, sessions: list[int], rate_hz: float, duration_s: float,
                              throughput_s: float, quick: bool = False
                              ) -> dict[str, Any]:
    """Run every phase; return the results dictionary (see :func:`report`)."""
    logging.getLogger("websockets").setLevel(logging.WARNING)
    rows: list[dict[str, Any]] = []
    added: dict[str, Any] = {}
    residence: dict[str, Any] = {}
    for n in sessions:
        lat_d, ticks_d = await _latency_direct(n, rate_hz, duration_s)
        async with relay_process(stats_interval_s=1.0, ledger_window=65536) as (ws_port, _, _):
            lat_r, ticks_r, status = await _latency_relay(ws_port, n, rate_hz, duration_s)
        offered = 2 * n * rate_hz
        total_s = duration_s + _WARMUP_S
        for path, lat, ticks in (("direct", lat_d, ticks_d), ("relay", lat_r, ticks_r)):
            p = _pcts(lat)
            rows.append({"path": path, "sessions": n, "offered_msgs_s": offered,
                         "sent_msgs_s": 2 * n * ticks / total_s,
                         "received_msgs_s": len(lat) / duration_s,
                         "p50_us": p["p50"], "p99_us": p["p99"], "max_us": p["max"]})
        pd, pr = _pcts(lat_d), _pcts(lat_r)
        added[str(n)] = {k: _diff(pr[k], pd[k]) for k in ("p50", "p99", "max")}
        res = [s["delay_us"][d]["relay"] for s in status["sessions"].values()
               for d in ("local_to_remote", "remote_to_local")]
        drops = sum(s["drops"][d]["latest_wins"] for s in status["sessions"].values()
                    for d in ("local_to_remote", "remote_to_local"))
        residence[str(n)] = {
            "p50": float(np.median([r["p50"] for r in res if r["p50"] is not None] or [0])),
            "p99": max((r["p99"] for r in res if r["p99"] is not None), default=None),
            "max": max((r["max"] for r in res if r["max"] is not None), default=None),
            "latest_wins_drops": drops}
    # saturation measures forwarding capacity: the per-connection message-rate limit (5,000/s
    # by default, far above the real streams) is lifted for this phase only
    async with relay_process(ordered_queue_len=4096, rate_limit_per_s=1e9,
                             rate_limit_burst=10**9) as (_, tcp_port, pid):
        tput = await _throughput(tcp_port, 4, throughput_s, window=1024, pid=pid)
    key = str(max(sessions))
    return {
        "added_latency_us": added[key], "added_latency_us_by_sessions": added,
        "relay_residence_us_by_sessions": residence, "rows": rows,
        "throughput_msgs_per_s": tput["throughput_msgs_per_s"], "throughput": tput,
        "rate_hz": rate_hz, "duration_s": duration_s, "quick": quick,
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, "
                   f"Python {platform.python_version()}, no GPU, load average "
                   f"{os.getloadavg()[0]:.1f} at the end",
        "targets": {"added_p99_us_at_20_sessions": 500, "throughput_msgs_per_s": 50000},
    }


def report(results: dict[str, Any], *, as_json: bool, out_dir: str | None, argv: str) -> None:
    """Print the results; optionally write ``relay.md``, ``relay.json`` and ``relay.png``."""
    publish(results, _markdown(results, argv), as_json=as_json, out_dir=out_dir, stem="relay",
            plot=lambda path: _plot(results, path))


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.0f}"


def _markdown(r: dict[str, Any], argv: str) -> str:
    lines = ["# Relay benchmark", "",
             f"Machine: {r['machine']} (shared with other jobs). Command: `{argv}`.", "",
             "One-way latency, same host and clock; `relay` = station -> relay process -> "
             "station, `direct` = the same traffic over one WebSocket between the stations. "
             f"{r['rate_hz']:g} Hz per direction per session, {r['duration_s']:g} s measured "
             "after a 0.5 s warm-up.", "",
             format_table(r["rows"], ["path", "sessions", "offered_msgs_s", "sent_msgs_s",
                                      "received_msgs_s", "p50_us", "p99_us", "max_us"]),
             "", "Added latency (relay minus direct) and the relay's own residence time "
             "(relay_in -> relay_out from /status):", "",
             "| sessions | added p50 us | added p99 us | added max us | residence p50 us | "
             "residence p99 us | latest-wins drops |", "|---|---|---|---|---|---|---|"]
    for n, a in r["added_latency_us_by_sessions"].items():
        res = r["relay_residence_us_by_sessions"][n]
        lines.append(f"| {n} | {_fmt(a['p50'])} | {_fmt(a['p99'])} | {_fmt(a['max'])} | "
                     f"{_fmt(res['p50'])} | {_fmt(res['p99'])} | {res['latest_wins_drops']} |")
    t = r["throughput"]
    lines += ["", f"Saturation throughput (TCP, {t['sessions']} sessions, arm_command, "
              f"{t['window']} in flight per session, nothing dropped): "
              f"**{r['throughput_msgs_per_s']:.0f} forwarded msgs/s** "
              f"(target >= {r['targets']['throughput_msgs_per_s']}); the relay process used "
              f"{t['relay_cpu_share']:.2f} CPU cores, i.e. "
              f"{t['relay_cpu_us_per_msg']:.1f} us of CPU per forwarded message "
              "(decode + validate + route + encode + socket I/O).",
              "", f"Target: added p99 <= {r['targets']['added_p99_us_at_20_sessions']} us "
              "at 20 sessions x 1 kHz per direction."]
    return "\n".join(lines)


def _plot(r: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    labels, p50, p99 = [], [], []
    for row in r["rows"]:
        labels.append(f"{row['path']}\n{row['sessions']} sess")
        p50.append(row["p50_us"] or 0)
        p99.append(row["p99_us"] or 0)
    x = np.arange(len(labels))
    ax.bar(x - 0.2, p50, 0.4, label="p50")
    ax.bar(x + 0.2, p99, 0.4, label="p99")
    ax.set_xticks(x, labels)
    ax.set_yscale("log")
    ax.set_ylabel("one-way latency (us)")
    ax.set_title(f"Relay vs direct WebSocket, {r['rate_hz']:g} Hz/direction; "
                 f"saturation {r['throughput_msgs_per_s']:.0f} msg/s")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
