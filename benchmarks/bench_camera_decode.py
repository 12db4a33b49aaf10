"""What a live camera paced below its own rate costs: decoding every image, or only those due.

A live camera read at ``--sensor-fps`` below its own rate drops the images between
published frames. Through OpenCV's V4L2 capture an image is taken off the device by
``grab()`` and decoded by ``retrieve()`` (an MJPEG image by ``cv2.imdecode``, a YUYV one by a
colour conversion: ``convertToRgb`` in OpenCV's ``cap_v4l.cpp``), and ``read()`` does both.
The camera sensor (``remote_site/sensor/camera.py``) now grabs every image but retrieves only
the due ones; before, it read (and so decoded) every image and then dropped most.

No camera is attached here, so a stand-in plays one with the same division of work: on the
camera's own clock (``--camera-fps``), ``grab()`` takes the next image's JPEG bytes and
``retrieve()`` decodes them with ``cv2.imdecode`` (OpenCV's own decoder, as the V4L2 capture
calls it). The images are the kit's real GelSight Mini presses
(``../shared/data/gelsight/gsmini_ball_9.47mm``), resized to ``--size`` and JPEG-encoded at
quality 90. Two ways, in the same process, alternating each round:

- ``read``: the stand-in without ``grab``/``retrieve`` (the sensor then reads every image:
  the previous behaviour);
- ``grab``: the stand-in as OpenCV's capture (grab all, decode the due ones).

Per run: the process's CPU time over the window (the camera's reader thread; the main thread
sleeps), the frames published, the images decoded. Run:
``python benchmarks/bench_camera_decode.py --out benchmarks/results/camera_decode``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks.cli_args import count, positive  # noqa: E402
from remote_site.sensor.camera import OpenCVCameraSensor  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "gelsight" / "gsmini_ball_9.47mm"


def jpeg_images(size: tuple[int, int], limit: int = 20) -> list[bytes]:
    """The kit's presses, resized to ``size`` (width, height), as JPEG bytes."""
    paths = sorted(DATA.glob("press_*.png"))[:limit]
    if not paths:
        raise SystemExit(f"no presses in {DATA} (the kit lies beside the repository)")
    out = []
    for path in paths:
        raw = cv2.imread(str(path))
        if raw is None:
            raise SystemExit(f"{path}: not an image")
        image = cv2.resize(raw, size, interpolation=cv2.INTER_LINEAR)
        ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])
        assert ok
        out.append(data.tobytes())
    return out


class V4l2LikeCapture:
    """A live camera on its own clock: ``grab`` takes the next image, ``retrieve`` decodes it."""

    def __init__(self, images: list[bytes], fps: float) -> None:
        self.images = images
        self.period_s = 1.0 / fps
        self.next_s = time.monotonic()
        self.index = -1
        self.decoded = 0
        self.released = threading.Event()

    def isOpened(self) -> bool:
        return True

    def grab(self) -> bool:
        self.next_s += self.period_s
        delay = self.next_s - time.monotonic()
        if delay > 0 and self.released.wait(delay):
            return False
        self.index += 1
        return True

    def retrieve(self) -> tuple[bool, Any]:
        data = np.frombuffer(self.images[self.index % len(self.images)], np.uint8)
        self.decoded += 1
        return True, cv2.imdecode(data, cv2.IMREAD_COLOR)

    def read(self) -> tuple[bool, Any]:
        if not self.grab():
            return False, None
        return self.retrieve()

    def release(self) -> None:
        self.released.set()


class ReadOnlyCapture:
    """The same camera offering only ``read`` (the sensor then decodes every image)."""

    def __init__(self, inner: V4l2LikeCapture) -> None:
        self.inner = inner

    def isOpened(self) -> bool:
        return True

    def read(self) -> tuple[bool, Any]:
        return self.inner.read()

    def release(self) -> None:
        self.inner.release()


