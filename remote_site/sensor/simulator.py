"""Simulated GelSight-style sensor: a depth-map provider rendered by the photometric model.

The simulator does not know where depth maps come from. It takes a *provider*, a callable
returning the current gel contact depth map (H x W, mm, >= 0, on the sensor's pixel grid),
or a map set with :meth:`SimulatedSensor.set_depth`. The phantom contact model plugs in as
``SimulatedSensor(depth_provider=lambda: phantom.contact(pose).depth_mm)``.
Each :meth:`read_latest` renders a fresh frame (seq + 1, timestamp = now).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable

import numpy as np

from remote_site.sensor.base import SensorFrame, SensorHealth, TactileSensor
from remote_site.sensor.photometric import PhotometricModel, PhotometricSettings
from shared.errors import ConfigError, DeviceInitError, DeviceOperationError, InputDataError
from shared.timebase import now_us

__all__ = ["DepthProvider", "SimulatedSensor", "StreamingSimulatedSensor"]

log = logging.getLogger(__name__)

DepthProvider = Callable[[], np.ndarray]


class SimulatedSensor(TactileSensor):
    """A tactile sensor backend that renders frames instead of capturing them.

    Args:
        depth_provider: returns the current depth map (mm); None = flat gel until
            :meth:`set_depth` is called.
        settings: optical parameters (GelSight Mini-like defaults, 320 x 240, 0.0634 mm/px).
        seed: camera-noise seed (and of the LED drift rates).
        led_drift_per_min: standard deviation of each colour channel's brightness drift
            rate (relative gain change per minute; 0 = none). Each channel drifts linearly,
            ``gain_c(t) = 1 + r_c t``, ``r_c ~ N(0, led_drift_per_min)`` drawn once.
        clock_s: the time the drift follows (seconds; default: since connect, wall clock).
    """

    captures_on_demand = True  # every read renders the gel as it is now

    def __init__(self, depth_provider: DepthProvider | None = None,
                 settings: PhotometricSettings | None = None, seed: int = 0, *,
                 led_drift_per_min: float = 0.0,
                 clock_s: Callable[[], float] | None = None) -> None:
        if not (np.isfinite(led_drift_per_min) and led_drift_per_min >= 0):
            raise InputDataError(f"led_drift_per_min must be >= 0, got {led_drift_per_min}")
        self.model = PhotometricModel(settings, seed=seed)
        rates = np.random.default_rng([seed, 1]).normal(0.0, led_drift_per_min, 3)
        self._drift_per_s = rates.astype(np.float32) / np.float32(60.0)
        self._clock = clock_s
        self._t0 = time.monotonic()
        super().__init__(self.model.settings.shape_hw, self.model.settings.mm_per_px)
        self._provider = depth_provider
        self._depth = np.zeros(self.shape_hw, np.float32)
        self._seq = 0
        self._lock = threading.Lock()

    @property
    def background_rgb(self) -> np.ndarray:
        """Noise-free no-contact frame (what a background capture averages to)."""
        return self.model.background_rgb

    def set_depth(self, depth_mm: np.ndarray) -> None:
        """Use a fixed depth map (mm, >= 0) until changed (ignored if a provider is set).

        Raises:
            InputDataError: wrong shape, NaN/Inf or negative values.
        """
        self.model.gel_surface_mm(depth_mm)  # validates
        self._depth = np.asarray(depth_mm, np.float32).copy()

    def render(self, depth_mm: np.ndarray) -> np.ndarray:
        """Render one RGB frame from a depth map without touching the sensor state."""
        return self.model.render(depth_mm)

    def _connect(self) -> None:
        self._seq = 0
        self._t0 = time.monotonic()

    def led_gain(self) -> np.ndarray:
        """The current per-channel brightness gain (1 without drift)."""
        t = self._clock() if self._clock is not None else time.monotonic() - self._t0
        return np.float32(1.0) + self._drift_per_s * np.float32(t)

    def _disconnect(self) -> None:
        pass

    def _latest(self) -> SensorFrame | None:
        return self._render_now()

    def _render_now(self) -> SensorFrame:
        """Render the gel as it is now (the next seq, stamped now)."""
        depth = self._provider() if self._provider is not None else self._depth
        # the LED drift scales the 8-bit frame per channel, saturating, in the render's pass
        gain = self.led_gain().astype(np.float64) if self._drift_per_s.any() else None
        try:
            rgb = self.model.render(depth, gain=gain)
        except InputDataError as err:
            raise DeviceOperationError(f"depth provider returned an unusable map: {err}") from err
        with self._lock:
            self._seq += 1
            seq = self._seq
        return SensorFrame(rgb=rgb, timestamp_us=now_us(), seq=seq)


class StreamingSimulatedSensor(SimulatedSensor):
    """The simulated sensor as a streaming camera (``--sensor sim-camera``): it renders the
    gel on a clock of its own, as a GelSight Mini streams at 25 frames/s, rather than when
    read. Each image is rendered at its exposure (the contact at that moment), delivered
    ``latency_ms`` after the exposure (or once rendered, if that takes longer), stamped at
    the exposure (a camera whose latency is known, as ``--sensor-latency-ms`` states it)
    and stamped again at its delivery (``SensorFrame.arrival_us``: the ledger's
    ``sensor_delivery`` holds the latency, or the render); the station is told of each one
    (:attr:`~remote_site.sensor.base.TactileSensor.notifies_frames`). Exposures keep their
    rate whatever the latency: images in flight wait in a queue, as in a camera's pipeline.

    Args:
        depth_provider, settings, seed, led_drift_per_min, clock_s: as for
            :class:`SimulatedSensor`.
        fps: images per second (``--sensor-fps``; a GelSight Mini's 25 by default).
        latency_ms: from an image's exposure to its delivery (``--sensor-latency-ms``).
        first_frame_timeout_s: how long connect() waits for the first image.

    Raises:
        ConfigError: a rate outside (0, 1000] or a negative or non-finite latency.
    """

    captures_on_demand = False
    notifies_frames = True

    def __init__(self, depth_provider: DepthProvider | None = None,
                 settings: PhotometricSettings | None = None, seed: int = 0, *,
                 led_drift_per_min: float = 0.0,
                 clock_s: Callable[[], float] | None = None,
                 fps: float = 25.0, latency_ms: float = 0.0,
                 first_frame_timeout_s: float = 5.0) -> None:
        fps, latency_ms = float(fps), float(latency_ms)
        if not (math.isfinite(fps) and 0.0 < fps <= 1000.0):
            raise ConfigError(f"sim-camera fps must be in (0, 1000], got {fps}")
        if not (math.isfinite(latency_ms) and latency_ms >= 0.0):
            raise ConfigError(f"sim-camera latency_ms must be finite and >= 0, got {latency_ms}")
        super().__init__(depth_provider, settings, seed, led_drift_per_min=led_drift_per_min,
                         clock_s=clock_s)
        self.fps, self.latency_ms = fps, latency_ms
        self.first_frame_timeout_s = float(first_frame_timeout_s)
        self._held: SensorFrame | None = None
        self._held_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        #: the last render failure (the thread goes on; connect() names it if no image came)
        self.render_error: str | None = None
        self._render_failures = 0

    def _connect(self) -> None:
        super()._connect()
        self._held = None
        self.render_error = None
        self._render_failures = 0
        self._stop.clear()
        self._thread = threading.Thread(target=self._stream, name="sim-camera", daemon=True)
        self._thread.start()
        deadline = time.monotonic() + self.first_frame_timeout_s
        while self._held is None and time.monotonic() < deadline:
            time.sleep(0.002)
        if self._held is None:
            self._disconnect()
            cause = f" (last render error: {self.render_error})" if self.render_error else ""
            raise DeviceInitError(f"sim-camera delivered no image within "
                                  f"{self.first_frame_timeout_s} s{cause}")

    def _disconnect(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def _is_healthy(self) -> bool:
        thread = self._thread
        return thread is not None and thread.is_alive()

    @property
    def health(self) -> SensorHealth:
        """Ended when its thread is gone while connected (it should never be)."""
        thread = self._thread
        if thread is not None and not thread.is_alive() and not self._stop.is_set():
            return SensorHealth(ended=True, reason=self.render_error or "stream thread ended")
        return SensorHealth()

    def _stream(self) -> None:
        # one clock for the schedule and the stamps (now_us never steps): an image is due
        # its latency after its exposure, so the arrival stamp follows the exposure stamp by
        # at least the latency, by construction
        period_us, latency_us = round(1e6 / self.fps), round(self.latency_ms * 1000.0)
        in_flight: collections.deque[tuple[int, SensorFrame]] = collections.deque()  # (due, image)
        next_us = now_us()
        while not self._stop.is_set():
            if now_us() >= next_us:  # an exposure: the gel as it is now
                exposure_us = now_us()
                frame = self._render_safely()
                if frame is not None:
                    in_flight.append((exposure_us + latency_us,
                                      SensorFrame(frame.rgb, exposure_us, frame.seq)))
                next_us = max(next_us + period_us, now_us())  # fell behind: no burst
            while in_flight and in_flight[0][0] <= (arrival_us := now_us()):
                image = dataclasses.replace(in_flight.popleft()[1], arrival_us=arrival_us)
                with self._held_lock:
                    self._held = image
                self._frame_arrived()
            wake_us = min(next_us, in_flight[0][0]) if in_flight else next_us
            self._stop.wait(max(0.0, (wake_us - now_us()) / 1e6))

    def _render_safely(self) -> SensorFrame | None:
        """One image, or None when rendering failed (logged the first time and counted:
        a failing depth provider must not end the stream)."""
        try:
            return self._render_now()
        except Exception as err:  # the world's provider, whatever it raises
            self.render_error = f"{type(err).__name__}: {err}"
            self._render_failures += 1
            if self._render_failures == 1:
                log.warning("sim-camera: no image: %s", self.render_error)
            return None

    def _latest(self) -> SensorFrame | None:
        with self._held_lock:
            return self._held
