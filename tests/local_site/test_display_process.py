"""The display loop in a process of its own (``local.agent.render_loop = "process"``).

Its parts (the period mirror, the link as the child sees it, the counters of ended children,
the shared clock), and the station with a real child process against a real relay: frames
rejected without touching the pins, a silent station counted as a lost link, a killed child
started again, a child that stops when the station's socket ends, a frame too large to hand
over.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
import pickle
import select
import signal
import socket
import threading
import time
from collections.abc import AsyncIterator, Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from local_site.agent import LocalAgent, LocalAgentConfig
from local_site.agent.display_loop import DisplayLoopCounters, PinState, SameClockLink
from local_site.agent.display_process import (
    HEARTBEAT_S,
    NO_WORD,
    SILENCE_S,
    DisplayProcess,
    LinkMirror,
    LinkState,
    fold_counters,
)
from local_site.agent.period_stats import PeriodStats
from local_site.agent.platform_process import ProcessPlatformReader
from local_site.display.base import DisplayStats
from local_site.recording import PinsSampler
from local_site.render import PinCommand, RendererConfig
from local_site.render.renderer import RenderStats
from shared import timebase
from shared.errors import ConfigError
from shared.freshness import ClockView
from shared.protocol import TactileFrame
from shared.timebase import monotonic_s, now_us
from tests.local_site.agent_support import (
    FakeRemote,
    any_loop_of,
    make_frame,
    relay_agent,
    wait_for,
)
from tests.relay_server.relay_clients import running_relay
from tests.support import scaled, wait_until

# ---------------------------------------------------------------------- the parts


@given(periods=st.lists(st.floats(1e-4, 5e-3), min_size=0, max_size=300),
       cuts=st.lists(st.integers(0, 300), max_size=8),
       capacity=st.sampled_from([2, 7, 64, 1024]))
def test_period_mirror_reports_what_the_loop_measured(periods: list[float], cuts: list[int],
                                                      capacity: int) -> None:
    # the child's PeriodStats, read in batches (since) into the station's (extend), give the
    # same summary as the child's own, the ring's overwriting included
    child, mirror = PeriodStats(1e-3, capacity), PeriodStats(1e-3, capacity)
    starts = np.concatenate([[0.0], np.cumsum(periods)]) if periods else np.zeros(0)
    recorded = 0
    bounds = sorted({0, len(starts), *(c for c in cuts if c <= len(starts))})
    for a, b in itertools.pairwise(bounds):
        for t in starts[a:b]:
            child.tick(float(t))
        child.overruns = b
        recorded, new = child.since(recorded)
        mirror.extend(new, child.iterations, child.overruns)
    assert recorded == child.recorded == max(0, len(starts) - 1)
    assert mirror.summary() == child.summary()
    assert np.array_equal(mirror.periods_s(), child.periods_s())


def test_link_mirror_counts_the_stations_silence_as_a_lost_link() -> None:
    t0 = monotonic_s()
    mirror = LinkMirror(grace_s=0.04)
    # before the station's first word: down as long as it stays silent (beyond the grace)
    assert mirror.link_down_for_s(t0 + 0.5) == pytest.approx(0.5 - 0.04, abs=0.01)
    view = ClockView({"local": 5, "remote": -3}, {"local": 100, "remote": 100}, now_us())
    mirror.update(LinkState(None, view, {"local": 5, "remote": -3}), now_s=t0)
    assert mirror.link_down_for_s(t0 + 0.01) == 0.0
    assert mirror.clock_view is view and dict(mirror.clock_offsets_us) == {"local": 5,
                                                                          "remote": -3}
    assert mirror.link_down_for_s(t0 + 0.14) == pytest.approx(0.1)  # silent 140 ms
    # the station says the link is down since t0 - 1: that counts, whatever its silence
    mirror.update(LinkState(t0 - 1.0, None, {}), now_s=t0)
    assert mirror.link_down_for_s(t0) == pytest.approx(1.0)
    assert mirror.clock_view is None and dict(mirror.clock_offsets_us) == {}


def test_fold_counters_adds_every_field() -> None:
    a = DisplayLoopCounters(frames_accepted=3, safe_entries={"link_lost": 1},
                            safe_time_s=0.5, link_loss_to_safe_ms=[10.0],
                            last_reject_reason="nan", rendered_frame_age_max_ms=40.0)
    b = DisplayLoopCounters(frames_accepted=4, commands_sent=7,
                            safe_entries={"link_lost": 2, "no_frames": 1}, safe_time_s=0.25,
                            link_loss_to_safe_ms=[20.0], rendered_frame_age_max_ms=30.0)
    c = fold_counters(a, b)
    assert c.frames_accepted == 7 and c.commands_sent == 7
    assert c.safe_entries == {"link_lost": 3, "no_frames": 1}
    assert c.safe_time_s == pytest.approx(0.75) and c.link_loss_to_safe_ms == [10.0, 20.0]
    assert c.last_reject_reason == "nan" and c.rendered_frame_age_max_ms == 40.0
    assert fold_counters(DisplayLoopCounters(), DisplayLoopCounters()) == DisplayLoopCounters()


def test_adopted_wall_anchor_stamps_on_the_other_clock() -> None:
    before = timebase.wall_anchor_ns()
    try:
        timebase.adopt_wall_anchor(before + 7_000_000_000)  # a parent started 7 s "later"
        shifted = now_us()
        timebase.adopt_wall_anchor(before)
        plain = now_us()
        assert 7_000_000 - 50_000 < shifted - plain < 7_000_000 + 1  # ours ran in between
    finally:
        timebase.adopt_wall_anchor(before)


_ALL_FIELDS_NONE = ("{k: None for k in ('periods', 'loops', 'counters', 'render_stats', "
                    "'display_stats', 'superseded', 'priority', 'connected', 'feedback', "
                    "'pins', 'safe_since_s', 'started_s', 'accepted', 'rendered', "
                    "'pins_samples', 'shed', 'final')}")


@pytest.mark.parametrize("report", ["not a pickle", "a report without its fields",
                                    "a report with every field malformed"])
def test_a_report_the_station_cannot_read_restarts_the_child_not_the_station(
        report: str) -> None:
    """One malformed report from the display child left the supervisor with the exception:
    the child was killed before it could park the pins and the station stopped, exit 1
    (found by audit). Now the child is ended through the end of its socket (it parks the
    pins) and started again, like a child that died. A report is checked whole before any
    of it is taken (one partly taken then failing broke the next child's counts; found by
    review)."""
    payload = {"not a pickle": "b'not a pickle'",
               "a report without its fields": "pickle.dumps(('report', {'loops': (1, 0)}))",
               "a report with every field malformed":
                   f"pickle.dumps(('report', {_ALL_FIELDS_NONE}))"}[report]
    child = ("import json, pickle, socket, sys; "
             "s = socket.socket(fileno=json.loads(sys.argv[1])['sock_fd']); "
             f"s.send({payload})\n"  # then ends at its socket's end, or when told to stop
             "while (d := s.recv(1 << 20)) and b'stop' not in d: pass")
    process = _unserved(link=SameClockLink(), retry_min_s=0.05, retry_max_s=0.1)
    process.child_argv = ("-c", child)
    stop = threading.Event()
    failed: list[BaseException] = []

    def run() -> None:
        try:
            process.run_in_thread(stop)
        except BaseException as err:
            failed.append(err)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        wait_until(lambda: process.restarts >= 1 or failed, 20.0, "the child started again")
        assert not failed, failed
        assert process.child_error is not None and "cannot read" in process.child_error
    finally:
        stop.set()
        thread.join(scaled(15.0))
    assert not thread.is_alive() and not failed


def test_a_malformed_report_is_refused_whole_before_any_of_it_is_taken() -> None:
    """Valid loops, then no counters and no periods: the report was half taken (its counts
    replaced) before it failed, and the next retirement broke the supervisor (found by
    review)."""
    from local_site.agent.display_process import _BadReport

    process = _unserved()
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        kind, report = _report(5, None)
        report["counters"], report["periods"] = None, "x"
        theirs.send(pickle.dumps((kind, report)))
        before = process._counts
        with pytest.raises(_BadReport, match=r"malformed periods, .*counters"):
            process._drain(ours)
        assert process._counts is before
        process._retire()  # the child is ended: its counts join, without a crash
    finally:
        ours.close()
        theirs.close()


def test_a_fault_in_what_takes_a_report_is_the_stations_not_the_childs() -> None:
    """A bug on the station's side (here its recorder) is not blamed on the child: before,
    it restarted a healthy child for ever, parking the pins each time (found by review)."""

    class BrokenRecorder:
        def add_frame(self, *args: Any) -> None:
            raise RuntimeError("station recorder bug")

        record_pins = add_frame

    process = _unserved(link=SameClockLink(), retry_min_s=0.05, retry_max_s=0.1)
    process.recorder = BrokenRecorder()
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        kind, report = _report(1, None)
        report["pins_samples"] = [(1, None, None, "no_frames")]
        theirs.send(pickle.dumps((kind, report)))
        with pytest.raises(RuntimeError, match="station recorder bug"):
            process._drain(ours)
    finally:
        ours.close()
        theirs.close()


class _NoPlatform:
    """A platform record that is never read (for a DisplayProcess whose child never runs)."""

    read_timeout_s = 0.25
    record_fd = 0


def _unserved(**kw: Any) -> DisplayProcess:
    """A DisplayProcess that is never served: its parts alone."""
    return DisplayProcess(display="sim", display_options={}, render_config=RendererConfig(),
                          scene="remote", interpolation_order=1, platform=_NoPlatform(),
                          loop_args={}, **kw)


def test_a_frame_too_large_to_hand_over_is_counted_not_raised() -> None:
    frames = _unserved().frames
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        frames.sock = ours
        small = make_frame(1, None)
        frames.put(small, 5)
        got = pickle.loads(theirs.recv(1 << 20))
        assert got[0] == "frame" and got[1].seq == 1 and got[2] == 5
        big = TactileFrame(seq=2, center_mm=(30.0, 30.0), pitch_mm=0.1, layers={
            "height_mm": np.zeros((512, 512), np.float32)})  # 1 MB: more than a packet
        frames.put(big, 6)
        assert frames.too_large == 1 and frames.superseded == 1 and frames.put_count == 2
        assert frames.accepted(1, 5) is small and frames.accepted(2, 6) is None
        theirs.close()
        frames.put(small, 7)  # the child is gone: counted, never raised
        assert frames.superseded == 2
    finally:
        ours.close()
        theirs.close()


def test_the_process_needs_a_platform_read_in_a_process_and_json_options() -> None:
    common = dict(display="sim", render_config=RendererConfig(), scene="hemisphere",
                  interpolation_order=1, loop_args={})
    with pytest.raises(ConfigError, match="ProcessPlatformReader"):
        DisplayProcess(display_options={}, platform=object(), **common)  # type: ignore[arg-type]
    reader = ProcessPlatformReader("sim")
    with pytest.raises(ConfigError, match="JSON"):
        DisplayProcess(display_options={"x": object()}, platform=reader,
                       **common)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="render_loop"):
        LocalAgentConfig(render_loop="process-ish")


def test_the_child_stops_when_the_stations_socket_ends() -> None:
    # the station's end of the socket closes (the station is gone): the child parks the pins,
    # closes the board, sends what it can of a final report and exits
    reader = ProcessPlatformReader("sim", {"motion": "hold:x=30,y=30,z=100"})
    process = DisplayProcess(display="sim", display_options={}, render_config=RendererConfig(),
                             scene="hemisphere", interpolation_order=1, platform=reader,
                             loop_args={})
    reader.start()
    proc = None
    try:
        child = process._spawn(0, 0)
        assert child is not None
        proc, sock = child
        wait_until(lambda: select.select([sock], [], [], 0)[0], 30.0, "the child's first report")
        sock.shutdown(socket.SHUT_WR)  # its receiver sees the end; we still read its reports
        reports: list[dict[str, Any]] = []
        while not (reports and reports[-1]["final"]):
            assert select.select([sock], [], [], scaled(15.0))[0], "no final report"
            data = sock.recv(1 << 20)
            assert data, "the socket ended without a final report"
            reports.append(pickle.loads(data)[1])
        final = reports[-1]
        assert final["pins"].safe_reason == "shutdown" and final["pins"].command is None
        assert final["display_stats"].safe_states_sent >= 1
        assert proc.wait(scaled(15.0)) == 0
        sock.close()
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        reader.stop()


# ---------------------------------------------------------------------- the station


@contextlib.asynccontextmanager
async def _station(height_mm: float = 2.0, **overrides: Any) -> AsyncIterator[
        tuple[LocalAgent, DisplayProcess, FakeRemote]]:
    """A station with its display loop in a process of its own, against a real relay and a
    fake remote, once its pins show the remote's frames; stopped (exit 0) after the block."""
    async with running_relay() as relay:
        url = f"ws://127.0.0.1:{relay.ws_port}/"
        agent = relay_agent(url, render_loop="process", **overrides)
        run = asyncio.create_task(agent.run())
        try:
            async with FakeRemote(url, height_mm=height_mm) as remote:
                await wait_for(lambda: agent.loop is not None
                               and _pins_at(agent, height_mm), 20.0, "pins at the frames'")
                loop = any_loop_of(agent)
                assert isinstance(loop, DisplayProcess) and loop.child_pid is not None
                yield agent, loop, remote
        finally:
            agent.request_stop("test")
            assert await run == 0


