"""The ``teletouch`` command: one console script, one subcommand per job.

Each subcommand lives in the package it belongs to, as a module exposing::

    def configure_parser(parser: argparse.ArgumentParser) -> None: ...
    def run(args: argparse.Namespace) -> int: ...

CLI modules are kept import-light (heavy imports happen inside ``run``) so that
``teletouch --help`` stays fast. ``teletouch bench NAME`` dispatches the same way.

The dispatcher sits in the lab, the top layer of the import graph, because it names every
package: the stations and the relay import only ``shared``, and ``shared`` imports none of them.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys
import threading
from collections.abc import Sequence

from shared import __version__
from shared.errors import TeleTouchError
from shared.sd_notify import process_notifier

__all__ = ["BENCHMARKS", "COMMANDS", "build_parser", "main"]

#: subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "relay": ("relay_server.cli", "run the cloud relay (WebSocket + TCP) with latency accounting"),
    "display": ("lab.display_cli", "ArrayTac display tools (characterize the simulator)"),
    "board": ("lab.board_cli", "run the emulated ArrayTac drive board as its own process "
              "(TCP, serial framing)"),
    "link": ("lab.linkemu_cli", "emulate a long-haul link (delay, jitter, loss, outages)"),
    "sensor": ("remote_site.sensor_cli", "calibrate a GelSight-style sensor; reconstruct heights"),
    "local": ("local_site.cli", "run the local haptic station (platform, ArrayTac, relay link)"),
    "remote": ("remote_site.cli", "run the remote palpation station (arm, sensor, tactile frames)"),
    "demo": ("lab.demo.cli", "run relay + both stations on this machine and report"),
    "check": ("lab.check_cli", "probe a station's devices before a session (local|remote)"),
    "replay": ("lab.replay_cli", "play an MCAP recording back (or --summary of it)"),
    "report": ("lab.report_cli", "write a self-contained HTML report of a recording"),
}

#: ``teletouch bench NAME`` -> (module, one-line help)
BENCHMARKS: dict[str, tuple[str, str]] = {
    "relay": ("lab.bench.relay", "relay added latency vs direct WebSocket, and throughput"),
    "palpation": ("lab.bench.palpation", "tumor detection/localization/typing/ranking over "
                  "random phantoms and link profiles, with motion-to-touch latency"),
    "reconstruction": ("lab.bench.reconstruction", "height-map time vs error"),
    "stiffness": ("lab.bench.stiffness", "stiffness error vs noise/samples, time"),
    "fuzz": ("lab.bench.fuzz", "fuzz the decoder, session cores and relay (atheris and a "
             "mutation engine; real-socket smoke)"),
    "load": ("lab.bench.load", "realistic sessions stepped up until the relay's added p99 "
             "exceeds 5 ms; soak"),
    "relay-cpu": ("lab.bench.relay_cpu", "relay CPU per 1,000 forwarded messages per stream, "
                  "this tree against another revision, same run"),
    "nats-hop": ("lab.bench.nats_hop", "what a NATS hop between relay workers adds to a 19 kB "
                 "frame"),
    "tactile-codec": ("lab.bench.tactile_codec", "compact tactile codec: bytes/s vs rendered "
                      "height error over deadband settings"),
    "cpu": ("lab.bench.cpu", "demo CPU per process, thread and stage (py-spy), sim kept apart"),
    "faults": ("lab.bench.faults", "fault suite with real processes: relay kills, outages, "
               "SIGKILL/SIGSTOP, clock steps, CPU load; halt/safe/recovery/stale figures"),
}

log = logging.getLogger(__name__)


def _add_module_parser(sub: argparse._SubParsersAction, name: str, module: str, help_: str) -> None:
    mod = importlib.import_module(module)
    parser = sub.add_parser(name, help=help_, description=(mod.__doc__ or help_).strip(),
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    mod.configure_parser(parser)
    parser.set_defaults(_run=mod.run)


def build_parser() -> argparse.ArgumentParser:
    """Build the full argument parser (imports each subcommand's light CLI module)."""
    parser = argparse.ArgumentParser(
        prog="teletouch",
        description="Tele-Touch: remote palpation with the ArrayTac pin display.",
    )
    parser.add_argument("--version", action="version", version=f"teletouch {__version__}")
    parser.add_argument("--log-level", default="INFO",
                        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                        help="logging level (default: INFO)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_) in COMMANDS.items():
        _add_module_parser(sub, name, module, help_)
    if BENCHMARKS:
        bench = sub.add_parser("bench", help="run a benchmark (time against error, latency)",
                               description="Benchmarks; results tables go to benchmarks/results/.")
        bench_sub = bench.add_subparsers(dest="benchmark", metavar="BENCHMARK")
        for name, (module, help_) in BENCHMARKS.items():
            _add_module_parser(bench_sub, name, module, help_)
    return parser


def _ctrl_c_stops() -> None:
    """Make SIGINT (Ctrl-C) raise KeyboardInterrupt here even when it came in ignored.

    A process started in the background by a shell without job control (``cmd &`` in a
    script, a CI step, a test runner started that way) inherits SIGINT *ignored*, and
    Python then installs no KeyboardInterrupt handler: ``teletouch replay --view`` and the
    demo, which stop cleanly on KeyboardInterrupt, ignored Ctrl-C and ran on until killed
    (issue 9: a two-burner test run started in the background). Ctrl-C is how these
    commands are ended (the asyncio stations and the relay take it with their own signal
    handlers, which override an inherited ignore as well), so it always stops them.
    """
    if threading.current_thread() is threading.main_thread() \
            and signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        log.debug("SIGINT came in ignored; Ctrl-C stops this command all the same")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``teletouch`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    run = getattr(args, "_run", None)
    if run is None:
        parser.print_help(sys.stderr)
        return 2
    # systemd's variables (Type=notify), taken out of the environment before any thread or
    # child starts: only this process speaks for its unit (shared/sd_notify.py)
    process_notifier()
    _ctrl_c_stops()
    try:
        return int(run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except TeleTouchError as err:
        log.error("%s: %s", type(err).__name__, err)
        return 1


if __name__ == "__main__":
    sys.exit(main())
