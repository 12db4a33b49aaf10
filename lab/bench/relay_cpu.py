"""Relay CPU per forwarded message, this tree's relay against another revision's, same run.

How it measures (one machine; see :mod:`lab.bench.load` for the traffic and the generators):

* **Streams apart and together.** For each *mix* (``platform_state`` alone, ``arm_state``
  alone, ``tactile_frame`` alone, then all three: the realistic session of the load
  benchmark) N sessions send at the load benchmark's rates for ``--step-s`` seconds after a
  1 s warm-up. The relay's CPU seconds (user + system, every process of it, from ``/proc``)
  over the measured window are divided by the messages the receiving stations got in that
  window: **CPU ms per 1,000 forwarded messages**. Everything the relay process spends is
  charged (its reads, decode and validation, routing and books, writes and their system
  calls, its clock pings and ``stats``).
* **Before and after in the same run.** ``--baseline-rev REV`` extracts that revision of this
  repository (``git archive``) into a temporary directory and runs *its* relay with the same
  interpreter and libraries; in each round both relays run, and each mix runs on one then
  the other (seconds apart, the order alternating), with the same traffic. The machine is
  shared and its load changes by the minute, so the figure to trust is the **ratio**
  new/old of each round (its median over the rounds is reported, with the spread), not the
  absolute milliseconds.
* Results go to ``relay_cpu.md`` and ``relay_cpu.json`` with ``--write-results DIR``.
"""

from __future__ import annotations

import argparse

__all__ = ["configure_parser", "run"]

MIXES = ("platform_state", "arm_state", "tactile_frame", "all")


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Flags of ``teletouch bench relay-cpu``."""
    parser.add_argument("--baseline-rev", default=None, metavar="REV",
                        help="git revision whose relay to compare with (e.g. main); "
                             "without it only this tree's relay is measured")
    parser.add_argument("--sessions", type=int, default=5, help="sessions (default 5)")
    parser.add_argument("--step-s", type=float, default=5.0,
                        help="measured seconds per mix (default 5)")
    parser.add_argument("--rounds", type=int, default=3,
                        help="rounds; each runs every relay once (default 3)")
    parser.add_argument("--mixes", nargs="+", choices=MIXES, default=list(MIXES),
                        help="stream mixes to run (default: each stream alone, then all)")
    parser.add_argument("--transport", choices=("ws", "tcp"), default="ws",
                        help="how the stations connect (default ws)")
    parser.add_argument("--generators", type=int, default=3,
                        help="load generator processes (default 3)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--write-results", metavar="DIR", default=None,
                        help="write relay_cpu.md and relay_cpu.json to DIR")


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and report."""
    from lab.bench.relay_cpu_impl import CpuSettings, report, run_relay_cpu
    from shared.errors import ConfigError

    if args.sessions < 1 or args.rounds < 1 or args.step_s <= 0:
        raise ConfigError("--sessions and --rounds must be >= 1 and --step-s > 0")
    settings = CpuSettings(baseline_rev=args.baseline_rev, sessions=args.sessions,
                           step_s=args.step_s, rounds=args.rounds, mixes=tuple(args.mixes),
                           generators=args.generators, transport=args.transport)
    results = run_relay_cpu(settings)
    argv = " ".join(["teletouch bench relay-cpu",
                     *([f"--baseline-rev {args.baseline_rev}"] if args.baseline_rev else []),
                     f"--sessions {args.sessions} --step-s {args.step_s:g} "
                     f"--rounds {args.rounds}",
                     *([f"--mixes {' '.join(args.mixes)}"] if tuple(args.mixes) != MIXES
                       else []),
                     *([f"--transport {args.transport}"] if args.transport != "ws" else [])])
    report(results, as_json=args.json, out_dir=args.write_results, argv=argv)
    return 0
