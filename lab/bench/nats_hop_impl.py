"""Implementation of ``teletouch bench nats-hop`` (see :mod:`lab.bench.nats_hop`)."""

from __future__ import annotations

import asyncio
import contextlib
import os
import platform
from typing import Any

import msgpack
import numpy as np
from websockets.asyncio.client import ClientConnection, connect

from lab.bench.load_impl import (
    RelayUnderTest,
    _autogroup,
    start_nats_server,
    tactile_frame,
)
from lab.bench.nats_floor import PATHS, FloorSender, start_receiver
from lab.bench.results import publish
from shared.protocol import ClockPong, Hello, TactileFrame, encode
from shared.timebase import now_us
from shared.transport import set_nodelay

__all__ = ["report", "run_nats_hop"]

_WARMUP_S = 1.0


async def _station(port: int, role: str, session: str) -> ClientConnection:
    ws = await connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None)
    set_nodelay(ws.transport)
    await ws.send(encode(Hello(role=role, session=session, token="x")))
    welcome = msgpack.unpackb(await ws.recv())
    if welcome.get("type") != "welcome":
        raise RuntimeError(f"{role}@{session} refused: {welcome}")
    return ws


async def _pong_loop(ws: ClientConnection, out: list[tuple[int, int | None]] | None,
                     start_us: list[int]) -> None:
    with contextlib.suppress(Exception):
        async for data in ws:
            t_rx = now_us()
            obj = msgpack.unpackb(data, raw=False)
            if obj.get("type") == "clock_ping":
                await ws.send(encode(ClockPong(ping_id=obj["ping_id"], t0_us=obj["t0_us"],
                                               t1_us=t_rx, t2_us=now_us()), validate=False))
            elif obj.get("type") == "tactile_frame" and out is not None \
                    and obj["ts"] >= start_us[0]:
                stamps = {h[1]: h[2] for h in obj["hops"] if h[0] == "relay"}
                nats = (stamps["nats_in"] - stamps["nats_out"]) if "nats_in" in stamps \
                    else None
                out.append((stamps["relay_out"] - obj["ts"], nats))


async def _phase(port_local: int, port_remote: int, session: str, rate_hz: float,
                 seconds: float) -> list[tuple[int, int | None]]:
    local = await _station(port_local, "local", session)
    remote = await _station(port_remote, "remote", session)
    got: list[tuple[int, int | None]] = []
    start_us = [now_us() + int(_WARMUP_S * 1e6)]
    tasks = [asyncio.create_task(_pong_loop(local, got, start_us)),
             asyncio.create_task(_pong_loop(remote, None, start_us))]
    base = tactile_frame()
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    n = 0
    try:
        while loop.time() - t0 < seconds + _WARMUP_S:
            n += 1
            ts = now_us()
            await remote.send(encode(TactileFrame(
                seq=n, ts_us=ts, center_mm=base.center_mm, pitch_mm=base.pitch_mm,
                layers=base.layers, contact=True, force_n=1.0, indentation_mm=0.5),
                validate=False))
            await asyncio.sleep(max(0.0, t0 + n / rate_hz - loop.time()))
        await asyncio.sleep(0.2)
    finally:
        await local.close()
        await remote.close()
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    return got


def _p(values: list[int]) -> dict[str, float | None]:
    if not values:
        return {"p50": None, "p99": None}
    p50, p99 = np.percentile(np.asarray(values, dtype=np.float64), [50, 99])
    return {"p50": float(p50), "p99": float(p99)}


async def run_nats_hop(*, rate_hz: float, rounds: int, round_s: float) -> dict[str, Any]:
    """Alternate same-worker and cross-worker phases; return the figures."""
    load_start = os.getloadavg()
    nats, url = await asyncio.to_thread(start_nats_server)
    relays: list[RelayUnderTest] = []
    same: list[int] = []
    cross: list[int] = []
    nats_leg: list[int] = []
    frame_bytes = len(encode(tactile_frame(), validate=False))
    floor_sent = dict.fromkeys(PATHS, 0)
    receiver = sender = None
    try:
        for _ in range(2):
            relays.append(await asyncio.to_thread(RelayUnderTest, 1, url))
        a, b = relays
        await asyncio.to_thread(_wait_cluster, a, 2)
        receiver, pipe, port = await asyncio.to_thread(start_receiver, url, frame_bytes)
        sender = FloorSender(url, port, frame_bytes)
        await sender.open()
        for i in range(rounds):
            got = await _phase(a.ws_port, a.ws_port, f"same{i}", rate_hz, round_s)
            same += [added for added, _ in got]
            got = await _phase(a.ws_port, b.ws_port, f"cross{i}", rate_hz, round_s)
            cross += [added for added, hop in got if hop is not None]
            nats_leg += [hop for _, hop in got if hop is not None]
            for path in PATHS:
                floor_sent[path] += await sender.phase(path, rate_hz, round_s, _WARMUP_S)
        pipe.send("done")
        floor: dict[str, list[int]] = await asyncio.to_thread(pipe.recv)
    finally:
        if sender is not None:
            await sender.close()
        if receiver is not None:
            receiver.join(10)
            if receiver.is_alive():
                receiver.kill()
        for r in relays:
            r.close()
        nats.terminate()
        nats.wait(10)
    ps, pc = _p(same), _p(cross)
    hop = {k: None if ps[k] is None or pc[k] is None else pc[k] - ps[k]  # type: ignore[operator]
           for k in ("p50", "p99")}
    return {"frame_bytes": frame_bytes, "rate_hz": rate_hz,
            "rounds": rounds, "round_s": round_s, "frames": {"same": len(same),
                                                              "cross": len(cross)},
            "added_same_worker_us": ps, "added_cross_worker_us": pc,
            "nats_hop_added_us": hop, "nats_leg_stamps_us": _p(nats_leg),
            "floor_one_way_us": {p: _p(floor[p]) for p in PATHS},
            "floor_frames": {p: {"sent": floor_sent[p], "received": len(floor[p])}
                             for p in PATHS},
            "target_hop_p50_us": 500.0,
            "machine": {"nproc": os.cpu_count(), "loadavg_start": load_start,
                        "niceness": os.nice(0),
                    "autogroup": _autogroup(),
                        "loadavg_end": os.getloadavg(), "python": platform.python_version()}}