def _pins_at(agent: LocalAgent, height_mm: float) -> bool:
    fb = any_loop_of(agent).display.latest_feedback()
    return fb is not None and not fb.safe_state and \
        bool(np.all(np.abs(fb.position_mm - height_mm) < 0.15))


async def test_bad_frames_are_rejected_in_the_child_without_touching_the_pins() -> None:
    # every timeout that puts the pins safe made long: beside two CPU burners the platform
    # reader was once starved 256 ms, past the default 250, and the pins went safe (rightly:
    # platform_lost) mid-test; the child takes a station silent for about 140 ms as a lost
    # link, and the board's watchdog trips after 100 ms without a command (a stall of the
    # machine does either): what is tested is that bad frames leave the pins as they are
    # (5 s: the longest the settings allow, local_site.agent.config.MAX_SAFETY_TIMEOUT_S)
    async with _station(3.0, stale_frame_timeout_s=5.0, max_frame_age_s=5.0,
                        platform_read_timeout_s=5.0, platform_reopen_after_s=5.0,
                        link_loss_timeout_s=5.0,
                        display_watchdog_ms=5_000) as (agent, loop, remote):
        remote.paused = True
        await asyncio.sleep(scaled(0.2))  # frames in flight arrive, reports too
        sent = loop.counters.commands_sent
        nan = make_frame(900, None, 3.0)
        nan.layers["height_mm"][2, 3] = np.nan
        for bad in (nan, make_frame(901, None, 50.0),
                    TactileFrame(seq=902, center_mm=(30.0, 30.0), layers={
                        "height_mm": np.ones((4, 4)), "friction": np.ones((3, 3))})):
            agent.frames.put(bad, now_us())
            await asyncio.sleep(0.02)  # the child's hand-over keeps the newest only
        await wait_for(lambda: loop.counters.frames_rejected >= 3, 3.0,
                       "the child to reject the bad frames")
        await asyncio.sleep(scaled(0.1))
        assert loop.counters.frames_rejected == 3
        assert loop.counters.commands_sent == sent
        assert loop.counters.last_reject_reason
        assert _pins_at(agent, 3.0) and loop.safe_reason is None
    assert agent.summary is not None and agent.summary["frames_rejected"] == 3


