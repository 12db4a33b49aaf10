"""Sensor sources: simulator and OpenCV camera behind one base class, and the registry."""

from __future__ import annotations

import itertools
import re
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from remote_site.sensor import SENSORS, open_sensor
from remote_site.sensor.base import TactileSensor
from remote_site.sensor.camera import OpenCVCameraSensor, crop_and_resize
from remote_site.sensor.photometric import PhotometricModel, PhotometricSettings
from remote_site.sensor.shapes import ball_depth_mm
from remote_site.sensor.simulator import SimulatedSensor
from shared.errors import (
    ConfigError,
    DeviceInitError,
    DeviceNotConnectedError,
    DeviceOperationError,
    DeviceTimeoutError,
    InputDataError,
)
from shared.timebase import now_us
from tests.support import scaled, wait_until


class FakeCapture:
    """A VideoCapture stand-in delivering raw 2464 x 3280-like (scaled down) BGR frames."""

    def __init__(self, frames: list[np.ndarray], opened: bool = True,
                 repeat: np.ndarray | None = None) -> None:
        self.frames = list(frames)
        self.repeat = repeat
        self.opened = opened
        self.released = False

    def isOpened(self) -> bool:
        return self.opened

    def read(self) -> tuple[bool, Any]:
        if self.repeat is not None:
            time.sleep(0.002)
            return True, self.repeat.copy()
        if not self.frames:
            return False, None
        time.sleep(0.001)
        return True, self.frames.pop(0)

    def release(self) -> None:
        self.released = True


def _raw_frame(rows: int = 350, cols: int = 466) -> np.ndarray:
    """A raw BGR frame whose crop region is blue, border red (so crop errors show)."""
    bgr = np.zeros((rows, cols, 3), np.uint8)
    bgr[..., 2] = 200  # red border (BGR)
    top, left = rows // 7, cols // 7
    bgr[top:rows - top, left:cols - left] = (180, 60, 20)  # blue-ish inside (BGR)
    return bgr


# --------------------------------------------------------------------------- base class contract


@pytest.fixture(params=["sim", "sim_camera", "fake_camera"])
def any_sensor(request: pytest.FixtureRequest) -> TactileSensor:
    if request.param == "sim":
        return open_sensor("sim")
    if request.param == "sim_camera":
        return open_sensor("sim-camera", fps=50.0)
    return OpenCVCameraSensor(0, capture_factory=lambda src: FakeCapture([], repeat=_raw_frame()))


def test_every_backend_follows_the_contract(any_sensor: TactileSensor) -> None:
    with pytest.raises(DeviceNotConnectedError):
        any_sensor.read_latest()
    with any_sensor as sensor:
        assert sensor.is_connected
        first = sensor.read_latest(max_age_ms=scaled(500))
        wait_until(lambda: sensor.read_latest(max_age_ms=scaled(500)).seq != first.seq, 1.0,
                   "the next frame")  # a loaded capture thread may need more than 10 ms
        second = sensor.read_latest(max_age_ms=scaled(500))
        assert first.rgb.shape == (240, 320, 3) and first.rgb.dtype == np.uint8
        assert second.seq > first.seq
        assert second.timestamp_us >= first.timestamp_us
    assert not any_sensor.is_connected
    with pytest.raises(DeviceNotConnectedError):
        any_sensor.read_latest()
    any_sensor.disconnect()  # idempotent


# --------------------------------------------------------------------------- simulator