def run_once(way: str, images: list[bytes], camera_fps: float, publish_fps: float,
             seconds: float) -> dict[str, float]:
    camera = V4l2LikeCapture(images, camera_fps)
    capture: Any = camera if way == "grab" else ReadOnlyCapture(camera)
    sensor = OpenCVCameraSensor(0, capture_factory=lambda src: capture, fps=publish_fps)
    published = 0

    def one_published() -> None:
        nonlocal published
        published += 1

    sensor.on_frame = one_published
    with sensor:
        time.sleep(0.5)  # past the first frame
        cpu0, wall0, pub0, dec0 = time.process_time(), time.monotonic(), published, \
            camera.decoded
        time.sleep(seconds)
        cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
        frames, decoded = published - pub0, camera.decoded - dec0
    return {"cores": cpu / wall, "published_fps": frames / wall, "decoded_fps": decoded / wall,
            "cpu_ms_per_frame": 1e3 * cpu / max(frames, 1)}


def _size(text: str) -> tuple[int, int]:
    """``WxH``, both from 16 to 8192."""
    w, sep, h = text.lower().partition("x")
    if not (sep and w.isdigit() and h.isdigit() and 16 <= int(w) <= 8192
            and 16 <= int(h) <= 8192):
        raise argparse.ArgumentTypeError(f"{text!r}: WxH, e.g. 640x480 (16-8192 each)")
    return int(w), int(h)




def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=_size, default=(640, 480),
                    help="image size WxH (default 640x480)")
    ap.add_argument("--camera-fps", type=positive, default=60.0)
    ap.add_argument("--publish-fps", type=positive, default=25.0, help="the sensor's fps")
    ap.add_argument("--seconds", type=positive, default=5.0)
    ap.add_argument("--rounds", type=count, default=4)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    w, h = args.size
    images = jpeg_images((w, h))
    runs: list[dict[str, Any]] = []
    for rnd in range(1, args.rounds + 1):
        for way in (("read", "grab") if rnd % 2 else ("grab", "read")):
            result = run_once(way, images, args.camera_fps, args.publish_fps, args.seconds)
            runs.append({"round": rnd, "way": way, **result})
            print(json.dumps(runs[-1]), flush=True)
    lines = ["| way | runs | cores, median (range) | CPU ms per published frame | published "
             "frames/s | decoded images/s |", "|---|---|---|---|---|---|"]
    for way in ("read", "grab"):
        mine = [r for r in runs if r["way"] == way]

        def med(key: str, rows: list[dict[str, Any]] = mine) -> float:
            return statistics.median(r[key] for r in rows)

        lo, hi = min(r["cores"] for r in mine), max(r["cores"] for r in mine)
        lines.append(f"| `{way}` | {len(mine)} | {med('cores'):.4f} ({lo:.4f}-{hi:.4f}) | "
                     f"{med('cpu_ms_per_frame'):.2f} | {med('published_fps'):.1f} | "
                     f"{med('decoded_fps'):.1f} |")
    pairs = [(float(a["cores"]), float(b["cores"])) for a in runs for b in runs
             if a["round"] == b["round"] and a["way"] == "read" and b["way"] == "grab"]
    ratio = statistics.median(g / r for r, g in pairs)
    lower = sum(g < r for r, g in pairs)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "runs.json").write_text(json.dumps(runs, indent=1))
    (args.out / "README.md").write_text(
        "# A paced live camera: decoding every image against only the due ones\n\n"
        f"`python benchmarks/bench_camera_decode.py --size {w}x{h} --camera-fps "
        f"{args.camera_fps:g} --publish-fps {args.publish_fps:g} --seconds {args.seconds:g} "
        f"--rounds {args.rounds}`: {len(images)} real GelSight Mini presses from the kit at "
        f"{w}x{h}, JPEG quality 90, decoded by `cv2.imdecode` in the stand-in's `retrieve` "
        f"(see the script's docstring); 1-minute load at the end {os.getloadavg()[0]:.2f}; "
        f"OpenCV {cv2.__version__}.\n\n" + "\n".join(lines) +
        f"\n\n`grab` against `read` in the same round: cores x{ratio:.2f} (median of "
        f"{len(pairs)} rounds), lower in {lower} of {len(pairs)}.\n")
    print("\n".join(lines))
    print(f"grab/read cores x{ratio:.2f}, lower in {lower} of {len(pairs)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
