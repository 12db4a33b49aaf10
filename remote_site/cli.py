"""Run the remote palpation station: follow the operator's platform, stream what the probe feels.

Platform states from the relay drive the arm (workspace map, 100 ms stale-command drop,
halt after 100 ms without commands or on link loss, force limit, workspace clamp); every
sensor frame is reconstructed with the calibration at the display's pitch and sent as a
tactile frame with stiffness layers; arm state goes out at 50 Hz. SIGTERM / SIGINT stop
cleanly (arm halted) and write --summary-json.

With --phantom SCENE --seed N the simulated arm and sensor act on that phantom (scenes:
localization, severity, breast); --phantom FILE.toml reads a phantom file instead
(docs/phantoms.md).

examples:
  TELETOUCH_REMOTE_LINK_TOKEN=... teletouch remote --relay ws://127.0.0.1:8765/ \\
      --session lab1 --arm sim --sensor sim --phantom breast --seed 3 \\
      --summary-json remote.json
  teletouch remote --relay tcp://relay:8766 --session lab1 --arm franka --sensor 0 \\
      --calibration gsmini_calib.npz --stiffness-calibration gsmini_stiffness.json
  teletouch remote ... --arm sim --sensor presses.avi --sensor-preset mini-recording \\
      --sensor-loop --calibration gsmini_calib.npz --stiffness-calibration stiffness.json
"""

from __future__ import annotations

import argparse

__all__ = ["check_duration", "configure_parser", "parse_fiducials", "run"]


def check_duration(duration_s: float | None) -> None:
    """``--duration``: None (until stopped) or a finite number of seconds > 0.

    Raises:
        ConfigError: naming ``--duration``.
    """
    import math

    from shared.errors import ConfigError

    if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
        raise ConfigError(f"--duration must be a finite number of seconds > 0, got {duration_s}")


def parse_fiducials(text: str | None) -> tuple[tuple[float, float], ...]:
    """``"x,y;x,y;..."`` -> ((x, y), ...); None or empty -> ().

    Raises:
        ConfigError: not pairs of finite numbers, or fewer than 2 of them.
    """
    import math

    from shared.errors import ConfigError

    if not text:
        return ()
    out = []
    for part in text.split(";"):
        try:
            x, y = (float(v) for v in part.split(","))
        except ValueError as err:
            raise ConfigError(f"--fiducials: {part!r} is not 'x,y'") from err
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ConfigError(f"--fiducials: {part!r} is not finite")
        out.append((x, y))
    if len(out) < 2:
        raise ConfigError("--fiducials: a registration needs at least 2 fiducials")
    return tuple(out)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the remote station's flags (None = not given, so env/TOML/defaults apply)."""
    parser.add_argument("--relay", help="relay URL: ws://HOST:PORT/, wss://..., tcp://HOST:PORT")
    parser.add_argument("--session", help="session id")
    parser.add_argument("--token", help="session token (prefer $TELETOUCH_REMOTE_LINK_TOKEN)")
    parser.add_argument("--name", help="label shown in the relay's status")
    parser.add_argument("--ca-file", dest="ca_file", metavar="PEM",
                        help="CA to trust for wss:// and tls:// (a lab CA; default: the "
                             "system's trust store)")
    parser.add_argument("--arm", default="sim", help="arm backend: sim, franka (default sim)")
    parser.add_argument("--sensor", default="sim",
                        help="sensor: sim (renders on demand), sim-camera (the simulator streaming "
                             "on its own clock like a camera: --sensor-fps, default 25, and "
                             "--sensor-latency-ms), camera, or a camera index / URL / video file")
    parser.add_argument("--sensor-preset", dest="sensor_preset", metavar="NAME",
                        help="camera crop/size: mini-raw (raw GelSight Mini camera: 1/7 cropped "
                             "per side, resized to 320x240; default) or mini-recording (a "
                             "recording of the Mini's 320x240 output, taken as it is)")
    parser.add_argument("--sensor-fps", dest="sensor_fps", type=float, metavar="HZ",
                        help="publish camera frames at this rate (default: a video file's own "
                             "rate; a live camera paces itself; sim-camera: 25)")
    parser.add_argument("--sensor-latency-ms", dest="sensor_latency_ms", type=float,
                        metavar="MS",
                        help="how long before its arrival a camera image was taken, when known "
                             "for the device: frames are paired with the command and the arm "
                             "pose of that time (default 0: the arrival, an upper bound)")
    parser.add_argument("--sensor-loop", dest="sensor_loop", action="store_true",
                        help="restart a video file at its end (default: it ends, reported once)")
    parser.add_argument("--phantom",
                        help="simulated world for sim backends: a phantom scene (breast, "
                             "severity, localization) or a phantom FILE.toml")
    parser.add_argument("--seed", type=int, default=0,
                        help="phantom placement and simulated-noise seed (default 0)")
    parser.add_argument("--fiducials", default=None, metavar="X,Y;X,Y;...",
                        help="design positions (phantom mm) of the phantom's fiducials: "
                             "measure the arm <-> phantom registration on them at start-up "
                             "(docs/registration.md)")
    parser.add_argument("--ideal", action="store_true",
                        help="noise-free simulated world: perfectly registered phantom, no "
                             "force/position noise, linear tissue (default: realistic, see "
                             "docs/simulated-world.md)")
    parser.add_argument("--calibration", metavar="PATH.npz",
                        help="sensor calibration (default: the shipped one for --sensor sim)")
    parser.add_argument("--stiffness-calibration", dest="stiffness_calibration",
                        metavar="PATH.json",
                        help="probe stiffness calibration: gel and N/mm -> Shore 00, made by "
                             "'teletouch sensor calibrate-stiffness' (default: the shipped "
                             "one for --sensor sim; required for a real sensor)")
    parser.add_argument("--frame-rate-hz", dest="frame_rate_hz", type=float,
                        help="tactile frames per second (default 60)")
    parser.add_argument("--patch-pitch-mm", dest="patch_pitch_mm", type=float,
                        help="tactile patch pitch on the display side (default 0.5)")
    parser.add_argument("--tactile-codec", dest="tactile_codec", choices=("compact", "raw"),
                        help="tactile frames as compact deltas (protocol v2, default) or raw "
                             "float32 layers (version-1 peers)")
    parser.add_argument("--capture", choices=("pose", "clock"),
                        help="take a sensor frame as soon as the arm reached the commanded pose "
                             "(pose, default; a sensor that captures on demand, e.g. sim) or "
                             "on the frame clock (clock; what a streaming camera always does)")
    parser.add_argument("--lock-memory", dest="lock_memory",
                        action=argparse.BooleanOptionalAction, default=None,
                        help="keep the station's memory in RAM while it runs (mlockall; "
                             "default: on where RLIMIT_MEMLOCK is unlimited or with "
                             "CAP_IPC_LOCK; remote.agent.lock_memory)")
    parser.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    parser.add_argument("--record", metavar="PATH.mcap",
                        help="record the session to this MCAP file (docs/recording.md)")
    parser.add_argument("--summary-json", dest="summary_json", metavar="PATH",
                        help="write the run's counters and latencies here at exit")
    parser.add_argument("--config", help="TOML file ([remote.link], [remote.agent], "
                                         "[arm.safety], [workspace], [stiffness])")


