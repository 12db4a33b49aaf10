"""``tests.support.MachineStalls`` sees the whole process stopped (as a busy host stops it),
with its length, and not a thread of it kept busy (the event loop blocked by product code is
not the machine's stall)."""

from __future__ import annotations

import os
import signal
import subprocess
import time

from tests.support import MachineStalls, scaled


def test_the_process_stopped_is_one_stall_of_about_its_length() -> None:
    with MachineStalls() as stalls:
        time.sleep(0.05)  # the watch has ticked
        before = time.monotonic()
        # stopped by another process for 0.2 s, every thread of it (SIGSTOP, SIGCONT)
        subprocess.run(["sh", "-c", f"kill -STOP {os.getpid()}; sleep 0.2; "
                                    f"kill -CONT {os.getpid()}"], check=True)
        after = time.monotonic()
    assert stalls.count(0.1) >= 1, stalls.stalls_s
    assert 0.15 <= max(stalls.stalls_s) <= 0.2 + scaled(0.3), stalls.stalls_s
    assert stalls.total_s >= max(stalls.stalls_s)
    # where: within the stop, and seen by what overlaps it
    [(start, end)] = [span for span in stalls.spans if span[1] - span[0] > 0.1]
    assert before - stalls.tick_s <= start and end <= after + scaled(0.3), (before, after,
                                                                           stalls.spans)
    assert stalls.overlaps(start - 1.0, start + 0.01) and stalls.overlaps(end - 0.01, end + 1.0)
    assert not stalls.overlaps(end + 0.05, end + 1.0) or any(
        a > end for a, _ in stalls.spans)  # (unless a second stall came after)


def test_a_busy_thread_is_not_a_stall() -> None:
    with MachineStalls() as stalls:
        end = time.monotonic() + 0.3
        while time.monotonic() < end:  # the GIL held in turns, as a blocked event loop
            pass
    assert stalls.count(scaled(0.05)) == 0, stalls.stalls_s


def test_a_stall_under_way_at_the_stop_is_counted() -> None:
    """Stopped, then the watch stopped before its thread ran again (this thread stops the
    process itself and holds the GIL until the stop): the stall is counted all the same."""
    stalls = MachineStalls().start()
    time.sleep(0.05)
    waker = subprocess.Popen(["sh", "-c", f"sleep 0.2; kill -CONT {os.getpid()}"])
    try:
        os.kill(os.getpid(), signal.SIGSTOP)
        stalls.stop()
    finally:
        waker.wait()
    assert stalls.count(0.1) >= 1, stalls.stalls_s