async def test_a_silent_station_is_a_lost_link_for_the_child() -> None:
    # the station stops sending the link's state (as when it is stopped or starved) while
    # frames still arrive: the child cannot vouch for the link and puts the pins safe
    async with _station(safe_state="flat") as (agent, loop, _):
        silent = threading.Event()
        link_state = loop._link_state
        loop._link_state = lambda: None if silent.is_set() else link_state()  # type: ignore[method-assign]
        silent.set()
        await wait_for(lambda: loop.safe_reason == "link_lost", 2.0, "the child's safe state")
        await wait_for(lambda: (fb := loop.display.latest_feedback()) is not None
                       and fb.safe_state, 2.0, "pins flat")
        silent.clear()
        await wait_for(lambda: loop.safe_reason is None and _pins_at(agent, 2.0), 4.0,
                       "rendering again")
    assert agent.summary is not None
    assert agent.summary["safe_state"]["entries"].get("link_lost", 0) >= 1
    assert agent.summary["link"]["connection_losses"] == 0  # the relay link never went down


async def test_a_killed_child_is_started_again_and_its_counts_carry_over() -> None:
    async with _station(device_retry_min_s=0.05) as (agent, loop, _):
        first = loop.child_pid
        assert first is not None
        await wait_for(lambda: loop.counters.frames_rendered >= 3, 3.0, "frames")
        rendered = loop.counters.frames_rendered
        iterations = loop.periods.iterations
        os.kill(first, signal.SIGKILL)
        await wait_for(lambda: loop.restarts == 1, 5.0, "the child started again")
        assert loop.child_error is not None and "exited with -9" in loop.child_error
        # the dead child's counts stay (the new one needs a second to start)
        assert loop.counters.frames_rendered >= rendered
        assert loop.periods.iterations >= iterations
        await wait_for(lambda: loop.child_pid not in (None, first)
                       and loop.safe_reason is None and _pins_at(agent, 2.0)
                       and loop.counters.frames_rendered > rendered, 20.0,
                       "rendering by the new child")
        assert loop.periods.iterations > iterations
    s = agent.summary
    assert s is not None and s["display_loop"]["process_restarts"] == 1
    assert s["frames_rendered"] > rendered and s["display_loop"]["iterations"] > iterations
    assert s["display_loop"]["process_error"].startswith("display process exited")


