"""Fault suite with real processes: relay SIGKILL, link blackholes and resets, stations
SIGKILLed and SIGSTOPped, clock steps, CPU load; per scenario, against the issue's targets.

Each scenario starts its own relay, two link emulators and two probed stations
(``lab/faults.py``), injects its fault ``--repeats`` times into a steady flow, and reports:
halt and safe-state latency after the last valid input (p50/p99/max over every halt and safe
entry of the run, spurious ones included), time until fresh frames are rendered again after
the recovery, commands older than 100 ms executed, frames older than 150 ms (the display's
bound) rendered, and the stations that exited. ``--quick``: one injection per scenario (all
scenarios, the 60 s outages too); ``--short`` also leaves out the 20 s and 60 s outages.

The results table goes to ``benchmarks/results/faults.md`` (``--write-results DIR``; a partial
run with ``--only`` writes nowhere unless told), with the machine's load at the start: the
other jobs on this machine slow every process here.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from lab.faults import Scenario

__all__ = ["configure_parser", "results_dir", "run"]

#: the issue's targets
HALT_P99_MS = 100.0
FRESH_AFTER_MS = 1000.0


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Flags of ``teletouch bench faults``."""
    parser.add_argument("--quick", action="store_true", help="one injection per scenario")
    parser.add_argument("--short", action="store_true",
                        help="leave out the 20 s and 60 s outages")
    parser.add_argument("--repeats", type=int, default=None,
                        help="injections per scenario (default 3, --quick 1)")
    parser.add_argument("--only", metavar="TEXT", action="append", default=None,
                        help="run only scenarios whose name contains TEXT (repeatable)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--workdir", metavar="DIR", default=None,
                        help="keep logs and probe files here (default: a temporary dir)")
    parser.add_argument("--merge", metavar="JSON", nargs="+", default=None,
                        help="run nothing: one table from the faults.json of several runs "
                             "(e.g. parts run side by side); the last run of a scenario wins")
    parser.add_argument("--board-process", action="store_true",
                        help="run the local station's drive board as a process of its own "
                             "(teletouch board, reached over socket://); the display's safe "
                             "state is then the board's; results go to faults_board.md/json")
    parser.add_argument("--platform-process", action="store_true",
                        help="the local station reads its platform in a process of its own "
                             "(teletouch local --platform-process; the platform process's "
                             "own faults use it always); results go to faults_platform.md/json "
                             "(faults_board_platform.* with --board-process)")
    parser.add_argument("--no-lock-memory", dest="lock_memory", action="store_false",
                        help="start both stations with --no-lock-memory (their memory is "
                             "locked by default where it is safe); results go to "
                             "faults_nolock.md/json")
    parser.add_argument("--write-results", metavar="DIR", default=None,
                        help="write faults.md and faults.json (faults_board.* with "
                             "--board-process, faults_platform.* with --platform-process) "
                             "to DIR ('' = do not write; default benchmarks/results, but "
                             "nowhere for a partial run with --only, which must not replace "
                             "the whole suite's table)")


def select(items: list[Scenario], only: list[str] | None) -> list[Scenario]:
    """The scenarios whose name contains one of ``only`` (case-insensitive; all without it).

    Raises:
        ConfigError: ``only`` matched no scenario (the names are listed).
    """
    if not only:
        return items
    chosen = [s for s in items if any(t.lower() in s.name.lower() for t in only)]
    if not chosen:
        from shared.errors import ConfigError
        names = "; ".join(s.name for s in items)
        raise ConfigError(f"--only {only} matches no scenario; the scenarios are: {names}")
    return chosen


def results_dir(write_results: str | None, only: list[str] | None) -> str:
    """Where the tables go ('' = nowhere): as given, else ``benchmarks/results`` for the whole
    suite and nowhere for a partial run (``--only``), which must not replace its table."""
    if write_results is not None:
        return write_results
    return "" if only else "benchmarks/results"


def _fmt(x: object, digits: int = 0) -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        return f"{x:.{digits}f}"
    return str(x)


def _verdict(r: dict[str, Any]) -> list[str]:
    """The targets a scenario missed (empty: all met)."""
    missed = []
    for key in ("halt_ms", "safe_ms"):
        p99 = r[key]["p99"]
        if p99 is not None and p99 > HALT_P99_MS:
            missed.append(f"{key.split('_')[0]} p99")
    if r["stale_commands_executed"]:
        missed.append("stale commands")
    if r["stale_frames_rendered"]:
        missed.append("stale frames")
    if r.get("stale_at_pins"):
        missed.append("stale at the pins")
    fresh = r["fresh_after_ms"]["max"]
    if r["kind"] not in ("none", "clock_step") and (
            r["recoveries_missing"] or (fresh is not None and fresh > FRESH_AFTER_MS)):
        missed.append("recovery")
    if r["exits"]:
        missed.append("exits")
    if r["error"]:
        missed.append("rig error")
    return missed