def _wait_cluster(relay: RelayUnderTest, workers: int) -> None:
    import time

    deadline = time.monotonic() + 30.0
    while len(relay.status().get("cluster", {}).get("workers", {})) < workers:
        if time.monotonic() > deadline:
            raise RuntimeError("the relay workers did not see each other")
        time.sleep(0.1)


def _f(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.0f}"


_FLOOR_NAMES = {"direct": "TCP socket, process to process",
                "nats_raw": "nats-server, minimal client", "nats_py": "nats-server, nats-py"}


def _diff(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else a - b


def _markdown(r: dict[str, Any], argv: str) -> str:
    m = r["machine"]
    s, c, h, leg = (r["added_same_worker_us"], r["added_cross_worker_us"],
                    r["nats_hop_added_us"], r["nats_leg_stamps_us"])
    ok = h["p50"] is not None and h["p50"] <= r["target_hop_p50_us"]
    fl = r["floor_one_way_us"]
    return "\n".join([
        "# NATS hop: what a second relay worker on the path adds", "",
        f"Command: `{argv}` at niceness {m['niceness']} (scheduler {m['autogroup']}). "
        f"Machine: {m['nproc']} cores, Python "
        f"{m['python']}, load average "
        f"{m['loadavg_start'][0]:.2f} at the start, {m['loadavg_end'][0]:.2f} at the end "
        "(other jobs on the machine raise these figures).", "",
        f"One session, tactile_frame {r['frame_bytes']} bytes at {r['rate_hz']:g} Hz, "
        f"{r['rounds']} rounds of {r['round_s']:g} s per phase (same worker / across two "
        "workers via a local nats-server), alternating. Added = relay_out stamp - sender ts.",
        "", "| path | frames | added p50 us | added p99 us |", "|---|---|---|---|",
        f"| same worker | {r['frames']['same']} | {_f(s['p50'])} | {_f(s['p99'])} |",
        f"| across workers (NATS) | {r['frames']['cross']} | {_f(c['p50'])} | "
        f"{_f(c['p99'])} |",
        f"| **NATS hop (difference)** | | **{_f(h['p50'])}** | {_f(h['p99'])} |", "",
        f"NATS leg from the stamps (nats_out -> nats_in, publish to the receiving worker's "
        f"callback): p50 {_f(leg['p50'])} us, p99 {_f(leg['p99'])} us. The difference also "
        "holds the second worker's decode and re-encode of the frame.", "",
        f"Target: the NATS hop adds <= {r['target_hop_p50_us']:.0f} us p50 on a 19 kB frame: "
        f"**{'met' if ok else 'MISSED'}** in this run.", "",
        "## The floor: the same message with no relay on the path", "",
        "In the same rounds (`lab/bench/nats_floor.py`), one message of the frame's size from "
        "the benchmark process to a receiver process, stamped at the write and timed at the "
        "receiver's callback: over a plain TCP socket, through the nats-server with a minimal "
        "client speaking the NATS protocol from asyncio protocol callbacks (no library: the "
        "least any client can add), and through nats-py (the relay's client).", "",
        "| path | sent | received | one-way p50 us | one-way p99 us |", "|---|---|---|---|---|",
        *[f"| {_FLOOR_NAMES[p]} | {r['floor_frames'][p]['sent']} | "
          f"{r['floor_frames'][p]['received']} | {_f(fl[p]['p50'])} | {_f(fl[p]['p99'])} |"
          for p in PATHS], "",
        "A cross-worker frame pays one server traversal more than a same-worker frame, so "
        f"the minimal client's one-way figure ({_f(fl['nats_raw']['p50'])} us p50) is the "
        "least the hop can cost on this machine, whatever the relay does; nats-py adds "
        f"{_f(_diff(fl['nats_py']['p50'], fl['nats_raw']['p50']))} us to it and the relay "
        f"workers' own path (queue, envelope, decode, delivery) "
        f"{_f(_diff(h['p50'], fl['nats_py']['p50']))} us more.",
    ])


def report(results: dict[str, Any], *, as_json: bool, out_dir: str | None, argv: str) -> None:
    """Print the results; optionally write ``nats_hop.md`` and ``nats_hop.json``."""
    publish(results, _markdown(results, argv), as_json=as_json, out_dir=out_dir, stem="nats_hop")
