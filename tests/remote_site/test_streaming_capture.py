"""A streaming sensor's frame answers the command of its image's time, at the arm's pose then.

A camera that streams on its own clock hands the station an image taken before the frame
tick that reads it, perhaps before the newest command was applied. The frame must then name
the command applied by the image's time (never one applied after it: ``arm_command`` would
follow ``sensor_frame`` and motion-to-touch would count a movement the image cannot show),
leave the states after that command for the next frame, and place the patch where the arm
was when the image was taken.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import math
import threading
from collections.abc import Awaitable, Callable

import numpy as np
import pytest

from remote_site.agent.config import RemoteAgentConfig
from remote_site.agent.station import RemoteStation
from remote_site.arm.base import ArmReading
from remote_site.arm.safety import CommandResult, SafetyConfig
from remote_site.sensor.base import SensorFrame, TactileSensor
from remote_site.sensor.simulator import SimulatedSensor
from remote_site.tactile import AppliedCommand
from shared.protocol import Hop, PlatformState, TactileCompact, TactileFrame
from shared.timebase import now_us
from tests.remote_site.test_agent_safety import (
    WS,
    FakeLink,
    ScriptedSensor,
    _stamped,
    close_station,
    make_station,
    platform_state,
)
from tests.support import async_wait_until, motion_of, scaled


class LaggingCamera(ScriptedSensor):
    """A streaming camera: each read finds a new image, taken ``lag_us`` before the read and
    delivered ``delivery_us`` after it was taken."""

    def __init__(self, lag_us: int, delivery_us: int = 0) -> None:
        super().__init__([])
        self.lag_us, self.delivery_us = lag_us, delivery_us
        self.image = SimulatedSensor().render(np.zeros((240, 320)))

    def _latest(self) -> SensorFrame | None:
        self.seq += 1
        taken_us = now_us() - self.lag_us
        return SensorFrame(self.image, taken_us, self.seq, taken_us + self.delivery_us)


def _stamp(frame: TactileFrame | TactileCompact, stage: str) -> int:
    return next(h.t_us for h in frame.hops if h.clock == "remote" and h.stage == stage)


async def test_a_streamed_frame_answers_the_command_of_its_image_at_the_pose_then(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # states at 250 Hz move the arm along x at 20 mm/s; frames at 30 Hz from a camera whose
    # images are 30 ms old when read: 7-8 commands are applied between an image and its read
    import remote_site.agent.station as station_module

    monkeypatch.setattr(station_module, "_CHAIN_MAX_S", scaled(60.0))  # no outage here
    lag_us = 30_000
    link = FakeLink()
    station = make_station(link, SafetyConfig(max_command_age_ms=scaled(5_000.0)),
                           sensor=LaggingCamera(lag_us, delivery_us=12_000),
                           config=RemoteAgentConfig(frame_rate_hz=30.0, status_interval_s=10.0))
    station.pipeline.warm_up()  # a cold compile of the kernels would take the first second
    assert not station.captures_on_pose
    applied: list[AppliedCommand] = []  # in order
    apply = station.apply_platform_state

    def recording_apply(state: PlatformState) -> CommandResult | None:
        before = station.latest
        result = apply(state)
        if station.latest is not before and station.latest is not None:
            applied.append(station.latest)
        return result

    station.apply_platform_state = recording_apply  # type: ignore[method-assign]
    # the polls the station had when it placed each image (by the image's stamp)
    polls_then: dict[int, list[tuple[int, ArmReading]]] = {}
    reading_at = station.reading_at

    def recording_reading_at(t_us: int) -> ArmReading:
        polls_then[t_us] = list(station._readings)
        return reading_at(t_us)

    station.reading_at = recording_reading_at  # type: ignore[method-assign]
    stop = asyncio.Event()
    sent: dict[int, PlatformState] = {}

    async def operator() -> None:
        previous = None
        for seq in range(1, 250):
            state = _stamped(seq, previous)
            moved = platform_state(seq, (-12.0 + 0.08 * seq, -35.0, 2.0), state.ts_us)
            state = dataclasses.replace(state, position_mm=moved.position_mm)
            sent[seq], previous = state, state.ts_us
            link.inbox.put_nowait(state)
            await asyncio.sleep(0.004)
        await asyncio.sleep(0.2)
        stop.set()

    try:
        feeder = asyncio.create_task(operator())
        await station.run(stop, duration_s=scaled(30.0))
        await feeder
        frames = [m for m in link.sent if isinstance(m, TactileFrame | TactileCompact)]
        answering = [f for f in frames if any(h.clock == "local" for h in f.hops)]
        assert len(answering) >= 10, f"{len(answering)} answering frames"
        by_seq = {c.state.seq: c for c in applied}
        newer_than_image = placed = between = 0
        for frame in answering:
            image_us, command_us = _stamp(frame, "sensor_frame"), _stamp(frame, "arm_command")
            assert command_us <= image_us  # never a command the image cannot show
            assert frame.source_seq is not None
            command = by_seq[frame.source_seq]
            assert command.arm_command_us == command_us
            # ... and the newest such: the next command was applied after the image
            later = [c for c in applied if c.arm_command_us > command_us]
            assert not later or later[0].arm_command_us > image_us
            ready_us = _stamp(frame, "tactile_ready")
            # the image's delivery is its own stage, and the station's work starts after it
            assert _stamp(frame, "sensor_arrival") - image_us == 12_000
            newer_than_image += any(image_us < c.arm_command_us <= ready_us for c in applied)
            # placed where the arm was when the image was taken: on the straight line
            # between the readings polled just before and just after it, of those the
            # station had then (a reading at the read itself, 30 ms on, is 0.6 mm away at
            # 20 mm/s; the nearer of the two polls, 4 ms apart, up to 0.04 mm)
            readings = polls_then[image_us]
            polled_us = np.array([t for t, _ in readings], dtype=float)
            k = int(np.searchsorted(polled_us, image_us, side="right"))
            if k == 0 or k == len(readings):
                continue  # taken before the station's first poll or after its last then
            placed += 1
            where = [np.interp(image_us, polled_us[k - 1:k + 1],
                               [r.position_mm[axis] for _, r in readings[k - 1:k + 1]])
                     for axis in range(3)]
            assert math.dist(frame.center_mm, WS.inverse(where)[:2]) < 1e-6
            gap = polled_us[k] - polled_us[k - 1]
            between += 0.25 <= (image_us - polled_us[k - 1]) / gap <= 0.75
        # the cases under test happened (an image well between two polls among them)
        assert newer_than_image >= 5 and placed >= 5 and between >= 2
        # the station's summary keeps the camera's delivery apart too
        delivery = station.summary()["latency_ms"]["sensor_delivery"]
        assert delivery["p50"] == delivery["max"] == 12.0
        # the wait from each answered command to its image, once per answering frame
        waits = sorted(round(w * 1e6) for w in station.command_wait_s)
        assert waits == sorted(_stamp(f, "sensor_frame") - _stamp(f, "arm_command")
                               for f in answering)
        # the states applied after an image are first shown by the next frame
        for before, after in itertools.pairwise(answering):
            assert before.source_seq is not None and after.source_seq is not None
            assert after.source_seq > before.source_seq
            assert motion_of(after) == sent[before.source_seq].ts_us
    finally:
        close_station(station)


def test_applied_at_reading_at_and_the_chain_left_after_an_older_command(
        monkeypatch: pytest.MonkeyPatch) -> None:
    import remote_site.agent.station as station_module

    clock = itertools.count(1_000_000, 1_000)  # 1 ms per stamp
    monkeypatch.setattr(station_module, "now_us", lambda: next(clock))
    link = FakeLink()
    station = make_station(link, realtime=False, sensor=LaggingCamera(0))
    states = [_stamped(0, None)]
    try:
        assert station.applied_at(10**12) is None  # nothing applied yet

        def offer(refused: bool = False) -> AppliedCommand | None:
            state = _stamped(len(states), states[-1].ts_us)
            if refused:
                state = dataclasses.replace(state, position_mm=(float("nan"), 0.0, 0.0))
            states.append(state)
            station.apply_platform_state(state)
            return None if refused else station.latest

        first = offer()  # 1
        second = offer()  # 2
        offer(refused=True)  # 3
        third = offer()  # 4
        assert first is not None and second is not None and third is not None
        assert station.applied_at(first.arm_command_us - 1) is None
        assert station.applied_at(first.arm_command_us) is first
        assert station.applied_at(third.arm_command_us - 1) is second
        assert station.applied_at(10**12) is third
        # a frame of the image taken before the third command answers the second, starts at
        # the first state's predecessor and leaves the chain from state 3 (refused) on
        source, _ = station._frame_source(station.applied_at(third.arm_command_us - 1))
        assert source is not None and source.state.seq == 2
        assert motion_of(source.state) == states[0].ts_us
        station._answered = second
        source, _ = station._frame_source(station.latest)
        assert source is not None and source.state.seq == 4
        assert motion_of(source.state) == states[2].ts_us  # where 3 started
        # the arm between its polled readings (the current one before any was polled)
        assert station.reading_at(0).position_mm == station.pipeline.read_arm().position_mm
        a, b = (ArmReading((float(i), 0.0, 1.0), (0.0, 0.0, 0.0), 0.0, "ok", None, 0.0)
                for i in range(2))
        station._readings.extend([(100, a), (200, b)])
        assert station.reading_at(0) is a and station.reading_at(100) is a
        assert station.reading_at(175).position_mm == (0.75, 0.0, 1.0)
        assert station.reading_at(200) is b and station.reading_at(10**9) is b
        assert Hop("local", "capture", states[4].ts_us) in source.state.hops
        # the chain left after a command starts on the newest link connection: a state
        # refused before a reconnect does not start it, one refused after does
        offer(refused=True)  # 5, before the reconnect
        link.counters.connects += 1
        offer(refused=True)  # 6, after it
        fourth = offer()  # 7
        assert fourth is not None
        source, _ = station._frame_source(third)  # an image taken before 5 answers 4
        assert source is not None and source.state.seq == 4
        station._answered = third
        source, _ = station._frame_source(fourth)
        assert source is not None and source.state.seq == 7
        assert motion_of(source.state) == states[5].ts_us  # where 6 started, not 5
    finally:
        close_station(station)


class NotifyingCamera(TactileSensor):
    """A streaming camera on its own thread at ``fps`` that says when a new image arrives;
    ``paused`` stops it (a stalled camera). ``late_notices``: every other image is announced
    only after the next one was stored and announced (its notice then names an image the
    station has taken already)."""

    notifies_frames = True

    def __init__(self, fps: float, late_notices: bool = False) -> None:
        super().__init__((240, 320), 0.0634)
        self.period_s = 1.0 / fps
        self.late_notices = late_notices
        self.image = SimulatedSensor().render(np.zeros((240, 320)))
        self.paused = threading.Event()
        self.arrived_us: list[int] = []
        self._newest: SensorFrame | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _connect(self) -> None:
        self._thread = threading.Thread(target=self._run, name="test-camera", daemon=True)
        self._thread.start()

    def _disconnect(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def _run(self) -> None:
        seq = step = 0
        while not self._stop.wait(self.period_s / 2):  # two steps per image
            step += 1
            if self.paused.is_set():
                continue
            if not self.late_notices:
                if step % 2 == 0:
                    self._store(seq := seq + 1)
                    self._frame_arrived()
                continue
            phase = step % 4  # store (notice held), -, store and announce, the held notice
            if phase in (0, 2):
                self._store(seq := seq + 1)
            if phase in (2, 3):
                self._frame_arrived()

    def _store(self, seq: int) -> None:
        with self._lock:
            self._newest = SensorFrame(self.image, now_us(), seq)
            self.arrived_us.append(self._newest.timestamp_us)

    def _latest(self) -> SensorFrame | None:
        with self._lock:
            return self._newest


def _camera_station(camera: TactileSensor, frame_rate_hz: float,
                    sensor_max_age_ms: float = 100.0) -> RemoteStation:
    """The station on ``camera`` (its kernels warmed up: a cold compile would take the
    first second)."""
    station = make_station(FakeLink(), sensor=camera, config=RemoteAgentConfig(
        frame_rate_hz=frame_rate_hz, sensor_max_age_ms=sensor_max_age_ms,
        status_interval_s=10.0))
    station.pipeline.warm_up()
    return station


async def _run_while(station: RemoteStation, script: Callable[[], Awaitable[None]]) -> None:
    """Run ``station`` until ``script`` has returned (or failed: the error is raised)."""
    stop = asyncio.Event()

    async def driver() -> None:
        try:
            await script()
        finally:
            stop.set()

    task = asyncio.create_task(driver())
    await station.run(stop, duration_s=scaled(30.0))
    await task


async def test_a_camera_that_notifies_is_read_as_each_image_arrives() -> None:
    # a 25 frames/s camera and a station allowed 60 frames/s: each image is taken once, as
    # it arrives, instead of on a 60 Hz clock that finds the same image on most ticks
    camera = NotifyingCamera(25.0)
    station = _camera_station(camera, frame_rate_hz=60.0)
    try:
        await _run_while(station, lambda: async_wait_until(
            lambda: station.pipeline.processed >= 25, 20.0, "25 frames"))
        assert camera.on_frame is None  # let go when the station stopped
        processed = station.pipeline.processed
        # the images arrive 40 ms apart, far within sensor_max_age_ms: every tick but the
        # first had a new one (a clock at 60 Hz would have found the same image on about
        # 3 ticks in 5)
        assert station.captures.on_arrival >= processed - 1
        assert station.pipeline.repeated <= 2, station.pipeline.repeated
        assert station.summary()["frames"]["capture"] == "on_arrival"
    finally:
        close_station(station)


async def test_a_late_notice_of_an_image_already_taken_is_not_a_tick() -> None:
    # every other notice comes after the next image was stored and announced (and taken):
    # such a notice names nothing new, and the station waits on for the next image
    station = _camera_station(NotifyingCamera(50.0, late_notices=True), frame_rate_hz=400.0)
    try:
        await _run_while(station, lambda: async_wait_until(
            lambda: station.pipeline.processed >= 20, 20.0, "20 frames"))
        assert station.pipeline.repeated <= 1, station.pipeline.repeated
        assert station.captures.on_arrival <= station.pipeline.processed + 1
    finally:
        close_station(station)


async def test_a_notifying_camera_is_read_at_most_at_the_frame_rate_and_when_it_stalls(
        ) -> None:
    camera = NotifyingCamera(200.0)
    station = _camera_station(camera, frame_rate_hz=20.0, sensor_max_age_ms=50.0)
    at_pause: dict[str, int] = {}

    async def script() -> None:
        await async_wait_until(lambda: station.pipeline.processed >= 10, 20.0, "10 frames")
        camera.paused.set()  # a stalled camera: the ticks go on, and say so
        at_pause.update(timeouts=station.pipeline.rejected["sensor_timeout"],
                        arrivals=station.captures.on_arrival,
                        ticks=len(station.frame_period_s))
        await async_wait_until(
            lambda: station.pipeline.rejected["sensor_timeout"] >= at_pause["timeouts"] + 3,
            20.0, "ticks of the stalled camera")

    try:
        await _run_while(station, script)
        # no two frames sooner than a period apart (the camera offers one every 5 ms)
        assert min(station.frame_period_s) >= 1.0 / 20.0 - 1e-3
        # stalled, a tick comes a period plus sensor_max_age_ms after the last (0.1 s here),
        # and it is not an arrival (the image in flight at the pause may be one)
        assert station.captures.on_arrival <= at_pause["arrivals"] + 1
        stalled = list(station.frame_period_s)[at_pause["ticks"] + 2:]
        assert stalled and max(stalled) <= scaled(0.3), stalled
    finally:
        close_station(station)