async def test_a_stopped_child_leaves_the_pins_unknown_not_shown_as_before() -> None:
    # a child that stops reporting (SIGSTOP) must not leave its last command shown as the one
    # on the pins: the station shows no command until the child reports again
    async with _station() as (agent, loop, _):
        await wait_for(lambda: loop.last_command is not None, 2.0, "a command shown")
        pid = loop.child_pid
        assert pid is not None
        os.kill(pid, signal.SIGSTOP)
        try:
            await wait_for(lambda: loop.safe_reason == NO_WORD and loop.last_command is None,
                           1.0 + SILENCE_S, "the pin state marked unknown")
        finally:
            os.kill(pid, signal.SIGCONT)
        await wait_for(lambda: loop.safe_reason is None and loop.last_command is not None
                       and _pins_at(agent, 2.0), 10.0, "the child's state again")
        assert loop.restarts == 0 and loop.child_pid == pid
    s = agent.summary
    assert s is not None and s["display"]["last_feedback_safe_state"] is not None
    assert s["display"]["driver"]["safe_states_sent"] >= 1  # the shutdown's, at least


def test_heartbeat_is_well_inside_the_link_loss_timeout() -> None:
    # the child counts a silence beyond two heartbeats as a lost link; the default link-loss
    # timeout must leave room for a late heartbeat or two
    assert LocalAgentConfig().link_loss_timeout_s > 2 * HEARTBEAT_S


