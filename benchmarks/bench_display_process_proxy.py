"""Would the display loop meet its jitter target in a process of its own? A proxy, measured.

Section 19 of ``docs/speed.md`` found the display loop's jitter in the demo to be waits for the
GIL, held by the local station's other threads while the scheduler is not running them, and
named the loop in a process of its own (with the platform read and the board link) as the
structural answer. Before building it, this measures a stand-in: a second local station in
scene mode (no relay: no uplink, no frames, no recording), its platform board in a process of
its own (``--platform sim-process``, as a real encoder board is a device) and its drive board
in another (``teletouch board`` over ``socket://``, as the demo's). Its display loop then
shares its interpreter only with what such a process would hold: the two device readers, the
platform reader's health thread and an idle event loop. It runs while ``teletouch bench cpu``
runs the whole demo on the same two cores, so the proxy's loop sees the demo's load plus its
own, and the demo's station is measured in the same minutes.

Per round: the demo (``bench cpu --no-profile``), and once its local station runs, the proxy
for ``--proxy-s`` seconds (its summary's ``display_loop``: rate, jitter p50/p99, overruns over
the whole run). Reported: both loops side by side.

Run: ``python benchmarks/bench_display_process_proxy.py --rounds 3 --link lan
--out benchmarks/results/display_process_proxy`` (writes ``README.md`` and the JSONs there).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
PROXY_SCENE = "hemisphere:radius_mm=10"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait(predicate: Any, timeout_s: float, what: str) -> None:
    end = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > end:
            raise TimeoutError(f"{what} did not happen within {timeout_s} s")
        time.sleep(0.2)


def _demo_station_runs(parent: int) -> bool:
    from lab.bench.cpu_impl import demo_processes

    return "local" in demo_processes(parent).values()


def _port_open(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def one_round(label: str, link: str, proxy_s: float, out: Path,
              proxy_args: list[str]) -> dict[str, Any]:
    """One demo with the proxy beside it; the two loops' figures."""
    py = sys.executable
    demo = subprocess.Popen([py, "-m", "lab.cli", "bench", "cpu", "--no-profile", "--link", link,
                             "--label", label, "--out-dir", str(out)], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    port = _free_port()
    board = subprocess.Popen([py, "-m", "lab.cli", "board", "--listen", f"127.0.0.1:{port}"],
                             cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    summary = out / f"proxy-{label}.json"
    try:
        _wait(lambda: _port_open(port), 30.0, "the proxy's drive board")
        _wait(lambda: _demo_station_runs(demo.pid), 90.0, "the demo's local station")
        subprocess.run([py, "-m", "lab.cli", "local", "--scene", PROXY_SCENE,
                        "--platform", "sim-process", "--display", f"socket://127.0.0.1:{port}",
                        "--duration", str(proxy_s), "--summary-json", str(summary),
                        "--no-status", *proxy_args], cwd=ROOT, check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                       timeout=proxy_s + 120.0)
        demo.wait(timeout=300.0)
    finally:
        for proc in (board, demo):
            if proc.poll() is None:
                proc.terminate()
                proc.wait(timeout=30.0)
    proxy = json.loads(summary.read_text())["display_loop"]
    bench = json.loads((out / f"cpu-{label}.json").read_text())
    return {"label": label, "load_start": bench["load_start"][0], "proxy": proxy,
            "demo": bench["display_loop"], "demo_cores": sum(
                p["cores"] for p in bench["processes"].values())}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--link", default="lan")
    parser.add_argument("--proxy-s", type=float, default=14.0,
                        help="how long the proxy runs (the demo's measured window is 12 s)")
    parser.add_argument("--proxy-arg", action="append", default=[],
                        help="one more argument for the proxy station (repeatable), e.g. "
                             "--proxy-arg=--platform-process")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    rows = [one_round(f"{args.link}-{i + 1}", args.link, args.proxy_s, out, args.proxy_arg)
            for i in range(args.rounds)]
    lines = ["# The display loop in a process of its own: a proxy beside the demo", "",
             f"Command: `python benchmarks/bench_display_process_proxy.py --rounds "
             f"{args.rounds} --link {args.link} --proxy-s {args.proxy_s:g}"
             f"{''.join(f' --proxy-arg={a}' for a in args.proxy_arg)} --out ...` "
             f"(nproc {os.cpu_count()}). Proxy: `teletouch local --scene {PROXY_SCENE} "
             "--platform sim-process --display socket://...` (its drive board a `teletouch "
             "board` process), started once the demo's local station runs; its loop figures "
             "cover its whole run. Demo: `teletouch bench cpu --no-profile` (its loop over the "
             "12 s window). `cores`: the demo's processes only, the proxy's not counted.", "",
             "| round | load at start | demo cores | demo loop Hz | demo jitter p50 / p99 ms "
             "| proxy loop Hz | proxy jitter p50 / p99 ms | proxy overruns |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        d, p = r["demo"], r["proxy"]
        lines.append(f"| {r['label']} | {r['load_start']:.2f} | {r['demo_cores']:.2f} | "
                     f"{d['rate_hz']:.0f} | {d['jitter_p50_ms']:.3f} / {d['jitter_p99_ms']:.3f} "
                     f"| {p['rate_hz']:.0f} | {p['jitter_p50_ms']:.3f} / "
                     f"{p['jitter_p99_ms']:.3f} | {p['overruns']} |")
    text = "\n".join(lines) + "\n"
    (out / "README.md").write_text(text)
    (out / "rows.json").write_text(json.dumps(rows, indent=1))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
