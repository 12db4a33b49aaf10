"""Simulated GelSight-style sensor: a depth-map provider rendered by the photometric model.

The simulator does not know where depth maps come from. It takes a *provider*, a callable
returning the current gel contact depth map (H x W, mm, >= 0, on the sensor's pixel grid),
or a map set with :meth:`SimulatedSensor.set_depth`. The phantom contact model plugs in as
``SimulatedSensor(depth_provider=lambda: phantom.contact(pose).depth_mm)``.
Each :meth:`read_latest` renders a fresh frame (seq + 1, timestamp = now).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from remote_site.sensor.base import SensorFrame, TactileSensor
from remote_site.sensor.photometric import PhotometricModel, PhotometricSettings
from shared.errors import DeviceOperationError, InputDataError
from shared.timebase import now_us

__all__ = ["DepthProvider", "SimulatedSensor"]

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

    def _latest(self) -> SensorFrame:
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
