"""What the local station's live view shows, read from the running agent.

:class:`StationView` is a :class:`shared.view.ViewSource`: the view server calls
:meth:`StationView.live` from its own thread at its snapshot rate (40 Hz by default), never
from the display loop. The display loop's only part is :meth:`StationView.frame_accepted`,
one ``deque.append`` per accepted tactile frame (at the frame rate, not the loop rate); the
rest is read from what the agent already keeps (newest platform sample, last pin command and
board feedback, safe-state reason, last latency trace, last arm state, link state).

Every value that can go stale carries its age (``age_ms``), so the page shows old data as old.
"""

from __future__ import annotations

import collections
import math
import threading
from typing import TYPE_CHECKING, Any

import numpy as np

from local_site.render.pin_command import PIN_PITCH_MM
from local_site.view.analysis import LiveAnalysis, LiveAnalysisConfig
from shared.protocol import ArmState, TactileFrame
from shared.timebase import monotonic_s, now_us
from shared.view.encode import encode_patch, num, nums
from shared.workspace import WorkspaceMap

if TYPE_CHECKING:
    from local_site.agent.station import LocalAgent

__all__ = ["StationView"]

_DEFAULT_ANALYSIS = LiveAnalysisConfig()
_MAX_TRAIL = 50_000  # trajectory points kept: 50k-100k (20-40 min at 40 Hz); then the oldest go


