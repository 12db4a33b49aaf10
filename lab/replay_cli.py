"""Play a Tele-Touch MCAP recording back, or summarise it.

  teletouch replay run.mcap                 # real time into the simulated ArrayTac display
  teletouch replay run.mcap --speed 4       # four times faster
  teletouch replay run.mcap --summary       # streams, counts, rates, duration, latency per hop

A local station's recording drives the local station's display path (scene, safety rules,
renderer, display driver); any recording is published message by message to subscribers
(lab.replay.Replayer.subscribe). A file cut short (killed station) plays up to its last
complete chunk.
"""

from __future__ import annotations

import argparse

__all__ = ["configure_parser", "run"]


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


def run(args: argparse.Namespace) -> int:
    """Replay or summarise; 0 on success (errors name what is wrong with the file)."""
    from lab.replay import Replayer, format_summary, summarize
    from shared.recording import read_mcap
    from shared.report import emit, emit_json

    recording = read_mcap(args.file)
    if args.summary:
        summary = summarize(recording)
        if args.json:
            emit_json(summary)
        else:
            emit(format_summary(summary))
        return 0
    result = Replayer(recording, speed=args.speed, display=args.display).run()
    if args.json:
        emit_json(result.__dict__)
    else:
        d = result.display
        shown = (f"; display: {d['frames_accepted']} frames accepted, {d['frames_rendered']} "
                 f"rendered, {d['commands_sent']} pin commands" if d else "")
        emit(f"replayed {result.published} messages of {recording.station} "
             f"({result.recorded_duration_s:.2f} s recorded) in {result.duration_s:.2f} s"
             + shown)
    return 0