def table(results: list[dict[str, Any]]) -> str:
    """The per-scenario markdown table."""
    head = ("| scenario | n | halt ms p50/p99/max (count) | safe ms p50/p99/max (count) | "
            "fresh frames after recovery ms p50/max (any frame: max) | not recovered | "
            "stale cmds executed (max age ms) | stale frames rendered (max age ms) | "
            "station exits | targets missed |")
    lines = [head, "|" + "---|" * 10]
    for r in results:
        h, s, f = r["halt_ms"], r["safe_ms"], r["fresh_after_ms"]
        exits = ", ".join(f"{e['role']}#{e['instance']}:{e['code']}"
                          for e in r["exits"]) or "0"
        missed = _verdict(r)
        name = r["scenario"] + (" [platform process]" if r.get("platform_process") else "")
        lines.append(
            f"| {name} | {r['repeats']} | "
            f"{_fmt(h['p50'])}/{_fmt(h['p99'])}/{_fmt(h['max'])} ({h['n']}) | "
            f"{_fmt(s['p50'])}/{_fmt(s['p99'])}/{_fmt(s['max'])} ({s['n']}) | "
            f"{_fmt(f['p50'])}/{_fmt(f['max'])} ({_fmt(r['any_frame_after_ms']['max'])}) | "
            f"{r['recoveries_missing'] if r['kind'] not in ('none', 'clock_step') else '-'} | "
            f"{r['stale_commands_executed']} ({_fmt(r['stale_command_max_age_ms'])}) | "
            f"{r['stale_frames_rendered']} ({_fmt(r['stale_frame_max_age_ms'])}) | {exits} | "
            f"{', '.join(missed) or 'none'}"
            + (f" (rig error: {str(r['error']).splitlines()[0][:80]})" if r["error"] else "")
            + " |")
    return "\n".join(lines)


def _summaries_table(results: list[dict[str, Any]]) -> str:
    lines = ["| scenario | local safe entries | local link connects/losses | remote watchdog / "
             "link-loss halts | remote dropped stale / no clock | remote max measured age ms | "
             "remote link connects/losses | local platform process restarts | "
             "major page faults once the flow was steady (processes running at the end) | "
             "injected into an unsteady flow |",
             "|" + "---|" * 10]
    for r in results:
        sm = r["summaries"]
        loc = sm.get("local") or {}
        rem = sm.get("remote") or {}
        ll, rl = loc.get("link") or {}, rem.get("link") or {}
        plat = loc.get("platform") or {}
        lines.append(
            f"| {r['scenario']} | {_fmt(loc.get('safe_entries'))} | "
            f"{_fmt(ll.get('connects'))}/{_fmt(ll.get('connection_losses'))} | "
            f"{_fmt(rem.get('watchdog_halts'))} / {_fmt(rem.get('link_loss_halts'))} | "
            f"{_fmt(rem.get('dropped_stale'))} / {_fmt(rem.get('dropped_no_clock'))} | "
            f"{_fmt(rem.get('max_measured_age_ms'))} | "
            f"{_fmt(rl.get('connects'))}/{_fmt(rl.get('connection_losses'))} | "
            f"{_fmt(plat.get('process_restarts')) if plat.get('process') else '-'} | "
            f"{_major_faults(r.get('major_page_faults'))}"
            f"{'' if r.get('major_page_faults_since') == 'steady' else ' (since start)'} | "
            f"{r['injected_unsteady']} |")
    return "\n".join(lines)


def _major_faults(faults: dict[str, int] | None) -> str:
    """``name n`` for the processes with major page faults ('0': none; '-': not recorded)."""
    if faults is None:
        return "-"
    return ", ".join(f"{name} {n}" for name, n in sorted(faults.items()) if n) or "0"


def _windows_table(results: list[dict[str, Any]]) -> str:
    lines = ["| scenario | injection | frames rendered in the 5 s before the fault: stale / all "
             "(max age ms) | in the 5 s after the recovery: stale / all (max age ms) |",
             "|---|---|---|---|"]
    for r in results:
        for i, f in enumerate(r["faults"]):
            b, a = f.get("frames_before"), f.get("frames_after")
            if b is None or a is None:
                continue
            lines.append(f"| {r['scenario']} | {i + 1} | {b['stale']} / {b['rendered']} "
                         f"({_fmt(b['max_age_ms'])}) | {a['stale']} / {a['rendered']} "
                         f"({_fmt(a['max_age_ms'])}) |")
    return "\n".join(lines)


