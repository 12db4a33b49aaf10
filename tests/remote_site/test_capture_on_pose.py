"""Capture on pose: with the simulated sensor a frame is taken once the arm has reached the
commanded pose, not on an unrelated frame clock; a streaming sensor keeps the clock."""

from __future__ import annotations

import asyncio
import itertools
import math
from collections.abc import Callable, Iterator, Sequence

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from remote_site.agent.config import RemoteAgentConfig
from remote_site.agent.station import (
    closing_speed_mm_s,
    next_command_wait_s,
    next_frame_due_s,
    pose_eta_s,
    pose_reached,
)
from remote_site.arm.base import ArmReading
from remote_site.arm.safety import SafetyConfig
from shared.errors import ConfigError
from shared.protocol import TactileCompact, TactileFrame
from shared.timebase import now_us
from tests.remote_site.test_agent_safety import (
    WS,
    FakeLink,
    ScriptedSensor,
    close_station,
    make_station,
    platform_state,
)
from tests.support import MachineStalls, async_wait_until, scaled


def reading(position: tuple[float, float, float], target: tuple[float, float, float] | None,
            status: str = "moving") -> ArmReading:
    return ArmReading(position, (0.0, 0.0, 0.0), 0.0, status, target, 0.0)


def test_pose_reached_within_tolerance_or_when_the_arm_stopped() -> None:
    assert not pose_reached(reading((0, 0, 10), (1, 0, 10)), 0.25)
    assert pose_reached(reading((0.8, 0, 10), (1, 0, 10)), 0.25)
    assert pose_reached(reading((0, 0, 10), (1, 0, 10), "halted"), 0.25)  # will not get there
    assert pose_reached(reading((0, 0, 10), (1, 0, 10), "ok"), 0.25)
    assert pose_reached(reading((0, 0, 10), None), 0.25)


def test_pose_eta_from_the_speed_towards_the_target() -> None:
    def moving(velocity: tuple[float, float, float]) -> ArmReading:
        return ArmReading((0.0, 0.0, 10.0), velocity, 0.0, "moving", (1.25, 0.0, 10.0), 0.0)

    assert pose_eta_s(moving((100.0, 0.0, 0.0)), 0.25) == pytest.approx(0.01)
    assert pose_eta_s(moving((100.0, 100.0, 0.0)), 0.25) == pytest.approx(0.01)  # sideways
    assert pose_eta_s(moving((-5.0, 0.0, 0.0)), 0.25) == math.inf  # moving away
    assert pose_eta_s(moving((0.0, 3.0, 0.0)), 0.25) == math.inf
    assert pose_eta_s(reading((1.0, 0.0, 10.0), (1.25, 0.0, 10.0)), 0.25) == 0.0


def test_closing_speed_is_the_speed_towards_the_target() -> None:
    def arm(velocity: tuple[float, float, float],
            target: tuple[float, float, float] | None = (10.0, 0.0, 10.0)) -> ArmReading:
        return ArmReading((0.0, 0.0, 10.0), velocity, 0.0, "moving", target, 0.0)

    assert closing_speed_mm_s(arm((30.0, 0.0, 0.0))) == pytest.approx(30.0)
    assert closing_speed_mm_s(arm((30.0, 40.0, 0.0))) == pytest.approx(30.0)
    assert closing_speed_mm_s(arm((-2.0, 0.0, 0.0))) == pytest.approx(-2.0)
    # settling from the previous move, sideways: not on its way (given time to start)
    assert closing_speed_mm_s(arm((0.0, 3.0, 0.0))) == 0.0
    assert closing_speed_mm_s(arm((5.0, 0.0, 0.0), None)) == 0.0
    assert closing_speed_mm_s(arm((5.0, 0.0, 0.0), (0.0, 0.0, 10.0))) == 0.0  # at the target


def test_pose_settings_are_checked() -> None:
    with pytest.raises(ConfigError, match="pose_tolerance_mm"):
        RemoteAgentConfig(pose_tolerance_mm=0.0)
    with pytest.raises(ConfigError, match="pose_wait_max_ms"):
        RemoteAgentConfig(pose_wait_max_ms=math.inf)
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(ConfigError, match="command_fresh_ms"):
            RemoteAgentConfig(command_fresh_ms=bad)