def test_the_simulated_camera_streams_stamps_its_exposure_and_says_so() -> None:
    # 40 frames/s, 60 ms from exposure to delivery: each image is announced once, when it
    # is delivered, stamped with its exposure (at least the latency before the notice)
    sensor = open_sensor("sim-camera", fps=40.0, latency_ms=60.0)
    assert not sensor.captures_on_demand and sensor.notifies_frames
    notices: list[tuple[int, int]] = []  # (seq, lead of the notice over the stamp, us)
    deliveries: list[int] = []  # arrival - stamp, us

    def listener() -> None:
        frame = sensor._latest()
        assert frame is not None
        notices.append((frame.seq, now_us() - frame.timestamp_us))
        deliveries.append(frame.received_us - frame.timestamp_us)

    sensor.on_frame = listener
    with sensor:
        wait_until(lambda: len(notices) >= 6, 5.0, "six images")
        frame = sensor.read_latest(max_age_ms=scaled(1_000.0))
        assert frame.rgb.shape == (240, 320, 3)
        with pytest.raises(DeviceTimeoutError, match="old"):  # aged from the exposure
            sensor.read_latest(max_age_ms=50.0)
        # the latency (longer than a period) does not slow the rate: images in flight queue
        # (over 1.5 s: the camera skips the exposures a stall of this process passes over)
        count, t0 = len(notices), time.monotonic()
        time.sleep(1.5)
        rate = (len(notices) - count) / (time.monotonic() - t0)
        assert rate >= 0.6 * 40.0, f"{rate:.1f} images/s"
    seqs = [seq for seq, _ in notices]
    assert seqs == sorted(set(seqs)) and seqs[0] == 1  # each once, in order, from the first
    assert min(lead for _, lead in notices) >= 60_000
    # stamped again on delivery (the ledger's sensor_arrival): the latency lies between the
    # two stamps
    assert min(deliveries) >= 60_000
    assert not sensor.health.ended
    for bad in ({"fps": 0.0}, {"fps": float("nan")}, {"latency_ms": -1.0}):
        with pytest.raises(ConfigError):
            open_sensor("sim-camera", **bad)


def test_a_failing_depth_provider_does_not_end_the_simulated_camera() -> None:
    from remote_site.sensor.simulator import StreamingSimulatedSensor

    calls = [0]

    def flaky() -> np.ndarray:  # every third map fails
        calls[0] += 1
        if calls[0] % 3 == 0:
            raise ValueError("the world's contact model failed")
        return np.zeros((240, 320), np.float32)

    sensor = StreamingSimulatedSensor(flaky, fps=100.0)
    with sensor:
        first = sensor.read_latest(max_age_ms=scaled(1_000.0))
        wait_until(lambda: calls[0] >= 10, 5.0, "ten renders")
        assert sensor.read_latest(max_age_ms=scaled(1_000.0)).seq > first.seq
        assert not sensor.health.ended and sensor.render_error is not None
    broken = StreamingSimulatedSensor(lambda: np.full((2, 2), np.nan), fps=100.0,
                                      first_frame_timeout_s=0.3)
    with pytest.raises(DeviceInitError, match="last render error"):
        broken.connect()


def test_the_simulated_camera_takes_the_world_wiring() -> None:
    # (what --phantom gives the sim sensor: the depth provider at the arm pose, noise, drift)
    from remote_site.agent.devices import open_world_arm, open_world_sensor
    from remote_site.agent.world import build_world

    world = build_world("breast", 0)  # the realistic world: every wiring option
    arm = open_world_arm("sim", world)
    sensor = open_world_sensor("sim-camera", world, arm, fps=50.0)
    arm.connect()
    try:
        with sensor:
            first = sensor.read_latest(max_age_ms=scaled(500.0))
            wait_until(lambda: sensor.read_latest(max_age_ms=scaled(500.0)).seq > first.seq,
                       2.0, "a second image")
            assert np.array_equal(first.rgb.shape, (240, 320, 3))
    finally:
        arm.disconnect()


def test_simulator_renders_contacts_from_a_provider() -> None:
    depth = ball_depth_mm((240, 320), 0.0634, 160, 120, 3.0, 0.4)
    calls = []

    def provider() -> np.ndarray:
        calls.append(1)
        return depth

    with SimulatedSensor(depth_provider=provider) as sensor:
        frame = sensor.read_latest().rgb
    assert calls
    diff = np.abs(frame.astype(int) - sensor.background_rgb.astype(int)).max(axis=2)
    assert diff[120, 160 - 20] > 10  # shading where the gel is tilted
    assert diff[10, 10] < 6  # flat gel far away only shows noise


