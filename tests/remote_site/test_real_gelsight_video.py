"""Real GelSight Mini presses as a 25 frames/s video, through relay and remote as processes.

A lab's first session, as a new user runs it: the kit's GelSight Mini ball presses
(``gsmini_ball_9.47mm``) become a lossless 25 frames/s video (the no-contact background for
1.2 s, then each test-split press held for 10 frames, with 10 background frames between
presses), the calibration is made from the train split with ``teletouch sensor calibrate``,
and ``teletouch relay`` and ``teletouch remote --sensor presses.avi --sensor-preset
mini-recording --sensor-loop --arm sim`` run as real processes on 127.0.0.1. The local
station is played by the test (a real StationLink): it feeds every tactile frame to the local
station's own scene (:class:`~local_site.scenes.remote_stream.TactileFrameScene`, at the
station's default interpolation order) and renders
the pins with its :class:`~local_site.render.Renderer`, the window placed so that one pin
sits on the press centre (where an operator feeling for the peak puts it).

Targets (the issue): peak rendered height within 0.05 mm of the press depth derived from
the label (ball radius 4.735 mm, labelled contact radius a: d = R - sqrt(R^2 - a^2)); cap
shape within 0.05 mm RMS over the pins inside the contact. The calibration is made with
``--relief rim``: heights are the object's relief above its contact rim, not above the free
gel (which would add the gel's drape, ~0.1 mm here; see docs/reconstruction.md).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import os
import signal
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lab.cli import main as cli_main
from local_site.render import Renderer
from local_site.render.pin_command import PIN_PITCH_MM
from local_site.scenes.remote_stream import TactileFrameScene
from relay_server.auth import derive_token
from remote_site.reconstruction.contact_edge import fit_contact_edge
from remote_site.reconstruction.features import relative_change
from remote_site.reconstruction.frames import load_rgb
from remote_site.reconstruction.labels import BallLabel, labels_from_npz, write_labels_csv
from remote_site.reconstruction.sphere import cap_depth_mm, cap_height_mm
from shared.client import StationLink
from shared.protocol import TactileCompact, TactileFrame
from shared.protocol.tactile_codec import TactileDecoder
from shared.workspace import WorkspaceMap
from tests.relay_server.test_relay_isolation_and_status import wait_relay_ready
from tests.support import REPO_ROOT, free_tcp_port, kit_path, require_kit, scaled, teletouch_cmd

DATA = kit_path("data", "gelsight", "gsmini_ball_9.47mm")
BALL_RADIUS_MM = 4.735
MM_PER_PX = 0.0634
FPS = 25.0
LEAD_FRAMES, PRESS_FRAMES, GAP_FRAMES = 30, 10, 10
#: the camera latency given to the remote (``--sensor-latency-ms``): the frames are stamped
#: that much before they arrive (a video file has none; the stamps show the option applied)
LATENCY_MS = 10.0
SESSION = "gelsight-video"
STIFFNESS_CALIBRATION = REPO_ROOT / "remote_site" / "phantom" / "data" / "sim_stiffness_calib.json"
#: a frame whose highest point exceeds this shows a press
PRESS_HEIGHT_MM = 0.1
#: the issue's targets
PEAK_TOLERANCE_MM = 0.05
SHAPE_RMS_TOLERANCE_MM = 0.05


@pytest.fixture(autouse=True, scope="module")
def _kit_data() -> None:
    require_kit(DATA)


def _split(name: str) -> list[BallLabel]:
    entries = json.loads((DATA / "train_test_split.json").read_text())[name]
    return labels_from_npz(DATA, [f"press_{int(e.rsplit('/', 1)[1]):02d}.png" for e in entries])


@functools.cache
def _background() -> np.ndarray:
    return load_rgb(DATA / "background.png")


def edge_label(label: BallLabel) -> BallLabel:
    """The contact circle the press's own image shows, found from the frame and the
    background only (no calibration), seeded by the label."""
    change = relative_change(load_rgb(DATA / label.image), _background())
    edge = fit_contact_edge(change, label)
    assert edge is not None, label.image
    return BallLabel(label.image, edge.center_x, edge.center_y, edge.radius_px)


def label_depth_mm(radius_px: float) -> float:
    """Indentation of the ball for a labelled contact radius."""
    return cap_depth_mm(BALL_RADIUS_MM, radius_px * MM_PER_PX)


def label_cap_mm(r_mm: np.ndarray, radius_px: float) -> np.ndarray:
    """Sphere-cap height at distance ``r_mm`` from the press centre (0 outside)."""
    return cap_height_mm(r_mm, BALL_RADIUS_MM, radius_px * MM_PER_PX)


@pytest.fixture(scope="module")
def kit_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(presses.avi, calib.npz): the video of the test presses and the train calibration."""
    import cv2

    tmp = tmp_path_factory.mktemp("gelsight-video")
    labels_csv = tmp / "labels.csv"
    write_labels_csv(labels_csv, _split("train"))
    calib = tmp / "calib.npz"
    assert cli_main(["sensor", "calibrate", "--background", str(DATA / "background.png"),
                     "--images", str(DATA), "--labels", str(labels_csv),
                     "--ball-diameter-mm", "9.47", "--mm-per-px", str(MM_PER_PX),
                     "--drop-bad-labels", "--relief", "rim", "--out", str(calib)]) == 0
    video = tmp / "presses.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"FFV1"), FPS, (320, 240))
    assert writer.isOpened()
    background = load_rgb(DATA / "background.png")[:, :, ::-1]
    for _ in range(LEAD_FRAMES):
        writer.write(np.ascontiguousarray(background))
    for label in _split("test"):
        press = np.ascontiguousarray(load_rgb(DATA / label.image)[:, :, ::-1])
        for _ in range(PRESS_FRAMES):
            writer.write(press)
        for _ in range(GAP_FRAMES):
            writer.write(np.ascontiguousarray(background))
    writer.release()
    return video, calib


