"""Camera sources behave like cameras: paced video files, looping, presets, end and stall."""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from remote_site.sensor import open_sensor
from remote_site.sensor.base import TactileSensor
from remote_site.sensor.camera import OpenCVCameraSensor
from remote_site.sensor.camera_presets import CAMERA_PRESETS, camera_preset, shape_frame
from shared.errors import ConfigError, DeviceTimeoutError, InputDataError
from tests.support import scaled, wait_until


def _numbered_frame(i: int, hw: tuple[int, int] = (240, 320)) -> np.ndarray:
    """A BGR frame whose brightness encodes ``i`` (survives MJPG compression)."""
    return np.full((*hw, 3), 40 + 10 * (i % 20), np.uint8)


def _write_video(path: Path, n: int, fps: float = 25.0,
                 hw: tuple[int, int] = (240, 320)) -> Path:
    import cv2

    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (hw[1], hw[0]))
    assert writer.isOpened()
    for i in range(n):
        writer.write(_numbered_frame(i, hw))
    writer.release()
    return path


def _collect(sensor: TactileSensor, until_seq: int, timeout_s: float
             ) -> dict[int, int]:
    """seq -> timestamp_us of every frame seen while polling until ``until_seq``."""
    seen: dict[int, int] = {}

    def poll() -> bool:
        with contextlib.suppress(DeviceTimeoutError):
            frame = sensor.read_latest(max_age_ms=scaled(1000))
            seen.setdefault(frame.seq, frame.timestamp_us)
        return max(seen, default=0) >= until_seq

    wait_until(poll, timeout_s, f"frame {until_seq}", poll_s=0.002)
    return seen


class _GatedCapture:
    """A live camera stand-in that delivers frames only while ``flowing`` is set."""

    def __init__(self) -> None:
        self.flowing = threading.Event()
        self.flowing.set()
        self.released = False

    def isOpened(self) -> bool:
        return True

    def read(self) -> tuple[bool, Any]:
        while not self.flowing.wait(0.01):
            if self.released:
                return False, None
        time.sleep(0.005)
        return True, _numbered_frame(0)

    def release(self) -> None:
        self.released = True


# --------------------------------------------------------------------------- presets


def test_unknown_preset_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="mini-recording"):
        camera_preset("gelsight-xl")
    with pytest.raises(ConfigError):
        open_sensor("video.avi", preset="gelsight-xl")
    with pytest.raises(ConfigError):
        OpenCVCameraSensor("video.avi", fps=0)


@settings(max_examples=40, deadline=None)
@given(rows=st.integers(20, 400), cols=st.integers(20, 500))
def test_presets_deliver_their_size_or_refuse(rows: int, cols: int) -> None:
    bgr = np.random.default_rng(rows * 1000 + cols).integers(0, 256, (rows, cols, 3),
                                                             dtype=np.uint8)
    raw = shape_frame(bgr, CAMERA_PRESETS["mini-raw"])
    assert raw.shape == (240, 320, 3) and raw.dtype == np.uint8
    if (rows, cols) == (240, 320):
        assert np.array_equal(shape_frame(bgr, CAMERA_PRESETS["mini-recording"]),
                              bgr[:, :, ::-1])
    else:
        with pytest.raises(InputDataError, match="without resizing"):
            shape_frame(bgr, CAMERA_PRESETS["mini-recording"])


def test_mini_recording_takes_frames_as_they_are() -> None:
    bgr = np.random.default_rng(1).integers(30, 220, (240, 320, 3), dtype=np.uint8)

    class Once:
        def isOpened(self) -> bool:
            return True

        def read(self) -> tuple[bool, Any]:
            time.sleep(0.002)
            return True, bgr.copy()

        def release(self) -> None:
            pass

    with OpenCVCameraSensor(0, preset="mini-recording",
                            capture_factory=lambda src: Once()) as sensor:
        frame = sensor.read_latest(max_age_ms=scaled(500))
    assert np.array_equal(frame.rgb, bgr[:, :, ::-1])
    assert sensor.mm_per_px == pytest.approx(0.0634)


def test_mini_recording_refuses_a_raw_sized_video(tmp_path: Path) -> None:
    path = _write_video(tmp_path / "raw.avi", 5, hw=(350, 466))
    sensor = open_sensor(str(path), preset="mini-recording", first_frame_timeout_s=scaled(2))
    with pytest.raises(DeviceTimeoutError, match="wrong preset"):
        sensor.connect()


# --------------------------------------------------------------------------- pacing


