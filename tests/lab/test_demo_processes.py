"""The demo's child processes are never left behind, even by a second Ctrl-C."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from lab.demo.orchestrator import _Child, _Processes

# a child that ignores SIGTERM (a station stuck in its shutdown) and says when it is ready
STUBBORN = ("import signal, sys, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
            "sys.stdout.buffer.write(b'ready\\n'); sys.stdout.flush(); time.sleep(600)")


def _stubborn(procs: _Processes, name: str) -> None:
    proc = subprocess.Popen([sys.executable, "-c", STUBBORN], stdout=subprocess.PIPE)
    assert proc.stdout is not None and proc.stdout.readline().strip() == b"ready"
    procs.children.append(_Child(name, proc, procs.workdir / f"{name}.log"))


def test_a_second_ctrl_c_during_the_cleanup_kills_every_child_and_is_raised(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    procs = _Processes(tmp_path, sys.executable, {})
    _stubborn(procs, "first")
    _stubborn(procs, "second")
    real_stop = _Processes.stop

    def ctrl_c_while_waiting(self: _Processes, child: _Child,
                             timeout_s: float = 10.0) -> int | None:
        real_stop(self, child, timeout_s=0.01)  # SIGTERM (ignored), then killed
        raise KeyboardInterrupt  # the user presses Ctrl-C again while the demo waits

    monkeypatch.setattr(_Processes, "stop", ctrl_c_while_waiting)
    try:
        with pytest.raises(KeyboardInterrupt):
            procs.stop_all()
        for child in procs.children:
            assert child.proc.poll() is not None, f"{child.name} was left running"
    finally:  # a failing run must not leave them behind either
        for child in procs.children:
            child.proc.kill()
            child.proc.wait()
