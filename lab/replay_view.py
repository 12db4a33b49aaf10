"""A recording replayed into the live view (``teletouch replay FILE --view HOST:PORT``).

:class:`ReplayViewSource` is a :class:`shared.view.ViewSource` fed by a
:class:`lab.replay.Replayer` through its subscriber hook: the page a running station serves
(``shared/view/page``) shows the replayed session at the replay's pace, with the same panels.
Every snapshot carries a ``replay`` block (file, recording date, speed, position, paused,
ended), and the page labels itself a replay everywhere a live session says "live": nothing
old is shown as fresh.

What is shown comes from the recording (``docs/recording.md``): the pins as recorded
(``/local/pins``: commanded, measured, safe reason; a sample older than 2.5 sample periods
is not shown: what the pins did then is unknown, as in recordings made before the safe
state was sampled, which have no sample while the pins were safe), the newest tactile
frame (decoded in
order, compact frames included), the probe over the phantom (the recorded
``platform_state``, through the recorded workspace), the arm's end effector and force, and
the per-stage latency of the newest tactile frame (``/<station>/latency``; a stage whose
name is not ``<stage>_to_<stage>`` of protocol stage names, or whose value is not a finite
number, is left out: the file is input, not trusted). Ages are in
recorded time (the replay position minus the item's recorded time), so they stand still
while the replay is paused. The palpation analysis is re-run, as at the live station, on the
frames the station accepted (``/local/frame_accepted``), so findings appear as the replayed
palpation goes on.

Threads: the subscriber runs on the replay thread and only keeps references (and appends a
trajectory point at most 40 times a second of recorded time); :meth:`live` runs on the view
server's thread.
"""

from __future__ import annotations

import collections
import math
import re
import threading
from pathlib import Path
from typing import Any

import numpy as np

from lab.replay import Replayer, ReplayEvent
from local_site.render.pin_command import PIN_PITCH_MM
from local_site.view.analysis import LiveAnalysis, LiveAnalysisConfig
from shared.errors import ConfigError, InputDataError
from shared.protocol import ArmState, PlatformState, TactileCompact, TactileFrame, Welcome
from shared.protocol.messages import _STAGE_PATTERN
from shared.protocol.tactile_codec import TactileDecoder
from shared.timebase import now_us
from shared.view.encode import encode_patch, num, nums
from shared.workspace import load_workspace

__all__ = ["ReplayViewSource"]

_TRAIL_PERIOD_US = 25_000  # at most 40 trajectory points per recorded second
_MAX_TRAIL = 50_000
_PENDING = 512  # accepted frames / frames waiting for their partner (bounded)
_DEFAULT_ANALYSIS = LiveAnalysisConfig()
#: a latency stage name: ``<stage>_to_<stage>`` of protocol stage names, ``_<n>`` when repeated
#: (``shared.recording.writer.hop_stages_ms``)
_STAGE_NAME = re.compile(rf"(?:{_STAGE_PATTERN.pattern})_to_(?:{_STAGE_PATTERN.pattern})"
                         r"(?:_\d{1,4})?")
#: a pins sample older than this many sample periods is not shown (unknown)
_PINS_MAX_AGE_PERIODS = 2.5
_PINS_DEFAULT_RATE_HZ = 50.0  # the station's default record_pins_rate_hz


def _finite(v: Any) -> float | None:
    """``v`` when it is a finite number (not a bool), else None."""
    if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v):
        return float(v)
    return None


def _pins16(v: Any) -> list[float | None] | None:
    """The 16 pin values, or None unless ``v`` is a list of 16 finite numbers."""
    if not isinstance(v, list) or len(v) != 16:
        return None
    vals = [_finite(x) for x in v]
    return None if None in vals else vals


def _pins_period_us(rec: Any) -> float:
    """The recording's pins sample period: the recorded rate (``pins_rate_hz`` in the start
    metadata), else (older recordings) the median interval of the samples, else the
    station's default rate."""
    rate = _finite(rec.meta.get("pins_rate_hz"))
    if rate is not None and rate > 0:
        return 1e6 / rate
    t = np.asarray([m.t_us for m in rec.on(f"/{rec.station}/pins")], dtype=np.int64)
    gaps = np.diff(t)
    gaps = gaps[gaps > 0]
    return float(np.median(gaps)) if gaps.size else 1e6 / _PINS_DEFAULT_RATE_HZ


def _rx_us(frame: TactileFrame, fallback: int) -> int:
    return next((h.t_us for h in reversed(frame.hops)
                 if h.clock == "local" and h.stage == "station_rx"), fallback)


