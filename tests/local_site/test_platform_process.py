"""The platform read in a process of its own: the shared-memory record and the child's life."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import os
import signal
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import shared.memlock as memlock
from local_site.agent import LocalAgent, LocalAgentConfig
from local_site.agent.platform_process import (
    _NOT_STARTED,
    ProcessPlatformReader,
    ReaderHealth,
    SampleRecord,
)
from local_site.platform.base import PlatformSample
from shared.errors import ConfigError
from shared.timebase import monotonic_s, now_us
from tests.local_site.agent_support import loop_of, wait_for
from tests.support import MachineStalls, scaled, wait_until

HOLD = "hold:x=20,y=30,z=100"

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
int64 = st.integers(-(2**62), 2**62)


@settings(max_examples=50, deadline=None)
@given(position=st.tuples(finite, finite, finite), velocity=st.tuples(finite, finite, finite),
       t_us=st.integers(0, 2**62), seq=int64, board_t_us=int64, clamped=st.booleans(),
       counters=st.tuples(*(st.integers(0, 2**62) for _ in range(4))),
       lost=st.none() | st.floats(0, 1e9), error=st.none() | st.text(max_size=300))
def test_the_record_gives_back_what_was_written(
        position: tuple[float, float, float], velocity: tuple[float, float, float],
        t_us: int, seq: int, board_t_us: int, clamped: bool,
        counters: tuple[int, int, int, int], lost: float | None, error: str | None) -> None:
    writer = SampleRecord()
    reader = SampleRecord(writer.fd)
    try:
        first = reader.read()
        assert first is not None and first[1] is None  # no sample written yet
        sample = PlatformSample(position, velocity, t_us, seq, board_t_us, clamped)
        health = ReaderHealth(lost is None, lost, *counters, motion_done=clamped,
                              heartbeat_s=monotonic_s(), last_error=error)
        writer.write_sample(sample)
        writer.write_health(health)
        copy = reader.read()
        assert copy is not None
        counter, got, got_health = copy
        assert counter % 2 == 0 and counter == writer.counter
        assert got == sample
        want_error = None if error is None else \
            error.encode("utf-8", "replace")[:240].decode("utf-8", "replace")
        assert got_health == ReaderHealth(lost is None, lost, *counters, motion_done=clamped,
                                          heartbeat_s=health.heartbeat_s,
                                          last_error=want_error)
    finally:
        reader.close()
        writer.close()


def test_a_writer_that_died_inside_a_write_is_not_waited_for() -> None:
    """A child killed between the two counter steps leaves the counter odd: a reader gives
    up after a bounded number of tries (the display loop must never spin on it) and the
    next child claims the record back to an even counter."""
    writer = SampleRecord()
    reader = SampleRecord(writer.fd)
    try:
        sample = PlatformSample((1.0, 2.0, 3.0), (0.0, 0.0, 0.0), 5, 6, 7)
        writer.write_sample(sample)
        writer.write_health(dataclasses.replace(_NOT_STARTED, healthy=True))
        writer._HEAD.pack_into(writer._buf, 0, writer.counter + 1)  # it dies inside a write
        assert writer.counter % 2 == 1
        with MachineStalls() as stalls:
            t0 = time.perf_counter()
            assert reader.read() is None
            took_s = time.perf_counter() - t0
        assert took_s < scaled(0.05) + stalls.total_s, took_s  # a bounded try, not a wait
        successor = SampleRecord(writer.fd)
        successor.claim()
        # the half-written record reads back, but never as healthy (found by audit: the
        # dead writer's healthy health came with a mixed sample)
        claimed = reader.read()
        assert claimed is not None and not claimed[2].healthy
        assert claimed[2].lost_since_mono_s is not None
        successor.write_sample(sample)
        got = reader.read()
        assert got is not None and got[0] % 2 == 0 and got[1] == sample
        successor.close()
    finally:
        reader.close()
        writer.close()


def test_reads_beside_two_busy_writer_threads_are_never_torn() -> None:
    """The child writes samples from the driver's thread and its health from its main
    thread: every copy a reader accepts holds fields written together."""
    import threading

    writer = SampleRecord()
    reader = SampleRecord(writer.fd)
    stop = threading.Event()

    def samples() -> None:
        k = 0
        while not stop.is_set():
            k += 1
            v = float(k)
            writer.write_sample(PlatformSample((v, v, v), (v, v, v), k, k, k))

    def health() -> None:
        k = 0
        while not stop.is_set():
            k += 1
            writer.write_health(ReaderHealth(True, None, k, k, k, k, False, float(k), str(k)))

    threads = [threading.Thread(target=samples), threading.Thread(target=health)]
    for t in threads:
        t.start()
    accepted = 0
    try:
        deadline = time.perf_counter() + 1.0
        while time.perf_counter() < deadline:
            got = reader.read()
            if got is None:
                continue
            _, sample, h = got
            if sample is not None:
                k = sample.seq
                assert sample.position_mm == (k, k, k) == sample.velocity_mm_s
                assert sample.t_us == k and sample.board_t_us == k
            if h.reads:
                assert (h.errors, h.reconnects, h.recoveries) == (h.reads,) * 3
                assert h.heartbeat_s == h.reads and h.last_error == str(h.reads)
            accepted += 1
        stop.set()
        for t in threads:
            t.join()
        assert accepted > 100
        assert writer.counter % 2 == 0  # the two threads took turns: no write left open
    finally:
        stop.set()
        for t in threads:
            t.join()
        reader.close()
        writer.close()


def test_options_must_cross_to_the_child_as_json() -> None:
    with pytest.raises(ConfigError, match="JSON"):
        ProcessPlatformReader("sim", {"motion": object()})
    with pytest.raises(ConfigError, match="reopen_after_s"):
        ProcessPlatformReader("sim", read_timeout_s=0.25, reopen_after_s=0.1)


def _started(**kwargs: object) -> ProcessPlatformReader:
    kwargs.setdefault("retry_min_s", 0.05)
    reader = ProcessPlatformReader("sim", {"motion": HOLD}, read_timeout_s=scaled(0.5),
                                   **kwargs)  # type: ignore[arg-type]
    reader.start()
    # the child starts Python and imports the drivers first
    wait_until(lambda: reader.healthy and reader.latest is not None, 20.0, "a first sample")
    return reader


def test_the_process_reader_publishes_the_boards_samples_on_our_clock() -> None:
    reader = _started()
    try:
        first = reader.latest
        assert first is not None
        wait_until(lambda: (s := reader.latest) is not None and s.seq >= first.seq + 100, 5.0,
                   "100 more samples")
        sample = reader.latest
        assert sample is not None
        assert sample.position_mm == pytest.approx((20.0, 30.0, 100.0), abs=0.05)
        # capture stamps cross on the monotonic clock and land on this process's anchor
        assert 0 <= now_us() - sample.t_us < scaled(0.5) * 1e6
        # the child's counters ride on its heartbeat (every 20 ms), behind the samples
        wait_until(lambda: reader.reads >= 100, 5.0, "the child's read count")
        assert reader.lost_since_s is None and not reader.motion_done.is_set()
    finally:
        reader.stop()
    stats = reader.platform_stats()
    assert stats.frames_ok >= 100 and stats.crc_errors == 0  # the child's link counters
    assert not reader.healthy and reader.latest is not None  # the last sample stays readable
    assert reader.lost_since_s is not None and reader.reads >= 100


def _locked_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmLck:"):
                return int(line.split()[1])
    raise AssertionError("no VmLck line")


@pytest.mark.parametrize("lock", [True, False])
def test_the_platform_process_locks_its_memory_as_the_station_does(lock: bool) -> None:
    reader = _started(lock_memory=lock)
    try:
        assert reader._process is not None
        pid = reader._process.pid
        # the child locks before it starts reading: locked by its first sample
        expect = lock and memlock._refusal() is None
        assert (_locked_kb(pid) > 0) == expect
    finally:
        reader.stop()


def test_a_killed_platform_process_makes_it_lost_then_is_started_again() -> None:
    reader = _started()
    try:
        process = reader._process
        assert process is not None
        reads = reader.reads
        os.kill(process.pid, signal.SIGKILL)
        # its newest sample ages past the read timeout: lost (the pins go to their safe state)
        wait_until(lambda: not reader.healthy, 5.0, "the dead child reported lost")
        assert reader.lost_since_s is not None
        wait_until(lambda: reader.restarts >= 1 and reader.healthy, 30.0,
                   "the child started again and publishing")
        assert reader._process is not None and reader._process.pid != process.pid
        # the counters carry over; the death counts as a loss and says why
        assert reader.reads >= reads and reader.errors >= 1
        assert reader.child_error is not None and "exited" in reader.child_error
    finally:
        reader.stop()


def test_the_link_counters_of_a_child_that_ended_carry_over() -> None:
    """A child that ends on its own writes its link counters on the way out: they were
    dropped with its pipe, and the station's summary showed only the last child's (the
    very faults that led to a restart vanished; found by audit). The sim board counts its
    samples from 0 in each child: the totals must cover both."""
    reader = _started()
    try:
        wait_until(lambda: (s := reader.latest) is not None and s.seq >= 500, 10.0,
                   "500 samples from the first child")
        first = reader._process
        assert first is not None and first.stdin is not None
        first_seq = reader.latest.seq  # type: ignore[union-attr]
        first.stdin.close()  # it ends by itself (as on a crash, it writes its counters)
        first.wait(timeout=scaled(5.0))
        wait_until(lambda: reader.restarts >= 1 and reader._process is not first
                   and reader.healthy, 30.0, "the second child publishing")
    finally:
        reader.stop()
    second_seq = reader.latest.seq  # type: ignore[union-attr]
    stats = reader.platform_stats()
    # frames decoded by both children: at least their samples up to the last one seen
    assert stats.frames_ok >= 0.9 * (first_seq + second_seq), (stats, first_seq, second_seq)


def test_a_stop_while_a_dead_child_waits_for_its_restart_is_quiet(
        caplog: pytest.LogCaptureFixture) -> None:
    """stop() told the retired child to stop through its closed pipe and warned that it
    "did not stop" (found by audit)."""
    reader = _started(retry_min_s=5.0, retry_max_s=5.0)  # the stop comes inside the wait
    process = reader._process
    assert process is not None
    os.kill(process.pid, signal.SIGKILL)
    wait_until(lambda: reader.child_error is not None, 10.0, "the death noticed")
    assert reader.restarts == 0  # still waiting for the restart
    with caplog.at_level(logging.WARNING, logger="local_site.agent.platform_process"):
        reader.stop()
    assert "did not stop" not in caplog.text


def test_a_stopped_platform_process_is_reported_lost() -> None:
    reader = _started()
    process = reader._process
    assert process is not None
    try:
        os.kill(process.pid, signal.SIGSTOP)  # frozen: no heartbeat, no sample
        wait_until(lambda: not reader.healthy, 5.0, "the frozen child reported lost")
        latest = reader.latest
        os.kill(process.pid, signal.SIGCONT)
        wait_until(lambda: reader.healthy and reader.latest != latest, 10.0, "back")
    finally:
        os.kill(process.pid, signal.SIGCONT)
        reader.stop()


def test_the_child_ends_when_the_station_side_of_its_pipe_closes() -> None:
    """A station that died closes its end of the child's standard input: the child stops."""
    reader = _started()
    try:
        process = reader._process
        assert process is not None and process.stdin is not None
        reader._stop.set()  # no restart: this is about the child ending by itself
        process.stdin.close()
        process.wait(timeout=scaled(5.0))
        assert process.returncode == 0
    finally:
        reader.stop()