def test_simulator_set_depth_and_bad_maps() -> None:
    sensor = SimulatedSensor()
    with pytest.raises(InputDataError):
        sensor.set_depth(np.full((240, 320), -0.1))
    with pytest.raises(InputDataError):
        sensor.set_depth(np.zeros((10, 10)))
    bad = SimulatedSensor(depth_provider=lambda: np.full((240, 320), np.nan))
    with bad, pytest.raises(DeviceOperationError):
        bad.read_latest()


def test_simulator_is_fast_enough_for_60_fps() -> None:
    model = PhotometricModel()
    depth = ball_depth_mm((240, 320), 0.0634, 160, 120, 3.0, 0.4)
    model.render(depth)
    times_s = []
    for _ in range(20):
        start = time.perf_counter()
        model.render(depth)
        times_s.append(time.perf_counter() - start)
    per_frame_s = float(np.mean(sorted(times_s)[:18]))  # a stall of the machine: one or two
    assert per_frame_s < 1 / 60, times_s


def test_simulator_markers_and_drift() -> None:
    plain = PhotometricModel(seed=1).render(np.zeros((240, 320)), noise=False)
    marked = PhotometricModel(PhotometricSettings(marker_pitch_mm=1.0), seed=1).render(
        np.zeros((240, 320)), noise=False)
    assert (marked < plain).any()
    dim = PhotometricModel(PhotometricSettings(brightness=(0.8, 0.8, 0.8))).render(
        np.zeros((240, 320)), noise=False)
    assert dim.mean() == pytest.approx(0.8 * plain.mean(), rel=0.02)


def test_gel_surface_is_smoothed_but_keeps_volume() -> None:
    model = PhotometricModel()
    depth = np.zeros((240, 320), np.float32)
    depth[100:140, 150:170] = 0.3
    surface = model.gel_surface_mm(depth)
    assert surface.max() < 0.3 + 1e-6
    assert surface.sum() == pytest.approx(depth.sum(), rel=0.01)


# --------------------------------------------------------------------------- camera


def test_crop_and_resize_removes_one_seventh_per_side() -> None:
    rgb = crop_and_resize(_raw_frame())
    assert rgb.shape == (240, 320, 3)
    # inside colour (BGR 180,60,20) -> RGB (20,60,180) everywhere, no red border left
    assert np.abs(rgb.astype(int) - [20, 60, 180]).max() <= 2


def test_camera_reads_a_video_file(tmp_path: Path) -> None:
    import cv2

    path = tmp_path / "gelsight.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 25.0, (466, 350))
    assert writer.isOpened()
    for _ in range(10):
        writer.write(_raw_frame())
    writer.release()
    with open_sensor(str(path)) as sensor:
        frame = sensor.read_latest(max_age_ms=2000)
    assert frame.rgb.shape == (240, 320, 3)
    assert np.abs(frame.rgb.astype(int)[20:-20, 20:-20] - [20, 60, 180]).max() < 25


def test_camera_that_does_not_open() -> None:
    sensor = OpenCVCameraSensor(3, capture_factory=lambda src: FakeCapture([], opened=False))
    with pytest.raises(DeviceInitError):
        sensor.connect()
    assert not sensor.is_connected


def test_camera_without_frames_times_out() -> None:
    sensor = OpenCVCameraSensor(0, first_frame_timeout_s=0.2,
                                capture_factory=lambda src: FakeCapture([]))
    with pytest.raises(DeviceTimeoutError):
        sensor.connect()


def test_stale_frames_are_refused() -> None:
    capture = FakeCapture([_raw_frame()])
    with OpenCVCameraSensor(0, capture_factory=lambda src: capture) as sensor:
        sensor.read_latest(max_age_ms=1000)
        time.sleep(0.05)
        with pytest.raises(DeviceTimeoutError, match="old"):
            sensor.read_latest(max_age_ms=10)
    assert capture.released


