"""teletouch local: the local haptic station (XYZ platform + ArrayTac display).

With a relay: reads the platform (>= 500 Hz), sends platform_state to the relay, renders
the tactile frames it receives on the ArrayTac pins at the refresh rate, answers the
relay's clock pings and shows a live status line. Link loss longer than
--link-loss-timeout (default 100 ms), no tactile frame for --stale-timeout, or a frame that
may be older than --max-frame-age by its own capture stamp (clock-corrected with the relay's
offsets and their error bound) puts the pins in their safe state (--safe-state flat|hold); the
link reconnects with backoff and rendering resumes when fresh frames arrive again.

Without a relay: --scene SHAPE|FILE.npz renders a virtual shape (hemisphere, cone, cube,
bow, semi-ellipsoid, triangular-prism; "hemisphere:radius_mm=8,k=0.7", placed at the
workspace centre unless x_mm/y_mm are given) or a layer file under the moving platform.

Settings: flags > TELETOUCH_LOCAL_AGENT_* / TELETOUCH_LOCAL_LINK_* > --config TOML
([local.agent], [local.link], [local.render], [workspace]) > defaults.

Examples:
  teletouch local --relay ws://127.0.0.1:8765/ --session lab1 --token T \\
      --platform sim --display sim --motion raster:x0=5,x1=55,y0=5,y1=55,spacing=2 \\
      --until-motion-done --record run.mcap --summary-json run.json
  teletouch local --scene hemisphere:radius_mm=10 --platform sim --display sim --duration 10

Exit: 0 on a clean stop (duration, motion done, SIGTERM/SIGINT), 1 when the relay refuses
the station for good (a wrong token, or its connection replaced by another proving it), an
output cannot be written or the recording lost messages, 2 on bad usage. A role held by
another station (role_taken) is not final: the link keeps retrying until that station leaves.
"""

from __future__ import annotations

import argparse
from typing import Any

