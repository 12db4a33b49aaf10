"""CPU budget of the demo: CPU seconds per wall second per process, thread and stage.

How it measures (``teletouch bench cpu``):

1. :func:`lab.demo.orchestrator.run_demo` starts the demo's processes as usual (relay, the
   link emulators when a profile is given, the remote and the local station).
2. Once the relay has forwarded data both ways, and after a warm-up, a window of
   ``window_s`` seconds starts. At its start and end the CPU time (user + system) of every
   child process and of each of its threads is read from ``/proc/<pid>/task/<tid>/stat``:
   these per-process and per-thread figures are exact (kernel accounting). So are the
   context switches (``.../status``: voluntary + involuntary), reported per second: each
   costs tens of microseconds of CPU on this machine (``benchmarks/bench_wakeup_cost.py``).
   And so is the time each thread spent on a run queue, runnable but not running
   (``.../schedstat``'s second figure, ``run_delay``: from a wake-up or a preemption until
   it runs), summed over a process' threads and divided by the window
   (``waiting_threads``): the mean number of its threads waiting to run at any instant.
   It is the scheduler's part of the processes' latencies; a wait for the GIL or for I/O
   is a sleep, not counted there, and neither is time the host steals.
3. During the window every process is sampled by py-spy (``--nonblocking``: the process is
   never paused; ``--idle --threads``: every thread, every sample). py-spy's idle detection
   is unreliable in this container (a sleeping thread is reported as running), so a sample
   is judged idle by its innermost Python line instead: a line that calls a blocking wait
   (``sleep(``, ``wait(``, ``select(``, ``poll(``, ``recv(`` ... see :data:`_WAIT_CALL`).
   Each busy sample is given a stage by the files on its stack (:data:`STAGE_RULES`); a
   thread's exact CPU time is then split over stages in proportion to its busy samples.
   The stage split is therefore an estimate (sampling error ~ 1/sqrt(samples), and work
   in C that releases the thread between Python lines is charged to the line that called
   it), while each process' and thread's total is exact.

Simulated hardware (the ArrayTac plant and firmware emulator, the encoder board and the
scripted operator, the sensor and phantom simulation, the simulated arm, the link
emulators) is classified as ``sim:`` stages so that the product's own cost stands apart.
"""

from __future__ import annotations

import contextlib
import json
import linecache
import logging
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter, defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lab.demo import DEFAULT_DISPLAY
from shared.errors import ConfigError, TeleTouchError

__all__ = ["STAGE_RULES", "CpuBenchSettings", "CpuSnapshot", "classify_stack",
           "demo_processes", "parse_raw_profile", "pyspy_path", "run_cpu_bench", "window_drops"]

log = logging.getLogger(__name__)

_CLK_TCK = os.sysconf("SC_CLK_TCK")

