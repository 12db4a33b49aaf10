"""The station's loops go on after an arm fault: a transient device error (a lost state
packet, a failed move), a non-finite reading, a set_force_limit the arm refuses."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import time
from types import SimpleNamespace

import pytest

from remote_site.agent.station import RemoteStation
from remote_site.agent.stiffness_stage import StiffnessStage
from remote_site.arm.base import ArmReading, Vec3
from remote_site.arm.safety import SafeArm
from remote_site.arm.sim import SimArm, SimArmConfig
from remote_site.stiffness.estimator import StiffnessConfig
from shared.client import LinkCounters
from shared.errors import DeviceError, DeviceTimeoutError
from shared.freshness import ClockView
from shared.protocol import ArmCommand, Message, PlatformState
from shared.protocol.codec import encode
from shared.timebase import now_us


class FlakyArm(SimArm):
    """A sim arm whose next reads or moves fail (as a real arm's lost packet or reflex)."""

    fail_reads = 0
    fail_moves = 0
    nan_force = False

    def _read(self) -> ArmReading:
        if self.fail_reads:
            self.fail_reads -= 1
            raise TimeoutError("one lost state packet")  # -> DeviceTimeoutError
        reading = super()._read()
        return dataclasses.replace(reading, force_n=math.nan) if self.nan_force else reading

    def _move_to(self, target_mm: Vec3) -> None:
        if self.fail_moves:
            self.fail_moves -= 1
            raise RuntimeError("reflex")  # -> DeviceOperationError
        super()._move_to(target_mm)


class Link:
    """A connected link with known clocks; sends are encoded as the real link does."""

    def __init__(self, *msgs: Message) -> None:
        self.counters = LinkCounters(connects=1)
        self.inbox: asyncio.Queue[Message] = asyncio.Queue()
        for msg in msgs:
            self.inbox.put_nowait(msg)
        self.sent: list[Message] = []

    @property
    def is_connected(self) -> bool:
        return True

    @property
    def clock_view(self) -> ClockView:
        return ClockView({"local": 0, "remote": 0}, {"local": 1000, "remote": 1000}, now_us())

    def link_down_for_s(self, now_s: float | None = None) -> float:
        return 0.0

    async def send(self, msg: Message) -> None:
        encode(msg)  # an invalid message (NaN) raises here, as StationLink.send does
        self.sent.append(msg)

    async def recv(self, timeout_s: float | None = None) -> Message:
        return await self.inbox.get()


def make_station(link: Link) -> tuple[RemoteStation, FlakyArm]:
    arm = FlakyArm(None, SimArmConfig(realtime=False))
    arm.connect()
    stage = StiffnessStage(StiffnessConfig(gel_stiffness_n_per_mm=20.0))
    return RemoteStation(link, SafeArm(arm), None, stage, lambda p: p), arm  # type: ignore[arg-type]


async def run_for(coro: object, seconds: float) -> None:
    """Run a loop for ``seconds``: it must still be running then."""
    with pytest.raises(TimeoutError):
        await asyncio.wait_for(coro, seconds)  # type: ignore[arg-type]


def test_one_failed_arm_read_does_not_end_the_arm_loop(
        caplog: pytest.LogCaptureFixture) -> None:
    link = Link()
    station, arm = make_station(link)
    arm.fail_reads = 2  # two in a row: one warning
    with caplog.at_level(logging.WARNING, logger="remote_site.agent.station"):
        asyncio.run(run_for(station._arm_loop(), 0.2))
    assert station.counters.arm_errors == 2
    assert len([r for r in caplog.records if "arm error" in r.getMessage()]) == 1
    assert station.safe_arm.halted  # stopped after the fault
    assert station.last_reading is not None and station.counters.arm_states_sent > 0


def test_one_failed_move_does_not_end_the_receive_loop(
        caplog: pytest.LogCaptureFixture) -> None:
    states = [PlatformState(seq=i, ts_us=now_us(), position_mm=(0.0, 0.0, 10.0 + i))
              for i in (1, 2)]
    link = Link(*states)
    station, arm = make_station(link)
    arm.fail_moves = 1
    with caplog.at_level(logging.WARNING, logger="remote_site.agent.station"):
        asyncio.run(run_for(station._receive_loop(), 0.2))
    assert station.counters.arm_errors == 1
    assert station.counters.platform_applied == 1  # the second state was applied
    assert arm.state().target_mm == (0.0, 0.0, 12.0) and not station.safe_arm.halted
    assert len([r for r in caplog.records if "arm error" in r.getMessage()]) == 1


def test_a_refused_force_limit_does_not_end_the_receive_loop() -> None:
    """A zero limit that got past the codec (built in-process) is refused by the arm, not
    raised out of the receive loop."""
    bad = ArmCommand(seq=1, ts_us=now_us(), action="set_force_limit", force_limit_n=0.0)
    good = ArmCommand(seq=2, ts_us=now_us(), action="set_force_limit", force_limit_n=4.0)
    station, _ = make_station(Link(bad, good))
    asyncio.run(run_for(station._receive_loop(), 0.2))
    assert station.counters.arm_commands == 2 and station.counters.arm_commands_applied == 1
    assert station.safe_arm.force_limit_n == 4.0


def test_a_non_finite_reading_does_not_end_the_arm_loop() -> None:
    """The arm halts (SafeArm) and the NaN reading is not put on the wire, whose codec would
    refuse it and end the loop."""
    link = Link()
    station, arm = make_station(link)
    arm.nan_force = True
    asyncio.run(run_for(station._arm_loop(), 0.1))
    assert station.safe_arm.counters.fault_halts == 1 and station.safe_arm.halted
    assert station.last_reading is not None and station.last_reading.status == "fault"
    assert link.sent == []
    arm.nan_force = False
    asyncio.run(run_for(station._arm_loop(), 0.1))
    assert link.sent  # finite again: arm_state goes out


def test_arm_errors_are_in_the_summary(monkeypatch: pytest.MonkeyPatch) -> None:
    from tests.remote_site.test_agent_safety import FakeLink, close_station
    from tests.remote_site.test_agent_safety import make_station as make_full_station

    station = make_full_station(FakeLink(), realtime=False)
    try:
        arm = station.safe_arm.arm
        real_read = arm._read
        failed = [False]

        def read_once_failing() -> ArmReading:
            if not failed[0]:
                failed[0] = True
                raise TimeoutError("one lost state packet")
            return real_read()

        monkeypatch.setattr(arm, "_read", read_once_failing)
        asyncio.run(run_for(station._arm_loop(), 0.05))
        assert station.summary()["arm"]["errors"] == 1
    finally:
        close_station(station)


def test_an_arm_fault_that_lasts_ends_the_station_for_its_supervisor(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """Found by review: riding out every DeviceError left a station up with a dead arm
    (a Franka's reflex is recovered only as the backend connects). A run of failures with
    no success between ends the loop, and so the station, after ARM_FAULT_RESTART_S."""
    import remote_site.agent.station as station_module

    monkeypatch.setattr(station_module, "ARM_FAULT_RESTART_S", 0.05)
    station, arm = make_station(Link())
    arm.fail_reads = 10**9  # every read fails from now on
    with caplog.at_level(logging.ERROR, logger="remote_site.agent.station"), \
            pytest.raises(DeviceError):
        asyncio.run(asyncio.wait_for(station._arm_loop(), 5.0))
    assert station.counters.arm_errors >= 2
    assert any("ending the station" in r.getMessage() for r in caplog.records)


def test_failures_with_successes_between_never_end_the_loop(
        monkeypatch: pytest.MonkeyPatch) -> None:
    import remote_site.agent.station as station_module

    monkeypatch.setattr(station_module, "ARM_FAULT_RESTART_S", 0.05)
    station, arm = make_station(Link())

    async def every_other_read_fails() -> None:
        loop = asyncio.create_task(station._arm_loop())
        for _ in range(40):  # about 0.2 s of reads, a failure after each success
            arm.fail_reads = 1
            await asyncio.sleep(0.005)
        assert not loop.done()
        loop.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await loop

    asyncio.run(every_other_read_fails())
    assert station.counters.arm_errors >= 10


def test_a_reading_beyond_the_wires_ranges_does_not_end_the_arm_loop() -> None:
    """Found by review: a finite force beyond the wire's +-1000 N (a sensor glitch) made
    the arm_state's encoding raise and ended the loop; it is counted and not sent."""
    link = Link()
    station, arm = make_station(link)
    real_read = arm._read

    def wild() -> ArmReading:
        return dataclasses.replace(real_read(), force_n=1500.0)

    arm._read = wild  # type: ignore[method-assign]
    asyncio.run(run_for(station._arm_loop(), 0.1))
    assert station.counters.arm_states_refused >= 1 and link.sent == []


def test_a_lost_arm_read_costs_a_frame_not_the_frame_loop() -> None:
    """Found by review: the frame pipeline read the arm outside any handler, so one lost
    read ended the frame loop (and the station); it is a rejected frame now."""
    from tests.remote_site.test_agent_safety import FakeLink, close_station
    from tests.remote_site.test_agent_safety import make_station as make_full_station

    station = make_full_station(FakeLink(), realtime=False)
    try:
        pipeline = station.pipeline
        real_read = pipeline.read_arm
        failed = [False]

        def read_once_failing() -> ArmReading:
            if not failed[0]:
                failed[0] = True
                raise DeviceTimeoutError("one lost state packet")
            return real_read()

        pipeline.read_arm = read_once_failing
        outcome = pipeline.process(1, None)
        assert outcome.frame is None and pipeline.rejected["arm_error"] == 1
        assert pipeline.process(2, None).frame is not None  # the next read works
    finally:
        close_station(station)


def test_lone_failures_far_apart_are_not_a_lasting_fault(monkeypatch: pytest.MonkeyPatch) -> None:
    """Found by review: a failure, a quiet gap with nothing to do (no success either), then
    another failure counted as one run of the gap's length and ended the station."""
    import remote_site.agent.station as station_module

    monkeypatch.setattr(station_module, "ARM_FAULT_RESTART_S", 0.05)
    monkeypatch.setattr(station_module, "_ARM_FAULT_GAP_S", 0.02)
    station, _ = make_station(Link())
    err = DeviceTimeoutError("one lost state packet")
    station._arm_error("receive", err)
    deadline = time.monotonic() + 0.1
    while time.monotonic() < deadline:  # a quiet gap longer than the restart limit
        time.sleep(0.005)
    station._arm_error("receive", err)  # a new run: not raised
    assert station.counters.arm_errors == 2


def test_a_lost_read_in_the_pose_wait_does_not_end_the_frame_loop() -> None:
    """Found by review: the pose wait (capture on pose, the default) read the arm with no
    handler, so one lost packet while waiting ended the frame loop and the station."""
    from remote_site.tactile import AppliedCommand

    station, arm = make_station(Link())
    station.pipeline = SimpleNamespace(read_arm=arm.state)  # type: ignore[assignment]
    arm.fail_reads = 1
    command = AppliedCommand(PlatformState(seq=1, ts_us=now_us(), position_mm=(0.0, 0.0, 1.0)),
                             now_us(), None)
    asyncio.run(asyncio.wait_for(station._until_pose(command), 5.0))
    assert station.counters.arm_errors == 1
    # not stopped for it (found by review: the operator's arm was halted short of its
    # target), and the capture is counted as not on pose
    assert not station.safe_arm.halted and station.captures.moving == 1


def test_a_receive_run_is_reset_only_by_a_command_the_arm_took(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Found by review: any message that made no arm call (a stale command, an ignored type)
    counted as a success, so a reflex (moves failing) with a few stale commands between
    never escalated."""
    import remote_site.agent.station as station_module

    monkeypatch.setattr(station_module, "ARM_FAULT_RESTART_S", 0.05)
    stale = [PlatformState(seq=2 * i + 2, ts_us=now_us() - 10_000_000,
                           position_mm=(0.0, 0.0, 5.0)) for i in range(200)]
    fresh = [PlatformState(seq=2 * i + 1, ts_us=0, position_mm=(0.0, 0.0, 5.0))
             for i in range(200)]
    link = Link()
    station, arm = make_station(link)
    arm.fail_moves = 10**9

    async def feed() -> None:
        loop = asyncio.create_task(station._receive_loop())
        for f, s in zip(fresh, stale, strict=True):
            link.inbox.put_nowait(dataclasses.replace(f, ts_us=now_us()))
            link.inbox.put_nowait(s)  # refused as stale: no arm call
            await asyncio.sleep(0.002)
            if loop.done():
                break
        with pytest.raises(DeviceError):
            await asyncio.wait_for(loop, 5.0)

    asyncio.run(feed())
