"""Reconstruction benchmark: time per frame against height error (glue for ``teletouch bench``).

Runs ``benchmarks/bench_reconstruction.py`` of the source tree: resolutions (full, 1/2,
1/4, display pitch), models (LUT baseline vs position-aware polynomial), Poisson solvers
(DCT, DST, FFT), on simulated presses and on the real GelSight Mini recordings; writes
``benchmarks/results/reconstruction.md`` and ``.png``.
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

__all__ = ["configure_parser", "run"]

_SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_reconstruction.py"


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Benchmark options (shared with ``python benchmarks/bench_reconstruction.py``)."""
    parser.add_argument("--quick", action="store_true", help="short run (fewer repeats)")
    parser.add_argument("--data", default=None,
                        help="gsmini_ball_9.47mm directory (default: the team kit's copy)")
    parser.add_argument("--out-dir", default=None,
                        help="where reconstruction.md/.png go (default benchmarks/results)")


def run(args: argparse.Namespace) -> int:
    """Run the benchmark script with single-threaded BLAS (the one-core target)."""
    import os
    import subprocess
    import sys

    from shared.errors import ConfigError

    if not _SCRIPT.is_file():
        raise ConfigError(f"benchmark script not found: {_SCRIPT} (needs a source checkout)")
    if os.environ.get("OPENBLAS_NUM_THREADS") != "1":
        # BLAS threads are fixed at import; on a shared 2-core machine they are 5x slower.
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
        argv = [sys.executable, str(_SCRIPT)]
        argv += ["--quick"] if args.quick else []
        argv += ["--data", args.data] if args.data else []
        argv += ["--out-dir", args.out_dir] if args.out_dir else []
        return subprocess.run(argv, env=env, check=False).returncode
    spec = importlib.util.spec_from_file_location("bench_reconstruction", _SCRIPT)
    if spec is None or spec.loader is None:
        raise ConfigError(f"cannot load {_SCRIPT}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return int(module.main(args))