def run(args: argparse.Namespace) -> int:
    """Run the station until SIGTERM/SIGINT or --duration; 0 on a clean stop."""
    import asyncio
    import json
    import signal
    from pathlib import Path
    from typing import Any

    from remote_site.agent.app import AgentOptions, run_agent
    from shared.report import StatusLine, emit, to_jsonable

    check_duration(args.duration)  # before the arm and the sensor open, not after
    options = AgentOptions(
        relay=args.relay, session=args.session, token=args.token, name=args.name,
        ca_file=args.ca_file,
        arm=args.arm, sensor=args.sensor, sensor_preset=args.sensor_preset,
        sensor_fps=args.sensor_fps, sensor_latency_ms=args.sensor_latency_ms,
        sensor_loop=args.sensor_loop, phantom=args.phantom,
        seed=args.seed, ideal=args.ideal, fiducials=parse_fiducials(args.fiducials),
        calibration=Path(args.calibration) if args.calibration else None,
        stiffness_calibration=(Path(args.stiffness_calibration)
                               if args.stiffness_calibration else None),
        frame_rate_hz=args.frame_rate_hz, patch_pitch_mm=args.patch_pitch_mm,
        tactile_codec=args.tactile_codec,
        capture_on_pose=None if args.capture is None else args.capture == "pose",
        lock_memory=args.lock_memory, duration_s=args.duration,
        config_path=Path(args.config) if args.config else None,
        record=Path(args.record) if args.record else None)
    status = StatusLine()

    def write_summary(summary: dict[str, Any]) -> None:
        if args.summary_json:
            Path(args.summary_json).write_text(
                json.dumps(to_jsonable(summary), indent=2, sort_keys=True, allow_nan=False))

    async def main() -> dict[str, Any]:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        return await run_agent(options, stop, status=status.update, on_summary=write_summary)

    try:
        summary = asyncio.run(main())
    finally:
        status.close()
    frames = summary["frames"]
    emit(f"remote station: {frames['sent']} tactile frames sent, "
         f"{frames['rejected_total']} rejected, "
         f"{summary['platform_states']['dropped_stale']} stale commands dropped")
    return 0
