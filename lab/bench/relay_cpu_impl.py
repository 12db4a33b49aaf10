"""Implementation of ``teletouch bench relay-cpu`` (see :mod:`lab.bench.relay_cpu`)."""

from __future__ import annotations

import io
import logging
import os
import platform
import statistics
import subprocess
import tarfile
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from lab.bench.load_impl import STREAMS, LoadSettings, RelayUnderTest, _autogroup, _run_step
from lab.bench.results import publish
from shared.errors import ConfigError
from shared.report import format_table

__all__ = ["CpuSettings", "cpu_ms_per_1k", "report", "run_relay_cpu", "summarise"]

log = logging.getLogger(__name__)

_REPO = Path(__file__).resolve().parents[2]
CURRENT = "this tree"


@dataclass(frozen=True)
class CpuSettings:
    """What to run (see :mod:`lab.bench.relay_cpu`)."""

    baseline_rev: str | None = None
    sessions: int = 5
    step_s: float = 5.0
    rounds: int = 3
    mixes: tuple[str, ...] = ("platform_state", "arm_state", "tactile_frame", "all")
    generators: int = 3
    transport: str = "ws"


def extract_revision(rev: str, into: Path) -> str:
    """Write revision ``rev`` of this repository's tree into ``into``; return its commit id.

    Raises:
        ConfigError: not a git checkout, or an unknown revision.
    """
    try:
        commit = subprocess.run(["git", "-C", str(_REPO), "rev-parse", "--verify",
                                 f"{rev}^{{commit}}"], capture_output=True, text=True,
                                check=True).stdout.strip()
        tar = subprocess.run(["git", "-C", str(_REPO), "archive", commit],
                             capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as err:
        raise ConfigError(f"cannot extract revision {rev!r} of {_REPO}: {err}") from err
    with tarfile.open(fileobj=io.BytesIO(tar)) as archive:
        archive.extractall(into, filter="data")
    return commit


def cpu_ms_per_1k(relay_cpu_cores: float, forwarded: int, measure_s: float) -> float | None:
    """Relay CPU milliseconds per 1,000 forwarded messages (None when nothing arrived)."""
    if forwarded <= 0:
        return None
    return relay_cpu_cores * measure_s / forwarded * 1e6


def _user_system_s(pids: list[int]) -> tuple[float, float]:
    """User and system CPU seconds used so far by ``pids`` (from ``/proc``)."""
    user = system = 0.0
    tick = os.sysconf("SC_CLK_TCK")
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            user += int(fields[11]) / tick
            system += int(fields[12]) / tick
        except (OSError, ValueError, IndexError):
            pass
    return user, system


def _measure(relay: RelayUnderTest, settings: CpuSettings, mix: str, tag: str
             ) -> dict[str, Any]:
    streams = STREAMS if mix == "all" else (mix,)
    load = LoadSettings(steps=(settings.sessions,), step_s=settings.step_s,
                        generators=settings.generators, streams=streams,
                        transport=settings.transport)
    u0, s0 = _user_system_s(relay.pids())
    step = _run_step(relay, settings.sessions, load, settings.step_s, tag)
    u1, s1 = _user_system_s(relay.pids())
    forwarded = sum(step["received"][k] for k in streams)
    cores = step["relay_cpu_cores"]
    return {"mix": mix, "relay_cpu_cores": cores,
            "cores_per_session": cores / settings.sessions,
            "forwarded": forwarded, "forwarded_per_s": forwarded / settings.step_s,
            "sent": sum(step["sent"][k] for k in streams),
            "cpu_ms_per_1k": cpu_ms_per_1k(cores, forwarded, settings.step_s),
            # of the whole step (connections, warm-up and window): kernel work is the share
            # no Python change removes but fewer system calls
            "system_share": (s1 - s0) / (u1 - u0 + s1 - s0) if u1 - u0 + s1 - s0 > 0 else None,
            "added_p50_us": step["added_latency_us"]["p50"],
            "added_p99_us": step["added_latency_us"]["p99"],
            "delivered_min": min(step["delivered"].values()),
            "gen_lag_p99_us": max((g["p99"] or 0.0) for g in step["generator_send_lag_us"]),
            "drops": step["drops"], "lost_connections": len(step["lost_connections"])}


def run_relay_cpu(settings: CpuSettings) -> dict[str, Any]:
    """Run every round (each mix on each relay in turn, alternating the order); return the
    results."""
    logging.getLogger("websockets").setLevel(logging.ERROR)
    load_start = os.getloadavg()
    started = time.monotonic()
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="teletouch-relay-cpu-") as tmp:
        relays: list[tuple[str, Path | None]] = [(CURRENT, None)]
        baseline_commit = None
        if settings.baseline_rev is not None:
            baseline = Path(tmp) / "baseline"
            baseline.mkdir()
            baseline_commit = extract_revision(settings.baseline_rev, baseline)
            relays.insert(0, (settings.baseline_rev, baseline))
        for rnd in range(settings.rounds):
            # both relays run through the round (an idle one costs nothing); each mix runs
            # on one then the other, so a pair is measured seconds apart
            running: list[tuple[str, RelayUnderTest]] = []
            try:
                for name, tree in relays:
                    running.append((name, RelayUnderTest(
                        tree=tree, ledger_window=8192, max_connections=100_000,
                        max_connections_per_ip=100_000)))
                for i, mix in enumerate(settings.mixes):
                    order = running if (rnd + i) % 2 == 0 else running[::-1]
                    for name, relay in order:
                        row = _measure(relay, settings, mix, f"c{rnd}-{len(runs)}")
                        runs.append({"round": rnd, "relay": name, **row,
                                     "loadavg": os.getloadavg()[0]})
                        log.info("round %d %s %s: %.3f ms CPU per 1k messages", rnd, name,
                                 mix, row["cpu_ms_per_1k"] or float("nan"))
            finally:
                for _, relay in running:
                    relay.close()
    try:
        head = subprocess.run(["git", "-C", str(_REPO), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, check=True).stdout.strip()
        dirty = bool(subprocess.run(["git", "-C", str(_REPO), "status", "--porcelain",
                                     "--untracked-files=no"], capture_output=True, text=True,
                                    check=True).stdout.strip())
    except (OSError, subprocess.CalledProcessError):
        head, dirty = "?", False
    return {"settings": asdict(settings), "baseline_commit": baseline_commit,
            "current": f"{head}{' (uncommitted changes)' if dirty else ''}",
            "runs": runs, "summary": summarise(runs, settings),
            "elapsed_s": time.monotonic() - started,
            "machine": {"nproc": os.cpu_count(), "loadavg_start": load_start,
                        "loadavg_end": os.getloadavg(), "python": platform.python_version(),
                        "niceness": os.nice(0), "autogroup": _autogroup(),
                        "note": "other jobs may share the machine: see the load averages"}}


#: a run counts only when every stream delivered this share in the window, with no
#: connection lost: a stalled run (a starved generator or relay on the shared machine) forwards
#: in bursts, a different regime whose CPU per message is not comparable
MIN_DELIVERED = 0.95


def valid(run: dict[str, Any]) -> bool:
    """The run delivered (see :data:`MIN_DELIVERED`) and has a CPU figure."""
    return (run["cpu_ms_per_1k"] is not None and run["delivered_min"] >= MIN_DELIVERED
            and not run["lost_connections"])


def summarise(runs: list[dict[str, Any]], settings: CpuSettings) -> list[dict[str, Any]]:
    """Per mix: each relay's median CPU per 1,000 messages and cores per session over its
    valid runs, and the ratio this tree / baseline of the rounds where both runs are valid
    (median, min, max)."""
    out = []
    names = list(dict.fromkeys(r["relay"] for r in runs))
    for mix in settings.mixes:
        row: dict[str, Any] = {"mix": mix}
        per: dict[str, dict[int, dict[str, Any]]] = {}
        for r in runs:
            if r["mix"] == mix and valid(r):
                per.setdefault(r["relay"], {})[r["round"]] = r
        for name in names:
            got = list(per.get(name, {}).values())
            row[name] = {
                "cpu_ms_per_1k": statistics.median(r["cpu_ms_per_1k"] for r in got)
                if got else None,
                "cores_per_session": statistics.median(r["cores_per_session"] for r in got)
                if got else None,
                "forwarded_per_s": statistics.median(r["forwarded_per_s"] for r in got)
                if got else None,
                "added_p99_us": statistics.median(r["added_p99_us"] or 0.0 for r in got)
                if got else None}
        if settings.baseline_rev is not None:
            base, cur = per.get(settings.baseline_rev, {}), per.get(CURRENT, {})
            ratios = [cur[k]["cpu_ms_per_1k"] / base[k]["cpu_ms_per_1k"]
                      for k in sorted(set(base) & set(cur))]
            row["ratio"] = {"median": statistics.median(ratios) if ratios else None,
                            "min": min(ratios, default=None), "max": max(ratios, default=None),
                            "rounds": len(ratios)}
        out.append(row)
    return out


# --------------------------------------------------------------------------- report


def report(results: dict[str, Any], *, as_json: bool, out_dir: str | None, argv: str) -> None:
    """Print the results; optionally write ``relay_cpu.md`` and ``relay_cpu.json``."""
    publish(results, markdown(results, argv), as_json=as_json, out_dir=out_dir, stem="relay_cpu")


def _f(v: float | None, digits: int = 3) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def markdown(r: dict[str, Any], argv: str) -> str:
    """The results as Markdown (``relay_cpu.md``)."""
    m, s = r["machine"], r["settings"]
    base = s["baseline_rev"]
    names = ([base] if base else []) + [CURRENT]
    rows = []
    for row in r["summary"]:
        line: dict[str, Any] = {"mix": row["mix"]}
        for name in names:
            got = row.get(name, {})
            label = "old" if name == base else "new"
            line[f"{label} ms/1k msgs"] = _f(got.get("cpu_ms_per_1k"))
            line[f"{label} cores/session"] = _f(got.get("cores_per_session"), 4)
            line[f"{label} msgs/s"] = _f(got.get("forwarded_per_s"), 0)
        if "ratio" in row:
            q = row["ratio"]
            line["new/old (median)"] = _f(q["median"], 2)
            line["new/old range"] = f"{_f(q['min'], 2)}-{_f(q['max'], 2)}"
            line["rounds"] = q["rounds"]
        rows.append(line)
    runs = [{"round": x["round"], "relay": "old" if x["relay"] == base else "new",
             "mix": x["mix"], "msgs_s": round(x["forwarded_per_s"]),
             "relay_cores": f"{x['relay_cpu_cores']:.3f}",
             "ms/1k msgs": _f(x["cpu_ms_per_1k"]),
             "system_share": _f(x.get("system_share"), 2),
             "added_p50_us": _f(x["added_p50_us"], 0), "added_p99_us": _f(x["added_p99_us"], 0),
             "delivered_min": f"{x['delivered_min']:.3f}",
             "gen_lag_p99_us": _f(x.get("gen_lag_p99_us"), 0),
             "counted": "yes" if valid(x) else "NO",
             "drops": ", ".join(f"{k} {v}" for k, v in sorted(x["drops"].items()) if v) or "0",
             "load_1min": f"{x['loadavg']:.1f}"} for x in r["runs"]]
    which = (f"old = revision `{base}` ({(r['baseline_commit'] or '?')[:10]}), extracted with "
             "`git archive` and run with the same interpreter and libraries; new = "
             f"this tree ({r['current']})") if base else f"this tree ({r['current']}) only"
    lines = [
        "# Relay CPU per forwarded message", "",
        f"Command: `{argv}`. {which}. {s['sessions']} sessions per step, "
        f"{s['generators']} generator processes, {s.get('transport', 'ws')} stations, "
        f"{s['step_s']:g} s measured per mix after 1 s warm-up, {s['rounds']} rounds; "
        "in each round both relays run, and "
        "each mix runs on one then the other (seconds apart), the order alternating.",
        f"Machine: {m['nproc']} cores, Python {m['python']}, load average "
        f"{m['loadavg_start'][0]:.2f} at the start and {m['loadavg_end'][0]:.2f} at the end "
        f"(each run's 1-minute load average is in the last column below); niceness "
        f"{m['niceness']}, scheduler {m['autogroup'] or 'group ?'}. Other jobs may share the "
        "machine (the load averages say how busy it was), and the load generators run on the "
        "same cores as the relay: absolute milliseconds move with the load; the per-round ratio "
        "new/old (same traffic, minutes apart) is the figure to compare.", "",
        "ms/1k msgs = relay CPU (user + system, /proc) over the measured window / messages the "
        "receiving stations got in it x 1,000, so it charges the relay's fixed costs (clock "
        "pings, stats) to the messages too. Mixes: each stream alone at its load-benchmark "
        "rate per session (platform_state 250 Hz, arm_state 50 Hz, tactile_frame 19 kB at "
        "60-120 Hz), and `all` = the realistic session (all three). system_share (every run "
        "below): the relay's system (kernel) CPU over its user + system CPU during the whole "
        "step (connects, warm-up and window).", "",
        f"Only runs that delivered >= {MIN_DELIVERED:.0%} of every stream in the window with "
        "no connection lost count (`counted`); a ratio needs both runs of its round counted "
        "(`rounds` = how many did). A run that did not deliver stalled (messages late by "
        "up to seconds, fewer forwarded); gen_lag_p99_us is the worst generator's send lag "
        "(a generator starved by the machine's load shows there).", "",
        format_table(rows), "",
        "Every run:", "", format_table(runs),
    ]
    return "\n".join(lines)
