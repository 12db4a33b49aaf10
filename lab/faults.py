"""The fault suite's harness: real processes, injected faults, figures measured from outside.

:class:`FaultRig` starts, as separate processes on 127.0.0.1 (as ``teletouch demo`` does):
``teletouch relay``; a ``teletouch link`` emulator on each leg (``local`` = local station <->
relay, ``remote`` = remote station <-> relay) that starts a blackhole (or, with
``--outage-close``, a reset) on SIGUSR1; ``teletouch remote`` (simulated arm, sensor and
phantom) and ``teletouch local`` (simulated platform on an endless raster, simulated display),
both through :mod:`lab.faults_probe`, each writing ``--summary-json``; optionally two CPU
burners (``python -c "while True: pass"``). With ``board_process=True`` the local station's
display is not simulated inside it: ``teletouch board`` (:mod:`lab.board`) runs the emulated
drive board as a process of its own, reached with ``--display socket://127.0.0.1:PORT``, and
its event file (:class:`BoardLog`) is the truth of what the pins did, so a frozen station's
display still goes safe, by the board's own watchdog.

Faults (:meth:`FaultRig.inject`): the relay SIGKILLed and restarted on the same ports after a
pause; a blackhole or a reset of either leg; a station SIGKILLed and restarted; a station
SIGSTOPped, then SIGCONTed; a step of a station's wall clock. The harness notes the monotonic
time of each injection and of the recovery (relay answering again, outage over, SIGCONT,
station restarted).

Measured per injection and over the run (:func:`analyse`), from the probe files (the host's
monotonic clock is shared by all processes; on one host the senders' wall-clock stamps are the
true time, less any clock step the harness injected):

* ``halt_ms``: arm halt minus the last command the arm accepted before it (every halt);
* ``safe_ms``: display safe state minus the last fresh frame accepted before it (every entry;
  with the board process, the board's safe-state entries, and the station's own in
  ``station_safe_ms``);
* ``fresh_after_ms``: first fresh frame rendered after the recovery minus the recovery;
* ``stale_executed``: commands executed older than ``command_bound_ms`` (true age);
* ``stale_rendered``: frames rendered older than ``frame_bound_ms`` (true age at render);
* station exits (code) and the stations' own summary counters.

``scenarios()`` lists the suite; ``run_scenario`` runs one; ``lab/bench/faults.py`` runs
them all and writes the table; ``tests/faults/`` runs a few short ones.
"""

from __future__ import annotations

import bisect
import collections
import contextlib
import functools
import json
import logging
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lab.child import module_argv
from lab.demo.orchestrator import free_port, relay_status

__all__ = ["BoardLog", "FaultRig", "FaultSpec", "ProbeLog", "RigError", "Scenario", "analyse",
           "run_scenario", "scenarios"]

log = logging.getLogger(__name__)

SESSION = "faults"
#: an endless raster pressed 3 mm into the phantom (see lab/demo/orchestrator.py)
MOTION = ("raster:x0=1,x1=59,y0=1,y1=59,spacing=4,speed=45,z=10,press_depth=0,"
          "press_every=0,pause=1,loop=1")
#: "the flow is back" for the harness's waits: a frame rendered at most this old (a loaded
#: machine may never render one within the 100 ms bound; the figures use the strict bound)
#: the local station's frame-age bound (``max_frame_age_s`` default)
FRAME_BOUND_MS = 150.0
FLOW_BOUND_MS = 1000.0
FAULT_KINDS = ("none", "relay_kill", "blackhole", "reset", "kill", "stop", "clock_step")


class RigError(RuntimeError):
    """A rig process failed to start or the rig did not reach a steady state in time."""


@dataclass(frozen=True)
class FaultSpec:
    """One kind of fault.

    Attributes:
        kind: one of ``FAULT_KINDS``.
        target: ``local`` or ``remote`` (the leg or the station); unused for the relay;
            ``platform`` (``kill`` and ``stop`` only): the local station's platform process
            (``--platform-process``), which the station itself restarts.
        duration_s: how long the relay is down / the leg is cut / the station is stopped or
            killed before its restart; for ``clock_step`` the step in seconds (signed).
    """

    kind: str = "none"
    target: str = "remote"
    duration_s: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault kind {self.kind!r}")
        if self.target not in ("local", "remote", "platform"):
            raise ValueError(f"fault target must be local, remote or platform, got "
                             f"{self.target!r}")
        if self.target == "platform" and self.kind not in ("kill", "stop"):
            raise ValueError(f"the platform process can only be killed or stopped, not "
                             f"{self.kind!r}")


@dataclass(frozen=True)
class Scenario:
    """A named fault, how often it is injected, and what runs beside it.

    Attributes:
        name: label in the results table.
        fault: the fault.
        cpu_burners: CPU-bound processes started beside the stations.
        observe_s: for ``none`` and ``clock_step``: how long to watch after the injection.
    """

    name: str
    fault: FaultSpec
    cpu_burners: int = 0
    observe_s: float = 10.0


