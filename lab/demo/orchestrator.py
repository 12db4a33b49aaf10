"""Run the whole Tele-Touch system on one machine and report what the operator found.

:func:`run_demo` starts, as separate processes talking over real sockets on 127.0.0.1:

1. ``teletouch relay`` (HMAC tokens from a random per-run secret);
2. optionally one ``teletouch link`` emulator serving both legs (local <-> relay and
   remote <-> relay, one port each) with a named link profile;
3. ``teletouch remote`` with the simulated arm, sensor and a phantom scene;
4. ``teletouch local`` with the simulated platform (a scripted raster operator) and the
   simulated ArrayTac display.

Both stations record the session to MCAP (``local.mcap``, ``remote.mcap``, with the ground
truth beside them) in ``record_dir`` (default: the work directory).

When the scripted operator has finished, the stations are stopped with SIGTERM, the
recording is analysed with :mod:`local_site.palpation` (only what reached the local station),
and the findings are scored against the phantom's ground truth (:mod:`lab.ground_truth`).
The report includes the motion-to-touch latency ledger measured by the local station. The
demo ends by writing the HTML session report (:mod:`lab.html_report`) and returns its path.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lab.child import module_argv
from lab.demo import DEFAULT_DISPLAY, DEFAULT_FRAME_RATE_HZ
from lab.ground_truth import write_ground_truth
from lab.html_report import write_report
from lab.linkemu import get_profile
from lab.scoring import score_findings
from local_site.palpation import analyse_recording, load_recording
from remote_site.agent.world import build_world
from shared.errors import ConfigError, DeviceError, TeleTouchError
from shared.view import parse_view_address
from shared.workspace import load_workspace

__all__ = ["DemoConfig", "DemoError", "run_demo"]

log = logging.getLogger(__name__)

SESSION = "demo"
#: how long the remote station may take to join: it registers the phantom (four fiducial
#: presses, about 8 s) and warms its reconstruction up (about 1 s; longer on a cold
#: checkout, whose kernels compile on first use) before it joins
REMOTE_JOIN_TIMEOUT_S = 180.0
#: the scripted operator: slides pressed 3 mm into the phantom (platform z 10 with the
#: default workspace map) over the whole reachable phantom, lines 4 mm apart at 45 mm/s
#: (about 25 s; the patches are 20 x 15 mm, so every point is felt several times)
DEFAULT_MOTION = ("raster:x0=1,x1=59,y0=1,y1=59,spacing=4,speed=45,z=10,press_depth=0,"
                  "press_every=0,pause=1,loop=0")


class DemoError(TeleTouchError):
    """A demo process failed to start or died; the message names it and quotes its log."""


@dataclass(frozen=True)
class DemoConfig:
    """What to run.

    Attributes:
        scene: phantom scene (``breast``, ``severity``, ``localization``) or a phantom
            ``FILE.toml`` (:mod:`remote_site.phantom.phantom_file`).
        seed: phantom placement seed.
        link: link-emulator profile of the path between the two sites, or None; each
            station <-> relay leg gets half its one-way delay and jitter.
        motion: the scripted operator (``teletouch local --motion`` spec).
        platform: the local station's simulated platform backend: ``sim`` (the board as a
            thread of the station's process) or ``sim-process`` (in a process of its own).
        platform_process: the local station reads its platform in a process of its own
            (``teletouch local --platform-process``; off by default: in paired runs it
            steadied the display loop without a link emulator but made motion-to-touch worse
            on ``city-1000km`` and beside CPU burners, ``benchmarks/results/platform_process/``
            and ``docs/speed.md`` section 13).
        render_loop: where the local station runs its display loop (``teletouch local
            --render-loop``): ``process`` (the default: a process of its own with the board
            link, which met the loop's 0.5 ms jitter target in paired runs where the thread
            did not, for 0.08-0.13 cores more; ``docs/speed.md`` section 21), ``thread`` or
            ``asyncio``.
        display: the ArrayTac drive board: ``board-process`` (the default: ``teletouch
            board``, a process of its own that the station reaches over ``socket://`` with
            its serial driver, as a separate board is reached; the board's simulation then
            does not share the station's interpreter with the 1 kHz display loop) or ``sim``
            (emulated inside the local station, on python-can's virtual CAN FD bus).
        ideal: the noise-free simulated world (default: the realistic one, with an unknown
            registration error drawn from ``seed``).
        register: let the remote station measure the registration on the phantom's
            fiducials before palpation (when it has any).
        max_duration_s: stop the operator after this long whatever happens.
        frame_rate_hz: remote sensor frame rate.
        workdir: where logs and files go (a temporary directory when None).
        keep_files: keep the temporary directory.
        python: the interpreter running the ``teletouch`` processes.
        extra_local_args: more flags for ``teletouch local``.
        extra_remote_args: more flags for ``teletouch remote``.
        record_dir: where the recordings, the ground truth and the HTML report go (None:
            the work directory; the report is then kept in the system's temporary
            directory when the work directory is deleted).
        view: the local station's live view, ``HOST:PORT`` (port 0: a free port), or None.
    """

    scene: str = "breast"
    seed: int = 0
    link: str | None = None
    motion: str = DEFAULT_MOTION
    platform: str = "sim"
    platform_process: bool = False
    render_loop: str = "process"
    display: str = DEFAULT_DISPLAY
    ideal: bool = False
    register: bool = True
    max_duration_s: float = 100.0
    frame_rate_hz: float = DEFAULT_FRAME_RATE_HZ
    workdir: Path | None = None
    keep_files: bool = False
    python: str = sys.executable
    extra_local_args: tuple[str, ...] = ()
    extra_remote_args: tuple[str, ...] = ()
    record_dir: Path | None = None
    view: str | None = None


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class _Child:
    name: str
    proc: subprocess.Popen[bytes]
    log_path: Path

    def log_tail(self, lines: int = 15) -> str:
        try:
            text = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return "(no log)"
        return "\n".join(text[-lines:])


@dataclass
class _Processes:
    """The demo's child processes; all are stopped on exit, whatever happened."""

    workdir: Path
    python: str
    env: dict[str, str]
    children: list[_Child] = field(default_factory=list)

    def start(self, name: str, *args: str) -> _Child:
        log_path = self.workdir / f"{name}.log"
        cmd = [*module_argv(python=self.python), "--log-level", "INFO", *args]
        log.debug("starting %s: %s", name, " ".join(cmd))
        with open(log_path, "wb") as out:
            proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, cwd=self.workdir, env=self.env)
        child = _Child(name, proc, log_path)
        self.children.append(child)
        return child

    def check_alive(self) -> None:
        for child in self.children:
            code = child.proc.poll()
            if code is not None:
                raise DemoError(f"{child.name} exited early with code {code}; its log "
                                f"({child.log_path}) ends with:\n{child.log_tail()}")

    def stop(self, child: _Child, timeout_s: float = 10.0) -> int | None:
        if child.proc.poll() is None:
            child.proc.send_signal(signal.SIGTERM)
            try:
                child.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop within %.0f s of SIGTERM; killing it",
                            child.name, timeout_s)
                child.proc.kill()
                child.proc.wait(5)
        return child.proc.returncode

    def stop_all(self) -> None:
        """SIGTERM each child, newest first, and wait for it. A second Ctrl-C while this
        runs kills the children still running at once (never leaves them behind) and is
        then raised."""
        try:
            for child in reversed(self.children):
                self.stop(child)
        except KeyboardInterrupt:
            for child in self.children:
                if child.proc.poll() is None:
                    child.proc.kill()
            for child in self.children:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    child.proc.wait(5)
            raise