def test_a_camera_stamps_its_frames_with_the_known_latency_taken_off() -> None:
    # the image was taken latency_ms before it arrived: stamped then, and aged from then;
    # a stall is still judged by the arrival (a long latency is not a stalled camera)
    capture = FakeCapture([], repeat=_raw_frame())
    latency_us = round(scaled(2.0) * 1e6)  # twice the stall timeout, on a loaded machine too
    before_us = now_us()
    with OpenCVCameraSensor(0, capture_factory=lambda src: capture, latency_ms=latency_us / 1e3,
                            stall_timeout_s=scaled(1.0)) as sensor:
        frame = sensor.read_latest(max_age_ms=scaled(3_000.0))
        assert before_us - latency_us <= frame.timestamp_us <= now_us() - latency_us
        # its arrival is kept apart (the ledger's sensor_delivery): exactly that latency
        assert frame.received_us - frame.timestamp_us == latency_us
        with pytest.raises(DeviceTimeoutError, match="old"):
            sensor.read_latest(max_age_ms=latency_us / 1e3 * 0.75)
        assert not sensor.health.stalled and not sensor.health.ended
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="latency_ms"):
            OpenCVCameraSensor(0, capture_factory=lambda src: capture, latency_ms=bad)


def test_a_paced_live_camera_drops_the_frames_between_rather_than_holding_them() -> None:
    # a live camera published at --sensor-fps below its own rate: the frame published is
    # the one just read, stamped then (not one held until due, which would reach the station
    # a period old), and the rate is kept
    period_us = 300_000
    seen: list[tuple[int, int]] = []  # (release less the arrival stamp, arrival stamp), us
    sensor = OpenCVCameraSensor(0, capture_factory=lambda src: FakeCapture(
        [], repeat=_raw_frame()), fps=1e6 / period_us)

    def listener() -> None:
        frame = sensor._latest()
        assert frame is not None
        seen.append((now_us() - frame.received_us, frame.received_us))

    sensor.on_frame = listener
    with sensor:
        wait_until(lambda: len(seen) >= 4, 5.0, "four images")
        sensor.read_latest(max_age_ms=scaled(100.0))  # fresh when published
    assert max(lag for lag, _ in seen) < scaled(0.05) * 1e6, seen
    gaps = [b - a for (_, a), (_, b) in itertools.pairwise(seen)]
    assert min(gaps) >= 0.8 * period_us, gaps  # paced: the frames between were dropped


def test_a_camera_says_when_each_frame_arrives_and_survives_a_failing_listener() -> None:
    capture = FakeCapture([_raw_frame() for _ in range(6)])
    calls: list[int] = []
    sensor = OpenCVCameraSensor(0, capture_factory=lambda src: capture)
    assert sensor.notifies_frames and not sensor.captures_on_demand

    def listener() -> None:  # the first call comes while connect() waits for a frame
        newest = sensor._latest()
        assert newest is not None
        calls.append(newest.seq)
        if len(calls) == 2:
            raise RuntimeError("a listener's own failure")

    sensor.on_frame = listener
    with sensor:  # the device then fails to read: it is opened again
        wait_until(lambda: sensor.health.reopens >= 1, 5.0, "the six frames read")
    assert calls == [1, 2, 3, 4, 5, 6]  # each frame once, after it was stored


def test_camera_rejects_odd_frames_from_the_device() -> None:
    gray = np.zeros((350, 466), np.uint8)
    sensor = OpenCVCameraSensor(0, first_frame_timeout_s=scaled(0.3),
                                capture_factory=lambda src: FakeCapture([gray]))
    with pytest.raises(DeviceTimeoutError, match="unexpected frame"):
        sensor.connect()


class GrabbingCapture(FakeCapture):
    """An OpenCV-like live capture: ``grab`` takes the next image off the device (every
    ``period_s``), ``retrieve`` decodes it (counted), ``read`` does both."""

    def __init__(self, frame: np.ndarray, period_s: float = 0.002, grab_ok: bool = True,
                 retrieve_ok: bool = True, retrieve_s: float = 0.0) -> None:
        super().__init__([], repeat=frame)
        self.frame = frame
        self.period_s = period_s
        self.retrieve_s = retrieve_s
        self.retrieve_started_us: list[int] = []
        self.grab_ok, self.retrieve_ok = grab_ok, retrieve_ok
        self.grabs = self.retrieves = self.reads = 0

    def grab(self) -> bool:
        time.sleep(self.period_s)
        self.grabs += 1
        return self.grab_ok

    def retrieve(self) -> tuple[bool, Any]:
        self.retrieve_started_us.append(now_us())
        time.sleep(self.retrieve_s)
        self.retrieves += 1
        return (True, self.frame.copy()) if self.retrieve_ok else (False, None)

    def read(self) -> tuple[bool, Any]:
        self.reads += 1
        return super().read()