_SECONDS = st.floats(0.0, 1.0, allow_nan=False)


@given(age=_SECONDS, interval=st.none() | st.floats(1e-4, 0.1), fresh=_SECONDS,
       period=st.floats(1e-3, 1.0))
def test_a_due_frame_waits_for_the_next_command_only_when_it_is_due_within_a_period(
        age: float, interval: float | None, fresh: float, period: float) -> None:
    wait = next_command_wait_s(age, interval, fresh, period)
    assert 0.0 <= wait <= period
    if age <= fresh or interval is None or interval - age > period:
        assert wait == 0.0  # a fresh command, no rate known, or the next one far off
    else:
        assert wait > 0.0
        # until the next command is due, or a whole period when that comes later
        assert age + wait >= interval or wait == period


def test_the_wait_for_the_next_command_in_numbers() -> None:
    # commands every 4 ms, frames at most every 8.3 ms: a command 3 ms old is not taken, its
    # successor (due in 1 ms) is waited for, with 2 ms of slack for its jitter
    assert next_command_wait_s(0.003, 0.004, 0.001, 0.0083) == pytest.approx(0.003)
    assert next_command_wait_s(0.0005, 0.004, 0.001, 0.0083) == 0.0  # fresh: at once
    assert next_command_wait_s(0.003, None, 0.001, 0.0083) == 0.0  # no rate known yet
    # commands every 50 ms, frames every 8.3 ms: the next one is 45 ms away, not waited for
    assert next_command_wait_s(0.005, 0.05, 0.001, 0.0083) == 0.0
    # a command overdue (late on the link): half an interval of slack, then the old one
    assert next_command_wait_s(0.006, 0.004, 0.001, 0.0083) == pytest.approx(0.002)


def test_the_frame_schedule_in_numbers() -> None:
    period = 1 / 60
    # a frame due at 1.0 that began 3 ms late: the next is due a period after 1.0, not
    # after its start (counted from the start, 60 frames/s gave 47 in the demo)
    assert next_frame_due_s(1.0, 1.003, 1.006, period, True) == (1.0 + period, False)
    # more than a period behind: restart now, no burst of catch-up frames
    assert next_frame_due_s(1.0, 1.003, 1.0 + 2.5 * period, period, True) == (
        1.0 + 2.5 * period, True)
    # behind by less: the next no sooner than half a period after this one began
    assert next_frame_due_s(1.0, 1.0 + 0.9 * period, 1.0 + 1.2 * period, period, True) == (
        pytest.approx(1.0 + 1.4 * period), False)
    # an idle frame (no new command within a period): the schedule restarts at its start
    assert next_frame_due_s(1.0, 1.0 + period, 1.02, period, False) == (
        pytest.approx(1.0 + 2 * period), False)


@given(steps=st.lists(st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 1.0)), min_size=1,
                      max_size=200),
       period=st.floats(1e-3, 1.0))
def test_frames_keep_their_rate_on_average_and_never_burst(
        steps: list[tuple[float, float]], period: float) -> None:
    """Frames that each wait (for a command, the pose) up to a quarter period and take up to
    a quarter to process: frame k is due exactly k periods after the first, whatever the
    waits, so the rate setting is met. With longer waits the schedule restarts rather than
    owing more than a period, and no frame starts within half a period of the previous."""
    due = start0 = 0.0
    now = 0.0
    for k, (wait_frac, busy_frac) in enumerate(steps, start=1):
        start = max(due, now) + wait_frac * 0.25 * period
        now = start + busy_frac * 0.24 * period
        due, late = next_frame_due_s(due, start, now, period, True)
        assert not late
        assert due == pytest.approx(start0 + k * period, abs=1e-9 * k)
        assert due >= now - period
    # and whatever the waits, at most a period of catch-up is owed after any frame
    for wait, busy in steps:
        start = max(due, now) + wait * 3 * period
        now = start + busy * 3 * period
        before = due
        due, late = next_frame_due_s(due, start, now, period, True)
        assert due >= now - period
        assert due >= start + 0.5 * period
        assert due == max(now if late else before + period, start + 0.5 * period)


def _frames(sent: Sequence[object]) -> list[TactileFrame | TactileCompact]:
    return [m for m in sent if isinstance(m, TactileFrame | TactileCompact)]