@dataclass
class PressResult:
    """What the pins rendered for one press, against the label's sphere cap."""

    image: str
    depth_mm: float
    peak_mm: float
    shape_rms_mm: float
    offset_mm: float
    shape_rms_without_offset_mm: float
    pins_inside: int


#: (remote summary, pins against the hand labels, report, pins on the image's contact circles)
Session = tuple[dict[str, Any], list[PressResult], str, list[PressResult],
                list[TactileFrame]]


def _remote_stamp(frame: TactileFrame, stage: str) -> int:
    return next(h.t_us for h in frame.hops if h.clock == "remote" and h.stage == stage)


def press_segments(frames: list[TactileFrame], n_presses: int) -> list[TactileFrame] | None:
    """The middle frame of each press of one full cycle of the video, in order.

    A cycle starts after the lead background (more than ``GAP_FRAMES`` flat frames in a
    row); None until a whole cycle has arrived.
    """
    pressed = [float(f.layers["height_mm"].max()) > PRESS_HEIGHT_MM for f in frames]
    flat_run, start = 0, None
    for i, p in enumerate(pressed):
        flat_run = 0 if p else flat_run + 1
        if flat_run > GAP_FRAMES + 5:
            start = i + 1
            break
    if start is None:
        return None
    segments: list[list[TactileFrame]] = []
    current: list[TactileFrame] = []
    for frame, p in zip(frames[start:], pressed[start:], strict=True):
        if p:
            current.append(frame)
        elif current:
            segments.append(current)
            current = []
            if len(segments) == n_presses:
                break
    if len(segments) < n_presses:
        return None
    return [seg[len(seg) // 2] for seg in segments]


def render_press(frame: TactileFrame, label: BallLabel, scale_xy: float) -> PressResult:
    """Render the pins with one pin on the press centre; compare with the sphere cap."""
    height = frame.layers["height_mm"]
    rows, cols = height.shape
    pitch_px = frame.pitch_mm * scale_xy / MM_PER_PX  # sensor pixels per grid cell
    # the grid covers rows * pitch_px sensor pixels centred on the image centre
    used_w, used_h = cols * pitch_px, rows * pitch_px
    x0 = (320 - used_w) / 2.0
    y0 = (240 - used_h) / 2.0
    cx_mm = frame.center_mm[0] + ((label.center_x - x0 + 0.5) / pitch_px - cols / 2.0) \
        * frame.pitch_mm
    cy_mm = frame.center_mm[1] + ((label.center_y - y0 + 0.5) / pitch_px - rows / 2.0) \
        * frame.pitch_mm
    scene = TactileFrameScene()  # at the station's default interpolation order
    scene.update(frame)
    renderer = Renderer()
    half = PIN_PITCH_MM / 2.0  # pin (1, 1) sits at (-half, -half) from the window centre
    command = renderer.render(scene, (cx_mm + half, cy_mm + half))
    pins_xy = renderer.pin_positions_mm((cx_mm + half, cy_mm + half))
    heights, _, _ = command.arrays()
    r_mm = np.hypot(pins_xy[..., 0] - cx_mm, pins_xy[..., 1] - cy_mm) * scale_xy
    # pins in the contact circle and over the sensor image (a press at the image's edge
    # leaves some of its circle outside the frame: the pins there have no data)
    inside = (r_mm < label.radius_px * MM_PER_PX) & scene.sample(pins_xy).inside
    expected = label_cap_mm(r_mm, label.radius_px)
    error = heights[inside] - expected[inside]
    rms = float(np.sqrt(np.mean(error**2)))
    offset = float(error.mean())
    rms_centred = float(np.sqrt(np.mean((error - offset) ** 2)))
    return PressResult(label.image, label_depth_mm(label.radius_px), float(heights.max()), rms,
                       offset, rms_centred, int(inside.sum()))


async def _collect(url: str, token: str, n_presses: int, timeout_s: float
                   ) -> list[TactileFrame]:
    frames: list[TactileFrame] = []
    decoder = TactileDecoder()  # the remote's default codec is the compact one (protocol v2)
    async with StationLink(url, session=SESSION, role="local", token=token) as link:
        await link.wait_connected(timeout_s=scaled(10.0))
        async with asyncio.timeout(timeout_s):
            while press_segments(frames, n_presses) is None:
                with contextlib.suppress(TimeoutError):
                    msg = await link.recv(timeout_s=0.2)
                    frame = decoder.decode(msg) if isinstance(msg, TactileCompact) else msg
                    if isinstance(frame, TactileFrame):
                        frames.append(frame)
    return frames


async def _stop(proc: asyncio.subprocess.Process) -> None:
    if proc.returncode is None:
        proc.kill()
        await proc.wait()


async def _run_session(video: Path, calib: Path, summary_path: Path, n_presses: int
                       ) -> list[TactileFrame]:
    """Relay and remote as processes, the test as the local station; the frames received."""
    cmd = teletouch_cmd()
    port = free_tcp_port()
    env = dict(os.environ, TELETOUCH_RELAY_SECRET="video-secret-0123456789abcdef0123456789")
    token = derive_token("video-secret-0123456789abcdef0123456789", SESSION)
    # the raw TCP listener on any free port: port + 1, the default, may be in use
    relay = await asyncio.create_subprocess_exec(
        *cmd, "relay", "--host", "127.0.0.1", "--port", str(port), "--tcp-port", "0", env=env,
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL)
    remote = None
    try:
        try:
            await wait_relay_ready(port)
        except TimeoutError:
            raise AssertionError(f"the relay did not come up (exit code {relay.returncode})"
                                 ) from None
        remote = await asyncio.create_subprocess_exec(
            *cmd, "remote", "--relay", f"ws://127.0.0.1:{port}/", "--session", SESSION,
            "--arm", "sim", "--sensor", str(video), "--sensor-preset", "mini-recording",
            "--sensor-loop", "--sensor-latency-ms", str(LATENCY_MS), "--calibration",
            str(calib),
            "--stiffness-calibration", str(STIFFNESS_CALIBRATION),
            "--summary-json", str(summary_path),
            env=dict(os.environ, TELETOUCH_REMOTE_LINK_TOKEN=token),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        cycle_s = (LEAD_FRAMES + n_presses * (PRESS_FRAMES + GAP_FRAMES)) / FPS
        frames = await _collect(f"ws://127.0.0.1:{port}/", token, n_presses,
                                scaled(30.0 + 2.5 * cycle_s))
        remote.send_signal(signal.SIGTERM)
        async with asyncio.timeout(scaled(15.0)):
            _, err = await remote.communicate()
        assert remote.returncode == 0, err.decode()[-2000:]
        return frames
    finally:
        if remote is not None:
            await _stop(remote)
        if relay.returncode is None:
            relay.send_signal(signal.SIGTERM)
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(scaled(10.0)):
                await relay.wait()
        await _stop(relay)


@pytest.fixture(scope="module")
def session(kit_files: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory
            ) -> Session:
    """One session over the video: (remote summary, per-press pin results, a report).

    Each press is scored twice: against its hand label (the issue's targets) and with the
    pins placed and scored on the contact circle its own image shows (:func:`edge_label`)."""
    video, calib = kit_files
    labels = _split("test")
    summary_path = tmp_path_factory.mktemp("gelsight-session") / "remote.json"
    frames = asyncio.run(_run_session(video, calib, summary_path, len(labels)))
    summary = json.loads(summary_path.read_text())
    mids = press_segments(frames, len(labels))
    assert mids is not None
    scale_xy = WorkspaceMap().config.scale_xy
    results = [render_press(f, lb, scale_xy) for f, lb in zip(mids, labels, strict=True)]
    on_edge = [render_press(f, edge_label(lb), scale_xy)
               for f, lb in zip(mids, labels, strict=True)]
    report = "\n".join(f"{r.image}: depth {r.depth_mm:.3f} peak {r.peak_mm:.3f} "
                       f"(err {r.peak_mm - r.depth_mm:+.3f}) shape rms {r.shape_rms_mm:.3f} "
                       f"(offset {r.offset_mm:+.3f}, without it "
                       f"{r.shape_rms_without_offset_mm:.3f}) over {r.pins_inside} pins; "
                       f"on the image's contact circle: shape rms {e.shape_rms_mm:.3f}, "
                       f"peak err {e.peak_mm - e.depth_mm:+.3f}"
                       for r, e in zip(results, on_edge, strict=True))
    f, bg = summary["frames"], summary["background"]
    report += (f"\nremote: {f['sent']} tactile frames in {summary['elapsed_s']:.1f} s, rejected "
               f"{f['rejected']}, repeated {f['repeated']}; background {bg['source']}, drift "
               f"{bg['drift_from_calibration_rgb']} grey levels")
    print(report)  # the measured figures, for the record (pytest -s)
    return summary, results, report, on_edge, frames


def test_the_video_plays_like_a_camera_and_the_station_captures_its_background(
        session: Session) -> None:
    summary, _, _, _, frames = session
    # paced at 25 frames/s: the 60 Hz station finds a fresh frame on every tick but the first
    assert summary["frames"]["rejected"].get("sensor_timeout", 0) <= 5
    assert not summary["sensor"]["ended"]  # looped: the source never ended
    assert summary["background"]["source"] == "station"
    assert summary["background"]["drift_from_calibration_mean"] < 1.0  # same gel, same day
    # --sensor-latency-ms reached the camera: every frame is stamped that much before it
    # arrived, so before the station read and processed it
    lead_ms = [(_remote_stamp(f, "tactile_ready") - _remote_stamp(f, "sensor_frame")) / 1e3
               for f in frames]
    assert min(lead_ms) >= LATENCY_MS, f"{min(lead_ms):.1f} ms"
    # and the ledger sees that latency as the sensor's own stage: arrival less stamp
    delivery_us = {_remote_stamp(f, "sensor_arrival") - _remote_stamp(f, "sensor_frame")
                   for f in frames}
    assert delivery_us == {round(LATENCY_MS * 1e3)}


def test_every_real_press_reaches_the_pins(
        session: Session) -> None:
    """What is achieved (measured 2026-11-24 on the 11 test presses, calibration made with
    ``--relief rim --drop-bad-labels`` on the train presses, centres moved to the contact
    edge, see the report): peak error -0.046..+0.040 mm, shape RMS 0.010..0.082 mm (9 of 11
    within 0.05); without the constant offset within 0.063 mm. With the labelled centres
    for training: peak -0.047..+0.036, shape 0.014..0.075 mm. Before the free border and
    the Keys cubic pins: peak -0.061..+0.027 mm (press_17, cut by the image edge, the low
    one); before the rim relief: peak +0.03..+0.16 mm, shape RMS up to 0.16 mm."""
    _, results, report, _, _ = session
    peak_err = np.array([r.peak_mm - r.depth_mm for r in results])
    assert (np.array([r.peak_mm for r in results]) > PRESS_HEIGHT_MM).all(), report
    assert (np.abs(peak_err) < 0.1).all(), report
    assert max(r.shape_rms_mm for r in results) <= 0.1, report
    assert max(r.shape_rms_without_offset_mm for r in results) <= 0.08, report
    assert all(r.pins_inside >= 2 for r in results), report


def test_issue_target_peak(session: Session) -> None:
    """Issue 14: the peak rendered height within 0.05 mm of the labelled press depth.

    Met since the rim relief's reconstruction leaves the border free where the contact runs
    off the frame and the station renders with Keys cubic interpolation: press_17 (contact
    crossing the left edge) went from -0.061 to -0.047 mm, and to -0.021 mm with the
    calibration trained on the contact edges; the tightest is now press_47 (-0.046)."""
    _, results, report, _, _ = session
    peak_err = np.array([r.peak_mm - r.depth_mm for r in results])
    assert np.abs(peak_err).max() <= PEAK_TOLERANCE_MM, report


@pytest.mark.xfail(strict=True, reason=(
    "issue 14 shape target not met against the hand labels on 2 of 11 test presses: with "
    "the rim relief the shape RMS over the pins in the contact is 0.010..0.045 mm on 9 "
    "presses but 0.064 (press_43) and 0.082 mm (press_47). Their hand-labelled centres, where "
    "the pins are placed, lie 2.6 and 4.2 px from the contact edge their images show "
    "(found without calibration; the reconstructed cap agrees with that edge); on the "
    "image's contact circles every press is within 0.05 mm (the next test; "
    "benchmarks/results/label_agreement.md)"))
def test_issue_target_shape(session: Session) -> None:
    _, results, report, _, _ = session
    assert max(r.shape_rms_mm for r in results) <= SHAPE_RMS_TOLERANCE_MM, report


def test_shape_on_the_contact_circle_each_image_shows(session: Session) -> None:
    """The pins placed and scored on the contact circle the press's own image shows (centre
    and radius from the frame and the background alone,
    :mod:`remote_site.reconstruction.contact_edge`): the cap shape within the issue's
    0.05 mm on every press (measured 2026-11-24: 0.009..0.041 mm), where the hand-labelled
    circles, 2.6 and 4.2 px off on press_43 and press_47, leave those two above it
    (``benchmarks/results/label_agreement.md``). The peak against the depth of that circle
    is in the report, not asserted: -0.047..-0.007 mm, the image's radius running about a
    pixel larger than the labels'."""
    _, _, report, on_edge, _ = session
    assert max(r.shape_rms_mm for r in on_edge) <= SHAPE_RMS_TOLERANCE_MM, report