def test_a_paced_live_camera_decodes_only_the_frames_it_publishes() -> None:
    # OpenCV's V4L2 capture decodes an MJPEG image (or converts a YUYV one) in retrieve(), not
    # in grab(): the images dropped between published frames are grabbed, never decoded
    capture = GrabbingCapture(_raw_frame())
    published: list[int] = []
    sensor = OpenCVCameraSensor(0, capture_factory=lambda src: capture, fps=20.0)

    def listener() -> None:
        frame = sensor._latest()
        assert frame is not None
        published.append(frame.seq)

    sensor.on_frame = listener
    with sensor:
        wait_until(lambda: len(published) >= 4, 5.0, "four frames")
        assert sensor.read_latest(max_age_ms=scaled(200.0)).rgb.shape == (240, 320, 3)
    assert capture.reads == 0
    assert capture.retrieves == len(published)  # every decoded image was published
    assert capture.grabs > capture.retrieves  # and the images between were not decoded


def test_an_unpaced_live_camera_decodes_every_image_it_grabs() -> None:
    # without fps a live camera paces itself: every image is published (a video file is
    # read(): the file tests run on OpenCV's own capture)
    capture = GrabbingCapture(_raw_frame())
    published: list[int] = []
    sensor = OpenCVCameraSensor(0, capture_factory=lambda src: capture)
    sensor.on_frame = lambda: published.append(1)
    with sensor:
        wait_until(lambda: len(published) >= 3, 5.0, "three frames")
    # every image is decoded but one grabbed as the sensor disconnects (not decoded then),
    # and published but one decoded then
    assert capture.reads == 0 and capture.retrieves <= capture.grabs <= capture.retrieves + 1
    assert capture.retrieves - 1 <= len(published) <= capture.retrieves


@pytest.mark.parametrize("fps", [None, 20.0])
def test_a_live_camera_stamps_an_image_when_grabbed_before_decoding_it(
        fps: float | None) -> None:
    # the image arrived when it was taken off the device: its stamp comes before its
    # decoding starts (a slow decoder does not make an image look younger)
    capture = GrabbingCapture(_raw_frame(), retrieve_s=0.01)
    arrivals: dict[int, int] = {}
    sensor = OpenCVCameraSensor(0, capture_factory=lambda src: capture, fps=fps)

    def listener() -> None:
        frame = sensor._latest()
        assert frame is not None
        arrivals[frame.seq] = frame.received_us

    sensor.on_frame = listener
    with sensor:
        wait_until(lambda: len(arrivals) >= 3, 5.0, "three frames")
    assert capture.reads == 0
    for seq, arrival_us in arrivals.items():  # frame seq n is the n-th image decoded
        assert arrival_us <= capture.retrieve_started_us[seq - 1], (seq, arrivals)


@pytest.mark.parametrize(("grab_ok", "retrieve_ok", "reason"), [
    (False, True, "capture.grab() failed"),
    (True, False, "capture.retrieve() failed"),
])
def test_a_paced_live_camera_that_never_grabs_or_decodes_is_refused_with_the_reason(
        grab_ok: bool, retrieve_ok: bool, reason: str) -> None:
    # every grab fails (reopened meanwhile) or every image is undecodable (skipped): connect
    # gives up at its first-frame timeout, naming the last failure
    capture = GrabbingCapture(_raw_frame(), grab_ok=grab_ok, retrieve_ok=retrieve_ok)
    sensor = OpenCVCameraSensor(0, capture_factory=lambda src: capture, fps=20.0,
                                first_frame_timeout_s=scaled(0.5))
    with pytest.raises(DeviceTimeoutError, match=re.escape(reason)):
        sensor.connect()
    assert capture.released