#: (stage, path fragments): the first rule with a fragment in a frame's file wins. ``sim:``
#: stages win over product stages anywhere on the stack (work done for the simulation);
#: among product stages the innermost frame decides.
STAGE_RULES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("sim: ArrayTac plant + firmware", ("local_site/arraytac_sim/", "local_site/display/emulator",
                                        "local_site/display/firmware", "local_site/display/sim")),
    ("sim: platform board + operator", ("local_site/platform/sim", "local_site/platform/motion")),
    ("sim: sensor + phantom", ("remote_site/sensor/simulator", "remote_site/sensor/shading",
                               "remote_site/sensor/shapes", "remote_site/sensor/sim_",
                               "remote_site/phantom/")),
    ("sim: arm", ("remote_site/arm/sim",)),
    ("sim: link emulator", ("lab/linkemu",)),
    ("bench/profiler", ("lab/bench/",)),
    ("platform read", ("local_site/agent/platform_reader", "local_site/platform/")),
    ("render", ("local_site/render/", "local_site/scenes/")),
    ("display drive", ("local_site/display/", "local_site/agent/display_loop",
                       "local_site/agent/period_stats", "/can/")),
    ("recording", ("local_site/recording",)),
    ("motion-to-touch ledger", ("shared/motion_to_touch", "shared/ledger")),
    ("reconstruction", ("remote_site/reconstruction/",)),
    ("stiffness", ("remote_site/stiffness/", "remote_site/agent/stiffness_stage")),
    ("tactile frame assembly", ("remote_site/tactile",)),
    ("arm control + safety", ("remote_site/arm/",)),
    ("sensor read (driver)", ("remote_site/sensor/",)),
    ("encode/validate", ("shared/protocol/codec", "shared/protocol/messages",
                         "shared/protocol/fields", "shared/protocol/tactile_codec", "msgpack")),
    ("relay forwarding", ("relay_server/", "shared/protocol/peer_session",
                          "shared/protocol/queues", "shared/protocol/ratelimit")),
    ("link client (uplink/downlink)", ("shared/client", "shared/transport",
                                       "shared/protocol/", "websockets/")),
    ("station control", ("local_site/agent/", "remote_site/agent/", "local_site/", "remote_site/")),
    ("event loop / runtime", ("asyncio/", "threading", "selectors", "logging/", "shared/")),
)
_SIM_PREFIXES = ("sim:", "bench/")
_FRAME = re.compile(r"^(?P<func>.*) \((?P<file>[^()]*):(?P<line>\d+)\)$")
#: a leaf line calling one of these is waiting, not computing
_WAIT_CALL = re.compile(r"\b(sleep|wait|wait_for|select|poll|recv|recv_into|recvfrom|accept|"
                        r"join|acquire|_recv|read|readinto|run_forever|run_until_complete|"
                        r"to_thread|communicate|asyncio\.run)\(|\.get\(block=True\)")


@dataclass(frozen=True)
class CpuBenchSettings:
    """What to run: the demo's scene and link, the warm-up and the measured window."""

    scene: str = "breast"
    link: str | None = None
    warmup_s: float = 3.0
    window_s: float = 12.0
    rate_hz: int = 200
    max_duration_s: float = 100.0
    profile: bool = True
    keep_record: Path | None = None
    display: str = DEFAULT_DISPLAY
    extra_local_args: tuple[str, ...] = ()
    extra_remote_args: tuple[str, ...] = ()


@dataclass
class CpuSnapshot:
    """CPU seconds of every thread of every watched process at one instant."""

    wall_s: float
    threads: dict[int, dict[int, float]] = field(default_factory=dict)  # pid -> tid -> cpu s
    #: pid -> tid -> context switches so far (voluntary + involuntary): each is a wake-up
    #: of the thread or a preemption, and on this machine each costs tens of us of CPU
    #: (``benchmarks/bench_wakeup_cost.py``)
    switches: dict[int, dict[int, int]] = field(default_factory=dict)
    #: pid -> tid -> seconds on a run queue so far (``schedstat``; a thread without the
    #: figure is left out)
    waits: dict[int, dict[int, float]] = field(default_factory=dict)
    #: the machine's stolen CPU seconds so far (``/proc/stat``: this VM's CPUs ready to
    #: run while the host ran something else); None where the file cannot be read
    steal_s: float | None = None


