"""The remote station's memory paged out mid-session, with and without its memory lock.

What it reproduces: a host's kernel evicting a running station's memory (this machine's
kernel runs DAMON proactive reclaim, a ``pageout`` scheme for memory that went cold; any host
under memory pressure does the same to file-backed pages) while the disk is busy. A thread
that touches an evicted page waits for the disk, holding the GIL.

How: the fault rig's demo (relay, link emulators, both stations, the drive-board process) runs
until the flow is steady; a disk writer (``dd ... conv=fsync`` in a loop) starts; then four
times, 4 s apart, every mapping of the remote station is advised ``MADV_PAGEOUT`` through
``process_madvise(2)`` (what reclaim does, on demand). Measured from the station's probe log
and ``/proc``: the longest gap between two accepted arm commands within 3 s of each page-out
(the operator sends 250 a second, 4 ms apart), the remote's major page faults over the run,
and its ``VmLck``. The arms alternate (``nolock`` = both stations ``--no-lock-memory``;
``lock`` = the default) and start in turn.

Needs Linux >= 5.10 (``process_madvise``) and the right to advise another process (root or
``CAP_SYS_NICE`` and ptrace access). Not a test: it depends on the disk and the kernel.

Run: ``python benchmarks/bench_memlock_pageout.py --rounds 3``
(writes ``benchmarks/results/memlock/pageout.{md,json}`` unless ``--no-write``).
"""

from __future__ import annotations

import argparse
import ctypes
import itertools
import json
import os
import statistics
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

from lab.faults import FaultRig, _major_faults

SYS_PROCESS_MADVISE = 440  # x86_64 and arm64
MADV_PAGEOUT = 21
PAGEOUTS = 4
RESULTS = Path(__file__).parent / "results" / "memlock"


class _IoVec(ctypes.Structure):
    _fields_ = [("iov_base", ctypes.c_void_p), ("iov_len", ctypes.c_size_t)]


def page_out(pid: int) -> tuple[int, int]:
    """Advise every mapping of ``pid`` (but the vdso) MADV_PAGEOUT; (bytes the kernel
    accepted the advice for, mappings refused: locked ones are)."""
    libc = ctypes.CDLL(None, use_errno=True)
    fd = os.pidfd_open(pid)
    accepted = refused = 0
    try:
        with open(f"/proc/{pid}/maps", encoding="ascii") as maps:
            for line in maps:
                parts = line.split()
                if len(parts) > 5 and parts[5].startswith("[v"):
                    continue
                lo, hi = (int(x, 16) for x in parts[0].split("-"))
                iov = _IoVec(lo, hi - lo)
                done = libc.syscall(SYS_PROCESS_MADVISE, fd, ctypes.byref(iov), 1, MADV_PAGEOUT,
                                    0)
                if done > 0:
                    accepted += done
                else:
                    refused += 1
    finally:
        os.close(fd)
    return accepted, refused


