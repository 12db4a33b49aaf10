"""Does the live view slow the station? Display loop rate and period jitter with 0 and 3 viewers.

The whole local agent runs in this process (sim platform with a raster operator, sim ArrayTac
on a virtual CAN FD bus, StationLink to an in-process relay, a remote answering every
platform_state with a pressed tactile frame at 60 Hz, so the live analysis has real work),
as in benchmarks/bench_display_loop_agent.py, once per setting:

* ``no view``: ``--view`` off (the reference);
* ``view, 0 viewers``: the view server thread publishing at 40 Hz and the analysis process;
* ``view, 3 ws clients``: plus 3 WebSocket clients in a child process that read and
  JSON-parse every message as fast as they come (what a browser's network side costs the
  station, without a browser's drawing);
* ``view, 3 chromium``: plus 3 headless chromium instances (Playwright, Debian's chromium)
  showing the page, drawing every snapshot on their canvases, on this same machine.

Settings alternate over ``--rounds`` rounds (A B C D, D C B A, ...) so a change in the
machine's load hits every setting alike; the table gives each run and the ratios to the
no-view runs of the same round.

Run:   python benchmarks/bench_view.py                (2 rounds x 4 settings x 20 s)
       python benchmarks/bench_view.py --quick        (1 round x 4 settings x 6 s)
Writes benchmarks/results/view.md and view.png.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import platform as host_platform
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from local_site.agent import LocalAgent, LocalAgentConfig  # noqa: E402
from relay_server.config import RelayConfig  # noqa: E402
from relay_server.server import RelayServer  # noqa: E402
from shared.client import StationLink, StationLinkConfig  # noqa: E402
from shared.protocol import Hop, PlatformState, TactileFrame  # noqa: E402
from shared.report import emit, format_table  # noqa: E402
from shared.timebase import now_us  # noqa: E402
from shared.view import ViewAddress  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
SESSION = "bench"
MOTION = "raster:x0=10,x1=50,y0=10,y1=50,spacing=4,speed=20,press_depth=3,press_every=10"
GRID = 17
PITCH_MM = 0.5
SETTINGS = ("no view", "view, 0 viewers", "view, 3 ws clients", "view, 3 chromium")


def _frame(seq: int, state: PlatformState) -> TactileFrame:
    """A pressed frame that depends on where the platform is (pins and maps keep changing)."""
    t = now_us()
    cx, cy = state.position_mm[0], state.position_mm[1]
    offs = (np.arange(GRID) - GRID // 2) * PITCH_MM
    gx, gy = np.meshgrid(cx + offs, cy + offs)
    pad = np.exp(-(offs[None, :] ** 2 + offs[:, None] ** 2) / 8.0)
    height = (pad * (1.0 + 0.3 * np.sin(gx / 3.0) * np.cos(gy / 3.0))).astype(np.float32)
    return TactileFrame(seq=seq, ts_us=t, hops=(*state.hops, Hop("remote", "arm_command", t),
                                                Hop("remote", "sensor_frame", t),
                                                Hop("remote", "sensor_arrival", t),
                                                Hop("remote", "tactile_ready", now_us())),
                        center_mm=(cx, cy), pitch_mm=PITCH_MM,
                        layers={"height_mm": height,
                                "stiffness_k": np.full((GRID, GRID), 0.75, np.float32)},
                        contact=True, force_n=3.0, indentation_mm=1.5,
                        source_seq=state.seq, source_ts_us=state.ts_us)


async def _remote(link: StationLink, rate_hz: float) -> None:
    latest: list[PlatformState] = []

    async def rx() -> None:
        async for msg in link.messages():
            if isinstance(msg, PlatformState):
                latest[:] = [msg]

    task = asyncio.create_task(rx())
    try:
        seq = 0
        while True:
            await asyncio.sleep(1.0 / rate_hz)
            if latest and link.is_connected:
                seq += 1
                await link.send(_frame(seq, latest[0]))
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


# ---------------------------------------------------------------------- viewers (child process)

async def _ws_clients(port: int, count: int, seconds: float) -> dict[str, Any]:
    from websockets.asyncio.client import connect

    connected = asyncio.Barrier(count + 1)
    start = asyncio.Event()

    async def one() -> int:
        async with connect(f"ws://127.0.0.1:{port}/ws", max_size=None) as ws:
            json.loads(await ws.recv())
            await connected.wait()
            n = 0
            while not start.is_set():
                json.loads(await ws.recv())
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                json.loads(await ws.recv())
                n += 1
        return n

    tasks = [asyncio.create_task(one()) for _ in range(count)]
    await connected.wait()
    print("ready", flush=True)
    start.set()
    counts = await asyncio.gather(*tasks)
    return {"messages_per_s": [c / seconds for c in counts]}


def _chromium_clients(port: int, count: int, seconds: float) -> dict[str, Any]:
    from playwright.sync_api import sync_playwright

    exe = os.environ.get("TELETOUCH_CHROMIUM") or shutil.which("chromium") or "chromium"
    with sync_playwright() as pw:
        browsers = [pw.chromium.launch(executable_path=exe, headless=True,
                                       args=["--no-sandbox", "--disable-gpu"])
                    for _ in range(count)]
        try:
            pages = [b.new_page(viewport={"width": 1600, "height": 900}) for b in browsers]
            for page in pages:
                page.goto(f"http://127.0.0.1:{port}/", timeout=120_000)
                page.wait_for_function("() => window.teletouchView.messages > 2",
                                       timeout=120_000)
            print("ready", flush=True)
            probe = "() => [window.teletouchView.messages, performance.now()]"
            start = [page.evaluate(probe) for page in pages]
            time.sleep(seconds)
            end = [page.evaluate(probe) for page in pages]
        finally:
            for b in browsers:
                with contextlib.suppress(Exception):
                    b.close()
    # each page's own clock: the evaluate calls themselves take time on a loaded machine
    return {"messages_per_s": [(e[0] - s[0]) / ((e[1] - s[1]) / 1e3)
                               for s, e in zip(start, end, strict=True)]}


def _viewers_main(kind: str, port: int, count: int, seconds: float) -> int:
    out = (asyncio.run(_ws_clients(port, count, seconds)) if kind == "ws"
           else _chromium_clients(port, count, seconds))
    print(json.dumps(out))
    return 0


# ---------------------------------------------------------------------- one run

def _analysis_cpu_s(agent: LocalAgent) -> float | None:
    """CPU seconds the live analysis process has used (its last report), or None."""
    view = agent.view
    result = view.analysis()[1] if view is not None else None
    return None if result is None else float(result["cpu_s_total"])


async def measure(setting: str, duration_s: float, warmup_s: float = 3.0) -> dict[str, Any]:
    """Run the full agent under one view setting; measure ``duration_s`` once viewers are on.

    The agent starts first (the view belongs to it), runs ``warmup_s``; then the viewers
    start (if any) and the window opens when they are all receiving snapshots.
    """
    relay = RelayServer(RelayConfig(host="127.0.0.1", port=0, tcp_port=0,
                                    allow_any_token=True, stats_interval_s=0.5))
    await relay.start()
    url = f"ws://127.0.0.1:{relay.ws_port}/"
    remote_link = StationLink(url, session=SESSION, role="remote", token="any")
    view = None if setting == "no view" else ViewAddress("127.0.0.1", 0)
    agent = LocalAgent(LocalAgentConfig(motion=MOTION, stale_frame_timeout_s=0.5),
                       link_config=StationLinkConfig(url=url, session=SESSION, token="any"),
                       view=view)
    remote_link.start()
    helpers = [asyncio.create_task(_remote(remote_link, 60.0))]
    window: dict[str, Any] = {}

    async def control() -> None:
        await asyncio.sleep(warmup_s)
        viewers = None
        if "3" in setting:
            server = agent.view_server
            assert server is not None and server.port is not None
            kind = "ws" if "ws" in setting else "chromium"
            viewers = await asyncio.create_subprocess_exec(
                sys.executable, __file__, "--viewers", kind, str(server.port), "3",
                f"{duration_s:g}", stdout=asyncio.subprocess.PIPE)
            assert viewers.stdout is not None
            line = await viewers.stdout.readline()
            if line.strip() != b"ready":
                raise RuntimeError(f"viewers did not start: {line!r}")
        loop = agent.loop
        assert loop is not None
        window["load"] = os.getloadavg()[0]
        n0 = loop.periods.iterations
        overruns0 = loop.periods.overruns
        cpu0 = agent.view_server.cpu_s if agent.view_server is not None else 0.0
        ana0 = _analysis_cpu_s(agent)
        t0 = time.monotonic()
        skipped0 = agent.view_server.counters["snapshots_skipped"] if agent.view_server else 0
        await asyncio.sleep(duration_s)
        window["periods_s"] = loop.periods.periods_s(last=loop.periods.iterations - n0)
        window["overruns"] = loop.periods.overruns - overruns0
        wall = time.monotonic() - t0
        if agent.view_server is not None:
            window["view_cpu_pct"] = 100.0 * (agent.view_server.cpu_s - cpu0) / wall
        ana1 = _analysis_cpu_s(agent)
        if ana0 is not None and ana1 is not None:
            window["analysis_cpu_pct"] = 100.0 * (ana1 - ana0) / wall
        if agent.view_server is not None:
            window["skipped"] = agent.view_server.counters["snapshots_skipped"] - skipped0
        if viewers is not None:
            assert viewers.stdout is not None
            out = await viewers.stdout.read()
            await viewers.wait()
            with contextlib.suppress(json.JSONDecodeError, IndexError):
                window["viewer_hz"] = json.loads(out.decode().strip().splitlines()[-1])[
                    "messages_per_s"]
        agent.request_stop("benchmark window done")

    helpers.append(asyncio.create_task(control()))
    try:
        await agent.run()
    finally:
        for task in helpers[:1]:
            task.cancel()
        results = await asyncio.gather(*helpers, return_exceptions=True)
        await remote_link.close()
        await relay.close()
    for result in results[1:]:
        if isinstance(result, BaseException):
            raise result
    periods = np.asarray(window["periods_s"])
    jitter_ms = np.abs(periods - 1e-3) * 1e3
    viewer_rates = window.get("viewer_hz") or []
    s = agent.summary or {}
    return {"setting": setting, "window_s": float(periods.sum()),
            "rate_hz": float(1.0 / periods.mean()),
            "period_p50_ms": float(np.percentile(periods, 50) * 1e3),
            "period_p99_ms": float(np.percentile(periods, 99) * 1e3),
            "period_max_ms": float(periods.max() * 1e3),
            "jitter_p50_ms": float(np.percentile(jitter_ms, 50)),
            "jitter_p99_ms": float(np.percentile(jitter_ms, 99)),
            "overruns": window["overruns"],
            "e2e_p50_ms": s["motion_to_touch_ms"].get("end_to_end", {}).get("p50"),
            "viewer_hz_min": min(viewer_rates) if viewer_rates else None,
            "snapshots_skipped": window.get("skipped"),
            "view_cpu_pct": window.get("view_cpu_pct"),
            "analysis_cpu_pct": window.get("analysis_cpu_pct"),
            "load_1min_start": window["load"], "periods_ms": periods * 1e3}


def _plot(path: Path, rows: list[dict[str, Any]]) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    bins = np.linspace(0.0, 5.0, 201)
    for setting in SETTINGS:
        periods = [r["periods_ms"] for r in rows if r["setting"] == setting]
        if not periods:
            continue
        allp = np.concatenate(periods)
        axes[0].hist(np.clip(allp, 0, 5), bins=bins, histtype="step",
                     label=f"{setting} (p99 {np.percentile(allp, 99):.2f} ms)")
    axes[0].set_yscale("log")
    axes[0].set_xlabel("display loop period (ms), target 1 ms")
    axes[0].set_ylabel("count (all rounds)")
    axes[0].legend(fontsize=8)
    axes[0].set_title("period distribution")
    for i, setting in enumerate(SETTINGS):
        pts = [r for r in rows if r["setting"] == setting]
        axes[1].scatter([i] * len(pts), [r["jitter_p99_ms"] for r in pts], marker="o",
                        label="jitter p99 (ms)" if i == 0 else None, color="C0")
        axes[1].scatter([i + 0.15] * len(pts), [1000.0 / r["rate_hz"] for r in pts],
                        marker="s", label="mean period (ms)" if i == 0 else None, color="C1")
    axes[1].set_xticks(range(len(SETTINGS)), [s.replace(", ", "\n") for s in SETTINGS])
    axes[1].set_title("per run")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """Run every setting for every round and write the table and the plot."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="1 round of 6 s per setting")
    parser.add_argument("--duration", type=float, default=None, help="seconds per run")
    parser.add_argument("--rounds", type=int, default=None, help="rounds (default 2)")
    parser.add_argument("--no-chromium", action="store_true", help="skip the chromium setting")
    parser.add_argument("--no-write", action="store_true", help="print only")
    parser.add_argument("--viewers", nargs=4, metavar=("KIND", "PORT", "N", "SECONDS"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.viewers:
        kind, port, n, secs = args.viewers
        return _viewers_main(kind, int(port), int(n), float(secs))
    duration_s = args.duration or (6.0 if args.quick else 20.0)
    rounds = args.rounds or (1 if args.quick else 2)
    settings = [s for s in SETTINGS if not (args.no_chromium and "chromium" in s)]
    nproc = os.cpu_count()
    load0 = os.getloadavg()
    rows: list[dict[str, Any]] = []
    for r in range(rounds):
        order = settings if r % 2 == 0 else list(reversed(settings))
        for setting in order:
            row = asyncio.run(measure(setting, duration_s))
            row["round"] = r + 1
            rows.append(row)
            emit(f"round {r + 1} {setting}: {row['rate_hz']:.0f} Hz, jitter p99 "
                 f"{row['jitter_p99_ms']:.3f} ms, viewers {row['viewer_hz_min']}")
    for row in rows:
        ref = next(x for x in rows if x["round"] == row["round"] and x["setting"] == "no view")
        row["rate_vs_no_view"] = row["rate_hz"] / ref["rate_hz"]
        row["jitter_p99_vs_no_view"] = row["jitter_p99_ms"] / max(1e-9, ref["jitter_p99_ms"])
    cols = ["round", "setting", "window_s", "rate_hz", "rate_vs_no_view", "period_p50_ms",
            "period_p99_ms", "period_max_ms", "jitter_p50_ms", "jitter_p99_ms",
            "jitter_p99_vs_no_view", "overruns", "viewer_hz_min", "snapshots_skipped",
            "view_cpu_pct", "analysis_cpu_pct", "e2e_p50_ms", "load_1min_start"]
    summary = []
    for setting in settings:
        pts = [r for r in rows if r["setting"] == setting]
        summary.append({"setting": setting,
                        "rate_hz (mean)": float(np.mean([p["rate_hz"] for p in pts])),
                        "rate_vs_no_view (mean)": float(np.mean([p["rate_vs_no_view"]
                                                                  for p in pts])),
                        "jitter_p99_ms (mean)": float(np.mean([p["jitter_p99_ms"]
                                                               for p in pts])),
                        "jitter_p99_vs_no_view (mean)": float(np.mean(
                            [p["jitter_p99_vs_no_view"] for p in pts]))})
    command = "python benchmarks/bench_view.py" + (" --quick" if args.quick else "") + \
        (f" --duration {args.duration:g}" if args.duration else "") + \
        (f" --rounds {args.rounds}" if args.rounds else "") + \
        (" --no-chromium" if args.no_chromium else "")
    text = "\n".join([
        "# Live view: the display loop with 0 and 3 viewers",
        "",
        f"Machine: {host_platform.machine()}, nproc {nproc}, other jobs may "
        f"share it (1/5/15-min load average at start {load0[0]:.2f} / {load0[1]:.2f} / "
        f"{load0[2]:.2f}; per run in the table); no GPU; Python "
        f"{host_platform.python_version()}.",
        f"Command: `{command}` ({rounds} round(s), {duration_s:g} s per run, settings "
        "alternating A B C D / D C B A). The whole agent runs in one process (sim platform "
        "at 1 kHz with a raster operator, sim ArrayTac on virtual CAN FD, in-process relay, "
        "a remote answering at 60 Hz with pressed frames so the live analysis works); "
        "viewers run in a child process on the same 2 cores.",
        "",
        "## Means over the rounds",
        "",
        format_table(summary, list(summary[0])),
        "",
        "## Every run",
        "",
        format_table([{k: r[k] for k in cols} for r in rows], cols),
        "",
        "rate = display loop iterations per second (target 1000); jitter = |period - 1 ms|; "
        "ratios are to the no-view run of the same round. viewer_hz_min = the slowest "
        "viewer's snapshots per second (the view publishes at 40 Hz; ws clients: messages "
        "read and JSON-parsed; chromium: messages the page handled and drew). "
        "snapshots_skipped = snapshots a viewer did not get because it was still busy with "
        "an earlier one (latest wins, nothing queues). view_cpu_pct = CPU time of the view "
        "server's thread (building, encoding and composing snapshots; thread CPU clock, so "
        "other processes' load does not count) in % of one core over the window; "
        "analysis_cpu_pct = the analysis process's CPU time (niced, reported at its runs) "
        "in % of one core. These two do not depend on the machine's load the way the loop's "
        "rate does.",
        "",
        "![periods](view.png)",
        ""])
    emit(text)
    if not args.no_write:
        RESULTS.mkdir(parents=True, exist_ok=True)
        (RESULTS / "view.md").write_text(text)
        _plot(RESULTS / "view.png", rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
