"""Run the whole Tele-Touch system on this machine: relay, remote and local stations.

Starts `teletouch relay`, `teletouch remote` (simulated arm, GelSight-style sensor and a
tissue phantom) and `teletouch local` (simulated XYZ platform driven by a scripted operator,
simulated ArrayTac display) as separate processes over real sockets, optionally through the
link emulator, then reports the tumors found in what reached the local station against the
phantom's ground truth, and the motion-to-touch latency ledger.

examples:
  teletouch demo
  teletouch demo --scene severity --seed 3 --link city-1000km
  teletouch demo --headless --json > report.json
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from lab.demo import DEFAULT_DISPLAY, DEFAULT_FRAME_RATE_HZ

__all__ = ["configure_parser", "format_report", "run"]

SCENES = ("breast", "severity", "localization")
LINKS = ("lan", "city-1000km", "intercontinental", "bad-wifi")


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the demo's flags."""
    parser.add_argument("--scene", choices=SCENES, default="breast",
                        help="phantom scene (default breast: one benign, one malignant tumor)")
    parser.add_argument("--phantom", metavar="FILE.toml", default=None,
                        help="a phantom file instead of --scene (docs/phantoms.md)")
    parser.add_argument("--seed", type=int, default=0, help="phantom placement seed (default 0)")
    parser.add_argument("--ideal", action="store_true",
                        help="noise-free simulated world (default: realistic noise and an "
                             "unknown arm <-> phantom registration error per seed)")
    parser.add_argument("--no-register", dest="register", action="store_false",
                        help="skip the fiducial registration before palpation")
    parser.add_argument("--link", choices=LINKS, default=None,
                        help="put the link emulator with this profile between the stations "
                             "and the relay (default: direct)")
    parser.add_argument("--motion", default=None,
                        help="scripted operator spec for the simulated platform "
                             "(default: a 3 mm-spaced raster, pressed 3 mm into the phantom)")
    parser.add_argument("--platform", choices=("sim", "sim-process"), default="sim",
                        help="the simulated platform's board as a thread of the local "
                             "station (sim, default) or in a process of its own")
    parser.add_argument("--platform-process", action=argparse.BooleanOptionalAction,
                        default=False,
                        help="the local station reads its platform in a process of its own, "
                             "the newest sample in shared memory (default: off; "
                             "docs/speed.md section 13)")
    parser.add_argument("--render-loop", choices=("process", "thread", "asyncio"),
                        default="process",
                        help="where the local station runs its display loop: a process of "
                             "its own with the board link (default; the platform is then read "
                             "in a process of its own too), a thread, or an asyncio task "
                             "(docs/speed.md section 21)")
    parser.add_argument("--display", choices=("sim", "board-process"), default=DEFAULT_DISPLAY,
                        help="the emulated ArrayTac drive board as a process of its own "
                             "reached over socket:// (board-process, default), like a "
                             "separate board, or inside the local station on a virtual CAN "
                             "bus (sim)")
    parser.add_argument("--duration", type=float, default=100.0,
                        help="stop the operator after this many seconds (default 100)")
    parser.add_argument("--frame-rate-hz", type=float, default=DEFAULT_FRAME_RATE_HZ,
                        help=f"remote sensor frame rate (default {DEFAULT_FRAME_RATE_HZ:g})")
    parser.add_argument("--headless", action="store_true",
                        help="no live status line")
    parser.add_argument("--json", action="store_true",
                        help="print the report as one JSON object")
    parser.add_argument("--view", metavar="HOST:PORT", default="127.0.0.1:0",
                        help="the local station's live view in the browser (default "
                             "127.0.0.1 on a free port; the URL is printed)")
    parser.add_argument("--no-view", action="store_true", help="no live view")
    parser.add_argument("--workdir", default=None,
                        help="keep logs, recordings and summaries in this directory")
    parser.add_argument("--record", metavar="DIR", default=None,
                        help="write both stations' MCAP recordings, the ground truth and the "
                             "HTML report into DIR (default: the work directory, which is "
                             "deleted at the end unless --workdir names it)")


