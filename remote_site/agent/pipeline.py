"""One sensor frame -> one tactile frame: capture, reconstruction, stiffness, assembly.

:meth:`FramePipeline.process` is synchronous and runs in the station's worker thread (or
directly in the benchmark). It never raises for a bad frame: a sensor timeout, a frame of
the wrong size, a saturated, black or NaN frame is logged (first of each kind at WARNING,
then at DEBUG), counted by reason and skipped. Skips the scene does not need are taken
here: frames without contact evidence are not integrated (the reconstructor returns zeros),
and reconstruction runs only at the patch pitch (block-pooled), not at full resolution.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from remote_site.agent.background import BackgroundTracker
from remote_site.agent.stiffness_stage import StiffnessStage
from remote_site.arm.base import ArmReading
from remote_site.reconstruction.reconstructor import Reconstructor
from remote_site.sensor.base import SensorFrame, TactileSensor
from remote_site.tactile import AppliedCommand, TactileAssembler
from shared.errors import DeviceError, DeviceTimeoutError, InputDataError
from shared.protocol.messages import TactileFrame

__all__ = ["FrameOutcome", "FramePipeline"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameOutcome:
    """What happened to one tick of the frame loop.

    Attributes:
        frame: the tactile frame to send, or None.
        status: ``ok``, ``rejected`` (see ``reason``) or ``repeated`` (no new sensor frame).
        reason: why the frame was rejected (``sensor_timeout``, ``sensor_error``,
            ``bad_frame``), else None.
        skipped_integration: the frame had no contact evidence (Poisson skipped).
        capture_s: time spent obtaining the sensor frame (the simulator renders here).
        reconstruct_s: reconstruction time.
        assemble_s: stiffness sampling and assembly time.
    """

    frame: TactileFrame | None
    status: str
    reason: str | None = None
    skipped_integration: bool = False
    capture_s: float = 0.0
    reconstruct_s: float = 0.0
    assemble_s: float = 0.0


class FramePipeline:
    """Sensor frame -> height patch + stiffness layers -> tactile frame.

    Args:
        sensor: a connected tactile sensor.
        reconstructor: built with the sensor's calibration.
        assembler: the tactile frame builder.
        stiffness: the station's stiffness state.
        read_arm: returns the arm's current reading (pad pose, force).
        platform_pitch_mm: wanted patch pitch on the display side (platform mm).
        sensor_max_age_ms: older sensor frames are refused.
        contact_force_n: a force at or above this means contact even without a visible
            height change.
        background: keeps the reconstructor's background fresh (offered every frame after
            its reconstruction); None: the calibration's background throughout.
    """

    def __init__(self, sensor: TactileSensor, reconstructor: Reconstructor,
                 assembler: TactileAssembler, stiffness: StiffnessStage,
                 read_arm: Callable[[], ArmReading], *, platform_pitch_mm: float = 0.5,
                 sensor_max_age_ms: float = 100.0, contact_force_n: float = 0.1,
                 background: BackgroundTracker | None = None) -> None:
        self.sensor = sensor
        self.reconstructor = reconstructor
        self.assembler = assembler
        self.stiffness = stiffness
        self.read_arm = read_arm
        self.phantom_pitch_mm = assembler.phantom_pitch_mm(platform_pitch_mm)
        self.sensor_max_age_ms = float(sensor_max_age_ms)
        self.contact_force_n = float(contact_force_n)
        self.background = background
        self.rejected: Counter[str] = Counter()
        self.skipped_integration = 0
        self.repeated = 0
        self.processed = 0
        self._last_sensor_seq: int | None = None

    def warm_up(self) -> float:
        """Run the reconstruction once on a synthetic press before the session starts.

        The compiled kernels load from numba's cache (or compile) on first use, holding the
        interpreter for tens to hundreds of ms; in the first frames of a session that
        stalled the station's other threads (the arm's watchdog halted 16-57 ms late in 13
        of 29 fault-suite scenarios, all within the first half second). Both the display-size
        and the full-resolution paths are run; the result is discarded.

        Returns:
            Seconds it took.
        """
        t0 = time.perf_counter()
        rgb = self.reconstructor.calibration.background_rgb.copy()
        h, w = rgb.shape[:2]
        yy, xx = np.ogrid[:h, :w]
        disc = (yy - h / 2) ** 2 + (xx - w / 2) ** 2 < (min(h, w) / 6) ** 2
        rgb[disc] = np.clip(rgb[disc].astype(np.int16) + np.array([40, -20, 10], np.int16),
                            0, 255).astype(np.uint8)
        for pitch in (self.phantom_pitch_mm, None):
            try:
                self.reconstructor.height_map(rgb, out_pitch_mm=pitch)
            except InputDataError as err:  # a calibration without this path: not fatal
                log.debug("reconstruction warm-up (pitch %s): %s", pitch, err)
        return time.perf_counter() - t0

    @property
    def patch_pitch_mm(self) -> float:
        """The phantom-side pitch actually used (a multiple of the sensor pixel)."""
        factor = self.reconstructor.pool_factor(self.phantom_pitch_mm)
        return float(self.reconstructor.calibration.mm_per_px * factor)

    def arm_read_failed(self, err: Exception) -> FrameOutcome:
        """The outcome of a tick whose arm read failed: a rejected frame (``arm_error``)."""
        return self._reject("arm_error", err)

    def _reject(self, reason: str, err: Exception) -> FrameOutcome:
        self.rejected[reason] += 1
        if self.rejected[reason] == 1:
            log.warning("sensor frame skipped (%s): %s", reason, err)
        elif log.isEnabledFor(logging.DEBUG):
            log.debug("sensor frame skipped (%s): %s", reason, err)
        return FrameOutcome(None, "rejected", reason)

    def process(self, seq: int, source: AppliedCommand | None) -> FrameOutcome:
        """Take the newest sensor frame and build the tactile frame ``seq`` (the arm's
        reading taken just before: a sensor that captures on demand takes the image now).

        Args:
            seq: sequence number for the tactile frame.
            source: the latest platform_state applied to the arm before this call.

        Returns:
            The outcome; never raises for bad frames or sensor hiccups.
        """
        t0 = time.perf_counter()
        try:
            reading = self.read_arm()
        except DeviceError as err:  # a lost read: no frame this tick, the loop goes on
            return self.arm_read_failed(err)
        taken = self.capture()
        if isinstance(taken, FrameOutcome):
            return taken
        return self.build(seq, taken[0], reading, source, time.perf_counter() - t0)

    @property
    def last_sensor_seq(self) -> int | None:
        """The ``seq`` of the last sensor frame taken (None: none yet)."""
        return self._last_sensor_seq

    def capture(self) -> tuple[SensorFrame, float] | FrameOutcome:
        """The newest sensor frame and the seconds it took (the simulator renders here), or
        the outcome of a tick without a new one (rejected or repeated). With a sensor that
        does not capture on demand this only takes the frame it holds (the station calls it
        on its event loop)."""
        t0 = time.perf_counter()
        try:
            sensor_frame = self.sensor.read_latest(self.sensor_max_age_ms)
        except DeviceError as err:
            reason = "sensor_timeout" if isinstance(err, DeviceTimeoutError) else "sensor_error"
            return self._reject(reason, err)
        if sensor_frame.seq == self._last_sensor_seq:
            self.repeated += 1
            return FrameOutcome(None, "repeated")
        self._last_sensor_seq = sensor_frame.seq
        return sensor_frame, time.perf_counter() - t0

    def build(self, seq: int, sensor_frame: SensorFrame, reading: ArmReading,
              source: AppliedCommand | None, capture_s: float = 0.0) -> FrameOutcome:
        """The tactile frame ``seq`` of one captured sensor frame.

        Args:
            seq: sequence number for the tactile frame.
            sensor_frame: from :meth:`capture`.
            reading: the arm when the image was taken (its pad pose places the patch).
            source: the platform_state the frame answers (applied before the image).
            capture_s: the capture's time, for the outcome.

        Returns:
            The outcome; never raises for bad frames.
        """
        t1 = time.perf_counter()
        try:
            height_map = self.reconstructor.height_map(sensor_frame.rgb,
                                                       out_pitch_mm=self.phantom_pitch_mm)
        except InputDataError as err:
            return self._reject("bad_frame", err)
        t2 = time.perf_counter()
        if height_map.skipped:
            self.skipped_integration += 1
        if self.background is not None:
            self.background.offer(sensor_frame.rgb, reading.force_n, height_map.contact)
        contact = height_map.contact or reading.force_n >= self.contact_force_n
        with self.stiffness.lock:
            current = self.stiffness.current_n_per_mm
            try:
                frame = self.assembler.assemble(
                    seq=seq, frame_ts_us=sensor_frame.timestamp_us,
                    sensor_arrival_us=sensor_frame.received_us,
                    height_mm=height_map.height_mm, pitch_mm=height_map.mm_per_px,
                    probe_mm=reading.position_mm, force_n=reading.force_n, contact=contact,
                    stiffness_map=self.stiffness.map, current_n_per_mm=current,
                    source=source)
            except InputDataError as err:
                return self._reject("bad_frame", err)
        t3 = time.perf_counter()
        self.processed += 1
        return FrameOutcome(frame, "ok", None, height_map.skipped, capture_s, t2 - t1, t3 - t2)
