"""``benchmarks/platform_send_gaps.py`` finds the stretches without a ``platform_state`` sent
in a real MCAP recording, with their sample gap and the movement across them."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.platform_send_gaps import send_gaps
from shared.protocol import Hop, PlatformState
from shared.recording import McapRecorder

T0 = 1_800_000_000_000_000


def test_a_stretch_without_sends_is_found_with_its_sample_gap_and_movement(
        tmp_path: Path) -> None:
    path = tmp_path / "local.mcap"
    rec = McapRecorder(path, "local", meta={"session": "synthetic"})
    # sent every 4 ms at 10 mm/s along x, but none from 400 to 700 ms; the state sent at
    # 700 ms carries a sample taken at 650 ms (read late)
    sends = [t for t in range(0, 1000, 4) if not 400 < t < 700]
    for seq, t in enumerate(sends, 1):
        sample = t - 50 if t == 700 else t
        ts = T0 + sample * 1000
        rec.wire("tx", PlatformState(seq=seq, ts_us=ts, hops=(Hop("local", "capture", ts),),
                                     position_mm=(0.01 * sample, 5.0, 10.0)), T0 + t * 1000)
    rec.close()
    gaps = send_gaps(str(path), min_ms=30.0)
    assert len(gaps) == 1
    start, send, sample_gap, moved = gaps[0]
    assert start == pytest.approx(400.0)
    assert send == pytest.approx(300.0)
    assert sample_gap == pytest.approx(250.0)
    assert moved == pytest.approx(2.5)
    assert send_gaps(str(path), min_ms=300.0) == []  # a threshold above it: none
