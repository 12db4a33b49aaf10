"""The ``sim-process`` platform backend: the simulated encoder board in a process of its own.

A real encoder board is a device of its own: the station's process only reads its port. The
``sim`` backend runs the simulated board as a thread of the station's process, where it takes
the GIL a thousand times a second beside the display loop and the driver's reader thread
(``benchmarks/results/platform_silence.md``: that reader, woken with data waiting, was seen
kept from running for 0.25-1 s on a busy host). :class:`ProcessSimulatedPlatform` is the
same pty and the same driver, but the board runs in a child process (``python -m
local_site.platform.sim_process``) that holds the pty's master side. The child builds the
motion from the same spec, keeps the board's power-up time (a reopened link finds the
scripted operator where it is now), and ends when it is told to (SIGTERM), when its pty is
closed, or when the station's process is gone.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import threading
import time
from typing import Any

from local_site.platform.kinematics import PlatformGeometry
from local_site.platform.sim import SimulatedPlatform, build_motion
from local_site.platform.sim_board import SimulatedEncoderBoard
from shared.errors import ConfigError, DeviceInitError

__all__ = ["ProcessSimulatedPlatform", "main"]

#: how often the child checks that the station's process still exists
_PARENT_CHECK_S = 0.1


class ProcessSimulatedPlatform(SimulatedPlatform):
    """Simulated platform whose board runs in a child process (see module docstring).

    Args:
        motion: a ``--motion`` spec string (or, with ``motion_options``, a bare name); a
            ready motion object cannot cross to the child.
        motion_options: as for :class:`SimulatedPlatform` (JSON-serialisable values).
        connect_timeout_s: how long ``connect()`` waits for the first sample (the child
            starts Python and imports numpy first: 5 s by default).
        **kwargs: as for :class:`SimulatedPlatform`.

    Raises:
        ConfigError: a motion that is not a string, options that are not JSON, or a bad
            spec.
    """

    def __init__(self, motion: str = "raster", *,
                 motion_options: dict[str, object] | None = None,
                 connect_timeout_s: float = 5.0, **kwargs: Any) -> None:
        if not isinstance(motion, str):
            raise ConfigError("the sim-process platform needs its motion as a spec string "
                              f"(it is rebuilt in the board's process), got {type(motion)}")
        try:
            json.dumps(motion_options)
        except (TypeError, ValueError) as err:
            raise ConfigError(f"sim-process motion options must be JSON values: {err}") from err
        super().__init__(motion, motion_options=motion_options,
                         connect_timeout_s=connect_timeout_s, **kwargs)
        self._motion_spec = motion
        self._motion_options = motion_options
        self._child: subprocess.Popen[bytes] | None = None

    @property
    def name(self) -> str:
        return f"simulated encoder board (own process) at {self.url}"

    def _start_board(self, master_fd: int, powered_at_s: float) -> None:
        settings = {
            "fd": master_fd, "motion": self._motion_spec,
            "motion_options": self._motion_options,
            "geometry": dataclasses.asdict(self.geometry),
            "sample_rate_hz": self._sample_rate_hz,
            "initial_counts": list(self._initial_counts),
            "start_board_t_us": self._start_board_t_us, "powered_at_s": powered_at_s,
        }
        try:
            self._child = subprocess.Popen(
                [sys.executable, "-P", "-m", "local_site.platform.sim_process",
                 json.dumps(settings)],
                pass_fds=(master_fd,), stdin=subprocess.DEVNULL)
        except OSError as err:
            raise DeviceInitError(f"cannot start the simulated board's process: {err}") from err

    def _stop_board(self) -> None:
        child, self._child = self._child, None
        if child is None:
            return
        child.terminate()
        try:
            child.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()


def main(argv: list[str] | None = None) -> int:
    """The board's process: stream frames to the inherited pty master until told to stop.

    Args:
        argv: ``[settings JSON]`` (written by :class:`ProcessSimulatedPlatform`).

    Returns:
        0 when stopped, 1 when the pty went away.
    """
    settings = json.loads((sys.argv[1:] if argv is None else argv)[0])
    fd = int(settings["fd"])
    geometry_args: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v
                                     for k, v in settings["geometry"].items()}
    geometry = PlatformGeometry(**geometry_args)
    rate_hz = float(settings["sample_rate_hz"])
    start_sample = max(0, int((time.perf_counter() - settings["powered_at_s"]) * rate_hz))
    board = SimulatedEncoderBoard(
        build_motion(settings["motion"], settings["motion_options"]),
        lambda data: os.write(fd, data), geometry=geometry, sample_rate_hz=rate_hz,
        initial_counts=tuple(settings["initial_counts"]),
        start_board_t_us=int(settings["start_board_t_us"]), start_sample=start_sample)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    parent = os.getppid()
    board.start()
    try:
        while not stop.wait(_PARENT_CHECK_S):
            if os.getppid() != parent or board.error is not None:
                break
    finally:
        board.stop()
    return 1 if board.error is not None else 0


if __name__ == "__main__":
    sys.exit(main())
