"""Check a station's devices before a session: ``teletouch check local|remote``.

Each device is opened through the station's own registry, exercised briefly within bounded
times, and closed again; one line per device says whether it works and, if not, what to fix
(could not open -> cable/port/permissions; opened but silent -> power, wiring, bus/baud).

  local   the XYZ encoder board (sample rate over ~1 s, position and counts; with --push-s N
          you are asked to push the platform and the counts must move) and the ArrayTac
          drive board (feedback rate, safe state, a zero command echoed, watchdog trips)
  remote  the arm (connects, pose, force, status; no motion unless --move) and the camera
          (frame rate over ~1 s, frame size and dtype; with --calibration, whether it
          matches the calibration's frame size and pixel pitch)

Exit code: 0 all devices good, 1 a device failed, 2 usage error. --json prints one JSON
object with one entry per device. Time bounds: [check] in --config, TELETOUCH_CHECK_<FIELD>
(connect_timeout_s, read_timeout_s, rate_window_s, move_mm, move_timeout_s), or --timeout-s.

examples:
  teletouch check local --platform /dev/ttyUSB0 --display can://socketcan/can0 --push-s 5
  teletouch check remote --arm franka --sensor 0 --calibration gsmini_calib.npz --json
  teletouch check local --platform sim --display sim
"""

from __future__ import annotations

import argparse
import sys

__all__ = ["configure_parser", "run"]


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="TOML file with a [check] table (time bounds)")
    parser.add_argument("--timeout-s", dest="timeout_s", type=float, metavar="S",
                        help="connect timeout of every device (default 3 s)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object, one entry per device")


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add ``check local`` and ``check remote``."""
    sub = parser.add_subparsers(dest="check_station", metavar="STATION", required=True)
    local = sub.add_parser("local", help="the encoder board and the ArrayTac drive board",
                           description="Probe the local station's platform and display.")
    local.add_argument("--platform", required=True,
                       help="platform spec: sim, /dev/ttyUSB0, socket://host:port, ...")
    local.add_argument("--display", required=True,
                       help="display spec: sim, can://socketcan/can0, /dev/ttyACM0, ...")
    local.add_argument("--push-s", dest="push_s", type=float, default=0.0, metavar="N",
                       help="ask the operator to push the platform for N s; the counts must "
                            "move (default 0: not asked)")
    local.add_argument("--watchdog-ms", dest="watchdog_ms", type=int, default=100,
                       help="drive-board watchdog to configure and check (default 100)")
    local.add_argument("--feedback-timeout-s", dest="feedback_timeout_s", type=float,
                       metavar="S", help="the drive board counts as lost after S s without "
                       "feedback: as the station's local.agent.display_feedback_timeout_s, "
                       "for a board set to feed back slower (default 0.2, at most 10)")
    _common(local)
    remote = sub.add_parser("remote", help="the arm and the tactile camera",
                            description="Probe the remote station's arm and sensor.")
    remote.add_argument("--arm", required=True, help="arm backend: sim, franka, module:Class")
    remote.add_argument("--sensor", required=True,
                        help="sensor: sim, camera, or a camera index / URL / video file")
    remote.add_argument("--calibration", metavar="PATH.npz",
                        help="sensor calibration to check the frames against")
    remote.add_argument("--move", action="store_true",
                        help="lift the pad move_mm (default 2 mm) and bring it back; "
                             "without it the arm never moves")
    _common(remote)


def run(args: argparse.Namespace) -> int:
    """Probe the chosen station's devices; 0 all good, 1 a device failed, 2 usage."""
    from shared.config import resolve_config
    from shared.device_check import EXIT_USAGE, CheckSettings
    from shared.errors import ConfigError
    from shared.report import emit, emit_json

    explicit = {} if args.timeout_s is None else {"connect_timeout_s": args.timeout_s}
    try:
        settings = resolve_config(CheckSettings, "check", explicit=explicit,
                                  toml_path=args.config)
    except ConfigError as err:
        emit(f"teletouch check: {err}", stream=sys.stderr)
        return EXIT_USAGE
    if args.check_station == "local":
        from local_site.agent.config import MAX_FEEDBACK_TIMEOUT_S

        feedback_s = args.feedback_timeout_s
        if args.push_s < 0 or not 1 <= args.watchdog_ms <= 0xFFFF or (
                feedback_s is not None and not 0 < feedback_s <= MAX_FEEDBACK_TIMEOUT_S):
            emit("teletouch check local: --push-s must be >= 0, --watchdog-ms in "
                 f"[1, 65535] and --feedback-timeout-s in (0, {MAX_FEEDBACK_TIMEOUT_S:g}]",
                 stream=sys.stderr)
            return EXIT_USAGE
        from local_site.check import check_local

        report = check_local(args.platform, args.display, settings, push_s=args.push_s,
                             notify=lambda text: emit(text, stream=sys.stderr),
                             watchdog_ms=args.watchdog_ms, feedback_timeout_s=feedback_s)
    else:
        from remote_site.check import check_remote

        report = check_remote(args.arm, args.sensor, settings, move=args.move,
                              calibration=args.calibration)
    if args.json:
        emit_json(report.to_dict())
    else:
        emit(report.to_text())
    return report.exit_code