async def hold_hand(link: FakeLink, position: tuple[float, float, float], interval_s: float,
                    *, until: Callable[[], bool], stop: asyncio.Event | None = None,
                    seq: int = 0) -> int:
    """A held hand: a fresh platform state at ``position`` every ``interval_s`` (on an
    absolute schedule, numbered on from ``seq``) until ``until()``; then ``stop`` is set.
    Returns the last state's number. After a stall the missed states are skipped, not sent
    at once (as a station's uplink sends its newest sample)."""
    loop = asyncio.get_running_loop()
    next_t = loop.time()
    while not until():
        seq += 1
        link.inbox.put_nowait(platform_state(seq, position))
        next_t = max(next_t + interval_s, loop.time())
        await asyncio.sleep(max(0.0, next_t - loop.time()))
    if stop is not None:
        stop.set()
    return seq


def _for(seconds: float) -> Callable[[], bool]:
    """True once ``seconds`` have passed (on the running loop's clock)."""
    end = asyncio.get_running_loop().time() + seconds
    return lambda: asyncio.get_running_loop().time() >= end


async def test_frames_are_taken_once_the_arm_reached_the_commanded_pose() -> None:
    """A 10 mm step takes the sim arm about 0.3 s. With a slow frame clock (5 Hz) and a long
    pose wait, every frame answering the step is taken with the pad within the tolerance of
    the target (on the frame clock the first one shows the pad on its way)."""
    tolerance_mm = 0.05
    link = FakeLink()
    # the arm's age limit and watchdog scaled like the test's waits: on a loaded machine a
    # state held up > 100 ms in the loop is refused or halts the arm, which then never
    # reaches the step (a frame then rightly shows it where it stopped: not what is tested)
    safety = SafetyConfig(max_command_age_ms=scaled(100.0), command_timeout_ms=scaled(100.0))
    station = make_station(link, safety, config=RemoteAgentConfig(
        frame_rate_hz=5.0, status_interval_s=10.0, pose_tolerance_mm=tolerance_mm,
        pose_wait_max_ms=1000.0))
    assert station.captures_on_pose
    start, target = (0.0, 0.0, 12.0), (10.0, 0.0, 12.0)
    stop = asyncio.Event()

    async def operator() -> None:  # a held hand: fresh states at 50 Hz
        seq = await hold_hand(link, start, 0.02, until=_for(scaled(1.0)))
        await async_wait_until(lambda: math.dist(station.safe_arm.arm.state().position_mm,
                                                 start) < 0.01, 10.0, "the arm at the start")
        station.captures.on_pose = station.captures.moving = 0
        before = len(_frames(link.sent))
        step_seq = seq + 1
        await hold_hand(link, target, 0.02, until=_for(scaled(1.5)), stop=stop, seq=seq)
        answered = [f for f in _frames(link.sent)[before:]
                    if f.source_seq is not None and f.source_seq >= step_seq]
        assert answered, "no frame answered the step"
        first = answered[0]
        stamps = {h.stage: h.t_us for h in first.hops if h.clock == "remote"}
        step_applied_us = min(stamps["arm_command"], now_us())
        assert stamps["sensor_frame"] >= step_applied_us
        # the frame shows the pad where it was commanded (platform coordinates)
        target_platform = WS.inverse(list(target))
        counters = station.safe_arm.counters
        assert math.dist(first.center_mm, target_platform[:2]) <= tolerance_mm * 1.05 + 1e-3, (
            f"first answering frame at {first.center_mm}, "
            f"{(stamps['sensor_frame'] - stamps['arm_command']) / 1e3:.1f} ms after its "
            f"command; {station.captures}; arm commands refused as stale "
            f"{counters.dropped_stale}, watchdog halts {counters.watchdog_halts}")
        assert station.captures.on_pose >= 1
        assert station.captures.moving <= 1

    try:
        task = asyncio.create_task(operator())
        await station.run(stop, duration_s=scaled(20.0))
        await task
        assert station.summary()["frames"]["capture"] == "on_pose"
    finally:
        close_station(station)


