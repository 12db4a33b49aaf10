"""Benchmark the relay: latency it adds over a direct WebSocket path, and throughput.

How it measures (one run, one machine):

* The relay runs as a separate process (``python -m lab.cli relay``) so the load
  generator (this process, one asyncio loop) does not share its event loop.
* **Latency.** N sessions, each with a local and a remote WebSocket station sending
  ``platform_state`` / ``arm_state`` at ``rate_hz`` per direction on a drift-free
  schedule; the receiver computes ``now_us() - ts_us`` (same host, same clock). The
  **direct** path sends the same traffic over one WebSocket connection between the two
  stations (a server in this process), with no relay. *Added latency* = relay percentile
  minus direct percentile. The relay's own ``relay_in -> relay_out`` residence (from
  ``/status``) is reported too.
* **Throughput.** K sessions over raw TCP; each local sends ``arm_command`` (ordered, never
  dropped) with at most ``window`` messages in flight per session; receivers count the
  frames. Forwarded messages per second = frames received by all receivers / time.
"""

from __future__ import annotations

import argparse

__all__ = ["configure_parser", "run", "run_benchmark"]


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Flags of ``teletouch bench relay``."""
    parser.add_argument("--quick", action="store_true", help="short run (CI)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--duration-s", type=float, default=None,
                        help="seconds per latency phase (default 5, quick 1.5)")
    parser.add_argument("--sessions", type=int, nargs="+", default=[1, 20],
                        help="concurrent session counts for the latency phases")
    parser.add_argument("--rate-hz", type=float, default=1000.0,
                        help="messages per second per direction per session")
    parser.add_argument("--write-results", metavar="DIR", default=None,
                        help="write relay.md and relay.png to DIR")


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and report."""
    import asyncio

    from lab.bench.relay_impl import report, run_benchmark_async

    duration_s = args.duration_s or (1.5 if args.quick else 5.0)
    results = asyncio.run(run_benchmark_async(
        sessions=args.sessions, rate_hz=args.rate_hz, duration_s=duration_s,
        throughput_s=1.5 if args.quick else 4.0, quick=args.quick))
    report(results, as_json=args.json, out_dir=args.write_results, argv=_argv(args))
    return 0


def _argv(args: argparse.Namespace) -> str:
    parts = ["teletouch bench relay"]
    if args.quick:
        parts.append("--quick")
    if args.duration_s:
        parts.append(f"--duration-s {args.duration_s:g}")
    if args.sessions != [1, 20]:
        parts.append("--sessions " + " ".join(map(str, args.sessions)))
    if args.write_results:
        import os

        parts.append(f"--write-results {os.path.relpath(args.write_results)}")
    return " ".join(parts)


def run_benchmark(**kwargs: object) -> dict[str, object]:
    """Programmatic entry (see :func:`lab.bench.relay_impl.run_benchmark_async`)."""
    import asyncio

    from lab.bench.relay_impl import run_benchmark_async

    return asyncio.run(run_benchmark_async(**kwargs))  # type: ignore[arg-type]