# ---------------------------------------------------------------------- the process alone
# (a review's findings, each failing on the code before its mend)


@contextlib.contextmanager
def _served(scene: str, link: Any = None, **kw: Any) -> Iterator[
        tuple[DisplayProcess, threading.Event]]:
    """A DisplayProcess served in a thread (as the station runs it), its platform read in a
    process of its own; stopped after the block (the serving thread must end)."""
    reader = ProcessPlatformReader("sim", {"motion": "hold:x=30,y=30,z=100"},
                                   read_timeout_s=scaled(0.25))
    reader.start()
    process = DisplayProcess(display="sim", display_options={},
                             render_config=RendererConfig(), scene=scene,
                             interpolation_order=1, platform=reader, loop_args={}, link=link,
                             retry_min_s=0.05, **kw)
    stop = threading.Event()
    thread = threading.Thread(target=process.run_in_thread, args=(stop,), daemon=True)
    thread.start()
    try:
        yield process, stop
    finally:
        stop.set()
        thread.join(scaled(20.0))
        reader.stop()
    assert not thread.is_alive(), "the display process's supervisor did not stop"


def test_the_pins_are_recorded_at_the_recorders_rate_stamped_when_read() -> None:
    # sampled in the child as the loop reads them, not one per 20 ms report stamped when
    # the report arrives
    samples: list[tuple[int, Any, Any, str | None, int]] = []

    class Recorder:
        pins_sampler = PinsSampler(200.0)

        def add_frame(self, frame: TactileFrame, rx_us: int) -> None:
            pass

        def record_pins(self, t_us: int, commanded: Any, measured: Any,
                        safe_reason: str | None) -> None:
            samples.append((t_us, commanded, measured, safe_reason, now_us()))

    with _served("hemisphere", recorder=Recorder()):
        wait_until(lambda: len(samples) > 100, 30.0, "pins samples")
    stamps = np.array([s[0] for s in samples], np.int64)
    gaps_ms = np.diff(stamps) / 1e3
    assert np.all(gaps_ms >= 5.0 - 0.1)  # never above the recorder's rate
    assert float(np.median(gaps_ms)) < 10.0  # at its rate (one per report: 20 ms)
    assert all(t <= arrived for t, *_, arrived in samples)  # stamped before they arrive
    assert all(isinstance(s[1], PinCommand) and s[3] is None for s in samples)
    # the board's measured positions
    assert any(s[2] is not None and np.size(s[2]) == 16 for s in samples)


def test_a_report_too_large_for_a_packet_sheds_its_oldest_items_not_all() -> None:
    # a station that took no report for long: what waits no longer fits one packet; the
    # reporter gives up the oldest half (counted) and sends the rest, never everything
    import errno as errno_

    from local_site.agent.display_child import _Reporter, _TappedLedger

    class Board:
        is_connected = True

        def latest_feedback(self) -> None:
            return None

        def stats(self) -> DisplayStats:
            return DisplayStats()

    class Loop:
        periods = PeriodStats(0.001)
        display = Board()
        counters = DisplayLoopCounters()
        priority_applied = realtime_applied = None
        pin_state = PinState()
        safe_since_s = started_s = None

        class renderer:
            stats = RenderStats()

    sent: list[dict[str, Any]] = []

    class Sock:
        def send(self, data: bytes, flags: int = 0) -> int:
            if len(data) > 20_000:
                raise OSError(errno_.EMSGSIZE, "Message too long")
            sent.append(pickle.loads(data)[1])
            return len(data)

    reporter = _Reporter(Loop(), _TappedLedger(), Sock(), None)  # type: ignore[arg-type]
    for seq in range(200):
        reporter.accepted.append((seq, seq))
    reporter._pins_samples = [(t, None, np.zeros(16), None) for t in range(200)]
    reporter.send()
    assert len(sent) == 1 and reporter.shed > 0 and reporter.dropped == 0
    report = sent[0]
    kept = [seq for seq, _ in report["accepted"]]
    assert kept and kept[-1] == 199 and kept == sorted(kept)  # the newest kept, in order
    assert len(kept) + len(report["pins_samples"]) + report["shed"] == 400
    assert report["shed"] == reporter.shed
    reporter.send()  # nothing pending now
    assert sent[-1]["accepted"] == [] and sent[-1]["pins_samples"] == []


