"""What does the recording's tactile image channel (``/local/tactile_image``) cost?

The channel is off by default (``record_image_rate_hz`` = 0). When on, the recorder's writer
thread turns a tactile frame's height layer into a colour PNG (OpenCV) at most
``image_rate_hz`` times a second and writes it as a ``foxglove.CompressedImage`` JSON message
(base64). This measures, for several patch sizes (17 x 17 is the demo's frame):

* one encode (``shared.recording.writer.patch_png``): thread CPU time p50/p99 per image, and
  the PNG's size;
* a recording of 10 s of frames at 60 Hz written through :class:`McapRecorder` with the
  image channel off, at 10 Hz and at 60 Hz (every frame): the writer thread's CPU time per
  recorded second (the share of one core it would take at the station), of which encoding
  images, and the file's growth per second.

CPU times are the thread's own clock (``time.thread_time``), so they depend little on how
loaded the machine is; the machine's load is recorded anyway.

Run:   python benchmarks/bench_recording_image.py   (writes benchmarks/results/recording_image.md)
"""

from __future__ import annotations

import argparse
import os
import platform as host_platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from shared.protocol import Hop, TactileFrame  # noqa: E402
from shared.recording import McapRecorder  # noqa: E402
from shared.recording.writer import patch_png  # noqa: E402
from shared.report import format_table  # noqa: E402

SIZES = (17, 48, 128)
FRAME_HZ = 60.0
SECONDS = 10.0
T0 = 1_790_000_000_000_000


def _heights(n: int, size: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size]
    out = []
    for i in range(n):
        cx = size / 2 + size / 4 * np.sin(i / 20)
        bump = 1.5 * np.exp(-((xx - cx) ** 2 + (yy - size / 2) ** 2) / (size * size / 20))
        out.append((bump + 0.02 * rng.random((size, size))).astype(np.float32))
    return out


def encode_costs(size: int, n: int = 300) -> dict[str, Any]:
    heights = _heights(n, size)
    cpu_us, png_bytes = [], []
    for h in heights:
        t0 = time.thread_time_ns()
        png = patch_png(h)
        cpu_us.append((time.thread_time_ns() - t0) / 1e3)
        assert png is not None
        png_bytes.append(len(png))
    a = np.asarray(cpu_us)
    return {"patch": f"{size}x{size}", "encodes": n, "cpu_p50_us": float(np.percentile(a, 50)),
            "cpu_p99_us": float(np.percentile(a, 99)),
            "png_bytes_mean": float(np.mean(png_bytes))}


def recording_cost(size: int, image_hz: float | None, workdir: Path) -> dict[str, Any]:
    n = int(SECONDS * FRAME_HZ)
    heights = _heights(n, size, seed=1)
    path = workdir / f"r_{size}_{image_hz}.mcap"
    rec = McapRecorder(path, "local", image_rate_hz=image_hz, queue_size=n + 16)
    for i, h in enumerate(heights):
        t = T0 + int(i * 1e6 / FRAME_HZ)
        rec.wire("rx", TactileFrame(
            seq=i + 1, ts_us=t - 2000,
            hops=(Hop("remote", "capture", t - 2000), Hop("local", "station_rx", t)),
            center_mm=(30.0, 30.0), pitch_mm=0.5, layers={"height_mm": h},
            contact=True, force_n=1.0, indentation_mm=0.5), t)
    counts = rec.close()
    size_b = path.stat().st_size
    return {"patch": f"{size}x{size}", "image_hz": image_hz or 0,
            "images": counts["per_topic"].get("/local/tactile_image", 0),
            "writer_cpu_pct": 100 * counts["writer_cpu_s"] / SECONDS,
            "image_cpu_pct": 100 * counts["image_cpu_s"] / SECONDS,
            "file_kB_per_s": size_b / 1e3 / SECONDS, "dropped": counts["dropped_queue_full"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results"
                                             / "recording_image.md"))
    args = parser.parse_args(argv)
    load0 = os.getloadavg()
    enc = [encode_costs(s) for s in SIZES]
    with tempfile.TemporaryDirectory() as tmp:
        rec = [recording_cost(s, hz, Path(tmp)) for s in SIZES for hz in (None, 10.0, FRAME_HZ)]
    load1 = os.getloadavg()
    lines = [
        "# Cost of the recording's tactile image channel (foxglove.CompressedImage PNG)", "",
        f"Machine: {host_platform.machine()}, `nproc` = {os.cpu_count()}, shared with other "
        f"agents' jobs during this run: load average {load0[0]:.1f} at the start, "
        f"{load1[0]:.1f} at the end (1 min). Python {host_platform.python_version()}.",
        "Command: `python benchmarks/bench_recording_image.py`. CPU figures are thread CPU "
        "time (`time.thread_time`), which the machine's load affects little.", "",
        "## One PNG encode (height layer -> viridis colour PNG, OpenCV)", "",
        format_table(enc), "",
        f"## A recording of {SECONDS:.0f} s of tactile frames at {FRAME_HZ:.0f} Hz, image "
        "channel off / 10 Hz / every frame", "",
        "`writer_cpu_pct`: the recorder's writer thread's CPU time per recorded second, in % "
        "of one core (all of its work: msgpack encoding, derived channels, zstd, images); "
        "`image_cpu_pct`: the part spent encoding PNGs; `file_kB_per_s`: file growth.", "",
        format_table(rec), "",
        "The synthetic heights carry 2 % uniform noise, which PNG and zstd compress worse "
        "than smooth real patches: the sizes are on the high side. The images are encoded on "
        "the writer thread, never in the display loop; what the station pays is that "
        "thread's CPU (and its GIL share) and the disk.", ""]
    Path(args.out).write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
