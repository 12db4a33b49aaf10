"""Stiffness benchmark (same as ``teletouch bench stiffness``).

Run from the repository root::

    python benchmarks/bench_stiffness.py            # the committed results
    python benchmarks/bench_stiffness.py --quick    # a short CI-like run

Writes ``benchmarks/results/stiffness.md`` and ``stiffness.png``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lab.bench import stiffness as bench_cli


def main() -> int:
    """Parse the options and run."""
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    bench_cli.configure_parser(parser)
    return bench_cli.run(parser.parse_args())


if __name__ == "__main__":
    sys.exit(main())