def scenarios(*, long: bool = True) -> list[Scenario]:
    """The whole suite (``long=False`` leaves out the 20 s and 60 s outages)."""
    out = [Scenario("baseline (no fault)", FaultSpec("none"), observe_s=15.0),
           Scenario("2 CPU burners, no fault", FaultSpec("none"), cpu_burners=2, observe_s=15.0)]
    out += [Scenario(f"relay SIGKILL, back after {d:g} s", FaultSpec("relay_kill", "remote", d))
            for d in (0.5, 2.0, 10.0)]
    for kind, label in (("blackhole", "blackhole"), ("reset", "reset")):
        for leg in ("local", "remote"):
            for d in (0.2, 2.0, 20.0, 60.0):
                if d > 2.0 and not long:
                    continue
                out.append(Scenario(f"{label} {d:g} s, {leg} leg", FaultSpec(kind, leg, d)))
    for role in ("local", "remote"):
        out.append(Scenario(f"{role} station SIGKILL, restarted after 0.5 s",
                            FaultSpec("kill", role, 0.5)))
        out.append(Scenario(f"{role} station SIGSTOP 3 s", FaultSpec("stop", role, 3.0)))
        out.append(Scenario(f"{role} clock +0.3 s step", FaultSpec("clock_step", role, 0.3),
                            observe_s=12.0))
    out.append(Scenario("platform process SIGKILL", FaultSpec("kill", "platform")))
    out.append(Scenario("platform process SIGSTOP 3 s", FaultSpec("stop", "platform", 3.0)))
    out.append(Scenario("relay SIGKILL 0.5 s + 2 CPU burners",
                        FaultSpec("relay_kill", "remote", 0.5), cpu_burners=2))
    out.append(Scenario("blackhole 2 s, remote leg + 2 CPU burners",
                        FaultSpec("blackhole", "remote", 2.0), cpu_burners=2))
    return out


# ---------------------------------------------------------------------------- probe files


def _new_lines(path: Path, offset: int) -> tuple[list[list[str]], int]:
    """The complete lines of ``path`` after byte ``offset``, split; and the new offset (a
    partial last line waits for the next call; a missing file is empty)."""
    try:
        with open(path, "rb") as f:
            f.seek(offset)
            data = f.read()
    except FileNotFoundError:
        return [], offset
    end = data.rfind(b"\n") + 1
    lines = [raw.split() for raw in data[:end].decode(errors="replace").splitlines()]
    return [p for p in lines if len(p) >= 2], offset + end


@dataclass
class BoardLog:
    """Events of the board process (``teletouch board --events``), read incrementally."""

    path: Path
    safe: list[tuple[float, str]] = field(default_factory=list)  # (mono, reason)
    resumed: list[float] = field(default_factory=list)
    applied: list[tuple[float, int]] = field(default_factory=list)  # (mono, command seq)
    refused: list[float] = field(default_factory=list)  # commands refused by the latch
    _offset: int = 0

    def poll(self) -> None:
        """Read the lines written since the last call."""
        lines, self._offset = _new_lines(self.path, self._offset)
        for p in lines:
            mono = float(p[1])
            if p[0] == "S" and len(p) == 3:
                self.safe.append((mono, p[2]))
            elif p[0] == "U":
                self.resumed.append(mono)
            elif p[0] == "R" and len(p) == 3:
                self.applied.append((mono, int(p[2])))
            elif p[0] == "X":
                self.refused.append(mono)

    def safe_at(self, t: float) -> bool:
        """The pins were in the safe state at ``t`` (the last change before it entered it)."""
        entered = [m for m, _ in self.safe if m <= t]
        left = [m for m in self.resumed if m <= t]
        return bool(entered) and (not left or entered[-1] >= left[-1])


@dataclass
class ProbeLog:
    """Events of one station process, read incrementally from its probe file."""

    path: Path
    role: str
    instance: int
    accepted: list[tuple[float, int]] = field(default_factory=list)  # (mono, ts_us)
    rendered: list[tuple[float, int]] = field(default_factory=list)
    #: pin commands sent while their frame turned stale, withdrawn at once (mono, ts_us)
    withdrawn: list[tuple[float, int]] = field(default_factory=list)
    #: pin command frames sent (mono before the send, command seq, newest frame's ts_us)
    sent: list[tuple[float, int, int]] = field(default_factory=list)
    safe: list[tuple[float, str]] = field(default_factory=list)
    resumed: list[float] = field(default_factory=list)
    commands: list[tuple[float, int, bool, float]] = field(default_factory=list)
    halts: list[tuple[float, str]] = field(default_factory=list)
    steps: list[tuple[float, int]] = field(default_factory=list)
    _offset: int = 0

    def poll(self) -> None:
        """Read the lines written since the last call (a partial last line waits)."""
        lines, self._offset = _new_lines(self.path, self._offset)
        for p in lines:
            mono = float(p[1])
            kind = p[0]
            if kind in ("A", "R", "W") and len(p) == 4:
                {"A": self.accepted, "R": self.rendered,
                 "W": self.withdrawn}[kind].append((mono, int(p[3])))
            elif kind == "S" and len(p) == 3:
                self.safe.append((mono, p[2]))
            elif kind == "U":
                self.resumed.append(mono)
            elif kind == "P" and len(p) == 4:
                self.sent.append((mono, int(p[2]), int(p[3])))
            elif kind == "C" and len(p) == 5:
                self.commands.append((mono, int(p[2]), p[3] == "1", float(p[4])))
            elif kind == "H" and len(p) == 3:
                self.halts.append((mono, p[2]))
            elif kind == "K" and len(p) == 3:
                self.steps.append((mono, int(p[2])))


# ---------------------------------------------------------------------------- processes


@dataclass
class _Proc:
    name: str
    proc: subprocess.Popen[bytes]
    log_path: Path
    started_s: float

    def tail(self, lines: int = 12) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"


@dataclass
class Exit:
    """A station process that ended before the rig stopped it."""

    role: str
    instance: int
    code: int | None
    at_s: float