async def test_a_streaming_sensor_keeps_the_frame_clock() -> None:
    """A sensor that does not capture on demand (a camera) is read on the frame clock."""
    import numpy as np

    from remote_site.sensor.simulator import SimulatedSensor

    good = SimulatedSensor().render(np.zeros((240, 320)))
    sensor = ScriptedSensor([good] * 400)
    assert not sensor.captures_on_demand
    link = FakeLink()
    station = make_station(link, sensor=sensor, config=RemoteAgentConfig(
        frame_rate_hz=50.0, status_interval_s=10.0))
    stop = asyncio.Event()

    async def stopper() -> None:
        await async_wait_until(lambda: station.captures.clock >= 5, 20.0, "5 clocked frames")
        stop.set()

    try:
        task = asyncio.create_task(stopper())
        await station.run(stop, duration_s=scaled(30.0))
        await task
        assert not station.captures_on_pose
        assert station.captures.on_pose == station.captures.idle == 0
        assert station.summary()["frames"]["capture"] == "clock"
    finally:
        close_station(station)


async def test_frames_answer_commands_as_they_arrive_not_after_they_aged() -> None:
    """Commands every 12 ms, frames at most every 20 ms: without the wait for the next
    command a due frame takes the newest command at whatever age it has then (8, 4, 0 or
    12 ms in turn: median about 6 ms); with it, frames are taken as commands arrive."""
    interval_s = 0.012
    link = FakeLink()
    safety = SafetyConfig(max_command_age_ms=scaled(100.0), command_timeout_ms=scaled(200.0))
    station = make_station(link, safety, config=RemoteAgentConfig(
        frame_rate_hz=50.0, status_interval_s=10.0, command_fresh_ms=1.0))
    position = (0.0, 0.0, 12.0)
    stop = asyncio.Event()

    try:
        # a stall of the machine is one long gap between two commands: the estimate (a mean
        # with weight 1/8; gaps above _COMMAND_GAP_MAX_S, 0.1 s, left out) moves up by at
        # most an eighth of it
        with MachineStalls() as stalls:
            task = asyncio.create_task(hold_hand(
                link, position, interval_s, until=lambda: len(station.command_wait_s) >= 30,
                stop=stop))
            await station.run(stop, duration_s=scaled(30.0))
            await task
        ages_ms = np.asarray(station.command_wait_s)[5:] * 1e3  # after the rate is known
        up_s = sum(min(stall, 0.1) for stall in stalls.stalls_s) / 8
        estimate = station.command_interval_s
        assert estimate is not None and \
            interval_s / 2 <= estimate <= 1.5 * interval_s + up_s, (estimate, stalls.stalls_s)
        assert float(np.median(ages_ms)) <= interval_s * 1e3 / 4, (
            f"command ages at capture {np.round(ages_ms, 1)} ms; {station.captures}")
        assert station.captures.waited_for_command >= 10
        assert station.summary()["latency_ms"]["arm_command_to_capture"]["n"] >= 30
    finally:
        close_station(station)


async def test_the_frame_rate_setting_is_met_while_commands_come_faster() -> None:
    """Frames at 10 Hz, commands every 20 ms, each frame waiting for the next command
    (``command_fresh_ms = 0``): 0-20 ms per frame. Counted from each frame's start, those
    waits would add up (about 10 ms a frame, 200 ms over 20 frames); on the frame schedule
    20 frames take 20 periods plus at most one wait. The schedule falls a period behind (a
    late frame) only when the machine stalls the process, which is allowed for: a CI run
    saw one late frame, with the arm halted for 200 ms without commands. (The stalls are
    the machine's, seen from a thread: the station's own loop blocked is not excused.)"""
    interval_s, period_s, n = 0.02, 0.1, 20
    link = FakeLink()
    safety = SafetyConfig(max_command_age_ms=scaled(100.0), command_timeout_ms=scaled(200.0))
    station = make_station(link, safety, config=RemoteAgentConfig(
        frame_rate_hz=1 / period_s, status_interval_s=10.0, command_fresh_ms=0.0))
    stop = asyncio.Event()
    skip = 3  # the first frames, before the commands' interval is known

    try:
        with MachineStalls() as stalls:
            task = asyncio.create_task(hold_hand(
                link, (0.0, 0.0, 12.0), interval_s,
                until=lambda: len(station.frame_period_s) >= skip + n, stop=stop))
            await station.run(stop, duration_s=scaled(30.0))
            await task
        periods = list(station.frame_period_s)[skip:skip + n]
        assert station.captures.waited_for_command >= n // 2, station.captures
        # a late frame needs the schedule a period behind: waits (<= 20 ms) cannot do that
        assert station.counters.frames_late <= stalls.count(period_s / 2), stalls.stalls_s
        assert sum(periods) <= n * period_s + scaled(0.06) + stalls.total_s, (
            f"{n} frames took {sum(periods) * 1e3:.0f} ms against {n * period_s * 1e3:.0f}; "
            f"periods {np.round(np.asarray(periods) * 1e3, 1)} ms; stalls {stalls.stalls_s}")
    finally:
        close_station(station)