# --------------------------------------------------------------------------- registry


def test_registry_names_and_camera_strings() -> None:
    assert set(SENSORS) >= {"sim", "camera"}
    assert isinstance(open_sensor("sim"), SimulatedSensor)
    cam = open_sensor("0")
    assert isinstance(cam, OpenCVCameraSensor) and cam.source == 0
    assert isinstance(open_sensor("rtsp://host/stream"), OpenCVCameraSensor)
    with pytest.raises(ConfigError):
        open_sensor("gelsight9000")
    with pytest.raises(ConfigError):
        open_sensor("sim", no_such_option=1)


def test_a_mistyped_sensor_is_named_before_anything_is_loaded(tmp_path: Path) -> None:
    from remote_site.sensor.registry import check_sensor_source

    video = tmp_path / "presses.avi"
    video.write_bytes(b"")  # exists: whether it decodes is the camera's business at connect
    for fine in ("sim", "camera", "0", 0, "rtsp://host/stream", str(video),
                 "remote_site.sensor.simulator:SimulatedSensor",
                 "v4l2src device=/dev/video9 ! videoconvert ! appsink"):
        check_sensor_source(fine)
    with pytest.raises(ConfigError, match="no such video file"):
        check_sensor_source(str(tmp_path / "missing.avi"))
    with pytest.raises(ConfigError, match="unknown sensor 'simm'"):
        check_sensor_source("simm")


def test_the_remote_cli_names_a_missing_video_file_first(tmp_path: Path,
                                                        caplog: pytest.LogCaptureFixture) -> None:
    """Before, a missing video file was reported as a missing stiffness calibration (the
    first thing loaded), which sent the user after the wrong file."""
    from lab.cli import main

    missing = tmp_path / "missing.avi"
    assert main(["remote", "--relay", "ws://127.0.0.1:9/", "--session", "s", "--token", "t",
                 "--arm", "sim", "--sensor", str(missing)]) != 0
    assert f"sensor '{missing}': no such video file" in caplog.text
    assert "stiffness" not in caplog.text


# --------------------------------------------------------------------------- transient faults


class ScriptedCapture:
    """A live camera (grab + retrieve) whose images follow a script: ``"ok"``, ``"undecodable"``
    (retrieve fails), ``"raises"`` (retrieve raises), ``"odd"`` (a grey 2-D image) or
    ``"unplugged"`` (grab fails); past the script every image is good."""

    def __init__(self, script: list[str]) -> None:
        self.script = list(script)
        self.step = "ok"
        self.opens = 0

    def isOpened(self) -> bool:
        return True

    def read(self) -> tuple[bool, Any]:
        raise AssertionError("read() is not used for a capture with grab()")

    def grab(self) -> bool:
        time.sleep(0.002)
        self.step = self.script.pop(0) if self.script else "ok"
        return self.step != "unplugged"

    def retrieve(self) -> tuple[bool, Any]:
        if self.step == "undecodable":
            return False, None
        if self.step == "raises":
            raise RuntimeError("a backend's own error")
        if self.step == "odd":
            return True, np.zeros((350, 466), np.uint8)
        return True, _raw_frame()

    def release(self) -> None:
        pass


def test_a_bad_image_is_skipped_and_the_camera_goes_on() -> None:
    """One image that cannot be decoded, one of the wrong shape: both skipped and counted,
    the frames after them delivered (found by an audit: one such image ended the camera for
    good, and nothing reconnected it)."""
    capture = ScriptedCapture(["ok", "ok", "undecodable", "ok", "odd", "ok", "raises", "ok"])
    seqs: list[int] = []
    sensor = OpenCVCameraSensor(0, capture_factory=lambda src: capture)
    sensor.on_frame = lambda: seqs.append(1)
    with sensor:
        wait_until(lambda: len(seqs) >= 10, 5.0, "ten frames")
        health = sensor.health
        sensor.read_latest(max_age_ms=scaled(500.0))
    assert health.bad_images == 3 and not health.ended and health.reopens == 0
    assert sensor.read_error is None  # the problem is over


