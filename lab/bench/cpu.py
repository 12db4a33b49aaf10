"""``teletouch bench cpu``: CPU seconds per wall second of the demo, per process, thread and
stage, with py-spy's top functions; simulated hardware kept apart from the product's code.

Each run is saved as ``benchmarks/results/cpu-<label>.json``; ``cpu.md`` and ``cpu.png`` are
rebuilt from every saved run, side by side (e.g. ``--label before`` then ``--label after``).
See :mod:`lab.bench.cpu_impl` for the method.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lab.demo import DEFAULT_DISPLAY

DEFAULT_OUT = Path(__file__).resolve().parents[2] / "benchmarks" / "results"


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the benchmark's options."""
    parser.add_argument("--label", default="run", help="name of this run (default: run)")
    parser.add_argument("--scene", default="breast")
    parser.add_argument("--link", default=None, help="link-emulator profile (default: none)")
    parser.add_argument("--warmup-s", type=float, default=3.0)
    parser.add_argument("--window-s", type=float, default=12.0,
                        help="measured window (the default operator runs about 25 s)")
    parser.add_argument("--rate-hz", type=int, default=200, help="py-spy sampling rate")
    parser.add_argument("--display", choices=("sim", "board-process"),
                        default=DEFAULT_DISPLAY,
                        help="the demo's drive board (see `teletouch demo --display`; "
                             f"default {DEFAULT_DISPLAY})")
    parser.add_argument("--no-profile", action="store_true",
                        help="per-process figures only (no py-spy)")
    parser.add_argument("--local-arg", action="append", default=[],
                        help="extra flag for `teletouch local` (repeat)")
    parser.add_argument("--remote-arg", action="append", default=[],
                        help="extra flag for `teletouch remote` (repeat)")
    parser.add_argument("--keep-record", type=Path, default=None,
                        help="copy the local station's recording (local.mcap) here")
    parser.add_argument("--note", default="", help="a note saved with the run")
    parser.add_argument("--out-dir", type=Path, default=DEFAULT_OUT, help="results directory")
    parser.add_argument("--report-only", action="store_true",
                        help="rebuild cpu.md/cpu.png from saved runs without running")


def run(args: argparse.Namespace) -> int:
    """Run the benchmark, save the run, rebuild the report and print it."""
    import json
    import re

    from lab.bench.cpu_impl import CpuBenchSettings, run_cpu_bench, to_json
    from lab.bench.cpu_report import write_report
    from shared.errors import ConfigError
    from shared.report import emit

    if not re.fullmatch(r"[A-Za-z0-9_.-]{1,40}", args.label):
        raise ConfigError("--label must be 1-40 characters of A-Z a-z 0-9 _ . -")
    args.out_dir.mkdir(parents=True, exist_ok=True)
    if not args.report_only:
        settings = CpuBenchSettings(scene=args.scene, link=args.link, warmup_s=args.warmup_s,
                                    window_s=args.window_s, rate_hz=args.rate_hz,
                                    profile=not args.no_profile, keep_record=args.keep_record,
                                    display=args.display,
                                    extra_local_args=tuple(args.local_arg),
                                    extra_remote_args=tuple(args.remote_arg))
        figures = run_cpu_bench(settings)
        figures["label"] = args.label
        figures["note"] = args.note
        figures["command"] = " ".join(["teletouch bench cpu", *sys.argv[3:]]) \
            if sys.argv[1:2] == ["bench"] else " ".join(["python", *sys.argv])
        (args.out_dir / f"cpu-{args.label}.json").write_text(to_json(figures))
    runs = [json.loads(p.read_text()) for p in sorted(args.out_dir.glob("cpu-*.json"))]
    write_report(runs, args.out_dir)
    emit((args.out_dir / "cpu.md").read_text())
    return 0
