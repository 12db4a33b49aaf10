"""``teletouch bench tactile-codec``: bytes per second of the tactile stream and the rendered
height error of the compact codec (protocol v2) against the uncompressed ``tactile_frame``
stream, over deadband settings.

Input: a local station recording (``local.mcap``, or an ``.npz`` of the same arrays as
:class:`~local_site.recording.Recording`: every tactile frame the station accepted, with its
layers), e.g. from ``teletouch bench cpu --keep-record PATH.mcap`` or ``teletouch demo
--workdir DIR``. Each frame is replayed as the remote sent it (``tactile_frame`` with float32
layers), encoded as ``tactile_compact`` through the real msgpack codec, decoded on the other
side, and rendered by the local station's renderer at the frame's centre, like the
uncompressed frame. Error = decoded minus original: of the height layer (every sample) and of
the rendered pin heights. A second pass loses a share of the frames at random (the relay's
latest-wins slot supersedes frames under load) to show that errors stay bounded and how many
frames wait for a key frame. Writes ``tactile_codec.md`` and ``tactile_codec.png``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

DEFAULT_OUT = Path(__file__).resolve().parents[2] / "benchmarks" / "results"

#: (weber fraction, height floor um): the settings compared
SETTINGS: tuple[tuple[float, float], ...] = (
    (0.0, 0.5), (0.0, 2.0), (0.0, 5.0), (0.0, 10.0), (0.0, 20.0),
    (0.02, 2.0), (0.05, 2.0), (0.1, 2.0), (0.05, 5.0), (0.1, 10.0))


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the benchmark's options."""
    parser.add_argument("--record", type=Path, required=True,
                        help="a local station recording (local.mcap, or .npz)")
    parser.add_argument("--frames", type=int, default=3000, help="frames replayed at most")
    parser.add_argument("--loss", type=float, default=0.2,
                        help="share of frames lost in the second pass (default 0.2)")
    parser.add_argument("--key-every", type=int, default=30)
    parser.add_argument("--out-dir", type=Path, default=DEFAULT_OUT, help="results directory")
    parser.add_argument("--seed", type=int, default=0)


def _arrays(path: Path) -> Any:
    """The recording's frame arrays by name (``frame_seq``, ``frame_height_mm``, ...)."""
    import dataclasses

    import numpy as np

    if path.suffix != ".mcap":
        return np.load(path, allow_pickle=False)
    from local_site.recording import load_recording

    rec = load_recording(path)
    zeros = np.zeros_like(rec.frame_height_mm)  # a layer not recorded
    return {f.name: zeros if value is None else value
            for f in dataclasses.fields(rec) if f.name.startswith("frame_")
            for value in (getattr(rec, f.name),)}


def _frames(path: Path, limit: int) -> tuple[list[Any], float]:
    import numpy as np

    from shared.protocol import TactileFrame

    d = _arrays(path)
    n = min(limit, int(d["frame_seq"].shape[0]))
    rx = d["frame_rx_us"][:n].astype(np.int64)
    rate = (n - 1) / ((rx[-1] - rx[0]) / 1e6) if n > 1 and rx[-1] > rx[0] else float("nan")
    frames = []
    for i in range(n):
        layers = {"height_mm": d["frame_height_mm"][i].astype(np.float32),
                  "stiffness_k": d["frame_stiffness_k"][i].astype(np.float32)}
        n_per_mm = d["frame_stiffness_n_per_mm"][i]
        if n_per_mm.any():
            layers["stiffness_n_per_mm"] = n_per_mm.astype(np.float32)
        c = d["frame_center_mm"][i]
        frames.append(TactileFrame(
            seq=int(d["frame_seq"][i]), ts_us=int(rx[i]), center_mm=(float(c[0]), float(c[1])),
            pitch_mm=float(d["frame_pitch_mm"][i]), layers=layers,
            contact=bool(d["frame_contact"][i]), force_n=float(d["frame_force_n"][i]),
            indentation_mm=float(d["frame_indentation_mm"][i]), source_seq=int(i),
            source_ts_us=int(rx[i])))
    return frames, rate


def _render(frame: Any) -> Any:
    from local_site.render import Renderer
    from local_site.scenes import TactileFrameScene

    scene = TactileFrameScene()
    scene.update(frame)
    return Renderer().render(scene, (frame.center_mm[0], frame.center_mm[1], 0.0)).arrays()[0]


