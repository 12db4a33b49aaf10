"""``teletouch bench stiffness``: stiffness error against noise and samples per estimator,
with time per estimate, the loading-only saving, and the contact model's frame rate.

Writes ``benchmarks/results/stiffness.md`` and ``stiffness.png`` (``--out-dir`` to change).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DEFAULT_OUT = Path(__file__).resolve().parents[2] / "benchmarks" / "results"


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the benchmark's options."""
    parser.add_argument("--quick", action="store_true", help="short run (20 presses per cell)")
    parser.add_argument("--trials", type=int, default=None, help="presses per cell (default 100)")
    parser.add_argument("--out-dir", type=Path, default=DEFAULT_OUT, help="results directory")
    parser.add_argument("--seed", type=int, default=0)


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and print the Markdown report."""
    from lab.bench.stiffness_impl import BenchSettings, run_benchmark
    from shared.report import emit

    trials = args.trials or (20 if args.quick else 100)
    settings = BenchSettings(trials=trials, frames=50 if args.quick else 200, seed=args.seed)
    command = " ".join(["teletouch bench stiffness", *sys.argv[3:]]) if sys.argv[1:2] == [
        "bench"] else " ".join(["python", *sys.argv])
    run_benchmark(settings, args.out_dir, command)
    emit((args.out_dir / "stiffness.md").read_text())
    return 0
