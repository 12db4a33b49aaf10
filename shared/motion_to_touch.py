"""Motion-to-touch latency: from a hand movement on the platform to the pins that render it.

A tactile frame carries, in its ``hops``, the stamps of the platform_state it answers (the
remote station copies them) followed by its own. Along one loop of the system the stamps are,
in order (``clock.stage``):

==========================  ======================================================
stamp                       taken when
==========================  ======================================================
``local.motion``            the earliest movement this frame is the first to show may
                            have started: the previous platform_state's sample, or an
                            earlier one handed on (below)
``local.capture``           the platform sample was read (its ``ts``)
``relay.relay_in``          the relay received the platform_state
``relay.relay_out``         the relay wrote it to the remote station
``remote.station_rx``       the remote station's link received it
``remote.arm_command``      the arm was commanded towards it
``remote.sensor_frame``     the first sensor frame taken after that was captured
``remote.sensor_arrival``   that image reached the station (a camera: its stamp plus
                            the latency it was given; the simulated camera: its delivery;
                            the capture stamp of a source that captures on demand)
``remote.tactile_ready``    reconstruction and stiffness finished, frame sent
``relay.relay_in``          the relay received the tactile_frame
``relay.relay_out``         the relay wrote it to the local station
``local.station_rx``        the local station's link received it
``local.rendered``          the first pin command rendered from it was sent to the display
==========================  ======================================================

Each stamp is converted to the relay's clock with the stations' clock offsets
(``t_relay = t - offset[clock]``; the relay's own offset is 0) and the differences between
consecutive stamps are the **stages**; ``rendered - motion`` is the end-to-end latency.

The platform is read at about 1 kHz but sent at ``platform_send_rate_hz`` (250 Hz), newest
sample only: a movement made just after one message's sample shows first in the next
message, one send period later. ``local.motion`` (the previous message's sample time) makes
that wait a stage of its own, ``uplink_sampling``, and end to end the latency of the
**earliest movement the frame is the first to show**: a bound, since a movement at a random
instant waits half a period on average. The first message of a link session (and the first
after a sample was skipped, or across a platform outage longer than the read timeout) has
no previous one and no ``local.motion``; its frames are counted from ``local.capture``.

A message that never reaches the next step passes its start on. One replaced unsent or
unread in a latest-wins slot gives its successor its ``local.motion``, or its
``local.capture`` when it had none (the known part of its wait;
:func:`shared.protocol.carry_motion`); a successor without ``local.motion`` keeps none. On
the way out that is a ``platform_state`` in the local station's send queue, the relay's queue
to the remote or the remote station's inbox; on the way back a tactile frame in the remote
station's send queue, the relay's queue to the local, the local station's inbox, or the
display loop's frame slot while the loop renders. Not across what is taken for an outage
of the touch path: a start more than a second (``MOTION_CARRY_MAX_US``) before the
successor's own is not handed on, nor the start of a frame replaced while the pins are
safe, the display is being reopened or the loop has not begun, nor that of one the display
process's full socket did not take (a child not reading). A ``tactile_compact`` key frame
is never replaced by a delta; in a station's queues a newer key frame replaces a waiting key
frame and a waiting delta, and takes their starts. The remote
station's frames come at ``frame_rate_hz`` (60-80), a few times slower than the states:
every state it received since the last capture that gave a frame (passed over, or
refused as too old or unusable: positions are absolute, so a newer state shows their
movements too) is first shown by the next frame, which starts where the first of them
started (``RemoteStation._frame_source``). A streaming camera's image was taken before
the frame tick that reads it: its frame answers the command applied by the image's time
(``RemoteStation.applied_at``; the camera's known latency is taken off its arrival), and the
states after that command are left for the next frame: its ``arm_command`` stamp never
follows its ``sensor_frame`` stamp (the arrival less the camera's latency when that is
known, ``--sensor-latency-ms``; else the arrival, and a real delay goes uncounted). Its
``sensor_delivery`` stage (``sensor_frame`` to ``sensor_arrival``) is therefore that known
latency, a constant the camera was given, not a measurement (the simulated camera's holds
its latency and its render). ``reconstruction_and_stiffness`` starts where the image
reached the station, so it holds the wait for the frame tick too. A source that captures
on demand has a delivery of 0 (it stamps as its read returns, so its render sits in
``arm_and_sensor``). A capture
that gives no frame (a streaming camera with no new image yet, a sensor error) hands that
chain back; states refused after the state
captured are left for the next frame; a reconnect of the remote's link, and a first state
that reached the remote more than a second before the capture (an outage of the touch path,
not a latency), end it; states the remote drops before their age can be judged (its clock
offsets not known yet) start none. A frame taken with no command newer than the last
frame's (idle) shows nothing first: it carries no platform stamps and is not counted end to
end. ``uplink_sampling`` is therefore the whole wait from the earliest movement to the sample
the frame answers: the send period plus every state passed over (by the frame schedule,
mostly), plus, for a frame that replaced another on the way back, the frames between them.
A tactile frame that is refused rather than replaced (a compact delta without its key
frame, a frame the display loop rejects), one replaced while the pins are safe, and one
whose successor is idle hand nothing on: their movements are not counted (not built).
A clustered relay's stamps for a hop between its workers (``relay.nats_out`` right after
``relay.relay_in``, then ``relay.nats_in``) lie inside ``relay_forward_platform`` or
``relay_forward_tactile``, which then include that hop; they bound no stage of their own.
The sending worker puts its stamps on the receiving worker's clock (measured on their
heartbeats, :mod:`relay_server.worker_clocks`); until that is known, or beyond the measure's
error, a NATS leg that ends before it began makes the frame ``unaligned``, and a smaller
disagreement goes into the forwarding stages.
The stages of a frame are counted only when every clock among its stamps has a known offset
(the remote station's offset reaches the local station a few seconds after joining) and every
pair of consecutive stamps is a documented stage: such a frame is **aligned**. The others are
never guessed and never reported under a made-up stage name: the ledger counts them apart,
as ``unaligned`` (a clock offset not yet known) or ``incomplete`` (a stamp missing, so two
stamps that are not neighbours in the table above would meet; a frame may lack a leading
part, e.g. one taken while no command was applied starts at ``remote.sensor_frame``).
``end_to_end`` needs only the
local clock (both of its stamps are the local station's) and is counted for every frame that
has ``local.rendered`` and ``local.motion`` or ``local.capture`` (the first of them).
"""

