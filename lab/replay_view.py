"""A recording replayed into the live view (``teletouch replay FILE --view HOST:PORT``).

:class:`ReplayViewSource` is a :class:`shared.view.ViewSource` fed by a
:class:`lab.replay.Replayer` through its subscriber hook: the page a running station serves
(``shared/view/page``) shows the replayed session at the replay's pace, with the same panels.
Every snapshot carries a ``replay`` block (file, recording date, speed, position, paused,
ended), and the page labels itself a replay everywhere a live session says "live": nothing
old is shown as fresh.

What is shown comes from the recording (``docs/recording.md``): the pins as recorded
(``/local/pins``: commanded, measured, safe reason), the newest tactile frame (decoded in
order, compact frames included), the probe over the phantom (the recorded
``platform_state``, through the recorded workspace), the arm's end effector and force, and
the per-stage latency of the newest tactile frame (``/<station>/latency``). Ages are in
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
import threading
from pathlib import Path
from typing import Any

import numpy as np

from lab.replay import Replayer, ReplayEvent
from local_site.render.pin_command import PIN_PITCH_MM
from local_site.view.analysis import LiveAnalysis, LiveAnalysisConfig
from shared.errors import ConfigError, InputDataError
from shared.protocol import ArmState, PlatformState, TactileCompact, TactileFrame
from shared.protocol.tactile_codec import TactileDecoder
from shared.timebase import now_us
from shared.view.encode import encode_patch, num, nums
from shared.workspace import load_workspace

__all__ = ["ReplayViewSource"]

_TRAIL_PERIOD_US = 25_000  # at most 40 trajectory points per recorded second
_MAX_TRAIL = 50_000
_PENDING = 512  # accepted frames / frames waiting for their partner (bounded)
_DEFAULT_ANALYSIS = LiveAnalysisConfig()


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
        if pins_item is not None:
            doc, t = pins_item
            pins = {"commanded_mm": doc.get("commanded_mm"),
                    "stiffness_k": doc.get("stiffness_k"), "friction": doc.get("friction"),
                    "measured_mm": doc.get("measured_mm"),
                    "measured_age_ms": None if doc.get("measured_mm") is None else age_ms(t),
                    "board_safe_state": None, "recorded": True}
            safe_reason = doc.get("safe_reason")
        arm = self._arm
        probe = {
            "platform_mm": None if platform is None else nums(platform, 3),
            "phantom_mm": None if phantom is None else nums(phantom, 3),
            "end_effector_mm": None if arm is None else nums(arm[0].position_mm, 3),
            "end_effector_force_n": None if arm is None else num(arm[0].force_n),
            "arm_status": None if arm is None else arm[0].status,
            "arm_age_ms": None if arm is None else age_ms(arm[1])}
        latency = None
        lat = self._latency
        if lat is not None:
            latency = {"stages_ms": {k: num(v, 3) for k, v in
                                     dict(lat[0].get("stages_ms") or {}).items()},
                       "end_to_end_ms": num(lat[0].get("end_to_end_ms"), 3),
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