class ReplayViewSource:
    """The live view's source for a replay (see the module docstring).

    Args:
        replayer: the replay (subscribed to here; its clock gives the position).
        analysis: settings of the re-run palpation analysis; None: none.

    Raises:
        ConfigError: the recorded workspace settings are invalid.
    """

    def __init__(self, replayer: Replayer,
                 analysis: LiveAnalysisConfig | None = _DEFAULT_ANALYSIS) -> None:
        rec = replayer.recording
        self.replayer = replayer
        self.station = rec.station
        recorded_ws = rec.meta.get("workspace")
        try:
            self.workspace = load_workspace(
                explicit=recorded_ws if isinstance(recorded_ws, dict) else None)
        except ConfigError as err:
            raise ConfigError(f"the recording's workspace settings: {err}") from err
        lo, hi = self.workspace.phantom_bounds_mm
        self._bounds = [nums(lo[:2], 3), nums(hi[:2], 3)]
        # recorded_at_us: the first message's wall-clock time at the recording station
        self._file = {"file": Path(rec.path).name, "station": rec.station,
                      "complete": rec.complete, "recorded_at_us": replayer.clock.start_us}
        self._lock = threading.Lock()
        self._decoder = TactileDecoder()
        self._frame: tuple[TactileFrame, int] | None = None
        self._platform: tuple[PlatformState, int] | None = None
        self._arm: tuple[ArmState, int] | None = None
        self._pins: tuple[dict[str, Any], int] | None = None
        self._pins_max_age_us = _PINS_MAX_AGE_PERIODS * _pins_period_us(rec)
        self._latency: tuple[dict[str, Any], int] | None = None
        self._trail: list[list[float]] = []
        self._trail_first = 0
        self._last_trail_us = -_TRAIL_PERIOD_US
        # frames and acceptances meet by (seq, station_rx): either may be replayed first
        self._frames_by_key: collections.OrderedDict[tuple[int, int], TactileFrame] = \
            collections.OrderedDict()
        self._accepted_keys: collections.OrderedDict[tuple[int, int], None] = \
            collections.OrderedDict()
        self._to_analyse: collections.deque[TactileFrame] = collections.deque(maxlen=4096)
        has_accepted = any(True for _ in rec.on(f"/{rec.station}/frame_accepted"))
        self._analysis = (LiveAnalysis(self.workspace.config, analysis)
                          if analysis is not None and has_accepted else None)
        replayer.subscribe(self.on_event)

    # ------------------------------------------------------------------ replay thread

    def on_event(self, ev: ReplayEvent) -> None:
        """One replayed message (the replayer's subscriber; keeps references only)."""
        msg, topic, t = ev.message, ev.topic, ev.t_us
        if isinstance(msg, Welcome):  # a new link session: the station forgot its key frame
            self._decoder.reset()
            return
        if isinstance(msg, TactileCompact):
            try:  # in order, as the station decoded them
                msg = self._decoder.decode(msg)
            except InputDataError:
                return  # the station refused it too
        if isinstance(msg, TactileFrame):
            with self._lock:
                self._frame = (msg, t)
            self._match((msg.seq, _rx_us(msg, t)), msg)
        elif isinstance(msg, PlatformState):
            self._platform = (msg, t)
            if t - self._last_trail_us >= _TRAIL_PERIOD_US:
                self._last_trail_us = t
                self._add_trail(msg, t)
        elif isinstance(msg, ArmState):
            self._arm = (msg, t)
        elif ev.data is not None:
            name = topic.rsplit("/", 1)[-1]
            if name == "pins":
                self._pins = (ev.data, t)
            elif name == "latency" and ev.data.get("type") in ("tactile_frame",
                                                               "tactile_compact"):
                self._latency = (ev.data, t)
            elif name == "frame_accepted":
                seq, rx = ev.data.get("seq"), ev.data.get("rx_us")
                if isinstance(seq, int) and isinstance(rx, int):
                    self._match((seq, rx), None)

    def _match(self, key: tuple[int, int], frame: TactileFrame | None) -> None:
        if self._analysis is None:
            return
        if frame is None:
            found = self._frames_by_key.pop(key, None)
            if found is None:
                self._accepted_keys[key] = None
                while len(self._accepted_keys) > _PENDING:
                    self._accepted_keys.popitem(last=False)
            else:
                self._to_analyse.append(found)
        elif key in self._accepted_keys:
            del self._accepted_keys[key]
            self._to_analyse.append(frame)
        else:
            self._frames_by_key[key] = frame
            while len(self._frames_by_key) > _PENDING:
                self._frames_by_key.popitem(last=False)

    def _add_trail(self, msg: PlatformState, t: int) -> None:
        ph = self.workspace.forward(np.asarray(msg.position_mm, dtype=np.float64))
        frame = self._frame
        contact = frame is not None and bool(frame[0].contact)
        with self._lock:
            if len(self._trail) >= 2 * _MAX_TRAIL:
                del self._trail[:_MAX_TRAIL]
                self._trail_first += _MAX_TRAIL
            self._trail.append([round(float(ph[0]), 2), round(float(ph[1]), 2),
                                round(float(ph[2]), 2), 1.0 if contact else 0.0])

    # ------------------------------------------------------------------ ViewSource

    def _replay_doc(self, position_us: int) -> dict[str, Any]:
        clock = self.replayer.clock
        return {**self._file, "speed": clock.speed, "paused": clock.paused,
                "started": clock.started, "ended": clock.finished,
                "position_s": num((position_us - clock.start_us) / 1e6, 3),
                "duration_s": num((clock.end_us - clock.start_us) / 1e6, 3),
                "position_us": position_us}

    def live(self) -> dict[str, Any]:
        """The replayed state at the replay's position (``docs/view.md``, plus ``replay``)."""
        pos = self.replayer.clock.position_us()

        def age_ms(t_us: int) -> float | None:
            return num(max(0, pos - t_us) / 1e3, 1)

        if self._analysis is not None:
            while self._to_analyse:
                self._analysis.add(self._to_analyse.popleft())
            self._analysis.poll()
        platform_item, frame_item = self._platform, self._frame
        platform = None if platform_item is None else tuple(
            float(v) for v in platform_item[0].position_mm)
        phantom = None if platform is None else self.workspace.forward(np.asarray(platform))
        patch = None
        if frame_item is not None:
            patch = encode_patch(frame_item[0], frame_item[1], platform, PIN_PITCH_MM)
            if patch is not None:
                patch["age_ms"] = age_ms(frame_item[1])
        pins = safe_reason = None
        pins_item = self._pins
        if pins_item is not None and pos - pins_item[1] > self._pins_max_age_us:
            pins_item = None  # no sample for 2.5 periods: what the pins did is unknown
        if pins_item is not None:
            doc, t = pins_item
            measured = _pins16(doc.get("measured_mm"))
            pins = {"commanded_mm": _pins16(doc.get("commanded_mm")),
                    "stiffness_k": _pins16(doc.get("stiffness_k")),
                    "friction": _pins16(doc.get("friction")), "measured_mm": measured,
                    "measured_age_ms": None if measured is None else age_ms(t),
                    "board_safe_state": None, "recorded": True}
            reason = doc.get("safe_reason")
            safe_reason = None if reason is None else str(reason)
        arm = self._arm
        probe = {
            "platform_mm": None if platform is None else nums(platform, 3),
            "phantom_mm": None if phantom is None else nums(phantom, 3),
            # on the replay's clock: a platform that stopped reporting in the recording is
            # drawn stale in the replay too
            "platform_age_ms": None if platform_item is None else age_ms(platform_item[1]),
            "end_effector_mm": None if arm is None else nums(arm[0].position_mm, 3),
            "end_effector_force_n": None if arm is None else num(arm[0].force_n),
            "arm_status": None if arm is None else arm[0].status,
            "arm_age_ms": None if arm is None else age_ms(arm[1])}
        latency = None
        lat = self._latency
        if lat is not None:
            stages = lat[0].get("stages_ms")
            stages = stages if isinstance(stages, dict) else {}
            latency = {"stages_ms": {k: num(_finite(v), 3) for k, v in stages.items()
                                     if _STAGE_NAME.fullmatch(k) and _finite(v) is not None},
                       "end_to_end_ms": num(_finite(lat[0].get("end_to_end_ms")), 3),
                       "age_ms": age_ms(lat[1])}
        analysis = None
        if self._analysis is not None:
            analysis = {"alive": self._analysis.alive,
                        "frames_sent": self._analysis.frames_sent,
                        "version": self._analysis.version}
        return {"station": self.station, "t_us": now_us(), "workspace_mm": self._bounds,
                "replay": self._replay_doc(pos), "pins": pins, "patch": patch,
                "probe": probe, "link": {"state": "replay"},
                "safe": {"reason": safe_reason, "known": pins_item is not None},
                "latency": latency, "display_loop": {}, "analysis_state": analysis}

    def trail_since(self, start: int, limit: int) -> tuple[int, list[list[float]]]:
        """Trajectory points (phantom x, y, z mm and contact 0/1) from index ``start``."""
        with self._lock:
            first = max(start, self._trail_first)
            offset = first - self._trail_first
            return first, self._trail[offset:offset + limit]

    def analysis(self) -> tuple[int, dict[str, Any] | None]:
        """The re-run analysis' newest result and its version."""
        if self._analysis is None:
            return 0, None
        return self._analysis.version, self._analysis.result

    def control(self, doc: dict[str, Any] | Any) -> None:
        """A browser's ``{"type": "control", "action": "pause" | "play"}``.

        Raises:
            ValueError: another action.
        """
        action = doc.get("action") if isinstance(doc, dict) else None
        if action == "pause":
            self.replayer.clock.pause()
        elif action == "play":
            self.replayer.clock.play()
        else:
            raise ValueError(f"unknown replay control {action!r} (pause, play)")

    def close(self) -> None:
        """Stop the analysis process (as a station's view does: a run still going after
        a second is cut short, its result is not kept anyway; Ctrl-C must end the replay
        promptly on a busy machine too)."""
        if self._analysis is not None:
            self._analysis.close()