__all__ = ["configure_parser", "run"]


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the ``teletouch local`` arguments."""
    link = parser.add_argument_group("relay link ([local.link])")
    link.add_argument("--relay", metavar="URL",
                      help="relay URL: ws://, wss://, tcp:// or tls://")
    link.add_argument("--ca-file", dest="ca_file", metavar="PEM",
                      help="CA to trust for wss:// and tls:// (a lab CA; default: the "
                           "system's trust store)")
    link.add_argument("--session", metavar="ID", help="session id")
    link.add_argument("--token", metavar="T",
                      help="session token (better: TELETOUCH_LOCAL_LINK_TOKEN)")
    link.add_argument("--name", help="label shown in the relay's status")
    dev = parser.add_argument_group("devices and scene ([local.agent])")
    dev.add_argument("--platform", metavar="SPEC", help="sim, /dev/ttyUSB0, socket://... "
                     "(default sim)")
    dev.add_argument("--platform-process", action=argparse.BooleanOptionalAction,
                     default=None, help="read the platform in a process of its own, the "
                     "newest sample in shared memory (default: off; local.agent."
                     "platform_process)")
    dev.add_argument("--lock-memory", action=argparse.BooleanOptionalAction, default=None,
                     help="keep the station's memory in RAM while it runs (mlockall; default: "
                     "on where RLIMIT_MEMLOCK is unlimited or with CAP_IPC_LOCK; local.agent."
                     "lock_memory)")
    dev.add_argument("--display", metavar="SPEC", help="sim, sim-serial, can://socketcan/can0, "
                     "socketcan:can0, /dev/ttyACM0 ... (default sim)")
    dev.add_argument("--motion", metavar="SPEC",
                     help="scripted operator of the sim platform, e.g. "
                     "raster:x0=5,x1=55,y0=5,y1=55,spacing=2,speed=20,press_depth=3,"
                     "press_every=4 | random:seed=1 | hold:x=30,y=30,z=100 | FILE.csv")
    dev.add_argument("--scene", metavar="FILE|SHAPE", help="render a local scene, no relay")
    run_ = parser.add_argument_group("run")
    run_.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    run_.add_argument("--until-motion-done", action="store_true",
                      help="stop when the sim platform's scripted motion has finished")
    run_.add_argument("--record", metavar="PATH.mcap",
                      help="record the session to this MCAP file (docs/recording.md)")
    run_.add_argument("--summary-json", metavar="PATH", help="write the summary JSON at exit")
    run_.add_argument("--config", metavar="FILE", help="TOML settings file")
    run_.add_argument("--no-status", action="store_true", help="no live status line")
    run_.add_argument("--view", metavar="HOST:PORT",
                      help="serve the live view in the browser (e.g. 127.0.0.1:8780; port 0: "
                           "any free port; the URL is printed). Bind loopback unless every "
                           "host that can reach it may watch: docs/view.md")
    tune = parser.add_argument_group("tuning ([local.agent])")
    tune.add_argument("--safe-state", choices=["flat", "hold"], help="display safe state")
    tune.add_argument("--link-loss-timeout", type=float, metavar="S",
                      help="safe state after the link is down this long (default 0.1)")
    tune.add_argument("--stale-timeout", type=float, metavar="S",
                      help="safe state after no tactile frame for this long (default 0.08: "
                           "safe within 100 ms of the last frame, 20 ms left for a late tick)")
    tune.add_argument("--max-frame-age", type=float, metavar="S",
                      help="never render a tactile frame that may be older than this, by its "
                           "own capture stamp (default 0.15)")
    tune.add_argument("--send-rate", type=float, metavar="HZ",
                      help="platform_state rate to the relay (default 250)")
    tune.add_argument("--render-rate", type=float, metavar="HZ",
                      help="display loop rate (default 1000)")
    tune.add_argument("--render-loop", choices=["thread", "asyncio", "process"],
                      help="where the display loop runs: a thread of the station (default), "
                           "a task on its event loop, or a process of its own with the board "
                           "link (the platform is then read in a process of its own too)")
    tune.add_argument("--record-pins-rate", type=float, metavar="HZ",
                      help="rate of the recording's /local/pins channel (default 50)")
    tune.add_argument("--record-images", type=float, metavar="HZ",
                      help="also record the tactile patch as a PNG image channel "
                      "(foxglove.CompressedImage) at most HZ times a second (default 0: off)")


def run(args: argparse.Namespace) -> int:
    """Run the local station until it stops; see the module docstring for exit codes."""
    import asyncio

    from local_site.agent import LocalAgent, LocalAgentConfig
    from local_site.render import RendererConfig
    from shared.client import StationLinkConfig
    from shared.config import resolve_config
    from shared.report import StatusLine, emit
    from shared.view import ViewServerConfig, parse_view_address
    from shared.workspace import WorkspaceConfig

    agent_flags: dict[str, Any] = {
        "platform": args.platform, "platform_process": args.platform_process,
        "lock_memory": args.lock_memory,
        "display": args.display, "motion": args.motion,
        "scene": args.scene, "safe_state": args.safe_state,
        "link_loss_timeout_s": args.link_loss_timeout,
        "stale_frame_timeout_s": args.stale_timeout, "max_frame_age_s": args.max_frame_age,
        "platform_send_rate_hz": args.send_rate,
        "render_rate_hz": args.render_rate, "render_loop": args.render_loop,
        "record_pins_rate_hz": args.record_pins_rate,
        "record_image_rate_hz": args.record_images, "view": args.view}
    config = resolve_config(LocalAgentConfig, "local.agent", explicit=agent_flags,
                            toml_path=args.config)
    link_config = resolve_config(StationLinkConfig, "local.link", explicit={
        "url": args.relay, "session": args.session, "token": args.token, "name": args.name,
        "ca_file": args.ca_file},
        toml_path=args.config)
    render_config = resolve_config(RendererConfig, "local.render", toml_path=args.config)
    workspace = resolve_config(WorkspaceConfig, "workspace", toml_path=args.config)
    agent = LocalAgent(config, link_config=link_config, render_config=render_config,
                       workspace=workspace, duration_s=args.duration,
                       until_motion_done=args.until_motion_done, record_path=args.record,
                       summary_path=args.summary_json,
                       status=None if args.no_status else StatusLine(min_interval_s=5.0),
                       handle_signals=True,
                       view=parse_view_address(config.view) if config.view.strip() else None,
                       view_config=ViewServerConfig(rate_hz=config.view_rate_hz,
                                                    allowed_hosts=config.view_allowed_hosts),
                       view_ready=lambda url: emit(f"live view: {url}"))
    agent.open()
    code = asyncio.run(agent.run())
    summary = agent.summary or {}
    e2e = (summary.get("motion_to_touch_ms") or {}).get("end_to_end") or {}
    loop = summary.get("display_loop") or {}
    emit(f"local station stopped ({agent.exit_reason}): frames received "
         f"{summary.get('frames_received')}, rendered {summary.get('frames_rendered')}, "
         f"rejected {summary.get('frames_rejected')}; e2e p50 {e2e.get('p50')} ms; display "
         f"loop {loop.get('rate_hz') or 0:.0f} Hz, period p99 {loop.get('period_p99_ms')} ms")
    return code
