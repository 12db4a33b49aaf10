"""A station's CPU per message sent to the relay, two checkouts paired (issue 12).

The whole demo's CPU moves by +-10 % from one minute to the next on this shared machine, so
a change worth a few hundredths of a core cannot be told apart there. This benchmark isolates
the station side of the uplink: one process (a child, with the checkout's code on its path)
opens a :class:`~shared.client.StationLink` as ``local`` to a real relay and sends
``platform_state`` at a fixed rate (the local station's 250 Hz uplink by default), on an
absolute schedule, for a warm-up and a window; it reports its own CPU time over the window
(``time.process_time``: every thread of the process) per message sent. The relay
(:class:`~relay_server.server.RelayServer`) and a ``remote`` station that takes every message
run in this process, from this checkout, and are not counted. Runs alternate between the
checkouts (A, B, A, B, ...): compare the ratios of pairs.

Run:   python benchmarks/bench_station_send.py --before ../base --after . --rounds 5
Writes benchmarks/results/station_send.md (``--out`` to change).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform as host_platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

TOKEN = "bench-token-0123456789abcdef"
SESSION = "bench"


async def _child(payload: dict[str, Any]) -> dict[str, Any]:
    """The sender: a local station's uplink alone, measured over the window."""
    from shared.client import StationLink
    from shared.protocol import PlatformState
    from shared.timebase import now_us

    period = 1.0 / payload["rate_hz"]
    async with StationLink(payload["url"], session=SESSION, role="local", token=TOKEN,
                           name="bench-sender") as link:
        await link.wait_connected(10.0)
        loop = asyncio.get_running_loop()
        seq = 0
        next_t = loop.time()
        warm_end = next_t + payload["warmup_s"]
        end = warm_end + payload["window_s"]
        cpu0 = sent0 = None
        while True:
            now = loop.time()
            if cpu0 is None and now >= warm_end:
                cpu0, sent0, t0 = time.process_time(), seq, now
            if now >= end:
                break
            seq += 1
            await link.send(PlatformState(seq=seq, ts_us=now_us(),
                                          position_mm=(float(seq % 50), 1.0, 2.0)))
            next_t += period
            await asyncio.sleep(max(0.0, next_t - loop.time()))
        cpu1, wall = time.process_time(), loop.time() - t0
        assert cpu0 is not None and sent0 is not None
    import shared.client

    return {"cpu_s": cpu1 - cpu0, "wall_s": wall, "sent": seq - sent0,
            "code": str(Path(shared.client.__file__).resolve())}


async def _run_pair(trees: list[tuple[str, Path]], args: argparse.Namespace
                    ) -> list[dict[str, Any]]:
    from benchmarks.tree_child import run_in_tree
    from relay_server.config import RelayConfig
    from relay_server.server import RelayServer
    from shared.client import StationLink

    relay = RelayServer(RelayConfig(host="127.0.0.1", port=0, tcp_port=0,
                                    tokens={SESSION: TOKEN}))
    await relay.start()
    results = []
    try:
        scheme_url = (f"ws://127.0.0.1:{relay.ws_port}/" if args.scheme == "ws"
                      else f"tcp://127.0.0.1:{relay.tcp_port}")
        async with StationLink(scheme_url, session=SESSION, role="remote",
                               token=TOKEN) as remote:
            await remote.wait_connected(10.0)

            async def drain() -> None:
                while True:
                    await remote.recv()

            drainer = asyncio.create_task(drain())
            try:
                for name, tree in trees:
                    payload = {"url": scheme_url, "rate_hz": args.rate_hz,
                               "warmup_s": args.warmup, "window_s": args.window}
                    load = os.getloadavg()[0]
                    got = await asyncio.to_thread(run_in_tree, __file__, tree, payload)
                    got.update(side=name, load=load,
                               us_per_msg=got["cpu_s"] / max(1, got["sent"]) * 1e6,
                               cores=got["cpu_s"] / got["wall_s"])
                    if not got["code"].startswith(str(tree)):
                        raise RuntimeError(f"the {name} side ran {got['code']}, not {tree}")
                    print(f"{name}: load {load:.2f}, {got['sent']} sent, "
                          f"{got['us_per_msg']:.1f} us CPU per message", flush=True)
                    results.append(got)
            finally:
                drainer.cancel()
    finally:
        await relay.close()
    return results


def report(runs: list[dict[str, Any]], args: argparse.Namespace) -> str:
    """The runs and the paired ratios as Markdown."""
    lines = ["# A station's CPU per message sent to the relay (issue 12)", "",
             f"Machine: {host_platform.machine()}, `nproc` {os.cpu_count()}; Python "
             f"{host_platform.python_version()}. Command: `python benchmarks/"
             f"bench_station_send.py --before {args.before} --after {args.after} --rounds "
             f"{args.rounds} --scheme {args.scheme} --rate-hz {args.rate_hz:g}`. Each run: a "
             f"process with the side's code sends `platform_state` at {args.rate_hz:g} Hz "
             f"through `StationLink` ({args.scheme}) to a real relay for {args.warmup:g} s "
             f"warm-up + {args.window:g} s window; CPU = that process's `process_time` over "
             "the window (all its threads). Sides alternate; pairs are adjacent runs.", "",
             "| run | side | load avg | sent | cores | us CPU per message |",
             "|---|---|---|---|---|---|"]
    for i, r in enumerate(runs):
        lines.append(f"| {i + 1} | {r['side']} | {r['load']:.2f} | {r['sent']} | "
                     f"{r['cores']:.4f} | {r['us_per_msg']:.1f} |")
    ratios = [a["us_per_msg"] / b["us_per_msg"] for b, a in zip(runs[::2], runs[1::2],
                                                                  strict=False)]
    if ratios:
        lines += ["", f"after/before, CPU per message: median {statistics.median(ratios):.2f}"
                  f" (range {min(ratios):.2f}-{max(ratios):.2f}, {len(ratios)} pairs; "
                  f"after lower in {sum(r < 1 for r in ratios)} of {len(ratios)}).", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the paired benchmark (or, with ``--child``, one sender) and write the table."""
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        print(json.dumps(asyncio.run(_child(json.loads(argv[1])))))
        return 0
    if str(ROOT) not in sys.path:  # the parent runs this checkout's relay (not the child)
        sys.path.insert(0, str(ROOT))
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--before", type=Path, required=True, help="the tree to compare with")
    parser.add_argument("--after", type=Path, default=ROOT, help="default: this tree")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--scheme", choices=("ws", "tcp"), default="ws")
    parser.add_argument("--rate-hz", type=float, default=250.0)
    parser.add_argument("--warmup", type=float, default=2.0)
    parser.add_argument("--window", type=float, default=8.0)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results"
                        / "station_send.md")
    args = parser.parse_args(argv)
    trees = [("before", args.before.resolve()), ("after", args.after.resolve())]
    runs = asyncio.run(_run_pair(trees * args.rounds, args))
    text = report(runs, args)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