def test_a_live_camera_whose_read_fails_is_opened_again() -> None:
    """A failed grab (an unplugged camera): released and opened again, frames resume with
    new seqs; a run of failures backs off instead of spinning."""
    captures: list[ScriptedCapture] = []

    def factory(src: Any) -> ScriptedCapture:
        # the first device fails after two images; the next one twice at once (still
        # unplugged), then delivers
        scripts = [["ok", "ok", "unplugged"], ["unplugged"], []]
        captures.append(ScriptedCapture(scripts[min(len(captures), 2)]))
        return captures[-1]

    sensor = OpenCVCameraSensor(0, capture_factory=factory)
    with sensor:
        first = sensor.read_latest(max_age_ms=scaled(500.0)).seq
        wait_until(lambda: sensor.health.reopens >= 2 and sensor._latest() is not None
                   and sensor._latest().seq > first + 3, 10.0, "frames again")  # type: ignore[union-attr]
        assert not sensor.health.ended
        sensor.read_latest(max_age_ms=scaled(500.0))
    assert len(captures) == 3


@pytest.mark.parametrize("late_grab", [False, True])
def test_a_reader_abandoned_while_its_read_hung_does_not_touch_the_next_connection(
        late_grab: bool) -> None:
    """A disconnect gives up on a reader whose grab hangs (an unplugged USB camera can
    block for seconds); that read failing later must not end the next connection, nor one
    returning an image decode it from the released device."""
    hang = threading.Event()
    release_hang = threading.Event()

    class Hanging(ScriptedCapture):
        hang_now = False
        hung = False
        late_retrieves = 0

        def grab(self) -> bool:
            if self.hang_now:
                hang.set()
                release_hang.wait(scaled(10.0))
                self.hung = True
                return late_grab
            return super().grab()

        def retrieve(self) -> tuple[bool, Any]:
            if self.hung:
                self.late_retrieves += 1
            return super().retrieve()

    first = Hanging([])
    sensor = OpenCVCameraSensor(0, capture_factory=lambda src: first)
    sensor.connect()
    first.hang_now = True
    assert hang.wait(scaled(5.0))
    reader = sensor._reader
    assert reader is not None
    reader.request_stop()
    sensor._reader = None  # what a disconnect whose join timed out leaves behind
    second = ScriptedCapture([])
    sensor._factory = lambda src: second
    sensor.disconnect()
    sensor.connect()
    try:
        release_hang.set()  # the old read returns now
        wait_until(lambda: not reader.is_alive, 5.0, "the old reader's end")
        assert first.late_retrieves == 0  # the released device is not decoded from
        assert not sensor.health.ended and sensor.read_error is None
        assert sensor.health.reopens == 0
        sensor.read_latest(max_age_ms=scaled(500.0))
    finally:
        sensor.disconnect()


def test_a_camera_giving_only_empty_images_is_reopened_not_spun_on() -> None:
    """A device that returns empty images at once (OpenCV 3 on an unplugged camera): no busy
    loop (bad images at most every 2 ms), and after stall_timeout_s of nothing usable it is
    taken as lost and opened again (found by review: 217,137 images skipped in 1.5 s,
    never reopened)."""

    class Empty(ScriptedCapture):
        def grab(self) -> bool:
            return True

        def retrieve(self) -> tuple[bool, Any]:
            return True, np.zeros((0, 0, 3), np.uint8)

    opened: list[ScriptedCapture] = []

    def factory(src: Any) -> ScriptedCapture:
        opened.append(ScriptedCapture([]) if opened else Empty([]))
        return opened[-1]

    sensor = OpenCVCameraSensor(0, capture_factory=factory, stall_timeout_s=0.2,
                                first_frame_timeout_s=scaled(5.0))
    with sensor:  # connect waits for the first good frame: from the reopened device
        health = sensor.health
        sensor.read_latest(max_age_ms=scaled(500.0))
    assert health.reopens == 1 and len(opened) == 2
    assert 1 <= health.bad_images <= 0.2 / 0.002 + 10, health
