"""Paired CPU cost of the hot paths, old tree against new tree, on one machine in one session.

Run from the repository root::

    git archive main | tar -x -C /tmp/teletouch-main      # the tree to compare against
    python benchmarks/bench_hot_paths.py --old /tmp/teletouch-main

Each measurement runs in a fresh child process with ``PYTHONPATH`` set to one tree, old and
new alternating ``--pairs`` times, and reports the thread CPU time (``time.thread_time``, so
time spent preempted by other jobs on a loaded machine is not counted) per operation: the best
of 5 repetitions inside each process, then the median over the pairs and the new/old ratio.

Operations: one render of the 4 x 4 pins from a 30 x 40 tactile frame while the platform
moves (the 1 kHz display path); one encoder sample turned into a platform sample by the
platform driver (``platform_sample_us``, its 1 kHz reader path); a tactile frame's per-hop
wire cost (encode with validation + decode with validation, as the remote, the relay and the
local station each do) as sent by each tree's default (old: ``tactile_frame`` float32; new:
``tactile_compact`` delta, plus the sender's encoder and the receiver's decoder); a
``platform_state`` encode + decode; the serial link framing (COBS + delimiter) of one
64-byte drive-board command; and, each call after a 0.2 ms sleep as in the display loop
(caches cold; net of an empty call with the same sleep), the loop's whole iteration
(``DisplayLoop.tick`` on a 30 x 40 tactile frame renewed every 16 ticks, the platform moving
20 mm/s, commands to an emulated drive board on a pty) and one ``send_command`` of a changed
16-pin command.
Writes ``benchmarks/results/hot_paths.md`` (``--stem`` for another name).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"

_CHILD = r'''
import json, time
import numpy as np
from local_site.render import Renderer
from local_site.scenes import TactileFrameScene
from shared.protocol import Hop, PlatformState, TactileFrame, decode, encode

def cost(fn, n, sleep_s=0.0):
    best = float("inf")
    for _ in range(5):
        t = time.thread_time()
        for _ in range(n):
            fn()
            if sleep_s:
                time.sleep(sleep_s)
        best = min(best, (time.thread_time() - t) / n)
    return best * 1e6

rng = np.random.default_rng(0)
h = np.clip(rng.normal(0.5, 0.3, (30, 40)), 0, 3).astype(np.float32)
k = np.full((30, 40), 0.8, np.float32)
hops = tuple(Hop("remote", f"s{i}", i) for i in range(6))
frame = TactileFrame(seq=1, center_mm=(30.0, 30.0), pitch_mm=0.5, hops=hops,
                     layers={"height_mm": h, "stiffness_k": k})
scene = TactileFrameScene()
scene.update(frame)
renderer = Renderer()
pos = [25.0]

def render():
    pos[0] = pos[0] + 0.045 if pos[0] < 38 else 22.0
    renderer.render(scene, (pos[0], 30.0, 10.0))

out = {"render_us": cost(render, 2000)}
h2 = h.copy()
h2[10:14, 10:14] += 0.05  # the next frame: a small local change
frame2 = TactileFrame(seq=2, center_mm=(30.1, 30.0), pitch_mm=0.5, hops=hops,
                      layers={"height_mm": h2, "stiffness_k": k})
try:
    from shared.protocol.tactile_codec import TactileDecoder, TactileEncoder
except ImportError:  # the old tree: raw frames
    data = encode(frame2)
    out["tactile_hop_us"] = cost(lambda: decode(encode(frame2)), 300)
    out["tactile_bytes"] = len(data)
else:
    enc = TactileEncoder()
    dec = TactileDecoder()
    dec.decode(decode(encode(enc.encode(frame))))
    msg = enc.encode(frame2)
    data = encode(msg)
    out["tactile_hop_us"] = cost(lambda: decode(encode(msg)), 300)
    out["tactile_bytes"] = len(data)
    probe = TactileEncoder()
    probe.encode(frame)
    out["tactile_encoder_us"] = cost(lambda: (probe.reset(), probe.encode(frame),
                                              probe.encode(frame2)), 300) / 2
    out["tactile_decoder_us"] = cost(lambda: dec.decode(msg), 300)
ps = PlatformState(seq=5, ts_us=123456789, hops=(Hop("local", "capture", 123456789),),
                   position_mm=(1.0, 2.0, 3.0), velocity_mm_s=(0.1, 0.2, 0.3))
out["platform_state_hop_us"] = cost(lambda: decode(encode(ps)), 3000)
from local_site.display.serial_framing import encode_link_frame
command = bytes(range(1, 65))  # a 64-byte drive-board command body (its zeros: none)
command = command[:20] + b"\x00" + command[21:40] + b"\x00" + command[41:]
out["drive_link_frame_us"] = cost(lambda: encode_link_frame(0x101, command), 3000)

# the display loop's whole iteration and its send, each call after a 0.2 ms sleep (as in
# the loop: caches and predictors cold), net of an empty call with the same sleep
def cost_after_sleep(fn, n):
    return cost(fn, n, sleep_s=0.0002)

from local_site.agent.display_loop import DisplayLoop, FrameSlot, SameClockLink
from local_site.devices import open_display
from local_site.platform.base import PlatformSample
from shared.timebase import now_us

display = open_display("sim-serial")
slot = FrameSlot()
tscene = TactileFrameScene()
px = [25.0]

def positions():
    return PlatformSample(position_mm=(px[0], 30.0, 10.0), velocity_mm_s=(20.0, 0.0, 0.0),
                          t_us=now_us(), seq=0, board_t_us=0)

loop = DisplayLoop(display, Renderer(), tscene, positions=positions, platform_ok=lambda: True,
                   frames=slot, link=SameClockLink())
ticks = [0]

def tick():
    # a new frame every 16 ticks (60 Hz at 1 kHz), the platform moving 20 mm/s
    if ticks[0] % 16 == 0:
        t = now_us()
        slot.put(TactileFrame(seq=ticks[0] + 1, ts_us=t, center_mm=(30.0, 30.0), pitch_mm=0.5,
                              hops=(Hop("remote", "sensor_frame", t),),
                              layers={"height_mm": h, "stiffness_k": k}), t)
    ticks[0] += 1
    loop.tick()
    px[0] = px[0] + 0.02 if px[0] < 38 else 22.0

for _ in range(100):
    tick()
empty = cost_after_sleep(lambda: None, 1000)
out["display_tick_cold_us"] = cost_after_sleep(tick, 1000) - empty
pins = [np.linspace(0.5, 2.0, 16), np.linspace(0.6, 2.1, 16)]
pin_k = np.full(16, 0.8)
pin_f = np.zeros(16)
for arr in (*pins, pin_k, pin_f):
    arr.setflags(write=False)  # as the renderer's commands
flip = [0]

def send():
    flip[0] ^= 1
    display.send_command(pins[flip[0]], pin_k, pin_f)

out["send_command_cold_us"] = cost_after_sleep(send, 1000) - empty
display.disconnect()

# the platform driver's per-sample work (1 kHz): one encoder sample decoded by the board
# link's reader thread into a PlatformSample (clock mapping, counts -> mm, velocity)
from local_site.platform.base import XYZPlatform
from local_site.platform.protocol import BoardInfo, EncoderSample

class FedPlatform(XYZPlatform):
    def _connect(self):
        pass

    def _disconnect(self):
        pass

board = FedPlatform()
board._publish_info(BoardInfo(1, 3, 1024, 4, 1000, 1))  # samples are used after an INFO
n_sample = [0]
t0_us = now_us()

def publish():
    k = n_sample[0] = n_sample[0] + 1
    board._publish(EncoderSample(k, k * 1000, (3000 + k % 500, 2000, 1000)), t0_us + k * 1000)

out["platform_sample_us"] = cost(publish, 5000)
print(json.dumps(out))
'''


def _measure(tree: Path) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(tree), "OPENBLAS_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True,
                          text=True, check=True, cwd="/")
    return dict(json.loads(proc.stdout.strip().splitlines()[-1]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--old", type=Path, required=True, help="the tree to compare against")
    parser.add_argument("--pairs", type=int, default=5)
    parser.add_argument("--stem", default="hot_paths", help="results file name (without .md)")
    args = parser.parse_args()
    load = os.getloadavg()[0]
    old_runs, new_runs = [], []
    for _ in range(args.pairs):
        old_runs.append(_measure(args.old.resolve()))
        new_runs.append(_measure(ROOT))
    keys = sorted(set(old_runs[0]) | set(new_runs[0]))
    lines = ["# Hot paths: CPU per operation, old tree vs this tree (paired)", "",
             f"Command: `python benchmarks/bench_hot_paths.py --old {args.old} --pairs "
             f"{args.pairs} --stem {args.stem}`. {args.pairs} pairs of fresh processes, old "
             "and new alternating; "
             "thread CPU time per operation (best of 5 repetitions per process), median over "
             f"the pairs. Machine: nproc {os.cpu_count()}, load average {load:.1f} at start "
             "(other jobs on the machine inflate even CPU time: compare the ratio).", "",
             "| operation | old (median) | new (median) | new / old | old runs | new runs |",
             "|---|---|---|---|---|---|"]
    for key in keys:
        o = [r[key] for r in old_runs if key in r]
        n = [r[key] for r in new_runs if key in r]
        om = statistics.median(o) if o else None
        nm = statistics.median(n) if n else None
        ratio = f"{nm / om:.2f}" if om and nm else "n/a"
        lines.append(f"| {key} | {om if om is None else f'{om:.1f}'} | "
                     f"{nm if nm is None else f'{nm:.1f}'} | {ratio} | "
                     f"{', '.join(f'{v:.0f}' for v in o)} | {', '.join(f'{v:.0f}' for v in n)} |")
    lines += ["", "`_us`: microseconds of CPU; `tactile_bytes`: bytes of one tactile frame on "
              "the wire (old: `tactile_frame`, new: a `tactile_compact` delta with a 4 x 4 "
              "change). `tactile_hop_us` is one encode + decode with validation (each hop does "
              "about this: sender, relay, receiver); the new tree adds the sender's "
              "`tactile_encoder_us` and the receiver's `tactile_decoder_us` once per frame."]
    text = "\n".join(lines) + "\n"
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{args.stem}.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
