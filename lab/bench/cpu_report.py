"""Markdown table and plot of saved ``teletouch bench cpu`` runs, side by side."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from shared.report import format_table

__all__ = ["product_and_sim", "write_report"]

_SIM = ("sim:", "bench/")


def product_and_sim(run: dict[str, Any]) -> tuple[float, float]:
    """Cores used by the product's code and by simulated hardware (all processes)."""
    product = sim = 0.0
    for per in run["stages"].values():
        for stage, cores in per.items():
            if stage.startswith(_SIM):
                sim += cores
            else:
                product += cores
    return product, sim


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def reference_values(run: dict[str, Any], key: str) -> list[float | None]:
    """A run's reference figure (``reference_speed``'s ``key``) just before and just after
    the demo, None where the run did not measure it."""
    ref = run.get("reference") or {}
    values = [(ref.get(when) or {}).get(key) for when in ("before", "after")]
    return [None if v is None else float(v) for v in values]


def _pair(run: dict[str, Any], key: str, digits: int) -> str:
    """A reference figure before / after the demo ("-" where the run did not measure it)."""
    values = reference_values(run, key)
    if all(v is None for v in values):
        return "-"
    return " / ".join("-" if v is None else f"{v:.{digits}f}" for v in values)


def write_report(runs: list[dict[str, Any]], out_dir: Path) -> None:
    """Write ``cpu.md`` and ``cpu.png`` from the saved runs."""
    labels = [r["label"] for r in runs]
    lines = ["# CPU budget of the demo (`teletouch bench cpu`)", "",
             "CPU seconds per wall second (1.0 = one core) over a measured window of the default "
             "demo (breast scene, scripted raster operator, sensor frames at the demo's default "
             "rate, 1 kHz display loop). Per-process and per-thread totals are exact "
             "(`/proc/<pid>/task/*/stat`); the split over stages is py-spy sampling "
             "(`--nonblocking --idle --threads`), idle judged by the innermost Python line, "
             "each thread's CPU shared out in proportion to its busy samples (method: "
             "`lab/bench/cpu_impl.py`). `sim:` stages are simulated hardware and test "
             "infrastructure, not product code.", "",
             "**The 1-minute load average at the start of each run is recorded, and (from "
             "2026-11-29) the CPU time the host took from this machine's CPUs over the "
             "window (steal, `/proc/stat`): other jobs raise the figures, so compare runs "
             "made back to back, and read figures as upper bounds.** Where the processes "
             "were starved (display loop far below 1 kHz, frames below their setting) CPU "
             "per wall second understates the cost; the "
             "last two columns divide by the work done (session-average loop rate and "
             "achieved frame rate), which holds better under load. From 2026-12-06 each run "
             "also times two fixed workloads by CPU time just before the demo starts and just "
             "after it ends (`reference_speed`: an interpreter loop, and an array pass larger "
             "than the caches): when two runs of the same code differ, these tell whether the "
             "machine itself was slower. Also from 2026-12-06, *threads waiting to run*: each "
             "thread's time on a run queue, runnable but not running (`schedstat`'s "
             "`run_delay`: from a wake-up or a preemption until it runs), summed over the "
             "threads and divided by the window, i.e. the mean number of threads waiting at "
             "any instant (it can exceed the CPU count). It is the scheduler's part of the "
             "latencies; GIL and I/O waits are sleeps, not in it. The run total is left out "
             "when a process lacks the figure.", ""]
    rows = []
    for r in runs:
        product, sim = product_and_sim(r)
        dl = r.get("display_loop", {}) or {}
        lat = r.get("latency_ms", {}) or {}
        e2e = lat.get("end_to_end", lat) if isinstance(lat, dict) else {}
        # the station with its own child processes (platform reader, display loop)
        local_cores = sum(r["processes"].get(name, {}).get("cores") or 0.0
                          for name in ("local", "platform", "display")) or None
        remote_cores = r["processes"].get("remote", {}).get("cores")
        fps = (r.get("remote_frames") or {}).get("achieved_fps")
        rate = dl.get("rate_hz")
        rows.append({
            "run": r["label"], "note": r.get("note", ""),
            "nproc": r.get("nproc"), "load avg at start": _fmt(r["load_start"][0], 2),
            "window s": _fmt(r["wall_s"], 1),
            # what the host took from this machine over the window (from 2026-11-29 on)
            "stolen by the host (cores)": _fmt((r.get("host") or {}).get("steal_cores")),
            # the machine's own speed just before and after the demo (from 2026-12-06 on)
            "reference loop us before / after": _pair(r, "python_us", 0),
            "memory GB/s before / after": _pair(r, "memory_gb_s", 1),
            "all processes (cores)": _fmt(sum(p["cores"] for p in r["processes"].values())),
            # on a run queue, all threads (from 2026-12-06 on)
            "threads waiting to run (mean)": _fmt(waiting_threads(r)),
            "product code": _fmt(product), "simulated hw": _fmt(sim),
            "display loop Hz": _fmt(dl.get("rate_hz"), 0),
            "period jitter p99 ms": _fmt(dl.get("jitter_p99_ms"), 2),
            "motion-to-touch p99 ms": _fmt(e2e.get("p99") if isinstance(e2e, dict) else None, 1),
            "local station CPU us per loop iteration": _fmt(
                1e6 * local_cores / rate if local_cores and rate else None, 0),
            "remote CPU ms per tactile frame": _fmt(
                1e3 * remote_cores / fps if remote_cores and fps else None, 2),
        })
    lines += ["## Runs", "", format_table(rows), ""]
    procs = sorted({p for r in runs for p in r["processes"]})
    prow = [{"process": p, **{lab: _fmt(r["processes"].get(p, {}).get("cores"))
                              for lab, r in zip(labels, runs, strict=True)}} for p in procs]
    lines += ["## Per process (cores)", "", format_table(prow), ""]
    # context switches (wake-ups and preemptions): recorded from this round on
    swrow = [{"process": p, **{lab: _fmt(r["processes"].get(p, {}).get("switches_per_s"), 0)
                               for lab, r in zip(labels, runs, strict=True)}} for p in procs]
    if any(r["processes"].get(p, {}).get("switches_per_s") is not None
           for r in runs for p in procs):
        lines += ["## Per process (context switches per second, all threads)", "",
                  format_table(swrow), ""]
    # run-queue waits: recorded from 2026-12-06 on
    wrow = [{"process": p, **{lab: _fmt(r["processes"].get(p, {}).get("waiting_threads"))
                              for lab, r in zip(labels, runs, strict=True)}} for p in procs]
    if any(r["processes"].get(p, {}).get("waiting_threads") is not None
           for r in runs for p in procs):
        lines += ["## Per process (threads waiting to run, mean: its threads' time on a run "
                  "queue per second)", "", format_table(wrow), ""]
    keys = sorted({(p, s) for r in runs for p, per in r["stages"].items() for s in per})
    srow = [{"process": p, "stage": s,
             **{lab: _fmt(r["stages"].get(p, {}).get(s)) for lab, r in
                zip(labels, runs, strict=True)}} for p, s in keys]
    lines += ["## Per stage (cores)", "", format_table(srow), ""]
    for r in runs:
        lines += [f"## Top functions, run `{r['label']}` (busy samples, innermost repository "
                  "function)", "", f"Command: `{r.get('command', '')}`", ""]
        for proc, top in sorted(r.get("top", {}).items()):
            if top:
                lines += [f"**{proc}**: " + "; ".join(f"{f} {n}" for f, n in top[:8]), ""]
    (out_dir / "cpu.md").write_text("\n".join(lines) + "\n")
    _plot(runs, out_dir / "cpu.png")


