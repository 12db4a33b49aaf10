"""Motion-to-touch latency: from a hand movement on the platform to the pins that render it.

A tactile frame carries, in its ``hops``, the stamps of the platform_state it answers (the
remote station copies them) followed by its own. Along one loop of the system the stamps are,
in order (``clock.stage``):

==========================  ======================================================
stamp                       taken when
==========================  ======================================================
``local.capture``           the platform sample was read (its ``ts``)
``relay.relay_in``          the relay received the platform_state
``relay.relay_out``         the relay wrote it to the remote station
``remote.station_rx``       the remote station's link received it
``remote.arm_command``      the arm was commanded towards it
``remote.sensor_frame``     the first sensor frame taken after that was captured
``remote.tactile_ready``    reconstruction and stiffness finished, frame sent
``relay.relay_in``          the relay received the tactile_frame
``relay.relay_out``         the relay wrote it to the local station
``local.station_rx``        the local station's link received it
``local.rendered``          the first pin command rendered from it was sent to the display
==========================  ======================================================

Each stamp is converted to the relay's clock with the stations' clock offsets
(``t_relay = t - offset[clock]``; the relay's own offset is 0) and the differences between
consecutive stamps are the **stages**; ``rendered - capture`` is the end-to-end latency.
Stamps that are missing or whose clock has no offset yet are skipped (the stage spanning them
is then reported under the combined name), never guessed.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from shared.ledger import LatencyLedger
from shared.protocol import Hop

__all__ = ["END_TO_END", "STAGE_NAMES", "MotionToTouchLedger", "StageTrace", "trace_hops"]

#: (from stamp, to stamp) -> stage name, for the documented sequence
STAGE_NAMES: dict[tuple[str, str], str] = {
    ("local.capture", "relay.relay_in"): "uplink_local_to_relay",
    ("relay.relay_in", "relay.relay_out"): "relay_forward_platform",
    ("relay.relay_out", "remote.station_rx"): "relay_to_remote",
    ("remote.station_rx", "remote.arm_command"): "remote_dispatch",
    ("remote.arm_command", "remote.sensor_frame"): "arm_and_sensor",
    ("remote.sensor_frame", "remote.tactile_ready"): "reconstruction_and_stiffness",
    ("remote.tactile_ready", "relay.relay_in"): "uplink_remote_to_relay",
    ("relay.relay_out", "local.station_rx"): "relay_to_local",
    ("local.station_rx", "local.rendered"): "render",
}
END_TO_END = "end_to_end"


@dataclass(frozen=True, slots=True)
class StageTrace:
    """Stage durations of one tactile frame, in microseconds (relay clock)."""

    stages_us: tuple[tuple[str, float], ...]
    end_to_end_us: float | None


def _stage_name(a: str, b: str, relay_seen: int) -> str:
    name = STAGE_NAMES.get((a, b))
    if name == "relay_forward_platform" and relay_seen > 1:
        return "relay_forward_tactile"
    return name if name is not None else f"{a}>{b}"


def trace_hops(hops: Sequence[Hop], offsets_us: Mapping[str, float | None]) -> StageTrace:
    """Split a frame's stamps into stage durations on the relay clock.

    Args:
        hops: the stamps, in the order they were appended (add ``local.rendered`` last).
        offsets_us: station clock minus relay clock per clock name (``local``,
            ``remote``); the relay's offset is 0 whatever is given.

    Returns:
        The stages between consecutive usable stamps, and end-to-end from the first
        ``local.capture`` to the last ``local.rendered`` (None when either is missing).
    """
    points: list[tuple[str, float]] = []
    for hop in hops:
        offset = 0.0 if hop.clock == "relay" else offsets_us.get(hop.clock)
        if offset is None:
            continue
        points.append((f"{hop.clock}.{hop.stage}", hop.t_us - offset))
    stages: list[tuple[str, float]] = []
    relay_seen = 0
    for (a, ta), (b, tb) in itertools.pairwise(points):
        if a == "relay.relay_in":
            relay_seen += 1
        stages.append((_stage_name(a, b, relay_seen), tb - ta))
    start = next((t for name, t in points if name == "local.capture"), None)
    end = next((t for name, t in reversed(points) if name == "local.rendered"), None)
    e2e = end - start if start is not None and end is not None else None
    return StageTrace(tuple(stages), e2e)


class MotionToTouchLedger:
    """Per-stage and end-to-end latency statistics over many frames.

    Args:
        window: samples kept per stage for percentiles (bounded memory).
    """

    def __init__(self, window: int = 8192) -> None:
        self._window = window
        self._ledgers: dict[str, LatencyLedger] = {}

    def _ledger(self, name: str) -> LatencyLedger:
        ledger = self._ledgers.get(name)
        if ledger is None:
            ledger = self._ledgers[name] = LatencyLedger(self._window)
        return ledger

    def add(self, trace: StageTrace) -> None:
        """Account the stages of one frame."""
        for name, duration in trace.stages_us:
            self._ledger(name).record(None, 0, round(duration))
        if trace.end_to_end_us is not None:
            self._ledger(END_TO_END).record(None, 0, round(trace.end_to_end_us))

    def add_hops(self, hops: Iterable[Hop], offsets_us: Mapping[str, float | None]) -> StageTrace:
        """Trace ``hops`` (see :func:`trace_hops`), account it and return it."""
        trace = trace_hops(tuple(hops), offsets_us)
        self.add(trace)
        return trace

    @property
    def frames(self) -> int:
        """Frames with an end-to-end figure."""
        ledger = self._ledgers.get(END_TO_END)
        return 0 if ledger is None else ledger.received

    def summary_ms(self) -> dict[str, dict[str, float | int | None]]:
        """Per stage (and ``end_to_end``): ``p50``, ``p99``, ``max`` in ms and the count."""
        out: dict[str, dict[str, float | int | None]] = {}
        for name, ledger in self._ledgers.items():
            snap = ledger.snapshot()
            out[name] = {
                "p50": None if snap.delay_p50_us is None else snap.delay_p50_us / 1000.0,
                "p99": None if snap.delay_p99_us is None else snap.delay_p99_us / 1000.0,
                "max": None if snap.delay_max_us is None else snap.delay_max_us / 1000.0,
                "count": snap.received,
            }
        return out