def _fmt(v: Any, digits: int = 2) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def format_report(report: dict[str, Any]) -> str:
    """The human-readable report."""
    loc = report["localization_error_mm"]
    lines = [
        f"Tele-Touch demo: scene {report['scene']} (seed {report['seed']}), link "
        f"{report['link']}, {report['elapsed_s']:.0f} s, {report['frames_received']} tactile "
        "frames received",
        f"  tumors found      {report['tumors_found']} / {report['tumors_expected']}"
        f" (false positives: {report['false_positives']})",
        f"  localization      mean {_fmt(loc['mean'])} mm, max {_fmt(loc['max'])} mm",
        f"  types correct     {report['types_correct']} / {report['types_total']}",
        f"  severity (tau)    {_fmt(report['kendall_tau'])}",
        "  per tumor:",
    ]
    reg = report.get("registration") or {}
    true, est = reg.get("true"), reg.get("estimated")
    if true:
        line = (f"  registration      true dx {true['dx_mm']:.2f} dy {true['dy_mm']:.2f} mm, "
                f"yaw {true['yaw_deg']:.2f} deg; ")
        line += (f"estimated dx {est['dx_mm']:.2f} dy {est['dy_mm']:.2f} mm, yaw "
                 f"{est['yaw_deg']:.2f} deg (+-{est['std_dx_mm']:.2f} mm, "
                 f"+-{est['std_yaw_deg']:.2f} deg)" if est else "not estimated")
        lines.insert(-1, line)
    for m in report["matches"]:
        lines.append(f"    {m['id']:<10} true {m['true_kind']:<9} found {m['found_kind']:<9} "
                     f"error {m['error_mm']:.2f} mm  rank true {m['true_severity_rank']} "
                     f"found {m['found_severity_rank']}")
    tail = report.get("latency_tail_ms") or {}
    shares = {stage: fig.get("share") for stage, fig in (tail.get("stages") or {}).items()}
    lines.append("  motion-to-touch latency (ms):        p50      p99      max  "
                 "share of the slowest 5 %")
    for stage, fig in report["latency_ms"].items():
        if isinstance(fig, dict):
            share = shares.get(stage)
            lines.append(f"    {stage:<32} {_fmt(fig.get('p50')):>7}  {_fmt(fig.get('p99')):>7}"
                         f"  {_fmt(fig.get('max')):>7}"
                         + ("" if share is None else f"  {100 * share:>5.0f} %"))
    if report.get("recordings"):
        lines.append(f"  recordings        {report['recordings']['local']}, "
                     f"{report['recordings']['remote']}")
    elif "recordings" in report:
        lines.append("  recordings        not kept (--record DIR keeps them)")
    lines.append(f"  report            {report.get('report_html') or 'not written (see log)'}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Run the demo and print its report."""
    from pathlib import Path

    from lab.demo.orchestrator import DEFAULT_MOTION, DemoConfig, run_demo
    from shared.report import StatusLine, emit, emit_json

    config = DemoConfig(scene=args.phantom or args.scene, seed=args.seed, ideal=args.ideal,
                        register=args.register,
                        link=args.link,
                        motion=args.motion or DEFAULT_MOTION, platform=args.platform,
                        platform_process=args.platform_process,
                        render_loop=args.render_loop, display=args.display,
                        max_duration_s=args.duration,
                        frame_rate_hz=args.frame_rate_hz,
                        workdir=Path(args.workdir) if args.workdir else None,
                        record_dir=Path(args.record) if args.record else None,
                        view=None if args.no_view else args.view)
    status = None if args.headless else StatusLine(min_interval_s=10.0)

    def progress(elapsed_s: float, relay: dict[str, Any] | None) -> None:
        if status is None:
            return
        status.update(f"demo {elapsed_s:5.1f} s | {_relay_line(relay)}")

    try:
        report = run_demo(config, progress,
                          lambda who, url: emit(f"live view ({who}): {url}",
                                                stream=sys.stderr))
    finally:
        if status is not None:
            status.close()
    if args.json:
        emit_json(report)
    else:
        emit(format_report(report))
    return 0


def _relay_line(relay: dict[str, Any] | None) -> str:
    """Messages forwarded each way and the relay's end-to-end delay estimates, live."""
    session = ((relay or {}).get("sessions") or {}).get("demo")
    if not session:
        return "waiting for both stations"
    fwd = session.get("forwarded", {})
    delay = session.get("delay_us", {})

    def e2e_ms(direction: str) -> str:
        p50 = delay.get(direction, {}).get("end_to_end", {}).get("p50")
        return "-" if p50 is None else f"{p50 / 1000:.1f} ms"

    return (f"platform states -> remote {fwd.get('local_to_remote', 0)} "
            f"(~{e2e_ms('local_to_remote')}), tactile frames -> local "
            f"{fwd.get('remote_to_local', 0)} (~{e2e_ms('remote_to_local')})")