def test_video_file_is_paced_at_its_frame_rate(tmp_path: Path) -> None:
    path = _write_video(tmp_path / "v.avi", 15, fps=25.0)
    with open_sensor(str(path), preset="mini-recording") as sensor:
        seen = _collect(sensor, 15, 5.0)
        wait_until(lambda: sensor.health.ended, 2.0, "the end of the file")
        health = sensor.health
    stamps = np.array([seen[s] for s in sorted(seen)], float)
    span_s = (stamps[-1] - stamps[0]) / 1e6
    first, last = min(seen), max(seen)
    # 25 frames/s: frame n is published n/25 s after the first, not as fast as decoding goes
    assert span_s >= (last - first) / 25.0 * 0.9
    assert len(seen) >= 12  # polled faster than 25 Hz: (almost) every frame seen
    assert not health.stalled and health.loops == 0


def test_fps_option_overrides_the_file_rate(tmp_path: Path) -> None:
    path = _write_video(tmp_path / "v.avi", 12, fps=100.0)
    with open_sensor(str(path), preset="mini-recording", fps=20.0) as sensor:
        seen = _collect(sensor, 8, 5.0)
    stamps = np.array([seen[s] for s in sorted(seen)], float)
    assert (stamps[-1] - stamps[0]) / 1e6 >= (max(seen) - min(seen)) / 20.0 * 0.9


def test_end_of_file_is_reported_once_and_frames_go_stale(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="remote_site.sensor.camera")
    path = _write_video(tmp_path / "v.avi", 4, fps=50.0)
    with open_sensor(str(path), preset="mini-recording") as sensor:
        wait_until(lambda: sensor.health.ended, 3.0, "the end of the file")
        for _ in range(5):
            sensor.health  # noqa: B018 - polling must not report again
        assert sensor.read_latest(max_age_ms=scaled(2000)).seq == 4
        time.sleep(0.03)
        with pytest.raises(DeviceTimeoutError, match="old"):
            sensor.read_latest(max_age_ms=20)
        assert "end of the video file" in (sensor.health.reason or "")
    ended = [r for r in caplog.records if "ended" in r.getMessage()]
    assert len(ended) == 1


def test_a_files_unusable_images_are_skipped_in_their_own_time(tmp_path: Path) -> None:
    """Eight images of a recording that cannot be used (a grey one, one of the wrong size)
    between two good ones, at 20 frames/s: skipped and counted, and the second good one is
    published in its own time, 9 periods after the first (before: one period after it, the
    rest of the recording early, and the bad ones read as fast as the disk goes)."""
    path = tmp_path / "v.avi"
    path.write_bytes(b"")  # a file on disk: paced; its images come from the capture below
    bad = [np.zeros((240, 320), np.uint8), _numbered_frame(0, (350, 466))] * 4
    images = [_numbered_frame(0), *bad, _numbered_frame(1)]

    class Recording:
        def isOpened(self) -> bool:
            return True

        def get(self, prop: int) -> float:
            return 20.0

        def read(self) -> tuple[bool, Any]:
            return (True, images.pop(0)) if images else (False, None)

        def release(self) -> None:
            pass

    arrivals: list[int] = []
    sensor = OpenCVCameraSensor(str(path), preset="mini-recording",
                                capture_factory=lambda src: Recording())
    sensor.on_frame = lambda: arrivals.append(sensor._latest().received_us)  # type: ignore[union-attr]
    with sensor:
        wait_until(lambda: sensor.health.ended, 5.0, "the end of the file")
        health = sensor.health
    assert len(arrivals) == 2 and health.bad_images == 8
    assert arrivals[1] - arrivals[0] >= 6 * 50_000, arrivals  # 9 periods due; 3 spared


def test_looped_file_keeps_delivering(tmp_path: Path) -> None:
    path = _write_video(tmp_path / "v.avi", 5, fps=100.0)
    with open_sensor(str(path), preset="mini-recording", loop=True) as sensor:
        _collect(sensor, 12, 5.0)
        health = sensor.health
    assert health.loops >= 2 and not health.ended


def test_a_silent_live_camera_is_reported_as_stalled_once(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="remote_site.sensor.camera")
    capture = _GatedCapture()
    with OpenCVCameraSensor(0, preset="mini-recording", stall_timeout_s=0.1,
                            capture_factory=lambda src: capture) as sensor:
        sensor.read_latest(max_age_ms=scaled(500))
        capture.flowing.clear()
        wait_until(lambda: sensor.health.stalled, 2.0, "a stall")
        for _ in range(5):
            assert sensor.health.stalls == 1
        capture.flowing.set()
        wait_until(lambda: not sensor.health.stalled, 2.0, "frames again")
        assert sensor.health.stalls == 1 and not sensor.health.ended
    stalls = [r for r in caplog.records if "stalled" in r.getMessage()]
    assert len(stalls) == 1
