"""The ``sim`` platform backend: a simulated encoder board on a pty pair, read by the normal
serial driver.

Nothing here special-cases the application: :class:`SimulatedPlatform` *is* a
:class:`~local_site.platform.serial_board.SerialEncoderPlatform` whose ``_connect()`` first
creates a pseudo-terminal, starts a :class:`~local_site.platform.sim_board.SimulatedEncoderBoard`
writing to the master side, then opens the slave side by its path with
``serial.serial_for_url`` exactly as it would open ``/dev/ttyUSB0``.
"""

from __future__ import annotations

import contextlib
import os
import time
import tty

from local_site.platform.motion import MotionSource, make_motion
from local_site.platform.motion_spec import parse_motion_spec
from local_site.platform.serial_board import SerialEncoderPlatform
from local_site.platform.sim_board import SimulatedEncoderBoard
from shared.errors import DeviceInitError

__all__ = ["SimulatedPlatform", "build_motion"]


def build_motion(motion: MotionSource | str,
                 motion_options: dict[str, object] | None = None) -> MotionSource:
    """The motion source of a simulated platform: ``motion`` itself, a ``--motion`` spec
    string parsed, or (with ``motion_options``) a bare name built with those options.

    Raises:
        ConfigError: a bad spec, name or option.
    """
    if isinstance(motion, str) and motion_options is None:
        return parse_motion_spec(motion)
    return make_motion(motion, **(motion_options or {}))


class SimulatedPlatform(SerialEncoderPlatform):
    """Simulated platform: a motion source -> simulated board -> pty -> serial driver.

    Args:
        motion: a :class:`MotionSource`, or a ``--motion`` spec string
            (:mod:`local_site.platform.motion_spec`: ``raster``, ``random:seed=3``, ``hold``,
            a trajectory file, ...).
        motion_options: keyword arguments for :func:`make_motion` when ``motion`` is a bare
            name (then the string is not parsed as a spec).
        sample_rate_hz: the simulated board's rate.
        initial_counts: board counters at power-up for position (0, 0, 0).
        start_board_t_us: board clock at the first sample.
        **kwargs: passed to :class:`SerialEncoderPlatform` / ``XYZPlatform`` (geometry, ...).
    """

    def __init__(self, motion: MotionSource | str = "raster", *,
                 motion_options: dict[str, object] | None = None,
                 sample_rate_hz: float = 1000.0,
                 initial_counts: tuple[int, int, int] = (0, 0, 0),
                 start_board_t_us: int = 0, **kwargs: object) -> None:
        super().__init__("pty://sim", **kwargs)  # type: ignore[arg-type]
        self.motion = build_motion(motion, motion_options)
        self._sample_rate_hz = sample_rate_hz
        self._initial_counts = initial_counts
        self._start_board_t_us = start_board_t_us
        self._master_fd: int | None = None
        self.board: SimulatedEncoderBoard | None = None
        self._powered_at_s: float | None = None  # perf_counter when the board powered up

    @property
    def name(self) -> str:
        return f"simulated encoder board at {self.url}"

    def _connect(self) -> None:
        try:
            master_fd, slave_fd = os.openpty()
        except OSError as err:
            raise DeviceInitError(f"cannot create a pty for the simulated board: {err}") from err
        try:
            tty.setraw(slave_fd)
            os.set_blocking(master_fd, False)
            self.url = os.ttyname(slave_fd)
        except OSError as err:
            os.close(master_fd)
            os.close(slave_fd)
            raise DeviceInitError(f"cannot configure the simulated board's pty: {err}") from err
        self._master_fd = master_fd
        # The platform and the hand on it do not stop when the link drops: a reopened link
        # finds the board (and the scripted operator) where they are now, not at the start.
        if self._powered_at_s is None:
            self._powered_at_s = time.perf_counter()
        try:
            super()._connect()
        except DeviceInitError:
            self._close_pty()
            raise
        finally:
            os.close(slave_fd)  # the driver holds its own descriptor of the slave
        try:
            self._start_board(master_fd, self._powered_at_s)
        except DeviceInitError:
            super()._disconnect()
            self._close_pty()
            raise

    def _start_board(self, master_fd: int, powered_at_s: float) -> None:
        """Start the board writing to the pty's master side (here: a thread of this process).

        Args:
            master_fd: the pty's master descriptor.
            powered_at_s: ``time.perf_counter()`` at the board's power-up (a reopened link
                finds it where it is now).
        """
        start_sample = int((time.perf_counter() - powered_at_s) * self._sample_rate_hz)
        self.board = SimulatedEncoderBoard(
            self.motion, lambda data: os.write(master_fd, data), geometry=self.geometry,
            sample_rate_hz=self._sample_rate_hz, initial_counts=self._initial_counts,
            start_board_t_us=self._start_board_t_us, start_sample=start_sample)
        self.board.start()

    def _stop_board(self) -> None:
        """Stop the board (idempotent)."""
        if self.board is not None:
            self.board.stop()

    def _disconnect(self) -> None:
        self._stop_board()
        super()._disconnect()
        self._close_pty()

    def _close_pty(self) -> None:
        fd, self._master_fd = self._master_fd, None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)

    def unplug(self) -> None:
        """Simulate the board disappearing: stop it and close its end of the link."""
        self._stop_board()
        self._close_pty()
