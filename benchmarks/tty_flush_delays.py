"""How long a kernel work item waited between being queued and run, from a ``perf`` trace.

A serial port's received bytes reach its reader only after the tty layer's flush work
(``flush_to_ldisc``) has run on an unbound kernel worker: a pseudo-terminal's (the simulated
platform's) and, by the kernel's code, a USB serial board's (not measured). While that worker
waits for a CPU the reader gets nothing, however high the station's own threads are ranked
(docs/speed.md section 36).

This lists the queue-to-start delays of one work function (p50, p99, max, how many over a
threshold) and, with ``--worst``, for the longest: the worker's wake-ups (``sched_waking``
names the CPU it last ran on, ``sched_wakeup`` the one it is queued on) and migrations, and
what each CPU ran while it waited (each CPU over the whole wait, whichever the worker was
queued on). ``perf`` drops events when its buffers overflow: a delay whose span holds a
loss is left out of the figures and counted apart.

Record (root; tracefs mounted at /sys/kernel/tracing)::

    perf record -a -k CLOCK_MONOTONIC -o run.data -e sched:sched_switch \\
        -e sched:sched_waking -e sched:sched_wakeup -e sched:sched_migrate_task \\
        -e workqueue:workqueue_queue_work -e workqueue:workqueue_execute_start -- COMMAND

Run: ``python benchmarks/tty_flush_delays.py run.data [--worst]``.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import math
import re
import subprocess
from collections.abc import Iterable, Sequence

# perf script -F comm,tid,cpu,time,event,trace: "  comm  tid [cpu] time: sys:event: fields"
_LINE = re.compile(r"^\s*(.+?)\s+(\d+)\s+\[(\d+)\]\s+(\d+\.\d+):\s+(\S+):\s*(.*)$")
# key=value pairs whose values may hold spaces (a thread name): up to the next key or "==>"
_FIELD = re.compile(r"(\w+)=(.*?)(?=\s+\w+=|\s+==>|\s*$)")
_WORK_STARTED = re.compile(r"work struct (\S+?): function (\S+)")
# perf script --show-lost-events: "  comm  tid [cpu] time: PERF_RECORD_LOST lost N"
_LOST = re.compile(r"^\s*.+?\s+\d+\s+\[(\d+)\]\s+(\d+\.\d+):\s+PERF_RECORD_LOST lost (\d+)")


@dataclasses.dataclass(frozen=True)
class Event:
    t: float  # seconds, the trace's clock
    cpu: int
    tid: int
    comm: str
    name: str  # the event without its system ("sched_switch")
    fields: dict[str, str]
    text: str  # the event's own text


@dataclasses.dataclass(frozen=True)
class Delay:
    queued_s: float
    started_s: float
    queued_by: str  # "comm/tid"
    worker_tid: int
    worker: str
    spans_loss: bool = False  # perf lost events between the queueing and the start

    @property
    def wait_s(self) -> float:
        return self.started_s - self.queued_s


def parse(lines: Iterable[str]) -> list[Event]:
    """The events of ``perf script --show-lost-events -F comm,tid,cpu,time,event,trace``
    text (other lines skipped); a lost-events record is an event named ``lost`` with the
    count in ``fields["lost"]``."""
    events = []
    for line in lines:
        lost = _LOST.match(line)
        if lost is not None:
            cpu, t, n = lost.groups()
            events.append(Event(float(t), int(cpu), 0, "", "lost", {"lost": n}, line.strip()))
            continue
        m = _LINE.match(line)
        if m is None:
            continue
        comm, tid, cpu, t, name, text = m.groups()
        events.append(Event(float(t), int(cpu), int(tid), comm, name.rsplit(":", 1)[-1],
                            dict(_FIELD.findall(text)), text))
    return events


@dataclasses.dataclass(frozen=True)
class WorkDelays:
    delays: list[Delay]  # every run paired with its queueing, in start order
    unstarted: int  # queueings followed by another with no start between (a start lost)
    lost_events: int  # events perf dropped over the whole trace

    @property
    def clean(self) -> list[Delay]:
        """The delays whose span holds no lost events."""
        return [d for d in self.delays if not d.spans_loss]


def work_delays(events: Sequence[Event], function: str) -> WorkDelays:
    """Queue-to-start delay of every run of work ``function``. The kernel traces a queueing
    only when the work was not pending, so a run pairs with the latest queueing before its
    start; a queueing replaced by another before any start lost its start event. Rarely it
    did not: the worker clears the pending flag microseconds before it traces the start, and
    a queueing in between takes that start, understating the earlier queueing's delay (it is
    counted as a lost start all the same)."""
    pending: dict[str, Event] = {}
    loss_times: list[float] = []
    delays = []
    unstarted = lost = 0
    for ev in events:
        if ev.name == "lost":
            loss_times.append(ev.t)
            lost += int(ev.fields["lost"])
        elif ev.name == "workqueue_queue_work" and ev.fields.get("function") == function:
            unstarted += ev.fields["struct"] in pending
            pending[ev.fields["struct"]] = ev
        elif ev.name == "workqueue_execute_start":
            m = _WORK_STARTED.search(ev.text)
            if m is not None and m.group(2) == function and m.group(1) in pending:
                q = pending.pop(m.group(1))
                spans_loss = any(q.t <= t <= ev.t for t in loss_times)
                delays.append(Delay(q.t, ev.t, f"{q.comm}/{q.tid}", ev.tid, ev.comm,
                                    spans_loss))
    return WorkDelays(delays, unstarted, lost)


def cpu_time(events: Sequence[Event], t0: float, t1: float) -> dict[tuple[int, str], float]:
    """Seconds each task ("comm/pid" with its priority) ran on each CPU between ``t0`` and
    ``t1``, from the context switches; a task already running at ``t0`` or still running at
    ``t1`` counts to the edge. A CPU with no switch before ``t1`` is not counted."""
    ran: dict[tuple[int, str], float] = collections.defaultdict(float)
    running: dict[int, tuple[str, float]] = {}  # cpu -> (task, since)
    for ev in events:
        if ev.name != "sched_switch":
            continue
        if ev.t >= t1:
            break
        f = ev.fields
        if ev.cpu in running and ev.t > t0:
            task, since = running[ev.cpu]
            ran[(ev.cpu, task)] += ev.t - max(since, t0)
        elif ev.t > t0:  # the first switch seen on this CPU: its previous task ran since t0
            ran[(ev.cpu, f"{f['prev_comm']}/{f['prev_pid']} prio {f['prev_prio']}")] += ev.t - t0
        running[ev.cpu] = (f"{f['next_comm']}/{f['next_pid']} prio {f['next_prio']}", ev.t)
    for cpu, (task, since) in running.items():
        ran[(cpu, task)] += t1 - max(since, t0)
    return dict(ran)


def quantile(sorted_values: Sequence[float], q: float) -> float:
    """The nearest-rank ``q`` quantile (0 < q <= 1) of ascending values: the smallest value
    with at least ``q`` of them at or below it."""
    return sorted_values[max(0, math.ceil(q * len(sorted_values)) - 1)]


def summary(work: WorkDelays, over_ms: float) -> str:
    loss = (f"; perf lost {work.lost_events} events, {len(work.delays) - len(work.clean)} "
            f"runs spanning a loss left out, {work.unstarted} starts lost"
            if work.lost_events or work.unstarted else "")
    if not work.clean:
        return "no runs of the work function in the trace" + loss
    w = sorted(d.wait_s * 1e3 for d in work.clean)
    return (f"{len(w)} runs; queue to start p50 {quantile(w, 0.5):.3f} ms, "
            f"p99 {quantile(w, 0.99):.2f} ms, max {w[-1]:.1f} ms; "
            f"{sum(x > over_ms for x in w)} over {over_ms:g} ms" + loss)


def worst_report(events: Sequence[Event], delays: Sequence[Delay], top: int = 12) -> list[str]:
    """The longest of ``delays``: the worker's wake-ups, migrations and switches in it, and
    the tasks that ran on each CPU meanwhile."""
    d = max(delays, key=lambda x: x.wait_s)
    out = [f"longest: {d.wait_s * 1e3:.1f} ms, queued at {d.queued_s:.6f} by {d.queued_by}, "
           f"started at {d.started_s:.6f} by {d.worker}/{d.worker_tid}"]
    pid = str(d.worker_tid)
    for ev in events:
        if not d.queued_s <= ev.t <= d.started_s:
            continue
        f = ev.fields
        woken = ev.name in ("sched_waking", "sched_wakeup", "sched_migrate_task")
        if (woken and f.get("pid") == pid) or (
                ev.name == "sched_switch" and pid in (f.get("prev_pid"), f.get("next_pid"))):
            out.append(f"  {ev.t:.6f} [cpu {ev.cpu}] {ev.name}: {ev.text}")
    out.append("ran meanwhile (cpu, task, ms):")
    ran = cpu_time(events, d.queued_s, d.started_s)
    shown = [kv for kv in sorted(ran.items(), key=lambda kv: -kv[1]) if kv[1] >= 5e-5]
    for (cpu, task), s in shown[:top]:
        out.append(f"  cpu {cpu} {task}: {s * 1e3:.1f}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trace", help="a perf.data file recorded as the module's doc says")
    ap.add_argument("--function", default="flush_to_ldisc", help="the work function")
    ap.add_argument("--over-ms", type=float, default=50.0, help="count delays over this")
    ap.add_argument("--worst", action="store_true", help="detail the longest delay")
    args = ap.parse_args(argv)
    try:
        text = subprocess.run(["perf", "script", "--show-lost-events", "-i", args.trace, "-F",
                               "comm,tid,cpu,time,event,trace"],
                              capture_output=True, text=True, check=True).stdout
    except FileNotFoundError:
        ap.error(f"cannot read {args.trace}: the perf tool is not installed")
    except subprocess.CalledProcessError as exc:
        why = exc.stderr.strip().splitlines()[-1:] or [f"perf exited with {exc.returncode}"]
        ap.error(f"cannot read {args.trace} as a perf trace: {why[0]}")
    events = parse(text.splitlines())
    work = work_delays(events, args.function)
    print(f"{args.trace}: {summary(work, args.over_ms)}")
    if args.worst and work.clean:
        print("\n".join(worst_report(events, work.clean)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
