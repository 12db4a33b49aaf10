"""Relay benchmark: writes benchmarks/results/relay.md and relay.png.

Same as ``teletouch bench relay --write-results benchmarks/results`` (see
:mod:`lab.bench.relay` for how latency and throughput are measured). Usage::

    python benchmarks/bench_relay.py            # default run (~40 s)
    python benchmarks/bench_relay.py --quick    # short run
"""

from __future__ import annotations

import sys
from pathlib import Path

from lab.cli import main

if __name__ == "__main__":
    results = Path(__file__).resolve().parent / "results"
    sys.exit(main(["bench", "relay", "--write-results", str(results), *sys.argv[1:]]))