async def test_the_local_station_renders_with_its_platform_in_a_process() -> None:
    agent = LocalAgent(LocalAgentConfig(scene="hemisphere", motion="hold:x=30,y=30,z=100",
                                        platform_process=True, device_retry_min_s=0.05,
                                        platform_read_timeout_s=scaled(0.25)))
    run = asyncio.create_task(agent.run())
    try:
        await wait_for(lambda: agent.loop is not None and
                       (fb := loop_of(agent).display.latest_feedback()) is not None
                       and abs(float(fb.position_mm.max()) - 4.34) < 0.1, 30.0,
                       "pins showing the hemisphere")
        reader = agent.reader
        assert isinstance(reader, ProcessPlatformReader) and reader._process is not None
        os.kill(reader._process.pid, signal.SIGKILL)
        await wait_for(lambda: loop_of(agent).safe_reason == "platform_lost", 5.0,
                       "safe state when the platform process died")
        await wait_for(lambda: reader.restarts >= 1 and loop_of(agent).safe_reason is None,
                       30.0, "rendering again")
    finally:
        agent.request_stop("test")
        assert await run == 0
    s = agent.summary
    assert s is not None and s["platform"]["reads"] > 0 and s["platform"]["process"] is True
    assert s["platform"]["process_restarts"] >= 1 and s["platform"]["errors"] >= 1
    assert s["platform"]["read_rate_hz"] > 0 and not math.isnan(s["platform"]["read_rate_hz"])
    assert s["safe_state"]["entries"].get("platform_lost", 0) >= 1