def _board_table(results: list[dict[str, Any]]) -> str:
    lines = ["| scenario | board safe entries by reason | station-logged safe ms p50/p99/max "
             "(count) | board commands applied / rejected | commands applied with touch older "
             "than 150 ms (max age ms) / matching no station send | board watchdog trips | "
             "board link connects / disconnects / feedback frames dropped | pins safe at each "
             "recovery moment | board niceness |", "|" + "---|" * 9]
    for r in results:
        b = (r["summaries"].get("board") or {})
        link = b.get("link") or {}
        s = r.get("station_safe_ms") or {}
        reasons = ", ".join(f"{k} {v}" for k, v in (r.get("board_safe_reasons") or {}).items())
        at_rec = ", ".join("yes" if f.get("board_safe_at_recovery") else "no"
                           for f in r["faults"]) or "-"
        lines.append(
            f"| {r['scenario']} | {reasons or '0'} | {_fmt(s.get('p50'))}/{_fmt(s.get('p99'))}/"
            f"{_fmt(s.get('max'))} ({_fmt(s.get('n'))}) | {_fmt(b.get('commands_applied'))} / "
            f"{_fmt(b.get('commands_rejected'))} | {_fmt(r.get('stale_at_pins'))} "
            f"({_fmt(r.get('stale_at_pins_max_age_ms'))}) / {_fmt(r.get('pins_unmatched'))} | "
            f"{_fmt(b.get('watchdog_trips'))} | "
            f"{_fmt(link.get('connects'))} / {_fmt(link.get('disconnects'))} / "
            f"{_fmt(link.get('feedback_dropped'))} | {at_rec} | {_fmt(b.get('niceness'))} |")
    return "\n".join(lines)


def report_markdown(results: list[dict[str, Any]], *, command: str, machine: str,
                    elapsed_s: float) -> str:
    """The whole results file."""
    board = any(r.get("board_process") for r in results)
    board_text = f"""
**Board process.** The local station's drive board is not simulated inside the station here:
`teletouch board` (lab/board.py) runs the emulated firmware and plant as a process of its own,
which the station reaches over TCP with its ordinary serial driver (`--display
socket://127.0.0.1:PORT`). The **safe** column is the *board's* safe-state entries (its event
file: watchdog or safe-state frame) after the last fresh frame the station accepted, so a
frozen station's display is measured, not assumed. The station's own safe-state log is in the
second table for comparison. The board runs at niceness -10 when the machine allows it (a real
board's MCU is not slowed by the host's load; an emulator starved by it applies buffered
commands late and trips its watchdog late, which the table would then count). The probe
logs every pin command the station sends with its sequence number and the stamp of the newest
frame (`P` lines); the board logs every command it applies with the same number, so the table
also says how old the touch was that the pins *actually* showed (true age when the board
applied the command; bound 150 ms).

{_board_table(results)}
""" if board else ""
    title = "Fault suite (issue 11 item 6)" + (", the drive board as its own process"
                                               if board else "")
    return f"""# {title}

Command: `{command}`. {machine} Run took {elapsed_s / 60:.1f} min.

Each scenario: relay, a link emulator on each leg, remote and local station (simulated devices,
60 Hz frames, 250 Hz platform states), all separate processes on 127.0.0.1, started afresh;
the fault is injected `n` times, each time into a flow that has been steady for 2 s (fresh
frames rendered and commands executed with no gap over 0.25 s). Figures come from the probe
files (`lab/faults_probe.py`: what the display rendered and when it went safe, what the arm
executed and when it halted, on the host's shared monotonic clock) and what the harness knows
(when it injected and when it recovered):

- **halt / safe ms**: arm halt (display safe state) minus the last command accepted (last fresh
  frame accepted) before it, over every halt (safe entry) of the run, spurious ones included;
  the count is in brackets. Target: p99 <= {HALT_P99_MS:.0f} ms.
- **fresh frames after recovery**: first frame rendered whose true age was <= 150 ms after the
  recovery moment (relay answering its /status again, the outage's end, SIGCONT, the killed
  station's restart command), per injection; in brackets the first frame rendered at all,
  however old; **not recovered**: injections after which no fresh frame came before the run
  ended (the harness waits at most 20 s, 60 s after a station's restart, for a frame at most
  1 s old, then 1 s more). Target:
  <= {FRESH_AFTER_MS:.0f} ms.
- **stale**: commands executed / frames rendered whose true age (same host: now minus the
  sender's stamp, less any clock step the harness injected) exceeded 100 ms (commands) /
  150 ms (frames). Target: 0.
- **station exits**: station processes that ended before the harness stopped them (role#instance:
  exit code). Target: none.

A SIGKILLed or SIGSTOPped station cannot log its own halt or safe state: the simulated arm and
display live in its process, so the halt of a stopped remote station is counted when it resumes
(what a real arm's own watchdog would prevent), and a killed one has none.

{table(results)}
{board_text}
The stations' own summaries (last instance of each, written at SIGTERM; `-` = not written):

{_summaries_table(results)}

Stale frames around each injection, to tell the load's share from the fault's (runs made
before this split was added have no rows here):

{_windows_table(results)}
"""