from __future__ import annotations

import collections
import itertools
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from shared.ledger import LatencyLedger
from shared.protocol import Hop

__all__ = ["END_TO_END", "FROM_CAPTURE", "INCOMPLETE", "SEQUENCE", "STAGES", "UNALIGNED",
           "MotionToTouchLedger", "StageTrace", "trace_hops"]

#: the documented stamps of one loop, in order
SEQUENCE: tuple[str, ...] = (
    "local.motion", "local.capture", "relay.relay_in", "relay.relay_out", "remote.station_rx",
    "remote.arm_command", "remote.sensor_frame", "remote.sensor_arrival",
    "remote.tactile_ready", "relay.relay_in", "relay.relay_out", "local.station_rx",
    "local.rendered")

END_TO_END = "end_to_end"
#: from the sample the frame answers (``local.capture``) to the pins: end to end without the
#: sampling wait, the figure sections 3b-22 of docs/speed.md (and issue 12's targets) counted
FROM_CAPTURE = "from_capture"
#: frames whose stages were not counted: a clock offset was not known yet
UNALIGNED = "unaligned"
#: frames whose stages were not counted: a stamp was missing
INCOMPLETE = "incomplete"


@dataclass(frozen=True, slots=True)
class StageTrace:
    """Stage durations of one tactile frame, in microseconds (relay clock).

    ``stages_us`` is empty when the frame is not aligned; ``skipped`` then says why
    (:data:`UNALIGNED` or :data:`INCOMPLETE`), else it is None.
    """

    stages_us: tuple[tuple[str, float], ...]
    end_to_end_us: float | None
    skipped: str | None = None
    #: ``local.rendered - local.capture`` (None when either is missing)
    from_capture_us: float | None = None


#: the stamps end to end may start from (the first present)
_STARTS = frozenset({"local.motion", "local.capture"})