def _wait_for(predicate: Callable[[], bool], what: str, timeout_s: float,
              procs: _Processes) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        procs.check_alive()
        if predicate():
            return
        time.sleep(0.1)
    raise DemoError(f"timed out after {timeout_s:.0f} s waiting for {what}")


def _port_open(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.2):
            return True
    except OSError:
        return False


def _peer_joined(status: dict[str, Any] | None, role: str) -> bool:
    """Whether the relay's /status shows a station of ``role`` in the demo's session."""
    session = (status or {}).get("sessions", {}).get(SESSION)
    peers = session.get("peers", []) if isinstance(session, dict) else []
    return any(isinstance(p, dict) and p.get("role") == role for p in peers)


def relay_status(port: int) -> dict[str, Any] | None:
    """The relay's /status JSON, or None when it does not answer."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=1.0) as resp:
            data = json.loads(resp.read())
            return data if isinstance(data, dict) else None
    except (OSError, urllib.error.URLError, json.JSONDecodeError):
        return None


def _read_json(path: Path, what: str) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise DemoError(f"{what} ({path}) was not written or is not JSON: {err}") from err
    if not isinstance(data, dict):
        raise DemoError(f"{what} ({path}) is not a JSON object")
    return data


def run_demo(config: DemoConfig,
             progress: Callable[[float, dict[str, Any] | None], None] | None = None,
             announce_view: Callable[[str, str], None] | None = None) -> dict[str, Any]:
    """Run one demo session end to end and return its report.

    Args:
        config: what to run.
        progress: called about once a second with the elapsed time and the relay status.
        announce_view: called with (who, URL) for each live view once it is started: the
            local station's, and the relay's for observers (URL with an observer token).

    Returns:
        The report (see ``docs/demo.md``): scene, findings, score against ground truth,
        latency ledger, and the stations' summaries.

    Raises:
        DemoError: a process failed; the message quotes its log.
        ConfigError: a bad setting.
    """
    if config.max_duration_s <= 0:
        raise ConfigError("max_duration_s must be > 0")
    if config.display not in ("sim", "board-process"):
        raise ConfigError(f"display must be 'sim' or 'board-process', got {config.display!r}")
    # the work directory is deleted at the end: a temporary one not asked to be kept
    deleted = config.workdir is None and not config.keep_files
    # absolute: the children run in the work directory, where a relative path would name
    # another place than the one this process reads back
    workdir = (Path(tempfile.mkdtemp(prefix="teletouch-demo-")) if config.workdir is None
               else Path(config.workdir).resolve())
    workdir.mkdir(parents=True, exist_ok=True)
    # the per-run secret reaches the children through their environment, never argv; one
    # BLAS thread per process: several processes share the cores, and threaded BLAS on a
    # busy machine made reconstruction 5x slower (benchmarks/results/reconstruction.md)
    env = {**os.environ, "TELETOUCH_RELAY_SECRET": os.urandom(16).hex(),
           "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    procs = _Processes(workdir, config.python, env)
    started = time.monotonic()
    try:
        ws_port, tcp_port = free_port(), free_port()
        relay_view: list[str] = []
        if config.view:
            relay_view_host = parse_view_address(config.view).host
            relay_view = ["--view", f"{relay_view_host}:{free_port()}"]
        procs.start("relay", "relay", "--host", "127.0.0.1", "--port", str(ws_port),
                    "--tcp-port", str(tcp_port), *relay_view)
        _wait_for(lambda: relay_status(ws_port) is not None, "the relay's /status", 20, procs)
        token = subprocess.run(
            [*module_argv(python=config.python), "relay", "--print-token", SESSION],
            check=True, capture_output=True, text=True, timeout=30, env=env).stdout.strip()
        local_port = remote_port = ws_port
        if config.link:
            local_port, remote_port = free_port(), free_port()
            # The profile describes the path between the two sites; the relay sits on it, so
            # each station <-> relay leg carries half its one-way delay and jitter and a loop
            # (local -> remote -> local) sees one round trip of the profile, not two.
            leg = get_profile(config.link)
            leg_delay = ["--delay-ms", f"{leg.delay_ms / 2:g}", "--jitter-ms",
                         f"{leg.jitter_ms / 2:g}"]
            # one process serves both legs (two ports, each leg its own emulated link and
            # seed: seed * 2 for the local leg, + 1 for the remote one)
            procs.start("link", "link", "--listen", f"127.0.0.1:{local_port}", "--listen",
                        f"127.0.0.1:{remote_port}", "--target", f"127.0.0.1:{ws_port}",
                        "--profile", config.link, *leg_delay, "--seed", str(config.seed * 2))
            for port in (local_port, remote_port):
                _wait_for(functools.partial(_port_open, port), "the link emulator", 20, procs)
        rec_dir = Path(config.record_dir).resolve() if config.record_dir is not None else workdir
        rec_dir.mkdir(parents=True, exist_ok=True)
        files = {k: rec_dir / v for k, v in {
            "ground_truth": "ground_truth.json", "record": "local.mcap",
            "remote_record": "remote.mcap", "report": "report.html"}.items()}
        # the recordings stay only where they outlive the temporary work directory
        kept = not (deleted and config.record_dir is None)
        if not kept:
            files["report"] = Path(tempfile.gettempdir()) / \
                f"teletouch-demo-report-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}.html"
        files.update(local_summary=workdir / "local_summary.json",
                     remote_summary=workdir / "remote_summary.json")
        # The truth of the phantom the remote station simulates: same scene and seed, the
        # workspace its settings give, the simulated probe's shipped stiffness calibration.
        remote_args = list(config.extra_remote_args)
        remote_toml = (Path(remote_args[remote_args.index("--config") + 1])
                       if "--config" in remote_args[:-1] else None)
        # a phantom file is passed by absolute path: the stations run in the work directory
        phantom = (str(Path(config.scene).resolve()) if Path(config.scene).suffix == ".toml"
                   else config.scene)
        world = build_world(phantom, config.seed, ideal=config.ideal)
        write_ground_truth(world, files["ground_truth"], load_workspace(toml_path=remote_toml))
        # the fiducials' DESIGN positions are part of the phantom's description (a lab knows
        # where it put them); where the phantom really lies is what the station measures
        fiducials = ";".join(f"{f.center_mm[0]:g},{f.center_mm[1]:g}"
                             for f in world.phantom.fiducials)
        common = ["--session", SESSION, "--token", token]
        view_args: list[str] = []
        view_url = None
        if config.view:
            address = parse_view_address(config.view)
            port = address.port or free_port()
            view_args = ["--view", f"{address.host}:{port}"]
            host = f"[{address.host}]" if ":" in address.host else address.host
            view_url = f"http://{host}:{port}/"
        remote = procs.start(
            "remote", "remote", "--relay", f"ws://127.0.0.1:{remote_port}/", *common,
            "--arm", "sim", "--sensor", "sim", "--phantom", phantom,
            "--seed", str(config.seed), *(["--ideal"] if config.ideal else []),
            *([f"--fiducials={fiducials}"] if fiducials and config.register else []),
            "--frame-rate-hz", f"{config.frame_rate_hz:g}",
            "--summary-json", str(files["remote_summary"]), "--record",
            str(files["remote_record"]), *config.extra_remote_args)
        # The scripted operator starts once the remote station is in the session, as a
        # person at the haptic station would: before that the remote is still registering
        # the phantom and warming up (seconds, more on a cold checkout or a busy machine),
        # and a sweep started earlier is felt only in part (its first lines lost).
        _wait_for(lambda: _peer_joined(relay_status(ws_port), "remote"),
                  "the remote station to join the session (registration, warm-up)",
                  REMOTE_JOIN_TIMEOUT_S, procs)
        display = "sim"
        if config.display == "board-process":
            board_port = free_port()
            procs.start("board", "board", "--listen", f"127.0.0.1:{board_port}")
            _wait_for(functools.partial(_port_open, board_port), "the drive board", 20, procs)
            display = f"socket://127.0.0.1:{board_port}"
        local = procs.start(
            "local", "local", "--relay", f"ws://127.0.0.1:{local_port}/", *common,
            "--platform", config.platform,
            "--platform-process" if config.platform_process else "--no-platform-process",
            "--render-loop", config.render_loop,
            "--display", display, "--motion", config.motion,
            "--until-motion-done", "--duration", f"{config.max_duration_s:g}", "--no-status",
            "--record", str(files["record"]), "--summary-json", str(files["local_summary"]),
            *view_args, *config.extra_local_args)
        if view_url is not None and announce_view is not None:
            announce_view("local station", view_url)
            observer = subprocess.run(
                [*module_argv(python=config.python), "relay", "--print-token", SESSION, "--role",
                 "observer", "--ttl-s", str(int(config.max_duration_s) + 3600)],
                check=True, capture_output=True, text=True, timeout=30, env=env).stdout.strip()
            obs_host, _, obs_port = relay_view[1].rpartition(":")
            obs_host = f"[{obs_host}]" if ":" in obs_host else obs_host
            announce_view("relay, for observers",
                          f"http://{obs_host}:{obs_port}/#session={SESSION}&token={observer}")
        deadline = time.monotonic() + config.max_duration_s + 60.0
        while local.proc.poll() is None:
            for child in procs.children:
                if child is not local and child.proc.poll() is not None:
                    raise DemoError(f"{child.name} exited early with code "
                                    f"{child.proc.returncode}; its log ends with:\n"
                                    f"{child.log_tail()}")
            if time.monotonic() > deadline:
                raise DemoError("the local station did not finish in time; its log ends with:"
                                f"\n{local.log_tail()}")
            if progress is not None:
                progress(time.monotonic() - started, relay_status(ws_port))
            time.sleep(1.0)
        if local.proc.returncode != 0:
            raise DemoError(f"the local station failed with code {local.proc.returncode}; "
                            f"its log ends with:\n{local.log_tail()}")
        relay_final = relay_status(ws_port)
        remote_code = procs.stop(remote)
        if remote_code not in (0, -signal.SIGTERM):
            raise DemoError(f"the remote station ended with code {remote_code}; its log ends "
                            f"with:\n{remote.log_tail()}")
        procs.stop_all()
        report = _report(config, files, relay_final, time.monotonic() - started, workdir)
        # None: deleted with the work directory below (the HTML report is kept)
        report["recordings"] = ({"local": str(files["record"]),
                                 "remote": str(files["remote_record"])} if kept else None)
        report["report_html"] = _write_html(files)
        return report
    except (OSError, subprocess.SubprocessError, DeviceError) as err:
        raise DemoError(f"demo failed: {err}") from err
    finally:
        procs.stop_all()
        if deleted:
            shutil.rmtree(workdir, ignore_errors=True)


def _write_html(files: dict[str, Path]) -> str | None:
    """Write the HTML session report; None (logged) when it cannot be made."""
    try:
        return str(write_report(files["record"], files["report"],
                                truth_path=files["ground_truth"],
                                remote_path=files["remote_record"]))
    except TeleTouchError as err:
        log.error("the HTML report was not written: %s", err)
        return None


def _report(config: DemoConfig, files: dict[str, Path], relay_final: dict[str, Any] | None,
            elapsed_s: float, workdir: Path) -> dict[str, Any]:
    truth = _read_json(files["ground_truth"], "the ground truth")
    local_summary = _read_json(files["local_summary"], "the local station's summary")
    remote_summary = _read_json(files["remote_summary"], "the remote station's summary")
    recording = load_recording(files["record"])
    findings = analyse_recording(recording)  # in the workspace the station recorded
    score = score_findings(findings, truth)
    latency = local_summary.get("motion_to_touch_ms", {})
    return {
        "scene": config.scene,
        "seed": config.seed,
        "link": config.link or "direct",
        "elapsed_s": elapsed_s,
        **{k: score[k] for k in ("tumors_expected", "tumors_found", "false_positives",
                                 "localization_error_mm", "types_correct", "types_total",
                                 "kendall_tau", "matches")},
        "findings": [f.to_dict() for f in findings],
        "frames_received": recording.frames,
        "latency_ms": latency,
        # where the slowest 5 % of the frames lose their time, stage by stage
        "latency_tail_ms": local_summary.get("motion_to_touch_tail_ms"),
        "local": local_summary,
        "registration": {"true": truth.get("world", {}).get("registration"),
                         "estimated": remote_summary.get("registration")},
        "remote": remote_summary,
        "relay": relay_final,
        "workdir": str(workdir) if (config.keep_files or config.workdir) else None,
    }
