"""Play a Tele-Touch MCAP recording back, or summarise it.

  teletouch replay run.mcap                 # real time into the simulated ArrayTac display
  teletouch replay run.mcap --speed 4       # four times faster
  teletouch replay run.mcap --summary       # streams, counts, rates, duration, latency per hop
  teletouch replay run.mcap --view          # and in the live view (prints its URL)
  teletouch replay run.mcap --view 127.0.0.1:8790 --paused   # starts when you press play

A local station's recording drives the local station's display path (scene, safety rules,
renderer, display driver); any recording is published message by message to subscribers
(lab.replay.Replayer.subscribe). A file cut short (killed station) plays up to its last
complete chunk.

With --view the replay is shown in the live view a station serves (same page, labelled as a
replay, with play / pause and the position); the view stays up after the end until Ctrl-C
(--exit-at-end: not).
"""

from __future__ import annotations

import argparse
import logging
import threading
from typing import Any

__all__ = ["configure_parser", "run"]

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the replay arguments."""
    parser.add_argument("file", metavar="FILE.mcap", help="a recording (--record)")
    parser.add_argument("--speed", type=float, default=1.0,
                        help="playback speed, 2 = twice as fast (default 1)")
    parser.add_argument("--summary", action="store_true",
                        help="print streams, rates, duration and latency; do not play")
    parser.add_argument("--display", default="sim",
                        help="display of a local recording's replay: sim (default) or none")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.add_argument("--view", metavar="HOST:PORT", nargs="?", const="127.0.0.1:0",
                        help="show the replay in the live view (default address 127.0.0.1, "
                        "a free port; the URL is printed)")
    parser.add_argument("--paused", action="store_true",
                        help="with --view: wait for the page's play button before starting")
    parser.add_argument("--exit-at-end", action="store_true",
                        help="with --view: stop serving the view when the replay ends")
    parser.add_argument("--no-analysis", action="store_true",
                        help="with --view: do not re-run the palpation analysis")
    parser.add_argument("--view-allowed-host", dest="view_allowed_hosts", action="append",
                        default=[], metavar="NAME",
                        help="with --view: a host name the page may also be opened by (a "
                        "tunnel's or proxy's; besides IP addresses, localhost and the bound "
                        "name, which need none); repeatable. Any other name gets HTTP 403")


def run(args: argparse.Namespace) -> int:
    """Replay or summarise; 0 on success (errors name what is wrong with the file)."""
    from lab.replay import Replayer, format_summary, summarize
    from shared.errors import ConfigError
    from shared.recording import read_mcap
    from shared.report import emit, emit_json
    from shared.view import ViewServerConfig

    recording = read_mcap(args.file)
    if args.summary:
        summary = summarize(recording)
        if args.json:
            emit_json(summary)
        else:
            emit(format_summary(summary))
        return 0
    if args.view_allowed_hosts and not args.view:
        raise ConfigError("--view-allowed-host needs --view")
    view_config = (ViewServerConfig(allowed_hosts=tuple(args.view_allowed_hosts))
                   if args.view else None)  # a bad name refused before the replay opens
    replayer = Replayer(recording, speed=args.speed, display=args.display,
                        start_paused=bool(args.view and args.paused))
    if args.paused and not args.view:
        raise ConfigError("--paused needs --view (the page's play button starts the replay)")
    result = (_replay_with_view(replayer, args, view_config) if view_config is not None
              else replayer.run())
    if args.json:
        emit_json(result.__dict__)
    else:
        d = result.display
        shown = (f"; display: {d['frames_accepted']} frames accepted, {d['frames_rendered']} "
                 f"rendered, {d['commands_sent']} pin commands" if d else "")
        emit(f"replayed {result.published} messages of {recording.station} "
             f"({result.recorded_duration_s:.2f} s recorded) in {result.duration_s:.2f} s"
             + shown + (f"; {result.undecodable} messages did not decode (skipped)"
                        if result.undecodable else ""))
    return 0


def _replay_with_view(replayer: Any, args: argparse.Namespace, config: Any) -> Any:
    """Serve the live view of the replay while it plays (and after, until Ctrl-C)."""
    import sys

    from lab.replay import ReplayResult
    from lab.replay_view import ReplayViewSource
    from local_site.view.analysis import LiveAnalysisConfig
    from shared.report import emit
    from shared.view import ViewServer, parse_view_address

    address = parse_view_address(args.view)
    if not address.is_loopback:
        log.warning("the replay's view listens on %s, not on loopback: whoever reaches it "
                    "sees this recording (no token; see docs/view.md)", address.host)
    source = ReplayViewSource(replayer, None if args.no_analysis else LiveAnalysisConfig())
    server = ViewServer(source, config, control=source.control)
    stop = threading.Event()
    try:
        port = server.start_thread(address.host, address.port)
        host = f"[{address.host}]" if ":" in address.host else address.host
        emit(f"replay view: http://{host}:{port}/", stream=sys.stderr)
        if args.paused:
            emit("replay paused: press play on the page to start", stream=sys.stderr)
        result = ReplayResult()
        try:
            result = replayer.run(stop)
            if not args.exit_at_end:
                emit("replay ended; the view stays up until Ctrl-C", stream=sys.stderr)
                while not stop.wait(3600.0):
                    pass
        except KeyboardInterrupt:  # the way to end a replay shown in the view
            stop.set()
        return result
    finally:
        server.stop_thread()
        source.close()