def steal_s(path: str = "/proc/stat") -> float | None:
    """The machine's stolen CPU seconds so far (``/proc/stat``'s first line, its 8th
    figure); None where it cannot be read. Only steal: the file's busy figures are sampled
    at the timer tick, which a 1 kHz thread can dodge (the machine's busy time came out
    0.05-0.11 cores below the demo's own exact thread times in two runs)."""
    try:
        with open(path) as f:
            fields = [int(v) for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    return fields[7] / _CLK_TCK if len(fields) >= 8 else None


def stolen_cores(start: CpuSnapshot, end: CpuSnapshot) -> float | None:
    """The CPU the host took from this machine between two snapshots, in cores (stolen CPU
    seconds per wall second), which the load average does not tell; None when either
    snapshot could not read it or no time passed."""
    wall = end.wall_s - start.wall_s
    if start.steal_s is None or end.steal_s is None or wall <= 0:
        return None
    return (end.steal_s - start.steal_s) / wall


#: the reference workloads' sizes: a fixed interpreter loop, and an array pass larger than
#: any cache here (3 x 32 MB)
_REFERENCE_LOOP = 20_000
_REFERENCE_BYTES = 32 * 2**20


def reference_speed(rounds: int = 7) -> dict[str, float]:
    """How fast this machine runs two fixed workloads now, by this thread's CPU time (so a
    wait for the CPU does not count; the caches, memory and clock shared with other jobs
    do): ``python_us``, CPU us per pass of a fixed interpreter loop (dict and integer
    work), and ``memory_gb_s``, GB/s of ``numpy.add`` over arrays larger than the caches
    (two read, one written); the median of ``rounds`` passes each. ``bench cpu`` runs it
    just before the demo starts and just after it ends, when this process has the machine
    to itself but for other jobs: when two runs of the same code differ, it tells whether
    the machine itself was slower."""
    import numpy as np

    if rounds < 1:
        raise ValueError("rounds must be >= 1")
    loop_us, gb_s = [], []
    a = np.ones(_REFERENCE_BYTES // 8)
    b, out = a.copy(), np.empty_like(a)
    for _ in range(rounds):
        table: dict[int, int] = {}
        t0 = time.thread_time()
        for i in range(_REFERENCE_LOOP):
            table[i & 255] = table.get(i & 127, 0) + i
        t1 = time.thread_time()
        np.add(a, b, out=out)
        t2 = time.thread_time()
        loop_us.append((t1 - t0) * 1e6)
        gb_s.append(3 * _REFERENCE_BYTES / 1e9 / max(t2 - t1, 1e-9))
    return {"python_us": statistics.median(loop_us), "memory_gb_s": statistics.median(gb_s)}


def _task_figures(pid: int, tid: int) -> tuple[float, int, float | None] | None:
    """A thread's CPU seconds (utime + stime, ``stat``), context switches (voluntary +
    involuntary, ``status``) and seconds on a run queue (``schedstat``; None where it is not
    kept) so far; None once it is gone."""
    base = f"/proc/{pid}/task/{tid}/"
    try:
        with open(base + "stat") as f:
            stat = f.read()
        with open(base + "status") as f:
            status = f.read()
    except OSError:
        return None
    fields = stat[stat.rfind(")") + 2:].split()
    cpu = (int(fields[11]) + int(fields[12])) / _CLK_TCK
    return cpu, sum(int(m) for m in _SWITCHES.findall(status)), _run_queue_wait_s(base)


def _run_queue_wait_s(task_dir: str) -> float | None:
    """Seconds the task waited on a run queue so far (``schedstat``: time on a CPU, time
    on a run queue, time slices; ns, ns, count); None where it cannot be read, or reads
    all zeros (what a kernel that keeps no such figures writes; a task that never ran)."""
    try:
        with open(task_dir + "schedstat") as f:
            fields = [int(v) for v in f.read().split()[:3]]
    except (OSError, ValueError):
        return None
    return None if len(fields) < 2 or not any(fields) else fields[1] / 1e9


_SWITCHES = re.compile(r"^(?:non)?voluntary_ctxt_switches:\s+(\d+)$", re.MULTILINE)


def snapshot(pids: list[int]) -> CpuSnapshot:
    """Read the CPU time and context switches of every thread of ``pids`` now."""
    snap = CpuSnapshot(time.perf_counter(), steal_s=steal_s())
    for pid in pids:
        per: dict[int, float] = {}
        sw: dict[int, int] = {}
        waits: dict[int, float] = {}
        try:
            tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
        except OSError:
            continue
        for tid in tids:
            figures = _task_figures(pid, tid)
            if figures is not None:
                per[tid], sw[tid], wait = figures
                if wait is not None:
                    waits[tid] = wait
        snap.threads[pid] = per
        snap.switches[pid] = sw
        snap.waits[pid] = waits
    return snap


#: the simulated encoder board's own process (``--platform sim-process``), a child of the
#: local station
_SIM_BOARD_MODULE = "local_site.platform.sim_process"
#: the local station's platform reader process (``local.agent.platform_process``)
_PLATFORM_PROCESS_MODULE = "local_site.agent.platform_child"
#: the local station's display loop process (``local.agent.render_loop = "process"``)
_DISPLAY_PROCESS_MODULE = "local_site.agent.display_child"


#: the demo's processes that are simulated hardware as a whole: their stage
_SIM_PROCESSES = {"sim-board": "sim: platform board + operator",
                  "board": "sim: ArrayTac plant + firmware"}


def _processes() -> Iterator[tuple[int, int, list[str]]]:
    """(pid, parent pid, argv) of every process that can be read."""
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                stat = f.read()
            ppid = int(stat[stat.rfind(")") + 2:].split()[1])
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                argv = f.read().decode(errors="replace").split("\0")
        except (OSError, ValueError):
            continue
        yield int(entry), ppid, argv


def demo_processes(parent: int) -> dict[int, str]:
    """Child processes of ``parent`` running ``lab.cli`` (pid -> subcommand; ``board``: the
    emulated ArrayTac drive board of ``--display board-process``), and the local station's
    simulated encoder board process when it has one (``sim-board``) and its platform reader
    process (``platform``, with ``local.agent.platform_process``), and its display loop
    process (``display``, with ``local.agent.render_loop = "process"``)."""
    out: dict[int, str] = {}
    table = list(_processes())
    for pid, ppid, argv in table:
        if ppid == parent and "lab.cli" in argv:
            rest = argv[argv.index("lab.cli") + 1:]
            cmd = next((a for a in rest if a in ("relay", "link", "local", "remote", "board")),
                       "?")
            out[pid] = cmd
    local = {p for p, c in out.items() if c == "local"}
    readers = {pid: "platform" for pid, ppid, argv in table
               if ppid in local and _PLATFORM_PROCESS_MODULE in argv}
    readers.update({pid: "display" for pid, ppid, argv in table
                    if ppid in local and _DISPLAY_PROCESS_MODULE in argv})
    boards = {pid: "sim-board" for pid, ppid, argv in table
              if (ppid in local or ppid in readers) and _SIM_BOARD_MODULE in argv}
    names: dict[int, str] = {**boards, **readers}
    links = sorted(p for p, c in out.items() if c == "link")
    for pid, cmd in out.items():
        # the demo runs one emulator for both legs; two (older runs) are told apart by pid
        names[pid] = (f"link-{'local' if pid == links[0] else 'remote'}"
                      if cmd == "link" and len(links) > 1 else cmd)
    return names


def classify_stack(frames: list[tuple[str, str, int]]) -> str:
    """The stage of one sample: ``frames`` are (function, file, line), outermost first."""
    product: str | None = None
    for _func, file, _line in frames:
        norm = file.replace("\\", "/")
        for stage, fragments in STAGE_RULES:
            if any(fr in norm for fr in fragments):
                if stage.startswith(_SIM_PREFIXES):
                    return stage
                product = stage  # innermost product match wins
                break
    return product or "other (interpreter, libraries)"


def _is_wait(frames: list[tuple[str, str, int]]) -> bool:
    if not frames:
        return True
    _func, file, line = frames[-1]
    text = linecache.getline(file, line)
    return bool(text) and _WAIT_CALL.search(text) is not None


def _raw_samples(text: str
                 ) -> Iterator[tuple[int, str | None, list[tuple[str, str, int]], int]]:
    """py-spy ``--format raw --threads`` lines -> (tid, thread name or None, frames outermost
    first as (function, file, line), sample count); lines of another shape are skipped."""
    for raw in text.splitlines():
        stack_s, _, count_s = raw.strip().rpartition(" ")
        if not count_s.isdigit():
            continue
        parts = stack_s.split(";")
        head = re.match(r"thread \((?:0x)?([0-9a-fA-F]+)\)(?::\s*(.*))?", parts[0])
        if head is None:
            continue
        tid = int(head.group(1), 16 if parts[0].startswith("thread (0x") else 10)
        frames = [(m["func"], m["file"], int(m["line"]))
                  for m in map(_FRAME.match, parts[1:]) if m]
        yield tid, head.group(2), frames, int(count_s)


def parse_raw_profile(text: str) -> dict[int, Counter[str]]:
    """py-spy ``--format raw --threads`` output -> tid -> Counter(stage or ``idle``)."""
    out: dict[int, Counter[str]] = defaultdict(Counter)
    for tid, _name, frames, count in _raw_samples(text):
        out[tid]["idle" if _is_wait(frames) else classify_stack(frames)] += count
    return out


def thread_roots(text: str) -> dict[int, str]:
    """py-spy ``--format raw --threads`` output -> tid -> the thread's name as py-spy saw it
    (``thread (101): MainThread``) and the outermost function below the threading bootstrap
    in most of its samples (``arm-watchdog: loop (safety.py)``)."""
    roots: dict[int, Counter[str]] = defaultdict(Counter)
    for tid, name, frames, count in _raw_samples(text):
        root = next((f"{func} ({Path(file).name})" for func, file, _ in frames
                     if not file.endswith("threading.py")), "?")
        roots[tid][f"{name}: {root}" if name else root] += count
    return {tid: c.most_common(1)[0][0] for tid, c in roots.items() if c}


def _top_functions(text: str, n: int = 12) -> list[tuple[str, int]]:
    """Busy samples per innermost project function (self time), most first."""
    c: Counter[str] = Counter()
    for raw in text.splitlines():
        stack_s, _, count_s = raw.strip().rpartition(" ")
        if not count_s.isdigit():
            continue
        frames = []
        for p in stack_s.split(";")[1:]:
            m = _FRAME.match(p)
            if m:
                frames.append((m["func"], m["file"], int(m["line"])))
        if not frames or _is_wait(frames):
            continue
        # innermost frame in the repository (library frames are charged to their caller)
        own = [f for f in frames if any(d in f[1] for d in ("local_site/", "remote_site/",
                                                           "relay_server/", "shared/", "lab/"))]
        func, file, _ = (own or frames)[-1]
        short = file.split("/wt/")[-1].split("/", 1)[-1] if "/wt/" in file else file
        c[f"{func} ({short.rsplit('site-packages/', 1)[-1]})"] += int(count_s)
    return c.most_common(n)


@dataclass
class _Window:
    settings: CpuBenchSettings
    workdir: Path
    pyspy: str | None
    ready_at: float | None = None
    start: CpuSnapshot | None = None
    end: CpuSnapshot | None = None
    names: dict[int, str] = field(default_factory=dict)
    spies: dict[int, subprocess.Popen[bytes]] = field(default_factory=dict)
    local_loop: dict[str, Any] | None = None
    #: the relay's drop counters (``/status``, per direction) at the window's start and end
    drops: list[dict[str, Any]] = field(default_factory=list)

    def progress(self, _elapsed: float, status: dict[str, Any] | None) -> None:
        now = time.perf_counter()
        session = ((status or {}).get("sessions", {}).get("demo", {}) or {})
        if self.ready_at is None:
            fwd = session.get("forwarded", {})
            if fwd and all((v or 0) > 0 for v in fwd.values()) and len(fwd) == 2:
                self.ready_at = now
            return
        if self.start is None and now - self.ready_at >= self.settings.warmup_s:
            self.names = demo_processes(os.getpid())
            self.start = snapshot(list(self.names))
            self.drops = [session["drops"]] if session.get("drops") else []
            if self.pyspy and self.settings.profile:
                for pid, name in self.names.items():
                    self.spies[pid] = subprocess.Popen(
                        [self.pyspy, "record", "--pid", str(pid), "--duration",
                         str(max(1, int(self.settings.window_s) - 1)), "--rate",
                         str(self.settings.rate_hz), "--format", "raw", "--threads", "--idle",
                         "--nonblocking", "--full-filenames", "-o",
                         str(self.workdir / f"profile-{name}.txt")],
                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            return
        if self.start is not None and self.end is None \
                and now - self.start.wall_s >= self.settings.window_s:
            self.end = snapshot(list(self.names))
            if self.drops and session.get("drops"):
                self.drops.append(session["drops"])
            # the window is measured: stop the operator early (the station exits 0 on
            # SIGTERM after writing its summary), the demo then finishes as usual
            for pid, name in self.names.items():
                if name == "local":
                    with contextlib.suppress(OSError):
                        os.kill(pid, signal.SIGTERM)


def pyspy_path() -> str | None:
    """py-spy on PATH or beside this interpreter (None: not installed)."""
    found = shutil.which("py-spy")
    if found:
        return found
    candidate = Path(sys.executable).parent / "py-spy"
    return str(candidate) if candidate.exists() else None


def run_cpu_bench(settings: CpuBenchSettings) -> dict[str, Any]:
    """Run the demo once, measure the window, and return the figures (JSON-able).

    Raises:
        ConfigError: bad settings, or the demo ended before the window did.
        DemoError: the demo failed.
    """
    from lab.demo.orchestrator import DemoConfig, run_demo

    if settings.window_s <= 0 or settings.warmup_s < 0:
        raise ConfigError("window_s must be > 0 and warmup_s >= 0")
    workdir = Path(tempfile.mkdtemp(prefix="teletouch-cpu-"))
    pyspy = pyspy_path() if settings.profile else None
    win = _Window(settings, workdir, pyspy)
    reference = {"before": reference_speed()}
    load_start = os.getloadavg()
    try:
        try:
            report = run_demo(DemoConfig(scene=settings.scene, link=settings.link,
                                         max_duration_s=settings.max_duration_s,
                                         display=settings.display,
                                         workdir=workdir / "demo",
                                         extra_local_args=settings.extra_local_args,
                                         extra_remote_args=settings.extra_remote_args),
                              progress=win.progress)
        except TeleTouchError as err:
            # the operator was stopped after the window: the palpation analysis may find
            # too little; the stations' summaries are all this benchmark needs
            summary = workdir / "demo" / "local_summary.json"
            if win.end is None or not summary.exists():
                raise
            local = json.loads(summary.read_text())
            remote_path = workdir / "demo" / "remote_summary.json"
            report = {"local": local, "latency_ms": local.get("motion_to_touch_ms", {}),
                      "demo_error": str(err), "remote": json.loads(remote_path.read_text())
                      if remote_path.exists() else None}
        for spy in win.spies.values():
            try:
                spy.wait(timeout=30)
            except subprocess.TimeoutExpired:
                spy.kill()
        if win.start is None or win.end is None:
            raise ConfigError("the demo ended before the measured window did; lower "
                              "--window-s or --warmup-s (the default operator runs ~25 s)")
        if settings.keep_record is not None:
            record = workdir / "demo" / "local.mcap"
            if record.exists():
                shutil.copyfile(record, settings.keep_record)
            else:  # the figures are still worth keeping
                log.warning("--keep-record: the demo left no recording (%s)", record)
        reference["after"] = reference_speed()
        return {**_figures(win, report, load_start, pyspy), "reference": reference}
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


def _figures(win: _Window, report: dict[str, Any], load_start: tuple[float, float, float],
             pyspy: str | None) -> dict[str, Any]:
    assert win.start is not None and win.end is not None
    wall = win.end.wall_s - win.start.wall_s
    processes: dict[str, Any] = {}
    threads: dict[str, list[dict[str, Any]]] = {}
    stages: dict[str, dict[str, float]] = defaultdict(dict)
    top: dict[str, list[tuple[str, int]]] = {}
    for pid, name in sorted(win.names.items(), key=lambda kv: kv[1]):
        t0, t1 = win.start.threads.get(pid, {}), win.end.threads.get(pid, {})
        thread_cpu = {tid: t1[tid] - t0.get(tid, 0.0) for tid in t1}
        s0, s1 = win.start.switches.get(pid, {}), win.end.switches.get(pid, {})
        thread_sw = {tid: (s1[tid] - s0.get(tid, 0)) / wall for tid in s1}
        w0, w1 = win.start.waits.get(pid, {}), win.end.waits.get(pid, {})
        # threads seen at both ends, or born in the window (from 0); a thread that ended
        # inside it is lost, as its CPU time is
        thread_wait = {tid: (w1[tid] - w0.get(tid, 0.0)) / wall for tid in w1
                       if tid in w0 or tid not in t0}
        total = sum(thread_cpu.values())
        processes[name] = {"cores": total / wall, "threads": len(t1),
                           "switches_per_s": sum(thread_sw.values())}
        if thread_wait:
            processes[name]["waiting_threads"] = sum(thread_wait.values())
        path = win.workdir / f"profile-{name}.txt"
        text = path.read_text() if path.exists() else ""
        per_thread = parse_raw_profile(text) if text else {}
        roots = thread_roots(text) if text else {}
        threads[name] = sorted(({"tid": tid, "runs": roots.get(tid, "?"), "cores": cpu / wall,
                                 "switches_per_s": thread_sw.get(tid),
                                 "waiting_threads": thread_wait.get(tid)}
                                for tid, cpu in thread_cpu.items()),
                               key=lambda t: -float(t["cores"]))
        if name.startswith("link") or name in _SIM_PROCESSES:
            stages[name]["sim: link emulator" if name.startswith("link")
                         else _SIM_PROCESSES[name]] = total / wall
            top[name] = _top_functions(text) if text else []
            continue
        unattributed = 0.0
        for tid, cpu in thread_cpu.items():
            counts = per_thread.get(tid)
            busy = {s: c for s, c in (counts or {}).items() if s != "idle"}
            n = sum(busy.values())
            if not n:
                unattributed += cpu
                continue
            for stage, c in busy.items():
                stages[name][stage] = stages[name].get(stage, 0.0) + cpu * c / n / wall
        if unattributed > 0:
            stages[name]["(threads without busy samples)"] = unattributed / wall
        top[name] = _top_functions(text) if text else []
    local = report.get("local", {})
    stolen = stolen_cores(win.start, win.end)
    return {
        "wall_s": wall, "nproc": os.cpu_count(), "load_start": load_start,
        "host": None if stolen is None else {"steal_cores": stolen},
        "load_end": os.getloadavg(), "profiler": "py-spy" if pyspy else "none",
        "processes": processes, "threads": threads,
        "stages": {k: dict(v) for k, v in stages.items()},
        "top": top, "display_loop": local.get("display_loop", {}),
        "latency_ms": report.get("latency_ms", {}),
        "latency_tail_ms": local.get("motion_to_touch_tail_ms"),
        "frames_received": report.get(
            "frames_received"), "demo_error": report.get("demo_error"),
        "remote_frames": (report.get("remote") or {}).get("frames"),
        "remote_platform_states": (report.get("remote") or {}).get("platform_states"),
        "remote_latency_ms": (report.get("remote") or {}).get("latency_ms"),
        "remote_elapsed_s": (report.get("remote") or {}).get("elapsed_s"),
        "tactile_codec": local.get("tactile_codec"),
        # frames replaced on the local side before the pins showed them (the session's, not
        # the window's): in the hand-overs to the loop, and unread in the link's inbox (the
        # inbox's count includes arm_state)
        "local_frames_superseded": local.get("frames_superseded"),
        "local_inbox_replaced": (local.get("link") or {}).get("stale_dropped_rx"),
        "relay_drops": window_drops(win.drops),
        "settings": {k: v for k, v in vars(win.settings).items()},
    }


def window_drops(drops: list[dict[str, Any]]) -> dict[str, dict[str, int]] | None:
    """The relay's drops over the window, per direction and reason (end minus start of its
    ``/status`` counters); None without both readings (a status poll that failed or did not
    show the session is no reading, not "no drops")."""
    if len(drops) != 2 or not all(drops):
        return None
    start, end = drops
    return {d: {k: int(v) - int((start.get(d) or {}).get(k, 0)) for k, v in counts.items()}
            for d, counts in end.items() if isinstance(counts, dict)}


def to_json(figures: dict[str, Any]) -> str:
    """The figures as indented JSON."""
    return json.dumps(figures, indent=1, default=str)