def _replay(frames: list[Any], weber: float, floor_um: float, key_every: int, loss: float,
            seed: int) -> dict[str, Any]:
    import numpy as np

    from shared.protocol import decode, encode
    from shared.protocol.tactile_codec import CodecSettings, TactileDecoder, TactileEncoder

    rng = np.random.default_rng(seed)
    enc = TactileEncoder(CodecSettings(weber=weber, floor={"height_mm": floor_um * 1e-3},
                                       key_every=key_every))
    dec = TactileDecoder()
    sizes, h_err, pin_err = [], [], []
    t_enc = t_dec = 0.0
    rendered = 0
    for i, frame in enumerate(frames):
        t0 = time.perf_counter()
        data = encode(enc.encode(frame))
        t1 = time.perf_counter()
        sizes.append(len(data))
        t_enc += t1 - t0
        if loss and i and rng.random() < loss:
            continue
        t0 = time.perf_counter()
        out = dec.decode(decode(data))  # type: ignore[arg-type]
        t_dec += time.perf_counter() - t0
        if out is None:
            continue
        rendered += 1
        h_err.append((np.asarray(out.layers["height_mm"], np.float64)
                      - np.asarray(frame.layers["height_mm"], np.float64)).ravel())
        if i % 10 == 0:  # rendering is the slow part: every 10th frame
            pin_err.append((_render(out) - _render(frame)).ravel())
    e = np.concatenate(h_err) * 1e3
    p = np.concatenate(pin_err) * 1e3 if pin_err else np.zeros(1)
    return {"bytes_per_frame": float(np.mean(sizes)), "key_frames": enc.keys_sent,
            "frames": len(frames), "rendered": rendered,
            "waiting_for_key": dec.counters.waiting_for_key,
            "height_rms_um": float(np.sqrt(np.mean(e ** 2))),
            "height_max_um": float(np.abs(e).max()),
            "pin_rms_um": float(np.sqrt(np.mean(p ** 2))), "pin_max_um": float(np.abs(p).max()),
            "encode_us": 1e6 * t_enc / len(frames),
            "decode_us": 1e6 * t_dec / max(1, rendered + dec.counters.waiting_for_key)}


def run(args: argparse.Namespace) -> int:
    """Replay the recording over every setting, write the table and plot, print them."""
    import os

    import numpy as np

    from lab.bench.results import write_results
    from shared.protocol import encode
    from shared.report import emit, format_table

    frames, rate = _frames(args.record, args.frames)
    raw = float(np.mean([len(encode(f)) for f in frames]))
    rows = []
    results = []
    for weber, floor in SETTINGS:
        r = _replay(frames, weber, floor, args.key_every, 0.0, args.seed)
        lossy = _replay(frames, weber, floor, args.key_every, args.loss, args.seed)
        results.append((weber, floor, r))
        rows.append({
            "weber": weber, "floor um": floor, "bytes/frame": round(r["bytes_per_frame"]),
            "kB/s": r["bytes_per_frame"] * rate / 1e3,
            "saved %": 100 * (1 - r["bytes_per_frame"] / raw),
            "key frames %": 100 * r["key_frames"] / r["frames"],
            "height RMS um": r["height_rms_um"], "height max um": r["height_max_um"],
            "pins RMS um": r["pin_rms_um"], "pins max um": r["pin_max_um"],
            f"{args.loss:.0%} lost: height RMS um": lossy["height_rms_um"],
            f"{args.loss:.0%} lost: waited for key": lossy["waiting_for_key"],
            "encode us": r["encode_us"], "decode us": r["decode_us"]})
    command = " ".join(["teletouch bench tactile-codec", *sys.argv[3:]]) if sys.argv[1:2] == [
        "bench"] else " ".join(["python", *sys.argv])
    shape = frames[0].layers["height_mm"].shape
    text = "\n".join([
        "# Compact tactile codec: bytes against rendered-height error", "",
        f"Command: `{command}`", "",
        f"Stream: {len(frames)} frames of a demo recording (`{args.record.name}`), "
        f"layers {shape[0]} x {shape[1]} ({', '.join(sorted(frames[0].layers))}), "
        f"{rate:.0f} frames/s as received. Uncompressed `tactile_frame` (float32 layers, "
        f"msgpack): **{raw:.0f} bytes/frame, {raw * rate / 1e3:.1f} kB/s** per hop. "
        f"Key frame at least every {args.key_every} frames. Errors are decoded minus "
        "uncompressed: the height layer at every sample, and the pin heights the local "
        "renderer commands at the frame centre (every 10th frame). The lost-frame columns "
        f"drop {args.loss:.0%} of the frames at random before the decoder (deltas then refer "
        "to key frames that may be missing: those wait, counted). Encode/decode times include "
        "msgpack and validation, wall time per frame on this machine "
        f"(nproc {os.cpu_count()}, 1-minute load {os.getloadavg()[0]:.1f} when the table was "
        "written): read them as upper bounds.",
        "", format_table(rows), ""])
    write_results(args.out_dir, "tactile_codec", text,
                  plot=lambda path: _plot(results, raw, rate, path))
    emit(text)
    return 0


def _plot(results: list[tuple[float, float, dict[str, Any]]], raw: float, rate: float,
          path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for weber in sorted({w for w, _, _ in results}):
        pts = [(r["bytes_per_frame"] * rate / 1e3, r["height_rms_um"], f)
               for w, f, r in results if w == weber]
        ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=f"weber {weber:g}")
        for x, y, f in pts:
            ax.annotate(f"{f:g} um", (x, y), fontsize=7)
    ax.axvline(raw * rate / 1e3, color="k", ls="--", label="uncompressed")
    ax.axvline(0.2 * raw * rate / 1e3, color="g", ls=":", label="-80 % target")
    ax.axhline(10.0, color="r", ls=":", label="10 um RMS target")
    ax.set_xscale("log")
    ax.set_xlabel("tactile stream, kB/s per hop")
    ax.set_ylabel("height error RMS, um")
    ax.legend(fontsize=7)
    ax.set_title("Compact tactile codec: bytes vs error (labels: floor)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
