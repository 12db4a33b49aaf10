"""The relay's live view for a session's observers (``view = "HOST:PORT"`` in ``[relay]``).

The relay serves the same page as a station (:mod:`shared.view`) on a listener of its own;
a browser must send the session id and an **observer** token of that session (the page
takes them from its URL fragment: ``http://HOST:PORT/#session=S&token=T``). What it shows is
built from the messages the relay routes for that session, so it needs nothing from the
stations:

* the newest tactile patch (height image, contact, force) and its age at the relay;
* the platform position (and, through the default workspace map, the probe over the
  phantom) as a trajectory, the arm's end effector and force;
* which stations are joined (``link`` is "up" with both), and the newest tactile frame's
  latency per stage up to the relay (stages after the relay happen at the local station).

What the relay cannot show (documented in ``docs/view.md``): the pins (rendered at the local
station), the local safe state, the analysis' maps and findings (the palpation analysis is
local-station code) and the render and end-to-end stages.
"""

from __future__ import annotations

from array import array
from collections import OrderedDict
from typing import TYPE_CHECKING, Any

import numpy as np

from shared.errors import InputDataError
from shared.motion_to_touch import trace_hops
from shared.protocol import ArmState, DataMessage, PlatformState, TactileCompact, TactileFrame
from shared.protocol.tactile_codec import TactileDecoder
from shared.timebase import now_us
from shared.view.encode import encode_patch, num, nums
from shared.workspace import WorkspaceMap

if TYPE_CHECKING:
    from relay_server.session import Session

__all__ = ["RelayViewHub", "SessionViewSource"]

_TRAIL_PERIOD_US = 25_000  # at most 40 trajectory points a second
_MAX_TRAIL = 50_000
_POINT = 4  # floats per trajectory point: phantom x, y, z (mm) and contact 0/1
_MAX_SESSIONS = 64  # views kept (the least recently active go first)


