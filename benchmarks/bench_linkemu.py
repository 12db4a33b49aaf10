"""Link emulator accuracy: measured one-way delay vs the model, and its CPU cost.

For every named profile, a 1 kHz stream of 32-byte records goes through
``lab.linkemu.LinkEmulator`` to a sink on 127.0.0.1. Reported side by side from one
run: the added one-way delay the sink measured (p50/p99/max) next to the profile's nominal
delay, the emulator's timing error (measured minus the delay the model planned for each
chunk), the chunks the loss model delayed, and the proxy's CPU time per chunk.

Run:  python benchmarks/bench_linkemu.py            (5 s per profile; writes the results)
      python benchmarks/bench_linkemu.py --quick    (1 s per profile)
Writes benchmarks/results/linkemu.md and benchmarks/results/linkemu.png.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import platform
import struct
import sys
import time
from pathlib import Path

import numpy as np

from lab.linkemu import PROFILES, LinkEmulator
from shared.report import emit, format_table

RECORD = struct.Struct(">Id24x")  # seq, send time; 32 bytes
RESULTS = Path(__file__).resolve().parent / "results"


async def _measure(profile_name: str, duration_s: float, rate_hz: float) -> dict[str, object]:
    loop = asyncio.get_running_loop()
    sent: dict[int, float] = {}
    added_ms: list[float] = []
    done = asyncio.Event()
    n = int(duration_s * rate_hz)

    async def sink(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        pending = b""
        with contextlib.suppress(ConnectionError):
            await _read(reader, pending)
        writer.close()

    async def _read(reader: asyncio.StreamReader, pending: bytes) -> None:
        while data := await reader.read(65536):
            now = loop.time()
            pending += data
            while len(pending) >= RECORD.size:
                seq, t_sent = RECORD.unpack_from(pending)
                pending = pending[RECORD.size:]
                added_ms.append((now - t_sent) * 1000.0)
                if seq == n - 1:
                    done.set()

    server = await asyncio.start_server(sink, "127.0.0.1", 0)
    target = ("127.0.0.1", server.sockets[0].getsockname()[1])
    async with LinkEmulator(target=target, profile=profile_name, seed=1) as emu:
        _, writer = await asyncio.open_connection("127.0.0.1", emu.port)
        cpu0 = time.process_time()
        start = loop.time()
        for i in range(n):
            await asyncio.sleep(max(0.0, start + i / rate_hz - loop.time()))
            sent[i] = loop.time()
            writer.write(RECORD.pack(i, sent[i]))
        await asyncio.wait_for(done.wait(), 30.0)
        cpu_s = time.process_time() - cpu0
        writer.close()
        up = emu.up_stats
        planned = np.array(up.planned_delay_ms)
        actual = np.array(up.actual_delay_ms)
    server.close()
    await server.wait_closed()
    k = min(len(planned), len(actual))
    error_ms = actual[:k] - planned[:k]
    added = np.array(added_ms)
    prof = PROFILES[profile_name]
    return {
        "profile": profile_name,
        "nominal_ms": prof.delay_ms,
        "jitter_ms": prof.jitter_ms,
        "added_p50_ms": float(np.percentile(added, 50)),
        "added_p99_ms": float(np.percentile(added, 99)),
        "added_max_ms": float(added.max()),
        "err_p50_ms": float(np.percentile(error_ms, 50)),
        "err_p99_abs_ms": float(np.percentile(np.abs(error_ms), 99)),
        "chunks": int(up.chunks),
        "loss_delayed": int(up.delayed_by_loss),
        "cpu_us_per_chunk": cpu_s / max(1, up.chunks) * 1e6,
        "_added": added,
        "_error": error_ms,
    }


def _plot(rows: list[dict[str, object]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    for row in rows:
        added = np.sort(np.asarray(row["_added"]))
        ax1.plot(added, np.linspace(0, 1, added.size), label=str(row["profile"]))
        ax1.axvline(float(row["nominal_ms"]), color="grey", lw=0.5, ls=":")  # type: ignore[arg-type]
        ax2.hist(np.asarray(row["_error"]), bins=60, histtype="step", label=str(row["profile"]))
    ax1.set_xscale("log")
    ax1.set_xlabel("measured added one-way delay (ms, log)")
    ax1.set_ylabel("CDF")
    ax1.set_title("delay through the emulator (dotted: nominal)")
    ax1.legend()
    ax2.set_xlabel("timing error: measured - planned (ms)")
    ax2.set_ylabel("chunks")
    ax2.set_title("emulator timing error per chunk")
    ax2.set_yscale("log")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    """Run the benchmark and write the table and the plot."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 s per profile")
    parser.add_argument("--rate-hz", type=float, default=1000.0)
    args = parser.parse_args()
    duration_s = 1.0 if args.quick else 5.0
    load_before = os.getloadavg()[0]
    rows = [asyncio.run(_measure(name, duration_s, args.rate_hz)) for name in PROFILES]
    load_after = os.getloadavg()[0]
    cols = ["profile", "nominal_ms", "jitter_ms", "added_p50_ms", "added_p99_ms", "added_max_ms",
            "err_p50_ms", "err_p99_abs_ms", "chunks", "loss_delayed", "cpu_us_per_chunk"]
    table = format_table([{c: r[c] for c in cols} for r in rows], cols)
    command = "python benchmarks/bench_linkemu.py" + (" --quick" if args.quick else "")
    text = (f"# Link emulator: measured delay vs model\n\n"
            f"Machine: {platform.machine()}, 2 cores shared with other jobs, no GPU; "
            f"Python {platform.python_version()}; 1-min load average {load_before:.1f} before, "
            f"{load_after:.1f} after the run.\n"
            f"Command: `{command}` ({duration_s:g} s per profile, {args.rate_hz:g} Hz of "
            f"32-byte records, one direction, seed 1).\n\n"
            f"`added_*`: one-way delay the sink measured (includes the proxy hop and in-order "
            f"head-of-line blocking). `err_*`: measured minus the delay the model planned "
            f"for that chunk (event-loop timer resolution and load). `cpu_us_per_chunk`: "
            f"process CPU time (sender + proxy + sink) per forwarded chunk.\n\n"
            f"Reading the figures: sub-millisecond `err_p50` is the event loop's 1 ms timer "
            f"tick; the p99 error of a few ms comes in runs of consecutive chunks, i.e. the "
            f"process being descheduled on a loaded 2-core host (the `lan` row, which never "
            f"sleeps, is immune because read and delivery are delayed together). `added_p50` "
            f"above nominal at 1 kHz is in-order delivery: a chunk waits for a later-jittered "
            f"one ahead of it, as in TCP. `added_p99` of `intercontinental` is the loss model: "
            f"one lost segment costs ~2 x 90 + 4 x 3 = 192 ms and holds the stream behind it.\n\n"
            f"{table}\n\n![delay CDF and timing error](linkemu.png)\n")
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "linkemu.md").write_text(text)
    _plot(rows, RESULTS / "linkemu.png")
    emit(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