class FaultRig:
    """Relay, two link emulators, two probed stations (see the module docstring).

    Args:
        workdir: logs, probe files and summaries go here.
        outage_s: the legs' emulators cut the link this long on SIGUSR1 (None: 1 s).
        outage_reset: the cut is a reset (connections closed, new ones refused).
        cpu_burners: CPU-bound processes to start beside the stations.
        frame_rate_hz: the remote station's frame rate.
        board_process: run the local station's drive board as a process of its own
            (``teletouch board``) instead of the simulator inside the station.
        platform_process: the local station reads its platform in a process of its own
            (``teletouch local --platform-process``).
        render_loop: where the local station runs its display loop (``--render-loop``;
            ``process``: a process of its own, probed there too).
        board_nice: the board process's niceness increment (``--nice``; -10 by default: a
            real board's MCU is not slowed by the host's load; refused without the
            privilege, then the board runs at normal priority and its summary says so).
        python: the interpreter of every process.
    """

    def __init__(self, workdir: Path, *, outage_s: float | None = None,
                 outage_reset: bool = False, cpu_burners: int = 0,
                 frame_rate_hz: float = 60.0, board_process: bool = False,
                 platform_process: bool = False, render_loop: str = "thread",
                 board_nice: int = -10, lock_memory: bool = True,
                 python: str = sys.executable) -> None:
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.outage_s = outage_s or 1.0
        self.outage_reset = outage_reset
        self.cpu_burners = cpu_burners
        self.frame_rate_hz = frame_rate_hz
        self.board_process = board_process
        self.platform_process = platform_process
        self.render_loop = render_loop
        self.lock_memory = lock_memory
        self.board_nice = board_nice
        self.board: _Proc | None = None
        self.board_port = 0
        self.board_log: BoardLog | None = None
        self.python = python
        self.env = {**os.environ, "TELETOUCH_RELAY_SECRET": os.urandom(16).hex(),
                    "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
        self.ws_port = self.tcp_port = 0
        self.leg_ports: dict[str, int] = {}
        self.token = ""
        self.relay: _Proc | None = None
        self.relay_starts = 0
        self.links: dict[str, _Proc] = {}
        self.stations: dict[str, _Proc] = {}
        self.instances: dict[str, int] = {"local": 0, "remote": 0}
        self.probes: list[ProbeLog] = []
        self.exits: list[Exit] = []
        self.burners: list[subprocess.Popen[bytes]] = []
        #: (mono, offset_us) steps the harness injected, per station
        self.clock_steps: dict[str, list[tuple[float, int]]] = {"local": [], "remote": []}
        #: wall clock (us) minus monotonic clock (us) of this host, unfaked
        self.wall_minus_mono_us = time.time_ns() / 1e3 - time.monotonic() * 1e6
        self._all: list[_Proc] = []
        self._stopping = False
        self._killed: set[tuple[str, int]] = set()  # (role, instance) the harness SIGKILLed
        #: major page faults per process name, read at :meth:`stop`
        self.major_faults: dict[str, int] = {}
        self._faults_mark: dict[str, int] = {}

    # ------------------------------------------------------------------ processes

    def _spawn(self, name: str, args: list[str], *, module: str = "lab.cli",
               env: dict[str, str] | None = None) -> _Proc:
        log_path = self.workdir / f"{name}.log"
        cmd = [*module_argv(module, self.python), "--log-level", "INFO", *args]
        with open(log_path, "ab") as out:
            proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, cwd=self.workdir,
                                    env=env or self.env)
        p = _Proc(name, proc, log_path, time.monotonic())
        self._all.append(p)
        return p

    def _wait(self, predicate: Callable[[], bool], what: str, timeout_s: float,
              watch: tuple[_Proc, ...] = ()) -> None:
        deadline = time.monotonic() + timeout_s
        while not predicate():
            for p in watch:
                if p.proc.poll() is not None:
                    raise RigError(f"{p.name} exited with code {p.proc.returncode} while "
                                   f"waiting for {what}; its log ends with:\n{p.tail()}")
            if time.monotonic() > deadline:
                raise RigError(f"timed out after {timeout_s:.0f} s waiting for {what}")
            time.sleep(0.01)

    def start_relay(self, timeout_s: float = 30.0) -> float:
        """Start the relay on the rig's ports; return the monotonic time it answered."""
        self.relay_starts += 1
        self.relay = self._spawn(f"relay-{self.relay_starts}", [
            "relay", "--host", "127.0.0.1", "--port", str(self.ws_port),
            "--tcp-port", str(self.tcp_port)])
        self._wait(lambda: relay_status(self.ws_port) is not None, "the relay's /status",
                   timeout_s, (self.relay,))
        return time.monotonic()

    def start_station(self, role: str) -> _Proc:
        """Start (or restart) a station through the probe."""
        self.instances[role] += 1
        n = self.instances[role]
        probe = self.workdir / f"probe-{role}-{n}.txt"
        self.probes.append(ProbeLog(probe, role, n))
        env = {**self.env, "TELETOUCH_FAULT_PROBE": str(probe),
               "TELETOUCH_FAULT_CLOCK": str(self.workdir / f"clock-{role}.txt")}
        (self.workdir / f"clock-{role}.txt").write_text("0\n")
        url = f"ws://127.0.0.1:{self.leg_ports[role]}/"
        common = ["--relay", url, "--session", SESSION, "--token", self.token,
                  "--summary-json", str(self.workdir / f"summary-{role}-{n}.json")]
        if role == "remote":
            args = ["remote", *common, "--arm", "sim", "--sensor", "sim", "--phantom", "breast",
                    "--frame-rate-hz", f"{self.frame_rate_hz:g}"]
        else:
            display = (f"socket://127.0.0.1:{self.board_port}" if self.board_process
                       else "sim")
            args = ["local", *common, "--platform", "sim", "--display", display,
                    "--motion", MOTION, "--no-status",
                    "--platform-process" if self.platform_process else "--no-platform-process",
                    "--render-loop", self.render_loop]
        if not self.lock_memory:
            args.append("--no-lock-memory")
        p = self._spawn(f"{role}-{n}", args, module="lab.faults_probe", env=env)
        self.stations[role] = p
        return p

    def start_board(self, timeout_s: float = 60.0) -> _Proc:
        """Start the drive-board process on a free port and wait until it listens."""
        self.board_port = free_port()
        events = self.workdir / "board-events.txt"
        self.board_log = BoardLog(events)
        self.board = self._spawn("board", [
            "board", "--listen", f"127.0.0.1:{self.board_port}", "--events", str(events),
            "--summary-json", str(self.workdir / "summary-board.json"),
            "--nice", str(self.board_nice)])
        board = self.board
        self._wait(functools.partial(_logged, board, "board listening"), "the drive board",
                   timeout_s, (board,))
        return board

    def start(self, timeout_s: float = 90.0) -> None:
        """Start everything and wait until frames and commands flow (fresh)."""
        self.ws_port, self.tcp_port = free_port(), free_port()
        self.start_relay()
        self.token = subprocess.run(
            [*module_argv(python=self.python), "relay", "--print-token", SESSION], check=True,
            capture_output=True, text=True, timeout=60, env=self.env).stdout.strip()
        for leg in ("local", "remote"):
            port = free_port()
            self.leg_ports[leg] = port
            args = ["link", "--listen", f"127.0.0.1:{port}", "--target",
                    f"127.0.0.1:{self.ws_port}", "--profile", "lan", "--stats-interval", "3600",
                    "--outage-on-signal", f"{self.outage_s:g}"]
            if self.outage_reset:
                args.append("--outage-close")
            self.links[leg] = self._spawn(f"link-{leg}", args)
        for leg, p in self.links.items():
            self._wait(functools.partial(_logged, p, "listening"),
                       f"the {leg} leg's link emulator", timeout_s, (p,))
        for _ in range(self.cpu_burners):
            self.burners.append(subprocess.Popen(
                [self.python, "-c", "while True: pass"], stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        if self.board_process:
            self.start_board(timeout_s)
        self.start_station("remote")
        self.start_station("local")
        if not self.wait_flowing(0.0, timeout_s, FLOW_BOUND_MS):
            tails = "\n".join(f"--- {p.name}:\n{p.tail()}" for p in self._all)
            raise RigError(f"no frames rendered and commands executed within "
                           f"{timeout_s:.0f} s of the start:\n{tails}")

    # ------------------------------------------------------------------ observation

    def probe(self, role: str) -> ProbeLog:
        """The newest probe log of a station."""
        return [p for p in self.probes if p.role == role][-1]

    def poll(self) -> None:
        """Read new probe lines and note stations that exited (before :meth:`stop`)."""
        for p in self.probes:
            p.poll()
        if self.board_log is not None:
            self.board_log.poll()
        if self._stopping:
            return
        if self.board is not None and self.board.proc.poll() is not None \
                and not any(e.role == "board" for e in self.exits):
            self.exits.append(Exit("board", 1, self.board.proc.returncode, time.monotonic()))
        for role, proc in self.stations.items():
            code = proc.proc.poll()
            n = self.instances[role]
            if code is None or (role, n) in self._killed:
                continue
            if not any(e.role == role and e.instance == n for e in self.exits):
                self.exits.append(Exit(role, n, code, time.monotonic()))

    def true_wall_us(self, mono: float) -> float:
        """The unfaked wall clock (us) at a monotonic time of this host."""
        return mono * 1e6 + self.wall_minus_mono_us

    def offset_us(self, role: str, mono: float) -> int:
        """How far ``role``'s stamps had been moved by the clock steps at ``mono``: what
        the probe measured on the station's stamp clock when the step arrived (a station
        whose stamps do not follow the wall clock is not moved at all), else the step the
        harness injected."""
        measured = sorted(st for pr in self.probes if pr.role == role for st in pr.steps)
        steps = measured or self.clock_steps[role]
        off = 0
        for t, o in steps:
            if t <= mono:
                off = o
        return off

    def age_ms(self, sender: str, mono: float, ts_us: int) -> float:
        """True age at ``mono`` of a stamp on ``sender``'s (possibly stepped) wall clock."""
        return (self.true_wall_us(mono) - (ts_us - self.offset_us(sender, mono))) / 1e3

    def pin_ages(self, since: float = -math.inf, until: float = math.inf) \
            -> list[tuple[float, int, float | None]]:
        """What the board's pins showed (board process only, else empty): for each command
        the board applied in [since, until], ``(board mono, command seq, true age in ms of
        the touch it carried when the board applied it)``; the age is None when no command
        the station sent matches (the probe's ``P`` line with that sequence number, the
        latest one before the board applied it: sequence numbers restart at each connect)."""
        if self.board_log is None:
            return []
        by_seq: dict[int, list[tuple[float, int]]] = {}
        for p in self.probes:
            if p.role == "local":
                for mono, seq, ts in p.sent:
                    by_seq.setdefault(seq, []).append((mono, ts))
        for sends in by_seq.values():
            sends.sort()
        out: list[tuple[float, int, float | None]] = []
        for mono, seq in self.board_log.applied:
            if not since <= mono <= until:
                continue
            sends = by_seq.get(seq, [])
            i = bisect.bisect_right(sends, (mono, math.inf))
            ts = sends[i - 1][1] if i > 0 else -1
            out.append((mono, seq, self.age_ms("remote", mono, ts) if ts >= 0 else None))
        return out

    def sends_logged_until(self) -> float:
        """The newest local send the probe has logged (its ``P`` mono; -inf before any).

        The probe writes a ``P`` line only once ``send_command`` has returned, so the board
        may apply a command before its line exists (a station preempted right after its
        write). The display loop sends from one thread, one command at a time: every
        command written before this moment already has its line. Judge
        :meth:`pin_ages` up to here while the stations run; an applied command without a
        line *before* it is a send the probe truly missed.
        """
        return max((m for p in self.probes if p.role == "local" for m, _, _ in p.sent),
                   default=-math.inf)

    def fresh_render_after(self, t: float, bound_ms: float) -> float | None:
        """Monotonic time of the first frame rendered after ``t`` that was fresh."""
        for p in self.probes:
            if p.role != "local":
                continue
            for mono, ts in p.rendered:
                if mono >= t and self.age_ms("remote", mono, ts) <= bound_ms:
                    return mono
        return None

    def command_after(self, t: float) -> float | None:
        """Monotonic time of the first command the arm accepted after ``t``."""
        for p in self.probes:
            if p.role == "remote":
                for mono, _, acc, _ in p.commands:
                    if mono >= t and acc:
                        return mono
        return None

    def wait_flowing(self, since: float, timeout_s: float, bound_ms: float = 100.0) -> bool:
        """Wait until a fresh frame was rendered and a command executed after ``since``.

        Returns False on timeout (a station may have given up); raises nothing.
        """
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.poll()
            if (self.fresh_render_after(since, bound_ms) is not None
                    and self.command_after(since) is not None):
                return True
            time.sleep(0.02)
        return False

    def wait_steady(self, hold_s: float, timeout_s: float, bound_ms: float = 100.0) -> bool:
        """Wait until, for ``hold_s``, fresh frames were rendered and commands executed with
        no gap over 0.25 s (what a fault is injected into). False on timeout."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.poll()
            now = time.monotonic()
            frames = [m for m, ts in self.probe("local").rendered[-2000:]
                      if m >= now - hold_s and self.age_ms("remote", m, ts) <= bound_ms]
            cmds = [m for m, _, acc, _ in self.probe("remote").commands[-5000:]
                    if acc and m >= now - hold_s]
            if all(len(t) >= 2 and t[0] - (now - hold_s) <= 0.25 and now - t[-1] <= 0.25
                   and float(np.max(np.diff(t))) <= 0.25 for t in (frames, cmds)):
                return True
            time.sleep(0.05)
        return False

    # ------------------------------------------------------------------ faults

    def inject(self, fault: FaultSpec) -> tuple[float, float]:
        """Inject one fault; return (fault time, recovery time), monotonic seconds.

        Blocks until the recovery moment (relay restarted and answering, outage over,
        SIGCONT sent, station restarted); the observation continues in the caller.
        """
        kind, d = fault.kind, fault.duration_s
        t0 = time.monotonic()
        if kind == "none":
            return t0, t0
        if kind == "relay_kill":
            assert self.relay is not None
            self.relay.proc.send_signal(signal.SIGKILL)
            self.relay.proc.wait(10)
            self._sleep_polling(t0 + d)
            return t0, self.start_relay()
        if kind in ("blackhole", "reset"):
            self.links[fault.target].proc.send_signal(signal.SIGUSR1)
            self._sleep_polling(t0 + self.outage_s)
            return t0, t0 + self.outage_s
        if fault.target == "platform":
            return self._inject_platform(fault)
        station = self.stations[fault.target]
        if kind == "stop":
            station.proc.send_signal(signal.SIGSTOP)
            self._sleep_polling(t0 + d)
            t1 = time.monotonic()
            station.proc.send_signal(signal.SIGCONT)
            return t0, t1
        if kind == "kill":
            station.proc.send_signal(signal.SIGKILL)
            station.proc.wait(10)
            self._killed.add((fault.target, self.instances[fault.target]))
            self._sleep_polling(t0 + d)
            t1 = time.monotonic()
            self.start_station(fault.target)
            return t0, t1
        if kind == "clock_step":
            total = self.offset_us(fault.target, t0) + round(d * 1e6)
            (self.workdir / f"clock-{fault.target}.txt").write_text(f"{total / 1e6:.6f}\n")
            t0 = time.monotonic()
            station.proc.send_signal(signal.SIGUSR2)
            self.clock_steps[fault.target].append((t0, total))
            return t0, t0
        raise ValueError(kind)

    def platform_pid(self) -> int | None:
        """The pid of the local station's platform process (None: it has none now)."""
        station = self.stations["local"].proc.pid
        for pid in _children(station):
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
            except OSError:
                continue
            if b"local_site.agent.platform_child" in cmd:
                return pid
        return None

    def _inject_platform(self, fault: FaultSpec, timeout_s: float = 60.0) -> tuple[float, float]:
        """SIGKILL the platform process (the recovery moment: the station has started a new
        one), or SIGSTOP it for the fault's duration (the recovery moment: SIGCONT)."""
        pid = self.platform_pid()
        if pid is None:
            raise RigError(f"the local station (pid {self.stations['local'].proc.pid}) has no "
                           "platform process; run the rig with platform_process=True")
        t0 = time.monotonic()
        if fault.kind == "kill":
            os.kill(pid, signal.SIGKILL)
            self._wait(lambda: self.platform_pid() not in (None, pid),
                       "the station's new platform process", timeout_s,
                       (self.stations["local"],))
            return t0, time.monotonic()
        os.kill(pid, signal.SIGSTOP)
        try:
            self._sleep_polling(t0 + fault.duration_s)
        finally:
            t1 = time.monotonic()
            os.kill(pid, signal.SIGCONT)
        return t0, t1

    def _sleep_polling(self, until: float) -> None:
        while (left := until - time.monotonic()) > 0:
            self.poll()
            time.sleep(min(0.05, left))

    def mark_major_faults(self) -> None:
        """Remember every running process's major page faults so far: :meth:`stop` then
        reports those since this moment (for a process started later, since its start), not
        the start-up's (imports read from disk, before a station locks its memory)."""
        self._faults_mark = {p.name: n for p in self._all if p.proc.poll() is None
                             and (n := _major_faults(p.proc.pid)) is not None}

    # ------------------------------------------------------------------ stop

    def stop(self) -> dict[str, Any]:
        """SIGTERM the stations (they write their summaries), then everything else.

        Returns:
            ``{"local": summary, "remote": summary}`` of the last instances (None if absent).
        """
        self.poll()
        self._stopping = True
        # major page faults of every process still running: a thread that faults in a page
        # the kernel dropped (proactive reclaim) waits for the disk, holding the GIL
        self.major_faults = {p.name: n - self._faults_mark.get(p.name, 0) for p in self._all
                             if p.proc.poll() is None
                             and (n := _major_faults(p.proc.pid)) is not None}
        summaries: dict[str, Any] = {}
        for role in ("local", "remote"):
            p = self.stations.get(role)
            if p is not None:
                _terminate(p.proc)
            path = self.workdir / f"summary-{role}-{self.instances[role]}.json"
            try:
                summaries[role] = json.loads(path.read_text())
            except (OSError, json.JSONDecodeError):
                summaries[role] = None
        self.close()  # the board last: it writes its summary at SIGTERM
        if self.board_process:
            try:
                summaries["board"] = json.loads((self.workdir / "summary-board.json").read_text())
            except (OSError, json.JSONDecodeError):
                summaries["board"] = None
        return summaries

    def close(self) -> None:
        """Kill whatever still runs (idempotent)."""
        for b in self.burners:
            with contextlib.suppress(OSError):
                b.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                b.wait(5)
        self.burners.clear()
        for p in reversed(self._all):
            if p.proc.poll() is None:
                with contextlib.suppress(OSError):
                    p.proc.send_signal(signal.SIGCONT)
                _terminate(p.proc)

    def __enter__(self) -> FaultRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _stat_fields(proc_dir: Path) -> list[str] | None:
    """The fields of ``/proc/<pid>/stat`` after the command name (which is in parentheses and
    may hold spaces): index 0 is field 3, the state. None: the process is gone."""
    try:
        stat = (proc_dir / "stat").read_text()
    except OSError:
        return None
    return stat[stat.rindex(")") + 2:].split()


def _major_faults(pid: int) -> int | None:
    """The major page faults of a process so far (None: it is gone)."""
    fields = _stat_fields(Path(f"/proc/{pid}"))
    return None if fields is None else int(fields[9])  # field 12, majflt


def _children(pid: int) -> list[int]:
    """The pids whose parent is ``pid`` (from /proc)."""
    return [int(entry.name) for entry in Path("/proc").iterdir() if entry.name.isdigit()
            and (fields := _stat_fields(entry)) is not None and int(fields[1]) == pid]


def _logged(p: _Proc, text: str) -> bool:
    return text in p.log_path.read_text(errors="replace")


def _terminate(proc: subprocess.Popen[bytes], timeout_s: float = 15.0) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


# ---------------------------------------------------------------------------- analysis


def _last_before(times: list[float], t: float) -> float | None:
    i = int(np.searchsorted(times, t, side="right"))
    return times[i - 1] if i > 0 else None


def _latencies(events: list[float], inputs: list[float]) -> list[tuple[float, float]]:
    """(event time, ms since the last input before it) for events that follow an input,
    counting an event only once per input (a second event after the same input is a repeat)."""
    out: list[tuple[float, float]] = []
    used: set[float] = set()
    for t in events:
        last = _last_before(inputs, t)
        if last is None or last in used:
            continue
        used.add(last)
        out.append((t, (t - last) * 1e3))
    return out


def _pct(values: list[float]) -> dict[str, float | int | None]:
    if not values:
        return {"n": 0, "p50": None, "p99": None, "max": None}
    arr = np.asarray(values, dtype=float)
    return {"n": int(arr.size), "p50": float(np.percentile(arr, 50)),
            "p99": float(np.percentile(arr, 99)), "max": float(arr.max())}


def analyse(rig: FaultRig, injections: list[tuple[float, float]], *,
            frame_bound_ms: float = 150.0, command_bound_ms: float = 100.0) -> dict[str, Any]:
    """The figures of one run (see the module docstring)."""
    rig.poll()
    halts: list[tuple[float, float]] = []
    safes: list[tuple[float, float]] = []  # the station's own entries (the probe's S lines)
    stale_exec: list[float] = []
    executed = 0
    stale_rend: list[float] = []
    rendered = 0
    withdrawn = 0
    for p in rig.probes:
        if p.role == "remote":
            accepted_t = [m for m, _, acc, _ in p.commands if acc]
            halts += _latencies([m for m, why in p.halts], accepted_t)
            for m, ts, acc, _ in p.commands:
                if acc:
                    executed += 1
                    age = rig.age_ms("local", m, ts)
                    if age > command_bound_ms:
                        stale_exec.append(age)
        else:
            fresh_t = [m for m, ts in p.accepted
                       if rig.age_ms("remote", m, ts) <= frame_bound_ms]
            safes += _latencies([m for m, _ in p.safe], fresh_t)
            withdrawn += len(p.withdrawn)
            for m, ts in p.rendered:
                rendered += 1
                age = rig.age_ms("remote", m, ts)
                if age > frame_bound_ms:
                    stale_rend.append(age)
    station_safes = safes
    board = rig.board_log
    if board is not None:
        # the board is the truth of what the pins do: its entries, after the last fresh frame
        # any local station instance accepted (the board outlives a restarted station)
        fresh_all = sorted(m for p in rig.probes if p.role == "local" for m, ts in p.accepted
                           if rig.age_ms("remote", m, ts) <= frame_bound_ms)
        safes = _latencies([m for m, _ in board.safe], fresh_all)

    def stale_window(t0: float, t1: float) -> dict[str, Any]:
        ages = [rig.age_ms("remote", m, ts) for p in rig.probes if p.role == "local"
                for m, ts in p.rendered if t0 <= m <= t1]
        stale = [a for a in ages if a > frame_bound_ms]
        return {"rendered": len(ages), "stale": len(stale),
                "max_age_ms": max(stale) if stale else None}

    per_fault: list[dict[str, Any]] = []
    for t_fault, t_rec in injections:
        fresh = rig.fresh_render_after(t_rec, frame_bound_ms)
        anyf = rig.fresh_render_after(t_rec, math.inf)
        cmd = rig.command_after(t_rec)
        halt = next(((t, ms) for t, ms in halts if t >= t_fault - 0.2), None)
        safe = next(((t, ms) for t, ms in safes if t >= t_fault - 0.2), None)
        per_fault.append({
            "fault_s": t_fault, "recovered_s": t_rec,
            "fresh_frames_after_ms": None if fresh is None else (fresh - t_rec) * 1e3,
            "any_frame_after_ms": None if anyf is None else (anyf - t_rec) * 1e3,
            "commands_after_ms": None if cmd is None else (cmd - t_rec) * 1e3,
            "halt_ms": None if halt is None else halt[1],
            "safe_ms": None if safe is None else safe[1],
            # the pins' state at the recovery moment (board process only; None without it)
            "board_safe_at_recovery": None if board is None else board.safe_at(t_rec),
            # frames rendered in the 5 s before the fault (what the load alone does) and in
            # the 5 s after the recovery (what the fault adds)
            "frames_before": stale_window(t_fault - 5.0, t_fault),
            "frames_after": stale_window(t_rec, t_rec + 5.0),
            "pins_after": None if board is None else _pins_figures(
                rig.pin_ages(t_rec, t_rec + 5.0), frame_bound_ms, True)})
    return {
        "halt_ms": _pct([ms for _, ms in halts]),
        "safe_ms": _pct([ms for _, ms in safes]),
        "safe_source": "board" if board is not None else "station",
        "station_safe_ms": _pct([ms for _, ms in station_safes]),
        "board_safe_reasons": None if board is None
        else dict(sorted(collections.Counter(why for _, why in board.safe).items())),
        "fresh_after_ms": _pct([f["fresh_frames_after_ms"] for f in per_fault
                                if f["fresh_frames_after_ms"] is not None]),
        "any_frame_after_ms": _pct([f["any_frame_after_ms"] for f in per_fault
                                    if f["any_frame_after_ms"] is not None]),
        "recoveries_missing": sum(1 for f in per_fault if f["fresh_frames_after_ms"] is None),
        "commands_executed": executed,
        "stale_commands_executed": len(stale_exec),
        "stale_command_max_age_ms": max(stale_exec) if stale_exec else None,
        "frames_rendered": rendered,
        "stale_frames_rendered": len(stale_rend),
        "stale_frame_max_age_ms": max(stale_rend) if stale_rend else None,
        "late_sends_withdrawn": withdrawn,
        **_pins_figures(rig.pin_ages(), frame_bound_ms, board is not None),
        "exits": [{"role": e.role, "instance": e.instance, "code": e.code} for e in rig.exits],
        "faults": per_fault,
    }


def _pins_figures(ages: list[tuple[float, int, float | None]], bound_ms: float,
                  board: bool) -> dict[str, Any]:
    """Commands the board applied, how many carried touch older than ``bound_ms`` when
    applied, and how many matched no command the station sent (None without a board)."""
    if not board:
        return {"pins_applied": None, "stale_at_pins": None, "stale_at_pins_max_age_ms": None,
                "pins_unmatched": None}
    stale = [a for _, _, a in ages if a is not None and a > bound_ms]
    return {"pins_applied": len(ages), "stale_at_pins": len(stale),
            "stale_at_pins_max_age_ms": max(stale) if stale else None,
            "pins_unmatched": sum(1 for _, _, a in ages if a is None)}


def _pick(d: dict[str, Any], *keys: str) -> dict[str, Any]:
    return {k: d.get(k) for k in keys if k in d}


def _summary_figures(summaries: dict[str, Any]) -> dict[str, Any]:
    """A few of the stations' own counters (None where a summary was not written)."""
    loc, rem = summaries.get("local"), summaries.get("remote")
    out: dict[str, Any] = {}
    if isinstance(loc, dict):
        link = loc.get("link") or {}
        out["local"] = {"exit_reason": loc.get("exit_reason"), "exit_code": loc.get("exit_code"),
                        "safe_entries": (loc.get("safe_state") or {}).get("entries"),
                        "link": _pick(link, "connects", "connection_losses"),
                        "platform": _pick(loc.get("platform") or {}, "process",
                                          "process_restarts", "reconnects", "recoveries")}
    board = summaries.get("board")
    if isinstance(board, dict):
        out["board"] = _pick(board, "commands_applied", "commands_rejected",
                             "commands_refused_latched", "watchdog_trips",
                             "overruns", "error", "link", "niceness")
    if isinstance(rem, dict):
        arm = rem.get("arm") or {}
        plat = rem.get("platform_states") or {}
        link = rem.get("link") or {}
        out["remote"] = {"watchdog_halts": arm.get("watchdog_halts"),
                         "link_loss_halts": arm.get("link_loss_halts"),
                         "max_measured_age_ms": arm.get("max_age_ms"),
                         "dropped_stale": plat.get("dropped_stale"),
                         "dropped_no_clock": plat.get("dropped_no_clock"),
                         "link": _pick(link, "connects", "connection_losses")}
    return out


def run_scenario(scenario: Scenario, workdir: Path, *, repeats: int = 1,
                 recovery_timeout_s: float = 20.0, settle_s: float = 1.0,
                 start_timeout_s: float = 150.0, steady_timeout_s: float = 20.0,
                 frame_bound_ms: float = 150.0,
                 command_bound_ms: float = 100.0, board_process: bool = False,
                 platform_process: bool = False, lock_memory: bool = True,
                 progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Start a rig, inject the scenario's fault ``repeats`` times, stop, analyse.

    After each injection the harness waits until fresh frames are rendered and commands
    executed again (at most ``recovery_timeout_s`` after the recovery, or ``observe_s`` for
    faults with no recovery), then ``settle_s`` more. Each fault is injected into a steady
    flow (:meth:`FaultRig.wait_steady`, 2 s, at most ``steady_timeout_s``; an injection into
    an unsteady flow is counted in ``injected_unsteady``).
    """
    f = scenario.fault
    rig = FaultRig(workdir, outage_s=f.duration_s if f.kind in ("blackhole", "reset") else None,
                   outage_reset=f.kind == "reset", cpu_burners=scenario.cpu_burners,
                   board_process=board_process,
                   platform_process=platform_process or f.target == "platform",
                   lock_memory=lock_memory)
    injections: list[tuple[float, float]] = []
    unsteady = 0
    started = time.monotonic()
    error = None
    summaries: dict[str, Any] = {}
    try:
        rig.start(start_timeout_s)
        for i in range(repeats):
            rig._sleep_polling(time.monotonic() + settle_s)
            if not rig.wait_steady(2.0, steady_timeout_s, frame_bound_ms):
                unsteady += 1  # injected anyway; the table says how often
            if i == 0:
                rig.mark_major_faults()  # the session's faults, not the start-up's
            t_fault, t_rec = rig.inject(f)
            injections.append((t_fault, t_rec))
            if f.kind in ("none", "clock_step"):
                rig._sleep_polling(t_rec + scenario.observe_s)
            else:
                # a restarted station first imports and calibrates: tens of seconds when loaded
                wait_s = recovery_timeout_s * (3 if f.kind == "kill" else 1)
                ok = rig.wait_flowing(t_rec, wait_s, FLOW_BOUND_MS)
                if progress is not None:
                    progress(f"  {scenario.name}: injection {i + 1}/{repeats} "
                             f"{'recovered' if ok else 'NOT recovered'}")
        rig._sleep_polling(time.monotonic() + settle_s)
    except RigError as err:
        error = str(err)
    finally:
        summaries = rig.stop()
    result = analyse(rig, injections, frame_bound_ms=frame_bound_ms,
                     command_bound_ms=command_bound_ms)
    result.update({"scenario": scenario.name, "kind": f.kind, "target": f.target,
                   "duration_s": f.duration_s, "cpu_burners": scenario.cpu_burners,
                   "repeats": len(injections), "injected_unsteady": unsteady,
                   "wall_s": time.monotonic() - started,
                   "board_process": board_process,
                   "platform_process": rig.platform_process,
                   "major_page_faults": rig.major_faults,
                   "major_page_faults_since": "steady",
                   "lock_memory": lock_memory,
                   "error": error, "summaries": _summary_figures(summaries),
                   "workdir": str(workdir)})
    return result


def iter_results(items: list[Scenario], root: Path, *, repeats: int,
                 board_process: bool = False, platform_process: bool = False,
                 lock_memory: bool = True,
                 progress: Callable[[str], None] | None = None) -> Iterator[dict[str, Any]]:
    """Run each scenario in its own directory under ``root``, yielding its result."""
    for i, sc in enumerate(items):
        if progress is not None:
            progress(f"[{i + 1}/{len(items)}] {sc.name}")
        yield run_scenario(sc, root / f"{i:02d}", repeats=repeats, board_process=board_process,
                           platform_process=platform_process, lock_memory=lock_memory,
                           progress=progress)