def test_the_pins_sampler_keeps_its_rate_and_records_the_safe_state() -> None:
    with pytest.raises(ConfigError, match="pins_rate_hz"):
        PinsSampler(0.0)

    class Board:
        is_connected = False

    sampler = PinsSampler(1e-3)
    assert sampler.offer(None, Board(), None) is None  # nothing on the pins, not safe
    first = sampler.offer("command", Board(), None)
    assert first is not None and first[1:] == ("command", None, None)
    assert abs(first[0] - now_us()) < 5e6
    assert sampler.offer("command", Board(), None) is None  # not due for 1,000 s
    safe = sampler.offer(None, Board(), "no_frames")  # the safe state: a change, at once
    assert safe is not None and safe[1:] == (None, None, "no_frames")


def test_frames_superseded_in_the_childs_hand_over_are_counted() -> None:
    with _served("remote", SameClockLink()) as (process, _):
        wait_until(lambda: process.periods.iterations > 200, 30.0, "the child's loop")
        for seq in range(1, 201):  # a burst, as after a stall of the relay's leg
            process.frames.put(make_frame(seq, None), now_us())
        wait_until(lambda: process.frames.put_count - process.counters.frames_accepted
                   - process.counters.frames_rejected - process.frames.superseded <= 1, 5.0,
                   "every frame accounted for")
    c = process.counters
    assert c.frames_accepted >= 1 and process.frames.superseded >= 100


def test_the_boards_and_renderers_counts_carry_over_a_killed_child() -> None:
    with _served("hemisphere") as (process, _):
        wait_until(lambda: process.counters.keepalives_sent > 50, 30.0, "the first child")
        first = process.child_pid
        assert first is not None
        before = process.display.stats().keepalives
        rendered = process.renderer.stats.rendered + process.renderer.stats.skipped
        os.kill(first, signal.SIGKILL)
        wait_until(lambda: process.restarts == 1, 10.0, "the second child")
        assert process.display.stats().keepalives >= before
        assert process.renderer.stats.rendered + process.renderer.stats.skipped >= rendered
        wait_until(lambda: process.child_pid not in (None, first)
                   and process.display.stats().keepalives > before, 30.0,
                   "the second child sending")
    stats = process.display.stats()
    assert stats.keepalives >= process.counters.keepalives_sent > 50


def test_stop_returns_when_the_child_does_not_read_its_socket() -> None:
    # a child that never reads (stopped, or stuck on a device): its socket fills up, and
    # stopping the station must still end (the child is killed after its grace)
    class Platform:
        read_timeout_s = 0.25

        def __init__(self) -> None:
            self.record_fd = os.open(os.devnull, os.O_RDONLY)

    platform = Platform()
    process = DisplayProcess(display="sim", display_options={}, render_config=RendererConfig(),
                             scene="remote", interpolation_order=1, platform=platform,
                             loop_args={}, link=SameClockLink(), hang_timeout_s=600.0)
    process.child_argv = ("-c", "import time; time.sleep(600)")
    stop = threading.Event()
    thread = threading.Thread(target=process.run_in_thread, args=(stop,), daemon=True)
    thread.start()
    try:
        wait_until(lambda: process.child_pid is not None, 10.0, "the child")
        pid = process.child_pid
        big = TactileFrame(seq=1, center_mm=(30.0, 30.0), pitch_mm=1.0,
                           layers={"height_mm": np.zeros((100, 100), np.float32)})
        while process.frames.dropped == 0:  # until its socket is full
            process.frames.put(big, 1)
        stop.set()
        thread.join(scaled(15.0))  # the child's grace is 6 s
        assert not thread.is_alive(), "stopping waited for a child that does not read"
        assert pid is not None
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)  # killed and reaped
    finally:
        stop.set()
        os.close(platform.record_fd)


