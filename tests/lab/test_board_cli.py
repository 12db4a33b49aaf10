"""``teletouch board``: the emulated drive board as a real process, reached by the ordinary
serial driver over ``socket://``; its event file against what the driver did."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from lab.faults import BoardLog
from local_site.devices import open_display
from local_site.display import frames as fr
from local_site.display.serial_framing import encode_link_frame
from tests.support import REPO_ROOT, scaled, wait_until

pytestmark = pytest.mark.slow

WATCHDOG_MS = 100


@pytest.fixture
def board(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], str, Path]]:
    events = tmp_path / "events.txt"
    proc = subprocess.Popen(
        [sys.executable, "-m", "lab.cli", "board", "--listen", "127.0.0.1:0",
         "--events", str(events), "--summary-json", str(tmp_path / "summary.json")],
        cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()  # blocks until the board listens (or exits)
        assert line.startswith("board listening on socket://"), \
            f"unexpected first line {line!r} (exit code {proc.poll()})"
        yield proc, line.split()[-1], events
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _polled(log: BoardLog) -> bool:
    log.poll()
    return True


def test_board_process_watchdog_events_and_station_restart(
        board: tuple[subprocess.Popen[str], str, Path], tmp_path: Path) -> None:
    proc, url, events = board
    display = open_display(url, keepalive_interval_s=0.02, watchdog_ms=WATCHDOG_MS,
                           connect_timeout_s=scaled(5.0))
    log = BoardLog(events)
    try:
        for _ in range(20):
            display.send_command(2.0)
            time.sleep(0.005)
        last_send = time.monotonic()
        # the driver falls silent (a frozen station): the board's own watchdog parks the pins
        wait_until(lambda: _polled(log) and [r for _, r in log.safe if r == "watchdog"], 3.0,
                   "the board's watchdog event")
        applied = [m for m, _ in log.applied]
        assert applied and applied[-1] <= last_send + scaled(0.05)
        (t_safe, _), = log.safe
        # the watchdog counts from the last command the board applied, on the board's tick
        assert WATCHDOG_MS / 1e3 <= t_safe - applied[-1] <= WATCHDOG_MS / 1e3 + scaled(0.1)
        assert log.safe_at(t_safe) and not log.safe_at(applied[-1])
        display.disconnect()
        # a command without RESUME after the trip (one that waited in a frozen station) is
        # refused: an X event, and the pins stay parked
        host, port = url.removeprefix("socket://").rsplit(":", 1)
        with socket.create_connection((host, int(port)), timeout=scaled(2.0)) as raw:
            raw.sendall(encode_link_frame(fr.ARB_ID_COMMAND, fr.encode_command(fr.CommandFrame(
                seq=7, flags=0, height_codes=np.full(16, 800, np.uint16),
                k_codes=np.full(16, 250, np.uint16), f_codes=np.zeros(16, np.uint16),
                watchdog_ms=WATCHDOG_MS))))
            wait_until(lambda: _polled(log) and log.refused, 3.0, "the board's X event")
        assert not log.resumed and 7 not in [seq for _, seq in log.applied]
        # a restarted station: new connection; it reads the trip, its command carries RESUME
        # and the pins leave the safe state
        display.connect()
        display.send_command(1.0)
        wait_until(lambda: _polled(log) and log.resumed, 3.0,
                   "the board to leave the safe state")
        assert not log.safe_at(log.resumed[-1]) and display.stats().resumes == 1
        display.safe_state("flat")
        wait_until(lambda: _polled(log) and log.safe[-1][1] == "safe_state_frame", 3.0,
                   "the safe-state frame's event")
    finally:
        display.disconnect()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(scaled(10.0)) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["link"]["connects"] == 3 and summary["watchdog_trips"] == 1
    assert summary["commands_applied"] == len(log.applied) and summary["error"] is None
    assert summary["commands_refused_latched"] == len(log.refused) == 1
    assert summary["events"]["X"] == 1


def test_board_rejects_bad_settings() -> None:
    from lab.cli import main

    assert main(["board", "--listen", "127.0.0.1:99999"]) == 1
    assert main(["board", "--watchdog-ms", "0"]) == 1
    with pytest.raises(SystemExit):
        main(["board", "--listen"])