def _plot(runs: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    procs = sorted({p for r in runs for p in r["processes"]})
    fig, ax = plt.subplots(figsize=(max(6, 1.6 * len(procs) * max(1, len(runs))), 4))
    width = 0.8 / max(1, len(runs))
    for i, r in enumerate(runs):
        prod = []
        sim = []
        for p in procs:
            per = r["stages"].get(p, {})
            sim.append(sum(v for s, v in per.items() if s.startswith(_SIM)))
            prod.append(sum(v for s, v in per.items() if not s.startswith(_SIM)))
        xs = [j + i * width for j in range(len(procs))]
        ax.bar(xs, prod, width, label=f"{r['label']}: product code")
        ax.bar(xs, sim, width, bottom=prod, label=f"{r['label']}: simulated hw", alpha=0.5)
    ax.set_xticks([j + 0.4 - width / 2 for j in range(len(procs))], procs)
    ax.set_ylabel("cores (CPU s per wall s)")
    ax.set_title("Demo CPU per process (see each run's load average in cpu.md)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def waiting_threads(run: dict[str, Any]) -> float | None:
    """All processes' threads waiting to run, mean (None when a process lacks the figure:
    runs from before it was recorded)."""
    waits = [p.get("waiting_threads") for p in run["processes"].values()]
    return None if not waits or None in waits else sum(w for w in waits if w is not None)