def test_sigterm_to_the_child_is_left_to_the_station() -> None:
    # systemd stops a unit with SIGTERM to all its processes: the child leaves it to the
    # station, which stops it cleanly (pins parked, final report), never a crash
    with _served("hemisphere") as (process, stop):
        wait_until(lambda: process.counters.keepalives_sent > 20, 30.0, "the child")
        assert process.child_pid is not None
        os.kill(process.child_pid, signal.SIGTERM)
        time.sleep(scaled(0.2))
        assert process.restarts == 0 and process.child_error is None
        stop.set()
    assert process.child_error is None and process.restarts == 0
    assert process.display.stats().safe_states_sent >= 1  # parked by the final act
    assert process.safe_reason == "shutdown" and process.last_command is None


def test_an_accepted_frame_reported_at_once_is_still_recorded() -> None:
    # the child's report accepting a frame may be folded in before put() returns
    recorded: list[int] = []

    class Recorder:
        pins_sampler = PinsSampler(50.0)

        def add_frame(self, frame: TactileFrame, rx_us: int) -> None:
            recorded.append(frame.seq)

        def record_pins(self, *args: Any) -> None:
            pass

    process = _unserved(recorder=Recorder())
    report = {"periods": np.zeros(0), "loops": (1, 0),
              "counters": DisplayLoopCounters(frames_accepted=1),
              "render_stats": RenderStats(), "display_stats": DisplayStats(), "superseded": 0,
              "priority": (None, None), "connected": True, "feedback": None,
              "pins": PinState(), "accepted": [(7, 123)], "rendered": [], "pins_samples": [],
              "safe_since_s": None, "started_s": None, "shed": 0, "final": False}

    class Sock:
        def send(self, data: bytes, flags: int = 0) -> int:
            process._take(("report", report))  # the supervisor runs in between
            return len(data)

    process.frames.sock = Sock()  # type: ignore[assignment]
    process.frames.put(make_frame(7, None), 123)
    assert recorded == [7]


def _report(iterations: int, safe_since_s: float | None, final: bool = False,
            started_s: float | None = None) -> tuple[str, dict[str, Any]]:
    return ("report", {
        "periods": np.zeros(0), "loops": (iterations, 0), "counters": DisplayLoopCounters(),
        "render_stats": RenderStats(), "display_stats": DisplayStats(), "superseded": 0,
        "priority": (None, None), "connected": True, "feedback": None,
        "pins": PinState(None, None if safe_since_s is None else "platform_lost", 1),
        "safe_since_s": safe_since_s, "started_s": started_s, "accepted": [], "rendered": [],
        "pins_samples": [], "shed": 0, "final": final})


def test_safe_time_counts_open_episodes_killed_children_and_gaps_without_a_child() -> None:
    # what no child's counters hold: the running child's open episode, the episode a
    # killed child had open, and the time until the next child drives the board
    process = _unserved()
    process._spawned_s = monotonic_s() - 10.0
    process._take(_report(10, monotonic_s() - 5.0))  # safe for 5 s, still open
    assert 5.0 <= process.counters.safe_time_s < 5.0 + scaled(1.0)
    process._retire()  # killed with the episode open: counted up to now, then the gap
    at_retire = process.counters.safe_time_s
    assert 5.0 <= at_retire < 5.0 + scaled(1.0)
    wait_until(lambda: process.counters.safe_time_s > at_retire, 5.0, "the gap counted")
    process._take(_report(1, None))  # the next child renders: the gap ends
    closed = process.counters.safe_time_s
    assert at_retire < closed < at_retire + scaled(1.0)
    time.sleep(0.05)
    assert process.counters.safe_time_s == closed
    process._loop_seen_s = monotonic_s() - 2.0  # its loop last advanced 2 s ago
    process._retire()  # killed while rendering: from its loop's last progress on
    assert closed + 2.0 <= process.counters.safe_time_s < closed + 2.0 + scaled(1.0)


def test_the_gap_ends_at_the_next_childs_first_tick_not_at_its_first_report() -> None:
    # the next child counts its own safe time from its first tick; the gap before it ends
    # there, not when its first report arrives (up to a heartbeat later): never both
    process = _unserved()
    process._spawned_s = monotonic_s() - 10.0
    process._take(_report(10, None))
    process._retire()
    counted, _, gap_since = process._untold  # the killed child's time since its progress
    assert gap_since is not None
    time.sleep(0.05)
    first_tick = gap_since + 0.02
    process._take(_report(1, first_tick, started_s=first_tick))  # safe from its first tick
    assert process._untold[0] - counted == pytest.approx(0.02, abs=1e-6)
    assert process._untold[1:] == (first_tick, None)


def test_safe_time_after_a_crash_counts_the_gap_not_the_episode_twice() -> None:
    # a loop that crashed still sends a final report (its counters hold its episode), then
    # the child ends unasked: the time until the next child is safe time
    process = _unserved()
    process._spawned_s = monotonic_s() - 10.0
    process._take(_report(5, None, final=True))
    process._retire()
    wait_until(lambda: process.counters.safe_time_s > 0.0, 5.0, "the gap counted")
    assert process.counters.safe_time_s < scaled(1.0)


