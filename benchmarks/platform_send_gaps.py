"""Gaps in a local station's ``platform_state`` sends, from its MCAP recording.

Motion-to-touch counts a movement from the previous state's sample (``local.motion``), so a
stretch with no state sent while the platform moves shows up whole in ``uplink_sampling``.
This lists every stretch longer than ``--min-ms`` between two sends: its length, the gap
between the two states' sample times (how long the platform process published nothing new)
and how far the platform moved across it.

Run: ``python benchmarks/platform_send_gaps.py RUN.mcap`` (``teletouch bench cpu
--keep-record RUN.mcap`` keeps one; docs/speed.md section 35).
"""

from __future__ import annotations

import argparse
import itertools
import math

from shared.protocol import PlatformState
from shared.recording import read_mcap


def send_gaps(path: str, min_ms: float) -> list[tuple[float, float, float, float]]:
    """(start ms after the recording's first message, send gap ms, sample gap ms, moved mm)
    of each stretch longer than ``min_ms`` between two ``platform_state`` sends."""
    rec = read_mcap(path)
    t0 = min((m.t_us for m in rec.messages), default=0)
    sent = [(m.t_us, msg) for m, msg in rec.wire_messages()
            if m.topic == "/local/tx/platform_state" and isinstance(msg, PlatformState)]
    gaps = []
    for (ta, a), (tb, b) in itertools.pairwise(sent):
        if (tb - ta) / 1e3 > min_ms:
            gaps.append(((ta - t0) / 1e3, (tb - ta) / 1e3, (b.ts_us - a.ts_us) / 1e3,
                         math.dist(a.position_mm, b.position_mm)))
    return gaps


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", help="a local station's MCAP recording")
    ap.add_argument("--min-ms", type=float, default=30.0)
    args = ap.parse_args(argv)
    gaps = send_gaps(args.recording, args.min_ms)
    for start, send, sample, moved in gaps:
        print(f"at {start:9.1f} ms: no state sent for {send:6.1f} ms (samples {sample:6.1f} ms "
              f"apart), the platform moved {moved:5.2f} mm")
    print(f"{len(gaps)} gaps over {args.min_ms:g} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
