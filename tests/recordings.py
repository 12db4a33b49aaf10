"""A synthetic local-station recording with every channel a real one has (for replay tests).

Written through the station's own recorder (:class:`shared.recording.McapRecorder`, the
writer thread, chunking and derived channels): a raster over the phantom, tactile frames
with a height patch showing a bump, the arm's state, the pins at 50 Hz, the frames the
station accepted and the findings at the end. Quick to make (no processes), so tests of the
replay and of the file format need no running session.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shared.protocol import ArmState, Bye, Hop, PlatformState, Stats, TactileFrame
from shared.recording import McapRecorder

T0 = 1_790_000_000_000_000  # 2026-09-21, a fixed recording date


def write_local_recording(path: Path, seconds: float = 6.0, *, frame_hz: float = 30.0,
                          platform_hz: float = 50.0, patch: int = 24,
                          image_hz: float | None = None,
                          chunk_bytes: int = 1 << 20) -> dict[str, int]:
    """Write the recording; return the number of messages per kind written."""
    rec = McapRecorder(path, "local", meta={"session": "synthetic"},
                       image_rate_hz=image_hz, chunk_bytes=chunk_bytes)
    rng = np.random.default_rng(7)
    counts = {"platform": 0, "frames": 0, "pins": 0}
    rec.wire("rx", Stats(metrics={"clock_offset_us": {"local": 0, "remote": 250}}), T0)
    yy, xx = np.mgrid[0:patch, 0:patch]
    events: list[tuple[int, str]] = []
    for i in range(int(seconds * platform_hz)):
        events.append((T0 + 1000 + int(i * 1e6 / platform_hz), "platform"))
    for i in range(int(seconds * frame_hz)):
        events.append((T0 + 1500 + int(i * 1e6 / frame_hz), "frame"))
    for i in range(int(seconds * 50)):
        events.append((T0 + 1700 + int(i * 1e6 / 50), "pins"))
    events.sort()
    for t, kind in events:
        s = (t - T0) / 1e6
        x, y = 20.0 + 20.0 * (s / seconds), 30.0 + 8.0 * np.sin(2 * np.pi * s / 2.0)
        if kind == "platform":
            counts["platform"] += 1
            rec.wire("tx", PlatformState(seq=counts["platform"], ts_us=t,
                                         hops=(Hop("local", "capture", t),),
                                         position_mm=(x, y, 39.0)), t)
        elif kind == "frame":
            counts["frames"] += 1
            seq = counts["frames"]
            cx, cy = patch / 2 + 4 * np.sin(s), patch / 2
            bump = 0.8 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / 18.0)
            height = (bump + 0.02 * rng.random((patch, patch))).astype(np.float32)
            rx = t + 900
            rec.wire("rx", TactileFrame(
                seq=seq, ts_us=t - 2000,
                hops=(Hop("remote", "capture", t - 2000), Hop("relay", "relay_in", t - 1200),
                      Hop("relay", "relay_out", t - 1100), Hop("local", "station_rx", rx)),
                center_mm=(x, y), pitch_mm=0.5, layers={"height_mm": height},
                contact=seq % 10 != 0, force_n=1.0 + 0.5 * np.sin(s), indentation_mm=0.5),
                rx + 50)
            rec.derived("frame_accepted", rx, {"seq": seq, "rx_us": rx})
            rec.wire("rx", ArmState(seq=seq, ts_us=t, position_mm=(x, y, -0.5),
                                    force_n=1.2), t + 100)
        else:
            counts["pins"] += 1
            h = (0.5 + 0.4 * np.sin(s * 3 + np.arange(16))).round(4).tolist()
            rec.derived("pins", t, {"commanded_mm": h, "stiffness_k": [0.8] * 16,
                                    "friction": [0.3] * 16,
                                    "measured_mm": [v * 0.95 for v in h],
                                    "safe_reason": None})
    end = T0 + int(seconds * 1e6)
    rec.derived("findings", end, {"findings": [
        {"x_mm": 30.0, "y_mm": 30.0, "kind": "benign", "radius_mm": 3.0, "confidence": 0.8,
         "severity_rank": 1}]})
    rec.wire("tx", Bye(reason="done"), end + 10)
    rec.close({"synthetic": True})
    return counts
