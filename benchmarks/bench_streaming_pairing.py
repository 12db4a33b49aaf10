"""What a streaming camera's frame is paired with: the command and the arm pose of its image.

Run from the repository root::

    python benchmarks/bench_streaming_pairing.py            # the committed results
    python benchmarks/bench_streaming_pairing.py --quick    # a short run

A camera that streams on its own clock (a GelSight Mini: 25 frames/s) hands the remote
station an image taken before the frame tick that reads it. The real :class:`RemoteStation`
runs here (sim arm with its 1 kHz loop, reconstruction, stiffness, assembly, an in-memory link
fed with states at 250 Hz by an operator sweeping across the phantom, pressed in), with the
simulated sensor turned into a streaming camera: an image every ``1 / fps`` s on its own
thread, exposed at the arm's pose at that instant (recorded: the reference), arriving
``latency`` later, stamped at the exposure (latency known: ``--sensor-latency-ms``) or at the
arrival (not known: the default 0).

Per frame that answers a command, against the reference:

* **the pairing before 96c0aac** (the newest command and the arm's reading when the tick
  took the image): the share of frames named after a command applied after their image was
  taken (``arm_command`` after ``sensor_frame``: motion-to-touch counted a movement the image
  cannot show), by how much, and how far the patch was placed from the arm's pose at the
  exposure;
* **the pairing now** (the command applied by the image's stamp, the arm where its polled
  readings around that stamp put it): the same figures;
* **the nearest poll** (how the patch was placed before 2026-12-06: the arm's polled reading
  nearest to the image's stamp among those the station had then, recorded in the same run):
  its placement error.

Writes ``benchmarks/results/streaming_pairing.md``.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import platform
import sys
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

from benchmarks.bench_remote_pipeline import MemoryLink, build_station, feed_states
from remote_site.agent.pipeline import FrameOutcome
from remote_site.arm.base import Arm
from remote_site.sensor.base import SensorFrame, TactileSensor
from remote_site.tactile import AppliedCommand
from shared.protocol import PlatformState, TactileFrame
from shared.report import emit, format_table
from shared.timebase import now_us
from shared.workspace import WorkspaceMap

RESULTS = Path(__file__).resolve().parent / "results"
WS = WorkspaceMap()


class StreamingSimCamera(TactileSensor):
    """The simulated sensor as a streaming camera (see the module docstring)."""

    captures_on_demand = False
    #: calls ``_frame_arrived`` for each new image (where the base class has it)
    notifies_frames = True

    def __init__(self, inner: TactileSensor, arm: Arm, fps: float, latency_s: float,
                 stamp_exposure: bool) -> None:
        super().__init__(inner.shape_hw, inner.mm_per_px)
        self.inner, self.arm = inner, arm
        self.period_s, self.latency_s, self.stamp_exposure = 1.0 / fps, latency_s, stamp_exposure
        #: seq -> (exposure time us, the arm's reported position then)
        self.truth: dict[int, tuple[int, tuple[float, ...]]] = {}
        #: the stamp each image was given -> its seq (a tactile frame carries the stamp)
        self.seq_of: dict[int, int] = {}
        #: seq -> when the image arrived (us)
        self.arrived: dict[int, int] = {}
        self._newest: SensorFrame | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _connect(self) -> None:
        self.inner.connect()
        self._thread = threading.Thread(target=self._run, name="streaming-camera", daemon=True)
        self._thread.start()

    def _disconnect(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.inner.disconnect()

    def _run(self) -> None:
        seq, next_s = 0, time.monotonic()
        while not self._stop.is_set():
            exposure_us = now_us()
            pose = tuple(float(v) for v in self.arm.state().position_mm)
            rgb = self.inner.read_latest(max_age_ms=1e9).rgb  # rendered at the pose now
            time.sleep(max(0.0, exposure_us / 1e6 + self.latency_s - now_us() / 1e6))
            seq += 1
            arrival_us = now_us()
            stamp = exposure_us if self.stamp_exposure else arrival_us
            with self._lock:
                self.truth[seq] = (exposure_us, pose)
                self.seq_of[stamp] = seq
                self.arrived[seq] = arrival_us
                self._newest = SensorFrame(rgb, stamp, seq, arrival_us=arrival_us)
            arrived = getattr(self, "_frame_arrived", None)  # (not before 2026-12-06)
            if arrived is not None:
                arrived()
            next_s += self.period_s
            self._stop.wait(max(0.0, next_s - time.monotonic()))

    def _latest(self) -> SensorFrame | None:
        with self._lock:
            return self._newest


def sweep_xyz(t_s: float, centre: tuple[float, float]) -> tuple[float, float, float]:
    """Phantom mm: pressed 1.5 mm in, sweeping x by +-15 mm (peak 20 mm/s) across a tumor."""
    period_s = 2.0 * math.pi * 15.0 / 20.0
    return (centre[0] + 15.0 * math.sin(2.0 * math.pi * t_s / period_s), centre[1], -1.5)


async def run_case(fps: float, latency_ms: float, stamp_exposure: bool, duration_s: float
                   ) -> dict[str, Any]:
    cameras: list[StreamingSimCamera] = []

    def streaming(sensor: TactileSensor, arm: Arm) -> TactileSensor:
        cameras.append(StreamingSimCamera(sensor, arm, fps, latency_ms / 1000.0,
                                          stamp_exposure))
        return cameras[0]

    station, link, world = build_station(60.0, sensor_for=streaming, tactile_codec="raw")
    camera, arm, pipeline = cameras[0], station.safe_arm.arm, station.pipeline
    # what the pairing before 96c0aac took: the newest command and the arm's reading when
    # the tick took the image (its worker read the arm, then the sensor)
    old: dict[int, tuple[AppliedCommand | None, tuple[float, ...]]] = {}
    capture = pipeline.capture

    def recording_capture() -> tuple[SensorFrame, float] | FrameOutcome:
        latest, reading = station.latest, arm.state()
        taken = capture()
        if not isinstance(taken, FrameOutcome):
            old[taken[0].seq] = (latest, tuple(float(v) for v in reading.position_mm))
        return taken

    pipeline.capture = recording_capture  # type: ignore[method-assign]
    applied: list[AppliedCommand] = []
    apply = station.apply_platform_state

    def recording_apply(state: PlatformState) -> Any:
        before = station.latest
        result = apply(state)
        if station.latest is not before and station.latest is not None:
            applied.append(station.latest)
        return result

    station.apply_platform_state = recording_apply  # type: ignore[method-assign]
    # where the nearest poll would have placed each image, from the polls the station had
    # when it placed it (the placement before 2026-12-06)
    nearest: dict[int, tuple[float, ...]] = {}
    # whether a poll followed the image's stamp when it was placed (interpolated) or not
    # (the newest poll held)
    bracketed: dict[int, bool] = {}
    reading_at = station.reading_at

    def recording_reading_at(t_us: int) -> Any:
        polls = list(station._readings)
        if polls:
            _, near = min(polls, key=lambda p: abs(p[0] - t_us))
            nearest[t_us] = tuple(float(v) for v in near.position_mm)
            bracketed[t_us] = polls[0][0] <= t_us < polls[-1][0]
        return reading_at(t_us)

    station.reading_at = recording_reading_at  # type: ignore[method-assign]
    tumor = world.phantom.tumors[1].center_mm
    centre = (float(tumor[0]), float(tumor[1]))
    stop = asyncio.Event()
    op = asyncio.create_task(feed_states(link, lambda t: sweep_xyz(t, centre), duration_s,
                                         stop))
    await station.run(stop, duration_s=duration_s + 5.0)
    await op
    station.safe_arm.close()
    camera.disconnect()
    arm.disconnect()
    out = score(link, camera, old, applied, nearest, fps, latency_ms, stamp_exposure)
    answered = [f.ts_us for f in link.sent if isinstance(f, TactileFrame)
                and any(h.stage == "arm_command" for h in f.hops)]
    known = [bracketed[t] for t in answered if t in bracketed]
    out["interpolated"] = sum(known) / len(known) if known else math.nan
    out["ticks_per_frame"] = station.captures.clock / max(1, station.pipeline.processed)
    return out


def score(link: MemoryLink, camera: StreamingSimCamera,
          old: dict[int, tuple[AppliedCommand | None, tuple[float, ...]]],
          applied: list[AppliedCommand], nearest: dict[int, tuple[float, ...]],
          fps: float, latency_ms: float, stamp_exposure: bool) -> dict[str, Any]:
    """The figures of one case (see the module docstring); ``nearest``: by image stamp, the
    position of the arm poll nearest to it among those the station had then."""
    times = np.array([c.arm_command_us for c in applied], dtype=np.int64)
    rows: dict[str, list[float]] = {k: [] for k in (
        "old_after", "old_lead_ms", "old_place_mm", "new_after", "new_lead_ms", "new_place_mm",
        "nearest_place_mm", "arrival_to_ready_ms")}
    frames = [m for m in link.sent if isinstance(m, TactileFrame)]
    for frame in frames:
        stamps = {h.stage: h.t_us for h in frame.hops if h.clock == "remote"}
        if "arm_command" not in stamps:
            continue
        seq = camera.seq_of.get(frame.ts_us)  # the camera's seq is not on the wire
        if seq is None or seq not in old:
            continue
        exposure_us, pose = camera.truth[seq]
        rows["arrival_to_ready_ms"].append((stamps["tactile_ready"] - camera.arrived[seq]) / 1e3)
        # the newest command applied by the exposure: what the image can show at most
        shown = int(np.searchsorted(times, exposure_us, side="right")) - 1
        shown_us = int(times[shown]) if shown >= 0 else None
        truth_xy = WS.inverse(list(pose))[:2]
        old_cmd, old_pos = old[seq]
        if old_cmd is not None and shown_us is not None:
            rows["old_after"].append(float(old_cmd.arm_command_us > exposure_us))
            rows["old_lead_ms"].append((old_cmd.arm_command_us - shown_us) / 1e3)
            rows["old_place_mm"].append(float(math.dist(WS.inverse(list(old_pos))[:2],
                                                        truth_xy)))
        if shown_us is not None:
            rows["new_after"].append(float(stamps["arm_command"] > exposure_us))
            rows["new_lead_ms"].append((stamps["arm_command"] - shown_us) / 1e3)
            rows["new_place_mm"].append(float(math.dist(frame.center_mm, truth_xy)))
            near = nearest.get(stamps["sensor_frame"])
            if near is not None:
                rows["nearest_place_mm"].append(float(math.dist(WS.inverse(list(near))[:2],
                                                                truth_xy)))
    out: dict[str, Any] = {"fps": fps, "latency_ms": latency_ms,
                           "stamped": "exposure" if stamp_exposure else "arrival",
                           "frames": len(rows["new_after"])}
    for key, values in rows.items():
        arr = np.asarray(values, dtype=float)
        if key.endswith("after"):
            out[key] = float(arr.mean()) if arr.size else float("nan")
        else:
            out[key] = (float(np.percentile(arr, 50)), float(np.percentile(arr, 99)),
                        float(arr.max())) if arr.size else (math.nan,) * 3
    return out


def _fmt(triple: tuple[float, float, float], digits: int) -> str:
    return " / ".join(f"{v:.{digits}f}" for v in triple)


def report(results: list[dict[str, Any]], command: str) -> str:
    header = ["camera fps", "latency ms", "stamped at", "frames",
              "before: named after a later command", "before: command lead ms p50/p99/max",
              "before: placement error mm p50/p99/max",
              "now: named after a later command", "now: command lead ms p50/p99/max",
              "now: placement error mm p50/p99/max",
              "nearest poll: placement error mm p50/p99/max",
              "placed between two polls",
              "arrival to tactile_ready ms p50/p99/max",
              "station ticks per frame"]
    rows = [dict(zip(header, [
        f"{r['fps']:.0f}", f"{r['latency_ms']:.0f}", r["stamped"], str(r["frames"]),
        f"{100 * r['old_after']:.0f} %", _fmt(r["old_lead_ms"], 1), _fmt(r["old_place_mm"], 2),
        f"{100 * r['new_after']:.0f} %", _fmt(r["new_lead_ms"], 1),
        _fmt(r["new_place_mm"], 3), _fmt(r["nearest_place_mm"], 3),
        f"{100 * r['interpolated']:.0f} %",
        _fmt(r["arrival_to_ready_ms"], 1),
        f"{r['ticks_per_frame']:.2f}"], strict=True)) for r in results]
    return "\n".join([
        "# A streaming camera's frame: the command and the arm pose it is paired with",
        "",
        f"Command: `{command}`; {platform.node()}, load average at the end "
        f"{', '.join(f'{v:.2f}' for v in os.getloadavg())}.",
        "",
        "The real remote station, the simulated sensor as a streaming camera (an image every "
        "1/fps s, exposed at the arm's pose then, arriving `latency` later), states at 250 Hz "
        "sweeping +-15 mm across a tumor at up to 20 mm/s, pressed 1.5 mm in; the station's "
        "frame clock at 60 Hz. *Command lead*: how much later the command a frame is named "
        "after was applied than the newest command applied by the image's exposure (0: the "
        "right one; above 0, motion-to-touch counted that much of a movement the image cannot "
        "show). *Placement error*: the patch centre against the arm's reported position at "
        "the exposure (platform mm). *Before* is the pairing before commit 96c0aac (the newest "
        "command and the arm's reading when the tick took the image), recorded in the same "
        "run; *now* is what the station sent; *nearest poll* places the patch at the arm's "
        "polled reading nearest to the image's stamp among those the station had when it "
        "placed the image (the placement before 2026-12-06), recorded in the same run. "
        "*Placed between two polls*: the share of answering frames whose image had a poll "
        "after it when placed (the others take the newest poll, as the nearest rule does). "
        "*Arrival to tactile_ready*: from the image's "
        "arrival at the station to its tactile frame being ready (the wait for the station's "
        "tick plus the pipeline). *Ticks per frame*: the station's frame ticks per tactile "
        "frame made (a tick without a new image makes none).",
        "",
        format_table(rows, header),
        "",
    ])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="4 s per case, not written")
    parser.add_argument("--duration-s", type=float, default=15.0)
    args = parser.parse_args(argv)
    duration = 4.0 if args.quick else args.duration_s
    cases = [(25.0, 0.0, True), (25.0, 30.0, True), (25.0, 30.0, False)]
    results = [asyncio.run(run_case(fps, lat, exp, duration)) for fps, lat, exp in cases]
    command = "python benchmarks/bench_streaming_pairing.py" + (" --quick" if args.quick else "")
    text = report(results, command)
    emit(text)
    if not args.quick:
        (RESULTS / "streaming_pairing.md").write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