class SessionViewSource:
    """One session as the relay sees it (a :class:`shared.view.ViewSource`)."""

    def __init__(self, session_id: str, workspace: WorkspaceMap) -> None:
        self.session_id = session_id
        self.workspace = workspace
        self.session: Session | None = None
        self._platform: tuple[PlatformState, int] | None = None
        self._frame: tuple[TactileFrame, int] | None = None
        #: compact frames (protocol v2): the newest key frame and the newest message, decoded
        #: only when a viewer asks (never per routed message on the relay's loop)
        self._key: TactileCompact | None = None
        self._compact: tuple[TactileCompact, int] | None = None
        self._decoded_of: TactileCompact | None = None
        self._arm: tuple[ArmState, int] | None = None
        #: the trajectory, flat and compact (float32, ``_POINT`` per point: 16 bytes a point,
        #: not ~170 as a list of lists): kept whether or not anyone watches, so an observer
        #: who comes later sees the path so far (at most 2 x _MAX_TRAIL points, 1.6 MB)
        self._trail = array("f")
        self._trail_first = 0
        self._last_trail_us = 0
        lo, hi = workspace.phantom_bounds_mm
        self._bounds = [nums(lo[:2], 3), nums(hi[:2], 3)]

    def observe(self, msg: DataMessage, t_in_us: int) -> None:
        """Take one routed message (called on the relay's loop; keeps references only)."""
        if isinstance(msg, PlatformState):
            self._platform = (msg, t_in_us)
            if t_in_us - self._last_trail_us >= _TRAIL_PERIOD_US:
                self._last_trail_us = t_in_us
                ph = self.workspace.forward(np.asarray(msg.position_mm, dtype=np.float64))
                contact = (self._compact is not None and bool(self._compact[0].contact)) or (
                    self._frame is not None and bool(self._frame[0].contact))
                if len(self._trail) >= 2 * _MAX_TRAIL * _POINT:
                    del self._trail[:_MAX_TRAIL * _POINT]
                    self._trail_first += _MAX_TRAIL
                self._trail.extend((float(ph[0]), float(ph[1]), float(ph[2]),
                                    1.0 if contact else 0.0))
        elif isinstance(msg, TactileFrame):
            self._frame, self._compact = (msg, t_in_us), None
        elif isinstance(msg, TactileCompact):
            if msg.key:
                self._key = msg
            self._compact = (msg, t_in_us)
        elif isinstance(msg, ArmState):
            self._arm = (msg, t_in_us)

    def _decode_compact(self) -> None:
        """Turn the newest compact message into the current frame (with its key frame);
        a delta whose key frame the relay did not see leaves the previous frame."""
        item = self._compact  # one read: observe() may replace it meanwhile
        if item is None or item[0] is self._decoded_of:
            return
        msg, t_in_us = item
        self._decoded_of = msg
        decoder = TactileDecoder()
        try:
            if not msg.key and self._key is not None and self._key.seq == msg.key_seq:
                decoder.decode(self._key)
            frame = decoder.decode(msg)
        except InputDataError:
            frame = None
        if frame is not None:
            self._frame = (frame, t_in_us)

    def _offsets(self) -> dict[str, float | None]:
        session = self.session
        if session is None:
            return {}
        return {role: peer.clock.offset_us for role, peer in session.stations.items()}

    def live(self) -> dict[str, Any]:
        """The session's current state in the page's format (``docs/view.md``)."""
        now = now_us()
        platform = None if self._platform is None else self._platform[0].position_mm
        phantom = None if platform is None else self.workspace.forward(
            np.asarray(platform, dtype=np.float64))
        patch = latency = None
        self._decode_compact()
        if self._frame is not None:
            frame, rx_us = self._frame
            patch = encode_patch(frame, rx_us, None, None)
            trace = trace_hops(frame.hops, self._offsets())
            latency = {"stages_ms": {name: num(us / 1e3, 3) for name, us in trace.stages_us},
                       "end_to_end_ms": None, "age_ms": num((now - rx_us) / 1e3, 1)}
        arm = self._arm
        stations = sorted(self.session.stations) if self.session is not None else []
        return {
            "station": "relay", "session": self.session_id, "t_us": now,
            "workspace_mm": self._bounds, "pins": None, "patch": patch,
            "probe": {
                "platform_mm": None if platform is None else nums(platform, 3),
                "phantom_mm": None if phantom is None else nums(phantom, 3),
                "platform_age_ms": None if self._platform is None
                else num((now - self._platform[1]) / 1e3, 1),
                "end_effector_mm": None if arm is None else nums(arm[0].position_mm, 3),
                "end_effector_force_n": None if arm is None else num(arm[0].force_n),
                "arm_status": None if arm is None else arm[0].status,
                "arm_age_ms": None if arm is None else num((now - arm[1]) / 1e3, 1)},
            "link": {"state": "up" if {"local", "remote"} <= set(stations) else "down",
                     "stations": stations},
            "safe": {"reason": None, "known": False}, "latency": latency,
            "display_loop": {}, "analysis_state": None}

    def trail_since(self, start: int, limit: int) -> tuple[int, list[list[float]]]:
        """Trajectory points (phantom x, y, z mm and contact 0/1) from index ``start``."""
        first = max(start, self._trail_first)
        offset = (first - self._trail_first) * _POINT
        flat = self._trail[offset:offset + limit * _POINT].tolist()
        return first, [[round(v, 2) for v in flat[i:i + _POINT]]
                       for i in range(0, len(flat), _POINT)]

    def analysis(self) -> tuple[int, dict[str, Any] | None]:
        """No analysis at the relay (it is local-station code)."""
        return 0, None


class RelayViewHub:
    """The relay's per-session view sources, fed by the routing (bounded in number)."""

    def __init__(self, workspace: WorkspaceMap | None = None) -> None:
        self.workspace = workspace or WorkspaceMap()
        self._sources: OrderedDict[str, SessionViewSource] = OrderedDict()

    def source(self, session_id: str) -> SessionViewSource:
        """The session's source (created when first asked for; the oldest are forgotten)."""
        src = self._sources.get(session_id)
        if src is None:
            src = self._sources[session_id] = SessionViewSource(session_id, self.workspace)
            while len(self._sources) > _MAX_SESSIONS:
                self._sources.popitem(last=False)
        self._sources.move_to_end(session_id)
        return src

    def observe(self, session: Session, msg: DataMessage, t_in_us: int) -> None:
        """Book one routed message of ``session``."""
        src = self.source(session.session_id)
        src.session = session
        src.observe(msg, t_in_us)
