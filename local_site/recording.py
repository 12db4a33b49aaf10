"""The local station's recording: written as MCAP while it runs, read back as arrays.

``teletouch local --record PATH.mcap`` writes, through
:class:`shared.recording.McapRecorder`, every message the station sends and receives
(``/local/tx/*``, ``/local/rx/*``), the derived JSON channels (trajectory, tactile,
latency) and two of its own (``docs/recording.md``):

* ``/local/frame_accepted``: each received tactile frame the display loop accepted into its
  scene (``seq``, ``rx_us``);
* ``/local/pins``: the 16 pins commanded and measured and the safe-state reason, at
  ``record_pins_rate_hz`` while rendering and while in the safe state, and at once on every
  change between them (in the safe state no command exists: the commanded values are null;
  the measured values are null while the board's latest feedback is older than
  :data:`MEASURED_MAX_AGE_S`). The rate is written into the start metadata
  (``pins_rate_hz``).

:func:`load_recording` reads such a file into :class:`Recording`, the arrays the palpation
analysis reads: the platform positions sent (``platform_state`` tx) and the tactile frames
accepted (``tactile_frame`` rx named in ``/local/frame_accepted``; ``tactile_compact``
messages are decoded in order, as the station decodes them). All frames of a
recording share the first accepted frame's layer shape; a frame of another shape is left
out and counted in ``meta["counts"]["frames_rejected_shape"]``. A file cut short (the
station was killed) is read up to its last complete chunk (``meta["complete"]`` is False).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from shared.errors import ConfigError, InputDataError
from shared.protocol import Message, PlatformState, TactileCompact, TactileFrame, Welcome
from shared.protocol.tactile_codec import TactileDecoder
from shared.recording import McapRecorder, McapRecording, RecordingFormatError, read_mcap
from shared.timebase import now_us

__all__ = ["MEASURED_MAX_AGE_S", "PinsSampler", "Recording", "SessionRecorder", "load_recording",
           "recording_from_mcap"]

log = logging.getLogger(__name__)


#: one pins sample: (wall-clock us, the command on the pins, the measured positions or None,
#: the safe-state reason or None)
PinsSample = tuple[int, Any, Any, "str | None"]

#: the board's measured positions are recorded only while its latest feedback arrived at
#: most this long before the sample (ten periods of the drive board's 500 Hz feedback, one
#: period of the default 50 Hz sampling); older ones are not what the pins do now: unknown
MEASURED_MAX_AGE_S = 0.02


class PinsSampler:
    """Samples the pins' state at ``rate_hz``, and at once on every change of that state.

    The state is what the pins do: rendering a command, or held in their safe state (and
    why; no command exists then: ``commanded`` None). Both are sampled, so a replay never
    shows the last command as rendering while the pins were safe. Neither (no command and no
    safe state: before the first command, or for the tick between leaving the safe state
    and the next command) is not sampled: a reader takes a sample older than a few periods
    as unknown.

    Offered the state on every display-loop tick (in whichever process the loop runs), it
    returns a sample when one is due: the command then on the pins (or None), the board's
    measured positions and the safe-state reason, with the wall-clock time they were read.
    The measured positions are None when there is no feedback (not connected, no report
    yet) or when the latest feedback arrived more than ``measured_max_age_s`` before the
    sample (a silent board, a link that stopped): a sample never presents old positions as
    the pins' state at its time. A sample is due ``1 / rate_hz`` after the previous one, or
    at once when the state changed (a new command alone is no change: commands change every
    frame).

    Args:
        rate_hz: samples per second while the state stays the same (> 0).
        measured_max_age_s: oldest feedback whose positions are recorded (> 0).

    Raises:
        ConfigError: a rate or an age that is not > 0.
    """

    def __init__(self, rate_hz: float, *,
                 measured_max_age_s: float = MEASURED_MAX_AGE_S) -> None:
        if not rate_hz > 0:
            raise ConfigError(f"pins_rate_hz must be > 0, got {rate_hz}")
        if not measured_max_age_s > 0:
            raise ConfigError(f"measured_max_age_s must be > 0, got {measured_max_age_s}")
        self.rate_hz = rate_hz
        self._period_s = 1.0 / rate_hz
        self._max_age_us = round(measured_max_age_s * 1e6)
        self._next_s = 0.0
        #: (a command is on the pins, safe reason) of the last sample; None: none yet
        self._state: tuple[bool, str | None] | None = None

    def offer(self, commanded: Any, display: Any, safe_reason: str | None
              ) -> PinsSample | None:
        """The sample, when one is due (else None, at once)."""
        if commanded is None and safe_reason is None:
            return None  # nothing on the pins and not safe: no state to record
        now = time.monotonic()
        state = (commanded is not None, safe_reason)
        if now < self._next_s and state == self._state:
            return None
        self._state = state
        self._next_s = now + self._period_s
        measured = display.latest_feedback() if display.is_connected else None
        # on the wall clock the station's messages are stamped on (shared.timebase: a
        # display process adopts the station's anchor), so /local/pins lines up with them;
        # the feedback's t_us (its arrival) is on the same clock
        t_us = now_us()
        positions = None
        if measured is not None and t_us - measured.t_us <= self._max_age_us:
            positions = measured.position_mm
        return (t_us, commanded, positions, safe_reason)


class SessionRecorder:
    """The local station's MCAP recorder (see the module docstring).

    Never blocks: every call is a bounded-queue put for the writer thread (drops counted).

    Args:
        path: the ``.mcap`` file.
        meta: settings written into the recording's start metadata (workspace, scene, ...).
        queue_size: see :class:`~shared.recording.McapRecorder`.
        pins_rate_hz: rate of ``/local/pins``.
        flush_interval_s: a chunk is completed at least this often.
        image_rate_hz: rate of the ``/local/tactile_image`` channel; None: none.

    Raises:
        ConfigError: the file cannot be created, or bad settings.
    """

    def __init__(self, path: str | os.PathLike[str], meta: Mapping[str, Any] | None = None, *,
                 queue_size: int = 8192, pins_rate_hz: float = 50.0,
                 flush_interval_s: float = 1.0, image_rate_hz: float | None = None) -> None:
        meta = {**(meta or {}), "pins_rate_hz": pins_rate_hz}
        self.mcap = McapRecorder(path, "local", meta=meta, queue_size=queue_size,
                                 flush_interval_s=flush_interval_s, image_rate_hz=image_rate_hz)
        self.path = self.mcap.path
        #: decides when the pins are sampled (at ``pins_rate_hz``)
        self.pins_sampler = PinsSampler(pins_rate_hz)
        self.frames = 0

    def tap(self, direction: str, msg: Message, t_us: int) -> None:
        """Record a message the station link sent or received (a ``StationLink.tap``)."""
        self.mcap.tap(direction, msg, t_us)

    def add_frame(self, frame: TactileFrame, rx_us: int) -> None:
        """Note that the display loop accepted ``frame`` (received at ``rx_us``)."""
        self.frames += 1
        self.mcap.derived("frame_accepted", rx_us, {"seq": frame.seq, "rx_us": rx_us})

    def add_pins(self, commanded: Any, display: Any, safe_reason: str | None) -> None:
        """Offer the pins' state; recorded at ``pins_rate_hz`` and on every change of state
        (see :class:`PinsSampler`; else returns at once).

        Args:
            commanded: the :class:`~local_site.render.PinCommand` on the pins, or None (the
                safe state, or no command yet: not recorded).
            display: the :class:`~local_site.display.base.ArrayTacDisplay` (its latest
                feedback is the measured heights).
            safe_reason: why the pins are in their safe state (None: rendering).
        """
        sample = self.pins_sampler.offer(commanded, display, safe_reason)
        if sample is not None:
            self.record_pins(*sample)

    def record_pins(self, t_us: int, commanded: Any, measured_mm: Any,
                    safe_reason: str | None) -> None:
        """Record one pins sample taken elsewhere (a :class:`PinsSampler`'s, e.g. in the
        display process), stamped when it was taken.

        Args:
            t_us: when the state was read (wall clock, us).
            commanded: the :class:`~local_site.render.PinCommand` then on the pins, or None
                (the safe state: recorded as null values).
            measured_mm: the board's measured pin positions then (None: no feedback, or
                none recent enough: see :class:`PinsSampler`).
            safe_reason: why the pins were in their safe state (None: rendering).
        """

        def payload() -> dict[str, Any]:
            h, k, f = ([None] * 3 if commanded is None
                       else [np.ravel(a).tolist() for a in commanded.arrays()])
            return {"commanded_mm": h, "stiffness_k": k, "friction": f,
                    "measured_mm": None if measured_mm is None
                    else np.ravel(measured_mm).tolist(),
                    "safe_reason": safe_reason}

        self.mcap.derived("pins", t_us, payload)

    def add_findings(self, workspace: Any = None) -> int | None:
        """Analyse what was recorded so far and record the findings (``/local/findings``).

        Blocks (waits for the writer, reads the file, builds the maps): call it at a stop,
        never from a loop.

        Args:
            workspace: the platform <-> phantom map (default: the recorded one).

        Returns:
            The number of findings recorded, or None when there was nothing to analyse
            (no contact frame, a cut file); the reason is logged.
        """
        from local_site.palpation import analyse_recording  # the analysis reads Recording

        if not self.mcap.sync():
            log.warning("findings not recorded: the recording is not all on disk (%s)",
                        "a write failed" if self.mcap.write_errors
                        else "the writer did not catch up in time")
            return None
        try:
            findings = analyse_recording(load_recording(self.path), workspace)
        except (InputDataError, ConfigError) as err:
            log.info("no findings recorded: %s", err)
            return None
        # the session's clock (shared.timebase), as every other message: never stepped
        self.mcap.derived("findings", now_us(), {"findings": [
            {"x_mm": f.center_mm[0], "y_mm": f.center_mm[1], "kind": f.kind,
             "radius_mm": f.equivalent_radius_mm, "confidence": getattr(f, "confidence", None),
             "severity_rank": f.severity_rank} for f in findings]})
        return len(findings)

    def counts(self) -> dict[str, Any]:
        """Frames accepted, messages written and dropped so far."""
        return {"frames": self.frames, **self.mcap.counts()}

    def close(self, end_meta: Mapping[str, Any] | None = None) -> Path:
        """Finish the file (idempotent); return its path.

        Raises:
            ConfigError: the file could not be finished.
        """
        self.mcap.close(end_meta)
        return self.path


@dataclass(frozen=True, eq=False)
class Recording:
    """Platform samples sent and tactile frames accepted by the local station.

    Attributes:
        platform_t_us: (P,) sample times (local clock).
        platform_mm: (P, 3) platform positions sent.
        frame_center_mm: (N, 2) patch centres, platform coordinates.
        frame_pitch_mm: (N,) patch pitch, platform mm.
        frame_contact: (N,) bool.
        frame_force_n: (N,) normal force.
        frame_indentation_mm: (N,) probe indentation.
        frame_height_mm: (N, H, W) height patches.
        frame_rx_us: (N,) receive times (local clock).
        frame_seq: (N,) tactile frame sequence numbers.
        frame_stiffness_k: (N, H, W) display k, or None when not recorded.
        frame_stiffness_n_per_mm: (N, H, W) measured stiffness, or None.
        meta: free-form metadata (session, workspace settings, counts).
    """

    platform_t_us: NDArray[np.int64]
    platform_mm: NDArray[np.float64]
    frame_center_mm: NDArray[np.float64]
    frame_pitch_mm: NDArray[np.float64]
    frame_contact: NDArray[np.bool_]
    frame_force_n: NDArray[np.float64]
    frame_indentation_mm: NDArray[np.float64]
    frame_height_mm: NDArray[np.float32]
    frame_rx_us: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    frame_seq: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    frame_stiffness_k: NDArray[np.float32] | None = None
    frame_stiffness_n_per_mm: NDArray[np.float32] | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = self.frame_center_mm.shape[0]
        checks = {
            "frame_center_mm": self.frame_center_mm.shape == (n, 2),
            "frame_pitch_mm": self.frame_pitch_mm.shape == (n,),
            "frame_contact": self.frame_contact.shape == (n,),
            "frame_force_n": self.frame_force_n.shape == (n,),
            "frame_indentation_mm": self.frame_indentation_mm.shape == (n,),
            "frame_height_mm": self.frame_height_mm.ndim == 3
            and self.frame_height_mm.shape[0] == n,
            "platform_mm": self.platform_mm.ndim == 2 and self.platform_mm.shape[1] == 3,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise InputDataError(f"recording arrays of inconsistent shape: {bad} ({n} frames)")
        for name in ("frame_center_mm", "frame_pitch_mm", "frame_force_n",
                     "frame_indentation_mm", "frame_height_mm", "platform_mm"):
            if not np.isfinite(getattr(self, name)).all():
                raise InputDataError(f"recording array {name} has NaN or Inf")
        if n and not (self.frame_pitch_mm > 0).all():
            raise InputDataError("recording frame_pitch_mm must be > 0")

    @property
    def frames(self) -> int:
        """Number of tactile frames."""
        return int(self.frame_center_mm.shape[0])


def _rx_us(frame: TactileFrame, fallback: int) -> int:
    return next((h.t_us for h in reversed(frame.hops)
                 if h.clock == "local" and h.stage == "station_rx"), fallback)


def load_recording(path: str | os.PathLike[str]) -> Recording:
    """Read a local station's MCAP recording into :class:`Recording`.

    Raises:
        InputDataError: not a Tele-Touch recording (:class:`RecordingFormatError`), another
            station's recording, or inconsistent / non-finite data.
    """
    return recording_from_mcap(read_mcap(path))


def recording_from_mcap(rec: McapRecording) -> Recording:
    """:func:`load_recording` of a recording already read with ``read_mcap``.

    Raises:
        InputDataError: another station's recording, or inconsistent / non-finite data.
    """
    if rec.station != "local":
        raise RecordingFormatError(f"{rec.path} is the {rec.station!r} station's recording; "
                                   "the palpation analysis reads the local station's")
    accepted: set[tuple[int, int]] = set()
    for m in rec.on("/local/frame_accepted"):
        doc = m.json()
        seq, rx_us = doc.get("seq"), doc.get("rx_us")
        if not (type(seq) is int and type(rx_us) is int):  # bool is no number either
            raise RecordingFormatError(
                f"{rec.path}: a /local/frame_accepted message without integer seq and rx_us "
                f"({str(doc)[:120]})")
        accepted.add((seq, rx_us))
    p_t: list[int] = []
    p_mm: list[tuple[float, float, float]] = []
    cols: list[tuple[Any, ...]] = []
    shape: tuple[int, int] | None = None
    rejected_shape = 0
    decoder = TactileDecoder()  # compact frames decode in order, as the station did
    for m, wire in rec.wire_messages():
        msg: Message | None = wire
        if isinstance(wire, Welcome):  # a new link session: the station forgot its key frame
            decoder.reset()
            continue
        if isinstance(wire, TactileCompact) and m.topic == "/local/rx/tactile_compact":
            try:
                msg = decoder.decode(wire)
            except InputDataError:
                msg = None  # the station refused it too
            if msg is None:
                continue
        if isinstance(msg, PlatformState) and m.topic == "/local/tx/platform_state":
            p_t.append(msg.ts_us)
            p_mm.append(msg.position_mm)
        elif isinstance(msg, TactileFrame) and m.topic in ("/local/rx/tactile_frame",
                                                           "/local/rx/tactile_compact"):
            rx = _rx_us(msg, m.t_us)
            if (msg.seq, rx) not in accepted:
                continue
            height = msg.layers["height_mm"]
            hw = (int(height.shape[0]), int(height.shape[1]))
            if shape is None:
                shape = hw
            elif hw != shape:
                rejected_shape += 1
                continue
            k = msg.layers.get("stiffness_k")
            n = msg.layers.get("stiffness_n_per_mm")
            cols.append((rx, msg.seq, msg.center_mm, msg.pitch_mm, msg.contact, msg.force_n,
                         msg.indentation_mm, height.astype(np.float32),
                         np.ones(hw, np.float32) if k is None else k.astype(np.float32),
                         np.zeros(hw, np.float32) if n is None else n.astype(np.float32)))
    hw = shape or (0, 0)
    z = list(zip(*cols, strict=True)) if cols else [()] * 10

    def stack(i: int) -> NDArray[np.float32]:
        return np.stack(z[i]).astype(np.float32) if cols else np.zeros((0, *hw), np.float32)

    meta = dict(rec.meta)
    meta.update(layer_shape=list(hw), complete=rec.complete, stop_reason=rec.stop_reason,
                counts={"frames": len(cols), "platform_samples": len(p_t),
                        "frames_accepted_recorded": len(accepted),
                        "frames_rejected_shape": rejected_shape})
    return Recording(
        platform_t_us=np.asarray(p_t, np.int64),
        platform_mm=np.asarray(p_mm, np.float64).reshape(-1, 3),
        frame_center_mm=np.asarray(z[2], np.float64).reshape(-1, 2),
        frame_pitch_mm=np.asarray(z[3], np.float64),
        frame_contact=np.asarray(z[4], bool),
        frame_force_n=np.asarray(z[5], np.float64),
        frame_indentation_mm=np.asarray(z[6], np.float64),
        frame_height_mm=stack(7),
        frame_rx_us=np.asarray(z[0], np.int64),
        frame_seq=np.asarray(z[1], np.int64),
        frame_stiffness_k=stack(8),
        frame_stiffness_n_per_mm=stack(9),
        meta=meta)