async def test_an_arm_tracking_a_moving_hand_is_judged_at_the_first_look() -> None:
    """An arm already closing in on a target it cannot reach within the pose wait (tracking
    a hand, 1 mm behind at 45 mm/s: 17 ms against 10) is captured at once, with no second
    look; one that sets off from rest is given until the deadline while it speeds up. Those
    are looked at with a longer pose wait (a stall of the test ended a 10 ms one before a
    third look) and a target far enough that at no speed they reach would it arrive within
    the wait: only the rule for an arm from rest keeps them looked at."""
    from remote_site.tactile import AppliedCommand

    station = make_station(FakeLink(), config=RemoteAgentConfig(
        frame_rate_hz=30.0, status_interval_s=10.0, pose_wait_max_ms=10.0))
    wait_s = min(1.0, scaled(0.3))
    patient = make_station(FakeLink(), config=RemoteAgentConfig(
        frame_rate_hz=30.0, status_interval_s=10.0, pose_wait_max_ms=wait_s * 1e3))
    target = (1.0, 0.0, 12.0)
    far = (1e6, 0.0, 12.0)  # 1 km: at the speeds below, never within the wait
    looks: list[float] = []

    def tracking() -> ArmReading:
        looks.append(asyncio.get_running_loop().time())
        return ArmReading((0.0, 0.0, 12.0), (45.0, 0.0, 0.0), 0.0, "moving", target, 0.0)

    def speeding_up(first_mm_s: float) -> Iterator[float]:
        """0.2 % faster every look (each look a millisecond or more apart)."""
        return (first_mm_s * 1.002 ** k for k in itertools.count())

    speeds: Iterator[float] = itertools.chain([0.0], speeding_up(20.0))

    def from_rest() -> ArmReading:  # speeding up, never arriving
        looks.append(asyncio.get_running_loop().time())
        return ArmReading((0.0, 0.0, 12.0), (next(speeds), 0.0, 0.0), 0.0,
                          "moving", far, 0.0)

    loop = asyncio.get_running_loop()
    try:
        command = AppliedCommand(platform_state(1, target), now_us())
        station.pipeline.read_arm = tracking
        await station._until_pose(command)
        assert len(looks) == 1 and station.captures.moving == 1

        looks.clear()
        given = loop.time()
        command = AppliedCommand(platform_state(2, far), now_us())
        patient.pipeline.read_arm = from_rest
        await patient._until_pose(command)
        assert len(looks) >= 3, "an arm setting off from rest was not given time"
        assert looks[-1] >= given + wait_s - 0.002, "not looked at until the deadline"
        assert patient.captures.moving == 1

        # looked at a moment after the command, an arm from rest may already be above
        # 1 mm/s: it was at rest when the command was given, so it is given time as well
        # (judged by the first look alone, a 10 mm step was captured 0.9 ms after its
        # command with the pad still at the start)
        looks.clear()
        speeds = speeding_up(2.0)
        command = AppliedCommand(platform_state(3, far), now_us(), arm_speed_mm_s=0.0)
        await patient._until_pose(command)
        assert len(looks) >= 3, "an arm given a command at rest was not given time"
        assert patient.captures.moving == 2
        # the same first look, for an arm that was moving when the command came: at once
        looks.clear()
        speeds = speeding_up(2.0)
        station.pipeline.read_arm = from_rest
        command = AppliedCommand(platform_state(4, far), now_us(), arm_speed_mm_s=40.0)
        await station._until_pose(command)
        assert len(looks) == 1
        assert station.captures.moving == 2
    finally:
        close_station(station)
        close_station(patient)