def _status(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return 0


def run_arm(arm: str, workdir: Path) -> dict[str, Any]:
    """One session: ``arm`` is ``lock`` (the stations' default) or ``nolock``."""
    rig = FaultRig(workdir)
    if arm == "nolock":
        spawn = rig._spawn

        def _spawn(name: str, args: list[str], **kw: Any) -> Any:
            if args and args[0] in ("local", "remote"):
                args = [*args, "--no-lock-memory"]
            return spawn(name, args, **kw)

        rig._spawn = _spawn  # type: ignore[method-assign]
    writer = None
    try:
        rig.start(150)
        if not rig.wait_steady(2.0, 30, 1000):
            raise RuntimeError("the demo's flow never became steady")
        remote = rig.stations["remote"].proc.pid
        locked_kb, rss_kb = _status(remote, "VmLck"), _status(remote, "VmRSS")
        hog = workdir / "iohog"
        writer = subprocess.Popen(["bash", "-c", f"while true; do dd if=/dev/zero of={hog} "
                                   "bs=1M count=1500 conv=fsync status=none; done"])
        time.sleep(3)
        marks = []
        faults_before = _major_faults(remote) or 0
        for _ in range(PAGEOUTS):
            time.sleep(4)
            rig.poll()
            t0 = time.monotonic()
            accepted, refused = page_out(remote)
            marks.append((t0, time.monotonic() - t0, accepted, refused))
            time.sleep(3)
        time.sleep(2)
        rig.poll()
        faults_after = _major_faults(remote) or 0
        commands = [m for m, _, ok, _ in rig.probe("remote").commands if ok]
        rows = []
        for t0, took_s, accepted, refused in marks:
            window = [m for m in commands if t0 - 0.5 <= m <= t0 + 3.0]
            gaps = [b - a for a, b in itertools.pairwise(window)]
            rows.append({"advised_mb": round(accepted / 1e6), "mappings_refused": refused,
                         "pageout_ms": round(took_s * 1e3),
                         "longest_command_gap_ms": round(max(gaps) * 1e3) if gaps else None})
        return {"arm": arm, "remote_vmlck_kb": locked_kb, "remote_rss_kb": rss_kb,
                "remote_major_faults": faults_after - faults_before, "pageouts": rows}
    finally:
        if writer is not None:
            writer.kill()
            subprocess.run(["pkill", "-f", f"of={workdir / 'iohog'}"], check=False)
        (workdir / "iohog").unlink(missing_ok=True)
        rig.stop()


def report(runs: list[dict[str, Any]]) -> str:
    """The markdown table."""
    out = ["# Remote station paged out mid-session, with and without its memory lock", "",
           "`python benchmarks/bench_memlock_pageout.py` (method in its docstring): four "
           "page-outs of the remote station's memory per run while a disk writer runs; per "
           "page-out the longest gap between two accepted arm commands within 3 s (commands "
           "come every 4 ms).", "",
           "| run | arm | remote VmRSS / VmLck MB | major faults | longest command gap per "
           "page-out ms | mappings refused |", "|---|---|---|---|---|---|"]
    for k, r in enumerate(runs, 1):
        gap_cells = ", ".join(str(p["longest_command_gap_ms"]) for p in r["pageouts"])
        refused = ", ".join(str(p["mappings_refused"]) for p in r["pageouts"])
        out.append(f"| {k} | {r['arm']} | {r['remote_rss_kb'] / 1024:.0f} / "
                   f"{r['remote_vmlck_kb'] / 1024:.0f} | {r['remote_major_faults']} | "
                   f"{gap_cells} | {refused} |")
    out.append("")
    for arm in ("nolock", "lock"):
        gaps = [p["longest_command_gap_ms"] for r in runs if r["arm"] == arm
                for p in r["pageouts"] if p["longest_command_gap_ms"] is not None]
        faults = [r["remote_major_faults"] for r in runs if r["arm"] == arm]
        if gaps:
            out.append(f"- **{arm}**: longest gap median {statistics.median(gaps):.0f} ms, "
                       f"range {min(gaps)}-{max(gaps)} ms over {len(gaps)} page-outs; major "
                       f"faults per run {', '.join(map(str, faults))}")
    return "\n".join(out) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args()
    runs = []
    with tempfile.TemporaryDirectory(prefix="memlock-") as tmp:
        for k in range(args.rounds):
            order = ("nolock", "lock") if k % 2 == 0 else ("lock", "nolock")
            for arm in order:
                run = run_arm(arm, Path(tmp) / f"{arm}-{k}")
                print(json.dumps(run), flush=True)
                runs.append(run)
    text = report(runs)
    print(text)
    if not args.no_write:
        RESULTS.mkdir(parents=True, exist_ok=True)
        (RESULTS / "pageout.md").write_text(text)
        (RESULTS / "pageout.json").write_text(json.dumps(runs, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