def test_safe_time_is_not_counted_before_a_child_ran_and_stops_growing_when_stopped() -> None:
    process = _unserved()
    process._retire()  # could not start (e.g. the platform's record not there yet)
    assert process.counters.safe_time_s == 0.0
    # stopped during the backoff after a child died: the gap ends with the supervisor
    process._spawned_s = monotonic_s() - 1.0
    process._take(_report(5, monotonic_s() - 0.5))
    process._retire()
    stop = threading.Event()
    stop.set()
    process.run_in_thread(stop)
    frozen = process.counters.safe_time_s
    assert frozen >= 0.5
    time.sleep(0.05)
    assert process.counters.safe_time_s == frozen


def test_the_pin_state_goes_unknown_when_read_even_without_the_supervisor() -> None:
    process = _unserved()
    command = PinCommand(np.full((4, 4), 2.0), np.full((4, 4), 0.8), np.zeros((4, 4)))
    report = {"periods": np.zeros(0), "loops": (10, 0), "counters": DisplayLoopCounters(),
              "render_stats": RenderStats(), "display_stats": DisplayStats(), "superseded": 0,
              "priority": (None, None), "connected": True, "feedback": None,
              "pins": PinState(command, None, 3), "accepted": [], "rendered": [],
              "pins_samples": [], "safe_since_s": None, "started_s": None, "shed": 0,
              "final": False}
    process._take(("report", report))
    assert process.last_command is command and process.safe_reason is None
    # nothing more from the child (no supervisor runs here): unknown once SILENCE_S passed
    wait_until(lambda: process.safe_reason == NO_WORD, 2.0, "the state marked unknown")
    assert process.last_command is None
    # a report whose loop did not advance (a wedged loop, a live reporter) does not revive it
    process._take(("report", report))
    assert process.safe_reason == NO_WORD
    process._take(("report", {**report, "loops": (11, 0)}))
    assert process.last_command is command


@pytest.mark.parametrize(("loop_realtime", "expected"), [
    (6, (os.SCHED_FIFO, 5)),  # one below the loop's
    (1, (os.SCHED_OTHER, 0)),  # no level below the lowest: an ordinary thread
    (None, (os.SCHED_OTHER, 0)),  # the loop is not real-time (refused, or not asked for)
])
def test_the_childs_receiving_thread_runs_just_below_a_real_time_loop(
        loop_realtime: int | None, expected: tuple[int, int]) -> None:
    # frames reach the loop when they arrive, not when an ordinary thread is next run; the
    # level follows the priority the loop actually got, once it runs
    from local_site.agent.display_child import _receive
    from local_site.agent.display_loop import thread_realtime

    with thread_realtime(5) as permitted:
        if permitted is None:
            pytest.skip("SCHED_FIFO 5 needs root, CAP_SYS_NICE or RLIMIT_RTPRIO here")
    seen: list[tuple[int, int]] = []

    class Slot:
        def put(self, frame: TactileFrame, rx_us: int) -> None:
            tid = threading.get_native_id()
            seen.append((os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority))

    class Loop:
        started_s: float | None = None  # not running yet: its scheduling is not decided
        realtime_applied = loop_realtime

    loop = Loop()
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    with ours, theirs:
        stop = threading.Event()
        receiver = threading.Thread(target=_receive, args=(theirs, Slot(), None, stop, loop),
                                    daemon=True)
        receiver.start()
        frame = pickle.dumps(("frame", make_frame(1, None), 7), protocol=5)
        ours.send(frame)
        wait_until(lambda: len(seen) == 1, 5.0, "the first frame handed over")
        loop.started_s = monotonic_s()  # the loop runs now
        ours.send(frame)
        ours.send(pickle.dumps(("stop",), protocol=5))
        receiver.join(scaled(5.0))
        assert not receiver.is_alive() and stop.is_set()
    assert seen == [(os.SCHED_OTHER, 0), expected]


def test_the_childs_receiving_thread_says_so_when_real_time_is_refused(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    # the refusal names this thread (not the loop's) and the thread goes on as it was
    from local_site.agent import display_child

    def refuse(*args: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)

    class Loop:
        started_s: float | None = monotonic_s()
        realtime_applied: int | None = 6

    with caplog.at_level("INFO"), contextlib.ExitStack() as scheduling:
        assert display_child._follow_the_loop(Loop(), scheduling)
    assert ("display process: its receiving thread keeps its scheduling policy "
            "(SCHED_FIFO 5 refused") in caplog.text
    assert "display loop thread" not in caplog.text
