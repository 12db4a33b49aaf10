"""What the NATS hop adds: one session's 19 kB tactile frames through one relay worker, and
through two workers joined by a local nats-server.

Two relay processes (``teletouch relay --workers 1 --nats URL``, as on two hosts) share one
``nats-server``. Phase *same*: both stations on worker A (no NATS hop). Phase *cross*: the
local station on A, the remote on B. The remote sends ``tactile_frame`` (19.4 kB) at
``--rate-hz``, alternating the two phases in rounds so load changes on the shared machine hit
both alike. Per frame, from the stamps it arrives with: added = ``relay_out - ts`` (as in
``teletouch bench load``) and the NATS leg ``nats_in - nats_out``. The hop's cost = cross
minus same, at p50 and p99.

Each round also sends the frame's size with no relay on the path (:mod:`lab.bench.nats_floor`):
over a plain TCP socket, and through the nats-server with a minimal protocol client and with
nats-py. The minimal client's one-way time is the least a cross-worker hop can cost on the
machine.
"""

from __future__ import annotations

import argparse

__all__ = ["configure_parser", "run"]


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Flags of ``teletouch bench nats-hop``."""
    parser.add_argument("--quick", action="store_true", help="short run")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--rate-hz", type=float, default=100.0, help="tactile frames per s")
    parser.add_argument("--rounds", type=int, default=None,
                        help="same/cross rounds (default 6, quick 2)")
    parser.add_argument("--round-s", type=float, default=5.0, help="seconds per phase")
    parser.add_argument("--write-results", metavar="DIR", default=None,
                        help="write nats_hop.md to DIR")


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and report."""
    import asyncio
    import math

    from lab.bench.nats_hop_impl import report, run_nats_hop
    from shared.errors import ConfigError

    rounds = args.rounds if args.rounds is not None else (2 if args.quick else 6)
    if rounds < 1:
        raise ConfigError(f"--rounds must be at least 1, got {rounds}")
    for flag, value in (("--rate-hz", args.rate_hz), ("--round-s", args.round_s)):
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"{flag} must be a positive number, got {value}")
    results = asyncio.run(run_nats_hop(rate_hz=args.rate_hz, rounds=rounds,
                                       round_s=args.round_s))
    argv = "teletouch bench nats-hop" + (" --quick" if args.quick else "") + (
        f" --rounds {args.rounds}" if args.rounds else "")
    report(results, as_json=args.json, out_dir=args.write_results, argv=argv)
    return 0