def run(args: argparse.Namespace) -> int:
    """Run the suite and report."""
    import os
    import platform
    import signal
    import sys
    import tempfile
    import time
    from pathlib import Path

    from lab.bench.results import write_results
    from lab.faults import iter_results, scenarios
    from shared.report import emit, emit_json

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt  # the running scenario stops its processes on the way out

    signal.signal(signal.SIGTERM, interrupt)
    args.write_results = results_dir(args.write_results, args.only)
    if args.merge:
        return _merge(args.merge, args.write_results)
    repeats = args.repeats or (1 if args.quick else 3)
    items = select(scenarios(long=not args.short), args.only)
    load = os.getloadavg()
    machine = (f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python "
               f"{platform.python_version()}, load average {load[0]:.1f} / {load[1]:.1f} / "
               f"{load[2]:.1f} (1/5/15 min) at the start: the machine is shared with other "
               "jobs, so every process here competes for the cores.")
    root = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="tt-faults-"))
    started = time.monotonic()
    parts = ["teletouch bench faults"] + (["--quick"] if args.quick else []) \
        + (["--short"] if args.short else []) \
        + (["--board-process"] if args.board_process else []) \
        + (["--platform-process"] if args.platform_process else []) \
        + ([] if args.lock_memory else ["--no-lock-memory"]) \
        + ([f"--repeats {args.repeats}"] if args.repeats else []) \
        + [f"--only '{t}'" for t in (args.only or [])]
    results: list[dict[str, Any]] = []
    md = ""
    name = "faults" + ("_board" if args.board_process else "") \
        + ("_platform" if args.platform_process else "") \
        + ("" if args.lock_memory else "_nolock")

    def write(partial: bool) -> None:
        nonlocal md
        now = os.getloadavg()[0]
        note = (f" Load average {now:.1f} when this file was written."
                + (f" **Partial: {len(results)} of {len(items)} scenarios so far.**"
                   if partial else ""))
        md = report_markdown(results, command=" ".join(parts), machine=machine + note,
                             elapsed_s=time.monotonic() - started)
        if args.write_results:
            write_results(args.write_results, name, md, data={
                "machine": machine, "load_average_start": load, "partial": partial,
                "results": results})

    for r in iter_results(items, root, repeats=repeats, board_process=args.board_process,
                          platform_process=args.platform_process,
                          lock_memory=args.lock_memory,
                          progress=lambda m: print(m, file=sys.stderr, flush=True)):
        results.append(r)
        print(f"  -> halt p99 {_fmt(r['halt_ms']['p99'])} ms, safe p99 "
              f"{_fmt(r['safe_ms']['p99'])} ms, fresh after "
              f"{_fmt(r['fresh_after_ms']['max'])} ms, stale cmds "
              f"{r['stale_commands_executed']}, stale frames {r['stale_frames_rendered']}, "
              f"exits {len(r['exits'])}", file=sys.stderr, flush=True)
        write(partial=len(results) < len(items))  # a long run leaves its table as it goes
    write(partial=False)
    if args.json:
        emit_json({"machine": machine, "results": results})
    else:
        emit(md)
    return 0


def _merge(paths: list[str], out_dir: str | None) -> int:
    """Write one faults.md / faults.json from several runs' faults.json, in suite order."""
    import json
    from pathlib import Path

    from lab.bench.results import write_results
    from lab.faults import scenarios
    from shared.report import emit

    by_name: dict[str, dict[str, Any]] = {}
    machines = []
    for path in paths:
        data = json.loads(Path(path).read_text())
        machines.append(f"`{Path(path).name}` ({'partial' if data.get('partial') else 'complete'}"
                        f" run): {data['machine']}")
        for r in data["results"]:
            by_name[r["scenario"]] = r
    order = [s.name for s in scenarios()]
    results = sorted(by_name.values(),
                     key=lambda r: order.index(r["scenario"]) if r["scenario"] in order
                     else len(order))
    machine = "Merged from " + str(len(paths)) + " runs, which ran side by side (more load " \
        "than one run alone). " + " ".join(machines)
    md = report_markdown(results, command="teletouch bench faults --merge " + " ".join(paths),
                         machine=machine, elapsed_s=sum(float(r["wall_s"]) for r in results))
    if out_dir:
        write_results(out_dir, "faults", md, data={
            "machine": machine, "partial": False, "results": results})
    emit(md)
    return 0