class StationView:
    """The local station's :class:`~shared.view.ViewSource` (see the module docstring).

    Args:
        agent: the opened agent (:meth:`LocalAgent.open` called).
        analysis: settings of the live analysis; None: no analysis (maps and findings off).
    """

    def __init__(self, agent: LocalAgent,
                 analysis: LiveAnalysisConfig | None = _DEFAULT_ANALYSIS) -> None:
        loop = agent.loop
        if loop is None or agent.reader is None:
            raise ValueError("StationView needs an opened LocalAgent")
        self.agent = agent
        self.loop = loop
        self.workspace = WorkspaceMap(agent.workspace)
        self._pin_pitch_mm = float(getattr(agent.render_config, "pitch_mm", PIN_PITCH_MM))
        self._inbox: collections.deque[tuple[TactileFrame, int]] = collections.deque(
            maxlen=4096)
        self.inbox_overflow = 0
        self._analysis = (LiveAnalysis(agent.workspace, analysis)
                          if analysis is not None and agent.remote_mode else None)
        self._latest: tuple[TactileFrame, int] | None = None
        self._trail: list[list[float]] = []
        self._trail_first = 0  # index of self._trail[0]
        self._trail_lock = threading.Lock()
        self._last_sample: object | None = None
        self._arm: tuple[ArmState, float] | None = None
        self._loop_stats: dict[str, Any] = {}
        self._loop_stats_at = -math.inf
        lo, hi = self.workspace.phantom_bounds_mm
        self._bounds = [nums(lo[:2], 3), nums(hi[:2], 3)]

    # ------------------------------------------------------------------ display-loop side

    def frame_accepted(self, frame: TactileFrame, rx_us: int) -> None:
        """Called by the display loop for each accepted frame: one append, nothing else."""
        if len(self._inbox) == self._inbox.maxlen:
            self.inbox_overflow += 1
        self._inbox.append((frame, rx_us))

    # ------------------------------------------------------------------ ViewSource

    def live(self) -> dict[str, Any]:
        """The current state (see ``docs/view.md`` for the fields)."""
        agent, loop = self.agent, self.loop
        while self._inbox:
            item = self._inbox.popleft()
            self._latest = item
            if self._analysis is not None:
                self._analysis.add(item[0])
        if self._analysis is not None:
            self._analysis.poll()
        reader = agent.reader
        sample = reader.latest if reader is not None else None
        platform = None if sample is None else tuple(float(v) for v in sample.position_mm)
        phantom = None
        if platform is not None:
            phantom = self.workspace.forward(np.asarray(platform))
            if sample is not self._last_sample:
                self._last_sample = sample
                latest = self._latest
                contact = bool(latest[0].contact) if latest is not None else False
                with self._trail_lock:
                    if len(self._trail) >= 2 * _MAX_TRAIL:
                        del self._trail[:_MAX_TRAIL]
                        self._trail_first += _MAX_TRAIL
                    self._trail.append([round(float(phantom[0]), 2), round(float(phantom[1]), 2),
                                        round(float(phantom[2]), 2), 1.0 if contact else 0.0])
        # the command and the safe-state reason of one moment (read once, never separately:
        # the loop may withdraw the command between two reads, see PinState)
        pin_state = loop.pin_state
        command = pin_state.command
        feedback = loop.display.latest_feedback() if loop.display.is_connected else None
        pins: dict[str, Any] = {
            "commanded_mm": None if command is None else nums(command.height_mm),
            "stiffness_k": None if command is None else nums(command.stiffness_k, 3),
            "friction": None if command is None else nums(command.friction, 3),
            "measured_mm": None if feedback is None else nums(feedback.position_mm),
            "measured_age_ms": None if feedback is None
            else num((now_us() - feedback.t_us) / 1e3, 1),
            "board_safe_state": None if feedback is None else bool(feedback.safe_state),
            "commands_sent": loop.counters.commands_sent,
        }
        latest = self._latest
        patch = None if latest is None else encode_patch(latest[0], latest[1], platform,
                                                   self._pin_pitch_mm)
        arm = agent.last_arm_state
        now_s = monotonic_s()
        if arm is not None and (self._arm is None or self._arm[0] is not arm):
            self._arm = (arm, now_s)
        probe = {
            "platform_mm": None if platform is None else nums(platform, 3),
            "phantom_mm": None if phantom is None else nums(phantom, 3),
            # the sample's capture time is on the host wall clock (PlatformSample.t_us)
            "platform_age_ms": None if sample is None
            else num((now_us() - sample.t_us) / 1e3, 1),
            "end_effector_mm": None if self._arm is None else nums(self._arm[0].position_mm, 3),
            "end_effector_force_n": None if self._arm is None else num(self._arm[0].force_n),
            "arm_status": None if self._arm is None else self._arm[0].status,
            "arm_age_ms": None if self._arm is None else num((now_s - self._arm[1]) * 1e3, 1),
        }
        link = agent.link
        link_doc = {"state": "none"} if link is None else {
            "state": "up" if link.is_connected else "down",
            "down_s": num(link.link_down_for_s(), 3)}
        trace = loop.last_trace
        latency = None
        if trace is not None:
            stages, e2e_us, at_s = trace
            latency = {"stages_ms": {name: num(us / 1e3, 3) for name, us in stages},
                       "end_to_end_ms": None if e2e_us is None else num(e2e_us / 1e3, 3),
                       "age_ms": num((now_s - at_s) * 1e3, 1)}
        if now_s - self._loop_stats_at >= 0.5:
            self._loop_stats_at = now_s
            summary = loop.periods.summary(last=500)
            self._loop_stats = {"rate_hz": num(summary.get("rate_hz"), 1),
                                "period_p99_ms": num(summary.get("period_p99_ms"), 3)}
        analysis = None
        if self._analysis is not None:
            analysis = {"alive": self._analysis.alive, "frames_sent": self._analysis.frames_sent,
                        "version": self._analysis.version}
        return {"station": "local", "t_us": now_us(), "workspace_mm": self._bounds,
                "pins": pins, "patch": patch, "probe": probe, "link": link_doc,
                "safe": {"reason": pin_state.safe_reason, "seq": pin_state.seq},
                "latency": latency,
                "display_loop": self._loop_stats, "analysis_state": analysis}

    def trail_since(self, start: int, limit: int) -> tuple[int, list[list[float]]]:
        """Trajectory points (phantom x, y, z mm and contact 0/1) from index ``start``."""
        with self._trail_lock:
            first = max(start, self._trail_first)
            offset = first - self._trail_first
            end = min(len(self._trail), offset + limit)
            points = self._trail[offset:end] if offset < end else []
        return first, points

    def analysis(self) -> tuple[int, dict[str, Any] | None]:
        """The newest analysis result and its version."""
        if self._analysis is None:
            return 0, None
        return self._analysis.version, self._analysis.result

    def close(self) -> None:
        """Stop the analysis process."""
        if self._analysis is not None:
            self._analysis.close()