#: stamps inside a stage, not bounds of one, each after the stamp it must follow: a
#: clustered relay's hop between two workers (``relay_server.cluster``: ``relay_in``,
#: ``nats_out``, ``nats_in``, ``relay_out``) lies inside the relay's forwarding, which the
#: stage then spans (the relay's own metrics book the NATS leg). Anywhere else such a stamp
#: breaks the sequence (``incomplete``)
_WITHIN_STAGE = {"relay.nats_out": "relay.relay_in", "relay.nats_in": "relay.nats_out"}

#: a tail whose stages exceed their medians by less than this in all (ms) has no shares:
#: they would be shares of rounding noise
_SHARE_FLOOR_MS = 1e-3

#: the stage between SEQUENCE[i] and SEQUENCE[i + 1]
STAGES: tuple[str, ...] = (
    "uplink_sampling", "uplink_local_to_relay", "relay_forward_platform", "relay_to_remote",
    "remote_dispatch", "arm_and_sensor", "sensor_delivery", "reconstruction_and_stiffness",
    "uplink_remote_to_relay", "relay_forward_tactile", "relay_to_local", "render")


def _start_in_sequence(names: Sequence[str]) -> int | None:
    """Where ``names`` starts as an unbroken run of :data:`SEQUENCE`, or None (a frame
    without the platform part, taken while no command was applied, starts at
    ``remote.sensor_frame``; one answering the first message of a link session, at
    ``local.capture``)."""
    n = len(names)
    return next((k for k in range(len(SEQUENCE) - n + 1)
                 if tuple(names) == SEQUENCE[k:k + n]), None)


def trace_hops(hops: Sequence[Hop], offsets_us: Mapping[str, float | None]) -> StageTrace:
    """Split a frame's stamps into stage durations on the relay clock.

    Args:
        hops: the stamps, in the order they were appended (add ``local.rendered`` last).
        offsets_us: station clock minus relay clock per clock name (``local``,
            ``remote``); the relay's offset is 0 whatever is given.

    Returns:
        The stages between consecutive stamps when the frame is aligned (every clock's
        offset known, every pair a documented stage; else no stages and ``skipped`` says
        why), and end-to-end from the first ``local.motion`` (else ``local.capture``) to the
        last ``local.rendered`` (None when either end is missing or the local offset is
        unknown).
    """
    points: list[tuple[str, float]] = []
    unaligned = False
    previous: Hop | None = None
    for hop in hops:
        prev, previous = previous, hop
        name = f"{hop.clock}.{hop.stage}"
        after = _WITHIN_STAGE.get(name)
        if after is not None and prev is not None and f"{prev.clock}.{prev.stage}" == after:
            # the NATS leg runs between two workers' clocks (the sender's stamps put on the
            # receiver's once measured): one that ends before it began shows them out of
            # step, by an offset not known here
            unaligned |= name == "relay.nats_in" and hop.t_us < prev.t_us
            continue
        offset = 0.0 if hop.clock == "relay" else offsets_us.get(hop.clock)
        if offset is None:
            unaligned = True
            continue
        points.append((f"{hop.clock}.{hop.stage}", hop.t_us - offset))
    start = next((t for name, t in points if name in _STARTS), None)
    capture = next((t for name, t in points if name == "local.capture"), None)
    end = next((t for name, t in reversed(points) if name == "local.rendered"), None)
    e2e = end - start if start is not None and end is not None else None
    from_capture = end - capture if capture is not None and end is not None else None
    if unaligned:
        return StageTrace((), e2e, UNALIGNED, from_capture)
    start_k = _start_in_sequence([name for name, _ in points])
    if start_k is None:
        return StageTrace((), e2e, INCOMPLETE, from_capture)
    stages = tuple((STAGES[start_k + i], tb - ta)
                   for i, ((_, ta), (_, tb)) in enumerate(itertools.pairwise(points)))
    return StageTrace(stages, e2e, None, from_capture)


