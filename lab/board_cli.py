"""Run the emulated ArrayTac drive board as a process of its own, behind a TCP port.

The board (firmware + physics plant, ``local_site/display``) listens on ``--listen`` and
speaks the serial framing of the ArrayTac link (docs/arraytac_can.md, §Serial); the local
station reaches it with its ordinary serial driver through a pyserial URL:

  teletouch board --listen 127.0.0.1:7700 --events board-events.txt
  teletouch local --display socket://127.0.0.1:7700 ...

The board outlives the station: a station that is stopped, killed or restarted leaves the
pins to the board's own link-loss watchdog (the ``watchdog_ms`` the station writes into every
command frame), and a restarted station connects again (a new connection replaces the old
one). ``--events FILE`` records what the pins do, stamped with the host's monotonic clock:
``S mono reason`` (safe state entered: watchdog, safe_state_frame, fault), ``U mono`` (left),
``R mono seq`` (command applied). The fault suite runs the local station against this process
(``teletouch bench faults --board-process``).
"""

from __future__ import annotations

import argparse

__all__ = ["configure_parser", "run"]


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Flags of ``teletouch board``."""
    parser.add_argument("--listen", metavar="HOST:PORT", default="127.0.0.1:0",
                        help="where the board listens (default 127.0.0.1:0 = a free port, "
                             "printed at start); any peer that connects commands the pins")
    parser.add_argument("--events", metavar="FILE", default=None,
                        help="append the pins' events (S/U/R lines) to FILE")
    parser.add_argument("--summary-json", metavar="FILE", default=None,
                        help="write the board's counters to FILE at exit")
    parser.add_argument("--watchdog-ms", type=int, default=100,
                        help="the firmware's watchdog when a command frame carries 0 "
                             "(the station writes its own into every frame; default 100)")
    parser.add_argument("--feedback-rate-hz", type=float, default=500.0,
                        help="feedback frames per second (default 500)")
    parser.add_argument("--tick-ms", type=float, default=2.0,
                        help="plant / watchdog / feedback tick (default 2)")
    parser.add_argument("--nice", type=int, default=0, metavar="N",
                        help="add N to the process's niceness (negative: higher priority, "
                             "needs the privilege; refused -> a warning, normal priority). A "
                             "real board has its own MCU: no host load delays its watchdog; "
                             "the fault suite runs this emulator at -10 to come closer")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stop after S seconds (default: until SIGTERM / Ctrl-C)")


def run(args: argparse.Namespace) -> int:
    """Run the board until SIGTERM, Ctrl-C or ``--duration``."""
    import json
    import logging
    import os
    import signal
    import threading
    from pathlib import Path

    from lab.board import run_board
    from lab.linkemu_cli import parse_host_port
    from shared.errors import ConfigError
    from shared.report import emit

    log = logging.getLogger("lab.board")
    host, port = parse_host_port(args.listen)
    if not 1 <= args.watchdog_ms <= 0xFFFF:
        raise ConfigError(f"--watchdog-ms must be in [1, 65535], got {args.watchdog_ms}")
    if not args.feedback_rate_hz > 0 or not args.tick_ms > 0:
        raise ConfigError("--feedback-rate-hz and --tick-ms must be > 0")
    if host not in ("127.0.0.1", "localhost", "::1"):
        log.warning("the emulated board listens on %s: any peer that connects commands the "
                    "pins", host)
    niceness = os.nice(0)
    if args.nice:
        try:
            niceness = os.nice(args.nice)
        except OSError as err:
            log.warning("cannot change the board's niceness by %d (%s): normal priority, host "
                        "load may delay its watchdog", args.nice, err)
    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    if args.duration is not None:
        timer = threading.Timer(args.duration, stop.set)
        timer.daemon = True
        timer.start()

    def ready(url: str) -> None:
        log.info("board listening on %s", url)
        emit(f"board listening on {url}")

    summary = run_board(stop, host=host, port=port,
                        events_path=Path(args.events) if args.events else None,
                        default_watchdog_ms=args.watchdog_ms,
                        feedback_rate_hz=args.feedback_rate_hz, tick_s=args.tick_ms / 1000.0,
                        on_ready=ready)
    summary["niceness"] = niceness
    if args.summary_json:
        Path(args.summary_json).write_text(json.dumps(summary, indent=1) + "\n")
    log.info("board stopped: %s", json.dumps(summary))
    return 1 if summary["error"] else 0