class MotionToTouchLedger:
    """Per-stage and end-to-end latency statistics over many frames.

    Args:
        window: samples kept per stage for percentiles (bounded memory).
    """

    def __init__(self, window: int = 8192) -> None:
        self._window = window
        self._ledgers: dict[str, LatencyLedger] = {}
        self._skipped: dict[str, int] = {}
        #: the newest complete frames (every stage, in STAGES order, then end-to-end; us)
        self._complete: collections.deque[tuple[float, ...]] = collections.deque(
            maxlen=window)

    def _ledger(self, name: str) -> LatencyLedger:
        ledger = self._ledgers.get(name)
        if ledger is None:
            ledger = self._ledgers[name] = LatencyLedger(self._window)
        return ledger

    def add(self, trace: StageTrace) -> None:
        """Account the stages of one frame (a skipped frame counts under its reason)."""
        if trace.skipped is not None:
            self._skipped[trace.skipped] = self._skipped.get(trace.skipped, 0) + 1
        for name, duration in trace.stages_us:
            self._ledger(name).record(None, 0, round(duration))
        if trace.from_capture_us is not None:
            self._ledger(FROM_CAPTURE).record(None, 0, round(trace.from_capture_us))
        if trace.end_to_end_us is not None:
            self._ledger(END_TO_END).record(None, 0, round(trace.end_to_end_us))
            if len(trace.stages_us) == len(STAGES):
                self._complete.append((*(d for _, d in trace.stages_us),
                                       trace.end_to_end_us))

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

    def tail_ms(self, quantile: float = 0.95) -> dict[str, Any] | None:
        """Where the slow frames lose their time: the complete frames (every stage counted)
        whose end-to-end latency is at or above its ``quantile``, each stage's mean over them
        against the stage's median over all complete frames.

        A complete frame's stages add up to its end-to-end latency (both ends are the local
        clock), so the stages' ``excess`` (tail mean minus median) add up to the tail's mean
        end-to-end minus the sum of the stage medians: ``share`` is each stage's part of that
        sum (None when the sum is under a microsecond: the tail is no slower than the rest).

        Args:
            quantile: the tail's lower bound, as a quantile of end-to-end latency (0 < q < 1).

        Returns:
            ``{"quantile", "frames" (in the tail), "of" (complete frames), "end_to_end":
            {"p50", "tail_mean"}, "stages": {stage: {"p50", "tail_mean", "excess",
            "share"}}}`` in ms; None without complete frames.

        Raises:
            ValueError: a quantile outside (0, 1).
        """
        if not 0.0 < quantile < 1.0:
            raise ValueError(f"quantile must lie in (0, 1), got {quantile}")
        if not self._complete:
            return None
        data = np.asarray(self._complete, np.float64) / 1000.0
        e2e = data[:, -1]
        tail = data[e2e >= np.quantile(e2e, quantile)]
        medians = np.median(data, axis=0)
        means = tail.mean(axis=0)
        excess = means[:-1] - medians[:-1]
        total = float(excess.sum())
        return {
            "quantile": quantile, "frames": int(tail.shape[0]), "of": int(data.shape[0]),
            "end_to_end": {"p50": float(medians[-1]), "tail_mean": float(means[-1])},
            "stages": {name: {"p50": float(medians[i]), "tail_mean": float(means[i]),
                              "excess": float(excess[i]),
                              "share": float(excess[i] / total)
                              if total > _SHARE_FLOOR_MS else None}
                       for i, name in enumerate(STAGES)}}

    def summary_ms(self) -> dict[str, dict[str, float | int | None]]:
        """Per stage (and ``end_to_end``, ``from_capture``): ``p50``, ``p99``, ``max`` in ms
        and the count.

        Frames whose stages were not counted appear as :data:`UNALIGNED` and
        :data:`INCOMPLETE` with their ``count`` only (their figures are None).
        """
        out: dict[str, dict[str, float | int | None]] = {}
        for name, ledger in self._ledgers.items():
            snap = ledger.snapshot()
            out[name] = {
                "p50": None if snap.delay_p50_us is None else snap.delay_p50_us / 1000.0,
                "p99": None if snap.delay_p99_us is None else snap.delay_p99_us / 1000.0,
                "max": None if snap.delay_max_us is None else snap.delay_max_us / 1000.0,
                "count": snap.received,
            }
        for name, count in self._skipped.items():
            out[name] = {"p50": None, "p99": None, "max": None, "count": count}
        return out
