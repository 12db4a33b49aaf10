"""The display loop renders a tactile frame only while its capture stamp says it is fresh.

Freshness is judged by the frame's own capture stamp on the remote clock, converted with the
relay's offsets and their error bound (``shared.freshness``), never by when it arrived: a
frame held in a socket or a queue through an outage, or one taken in after the local station
was stopped for a while, is old whenever it arrives.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from local_site.agent.display_loop import DisplayLoop, FrameSlot
from local_site.devices import open_display
from local_site.platform.base import PlatformSample
from local_site.render import Renderer
from local_site.scenes import TactileFrameScene
from shared.freshness import ClockView
from shared.protocol import TactileFrame
from shared.timebase import now_us


class FakeLink:
    """Clock offsets as the relay would report them; the link itself is up."""

    def __init__(self, local_us: int | None = 0, remote_us: int | None = 0,
                 u_local_us: int = 500, u_remote_us: int = 500) -> None:
        self.offsets = {"local": local_us, "remote": remote_us}
        self.unc = {"local": u_local_us, "remote": u_remote_us}
        self.view_received_us = now_us()

    def link_down_for_s(self, now_s: float | None = None) -> float:
        return 0.0

    @property
    def clock_offsets_us(self) -> dict[str, int | None]:
        return dict(self.offsets)

    @property
    def clock_view(self) -> ClockView | None:
        return ClockView(dict(self.offsets), dict(self.unc), self.view_received_us)


SAMPLE = PlatformSample(position_mm=(30.0, 30.0, 100.0), velocity_mm_s=(0.0, 0.0, 0.0),
                        t_us=0, seq=1, board_t_us=0)


def frame(seq: int, ts_us: int) -> TactileFrame:
    return TactileFrame(seq=seq, ts_us=ts_us, center_mm=(30.0, 30.0), pitch_mm=1.0,
                        layers={"height_mm": np.full((9, 9), 2.0, np.float32)}, contact=True)


Build = Callable[..., tuple[DisplayLoop, FrameSlot]]


@pytest.fixture(params=["prepared_where_put", "prepared_in_the_loop"])
def make_loop(request: pytest.FixtureRequest) -> Iterator[Build]:
    """A loop fed through a slot that prepares each frame where it is put (the station's
    way), or one that leaves it to the loop: every rule holds for both."""
    loops: list[DisplayLoop] = []

    def build(link: FakeLink, **kw: Any) -> tuple[DisplayLoop, FrameSlot]:
        scene = TactileFrameScene()
        slot = FrameSlot(prepare=scene.prepare if request.param == "prepared_where_put"
                         else None)
        display = open_display("sim")
        loop = DisplayLoop(display, Renderer(), scene, positions=lambda: SAMPLE,
                           platform_ok=lambda: True, frames=slot, link=link,
                           stale_timeout_s=kw.pop("stale_timeout_s", 10.0), **kw)
        loops.append(loop)
        return loop, slot

    yield build
    for loop in loops:
        loop.display.disconnect()


def test_a_fresh_frame_is_rendered(make_loop: Build) -> None:
    loop, slot = make_loop(FakeLink())
    slot.put(frame(1, now_us() - 20_000), now_us())
    loop.tick()
    assert loop.safe_reason is None and loop.counters.commands_sent == 1
    assert 20.0 <= loop.counters.rendered_frame_age_max_ms < 20.0 + 1000.0


def test_a_frame_old_by_its_stamp_is_never_rendered_however_recently_it_arrived(
        make_loop: Build) -> None:
    loop, slot = make_loop(FakeLink())
    slot.put(frame(1, now_us() - 2_000_000), now_us())  # held 2 s in a blackholed socket
    loop.tick()
    assert loop.safe_reason == "stale_frame" and loop.counters.commands_sent == 0
    assert loop.last_frame_verdict is not None and loop.last_frame_verdict.verdict == "stale"


def test_the_error_bound_counts_against_the_frame(make_loop: Build) -> None:
    """120 ms old by the estimate, bound 2 x 20 ms: it may be 160 ms old (> 150): refused."""
    loop, slot = make_loop(FakeLink(u_local_us=20_000, u_remote_us=20_000),
                           max_offset_uncertainty_s=0.05)
    slot.put(frame(1, now_us() - 120_000), now_us())
    loop.tick()
    assert loop.safe_reason == "stale_frame"


def test_the_remote_clock_is_corrected_with_the_offsets(make_loop: Build) -> None:
    """The remote clock runs 5 s ahead of the relay, ours on time: a stamp 5 s in our future
    is a fresh frame; uncorrected, it would look 5 s from the future (or, the other way
    round, 5 s old)."""
    loop, slot = make_loop(FakeLink(local_us=0, remote_us=5_000_000))
    slot.put(frame(1, now_us() + 5_000_000 - 10_000), now_us())
    loop.tick()
    assert loop.safe_reason is None
    loop2, slot2 = make_loop(FakeLink(local_us=0, remote_us=0))
    slot2.put(frame(1, now_us() + 5_000_000 - 10_000), now_us())
    loop2.tick()
    assert loop2.safe_reason == "clock_uncertain"  # from the future: the offsets are wrong
    assert loop2.last_frame_verdict is not None and loop2.last_frame_verdict.verdict == "future"


@pytest.mark.parametrize("link", [FakeLink(remote_us=None),
                                  FakeLink(u_local_us=40_000, u_remote_us=1_000)])
def test_unknown_or_uncertain_offsets_keep_the_pins_safe(make_loop: Build, link: FakeLink) -> None:
    loop, slot = make_loop(link)
    slot.put(frame(1, now_us()), now_us())
    loop.tick()
    assert loop.safe_reason == "clock_uncertain" and loop.counters.commands_sent == 0


class SteppedClock:
    """The loop's wall clock, moved on by the test (a process stopped at a chosen point)."""

    def __init__(self) -> None:
        self.t_us = now_us()

    def __call__(self) -> int:
        return self.t_us


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> SteppedClock:
    """The loop's wall clock and the monotonic clock of the loop and the display driver,
    moved together (a stopped process sees both jump)."""
    c = SteppedClock()
    monkeypatch.setattr("local_site.agent.display_loop.now_us", c)
    mono0, t0 = time.monotonic(), c.t_us

    def mono() -> float:
        return mono0 + (c.t_us - t0) / 1e6

    monkeypatch.setattr("local_site.agent.display_loop.monotonic_s", mono)
    monkeypatch.setattr("local_site.display.base.monotonic_s", mono)
    return c


def test_a_frame_goes_stale_on_the_pins_when_no_newer_one_comes(
        make_loop: Build, clock: SteppedClock) -> None:
    """Rendering stops when the frame on the pins ages past the bound, by its stamp (a
    stopped sender, or a local station that was itself stopped): nothing newer is needed.
    (The loop's clocks stepped by the test: on the real ones a stall of 10 ms between the
    put and the first tick aged the frame past the bound.)"""
    loop, slot = make_loop(FakeLink(), max_frame_age_s=0.15)
    stamp = clock.t_us - 140_000
    slot.put(frame(1, stamp), clock.t_us)
    loop.tick()
    assert loop.safe_reason is None
    while loop.safe_reason is None and clock.t_us - stamp < 2_000_000:
        clock.t_us += 1_000
        loop.tick()
    assert loop.safe_reason == "stale_frame"
    age_us = clock.t_us - stamp
    # at the bound, not before it (less the 2 x 500 us error bound), nor a tick after it
    assert 150_000 - 1_000 <= age_us <= 150_000 + 1_000, age_us


def test_a_frame_that_ages_out_between_the_check_and_the_send_is_not_sent(
        make_loop: Build, clock: SteppedClock) -> None:
    """The process stops for 3 s after the safety check, while rendering (a SIGSTOP, a
    starved thread): the age is judged again before the send, so nothing goes out."""
    loop, slot = make_loop(FakeLink())
    orig_render = loop.renderer.render

    def slow_render(*args: Any, **kw: Any) -> Any:
        clock.t_us += 3_000_000
        return orig_render(*args, **kw)

    loop.renderer.render = slow_render  # type: ignore[method-assign]
    slot.put(frame(1, clock.t_us - 20_000), clock.t_us)
    loop.tick()
    assert loop.safe_reason == "stale_frame"
    assert loop.counters.commands_sent == 0 and loop.counters.frames_rendered == 0
    assert loop.counters.late_sends_refused == 1 and loop.display.stats().frames_sent == 0


def test_a_keepalive_past_the_frames_deadline_is_not_sent(
        make_loop: Build, clock: SteppedClock) -> None:
    """The frame was rendered; the pins hold it and the driver re-sends it as a keepalive
    (the board's watchdog needs one). Stopped after the tick's check, the keepalive would
    re-send old touch (and, on a separate board, undo the safe state its watchdog took):
    the driver refuses it."""
    loop, slot = make_loop(FakeLink())
    slot.put(frame(1, clock.t_us - 20_000), clock.t_us)
    loop.tick()
    assert loop.counters.frames_rendered == 1
    before = loop.display.stats()
    loop._frame_deadline_s = 0.0  # as if the process slept past it after the tick's check
    clock.t_us += 300_000  # past the driver's keepalive interval
    loop._keepalive()
    assert loop.counters.late_sends_refused == 1 and loop.safe_reason == "stale_frame"
    after = loop.display.stats()
    assert after.frames_sent == before.frames_sent  # no keepalive went out
    assert after.safe_states_sent == before.safe_states_sent + 1


def test_a_command_sent_while_its_frame_aged_out_is_withdrawn_at_once(
        make_loop: Build, clock: SteppedClock) -> None:
    """The process stops for 3 s inside the send: the command may have reached the pins with
    a frame that is now 3 s old; the loop sends the safe state right after, counts it as
    withdrawn and never as rendered."""
    loop, slot = make_loop(FakeLink())
    display = loop.display
    orig_send = display.send_command
    calls: list[str] = []
    orig_safe = display.safe_state

    def stopped_in_send(*args: Any, **kw: Any) -> Any:
        out = orig_send(*args, **kw)
        calls.append("command")
        clock.t_us += 3_000_000
        return out

    def safe_state(*args: Any, **kw: Any) -> None:
        calls.append("safe")
        orig_safe(*args, **kw)

    display.send_command = stopped_in_send  # type: ignore[method-assign]
    display.safe_state = safe_state  # type: ignore[method-assign]
    slot.put(frame(1, clock.t_us - 20_000), clock.t_us)
    loop.tick()
    assert calls == ["command", "safe"]
    assert loop.safe_reason == "stale_frame"
    assert loop.counters.late_sends_withdrawn == 1 and loop.counters.frames_rendered == 0


def test_a_fresh_frame_is_rendered_once_the_clock_is_injected(
        make_loop: Build, clock: SteppedClock) -> None:
    """The control case of the two above: the same frame, no stop, is rendered."""
    loop, slot = make_loop(FakeLink())
    slot.put(frame(1, clock.t_us - 20_000), clock.t_us)
    loop.tick()
    assert loop.safe_reason is None and loop.counters.frames_rendered == 1
    assert loop.counters.late_sends_withdrawn == 0


def test_a_frame_is_gridded_in_the_thread_that_puts_it_not_in_the_loop(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The station prepares each frame where it arrives: the loop's tick only swaps the grid
    in (about half a millisecond of validation and gridding per frame kept out of the 1 ms
    period), and renders what preparing in the loop renders."""
    import threading

    built_in: list[int] = []
    original = TactileFrameScene._grid_from_frame

    def spy(self: TactileFrameScene, f: TactileFrame) -> Any:
        built_in.append(threading.get_ident())
        return original(self, f)

    monkeypatch.setattr(TactileFrameScene, "_grid_from_frame", spy)
    commands = []
    for prepare_where_put in (True, False):
        scene = TactileFrameScene()
        slot = FrameSlot(prepare=scene.prepare if prepare_where_put else None)
        display = open_display("sim")
        try:
            loop = DisplayLoop(display, Renderer(), scene, positions=lambda: SAMPLE,
                               platform_ok=lambda: True, frames=slot, link=FakeLink())
            built_in.clear()
            putter = threading.Thread(target=slot.put, args=(frame(1, now_us()), now_us()))
            putter.start()
            putter.join()
            loop.tick()
            assert loop.safe_reason is None and loop.counters.frames_accepted == 1
            where = putter.ident if prepare_where_put else threading.get_ident()
            assert built_in == [where]
            assert loop.last_command is not None
            commands.append(loop.last_command.height_mm)
        finally:
            display.disconnect()
    np.testing.assert_array_equal(commands[0], commands[1])


def test_a_bad_frame_prepared_where_put_is_refused_by_the_loop_and_counted() -> None:
    """The slot keeps the error with the frame: ``put`` never raises into the link task,
    and the loop refuses the frame as it refuses one it prepared itself (counted, the
    reason kept, the pins untouched)."""
    scene = TactileFrameScene()
    slot = FrameSlot(prepare=scene.prepare)
    display = open_display("sim")
    try:
        loop = DisplayLoop(display, Renderer(), scene, positions=lambda: SAMPLE,
                           platform_ok=lambda: True, frames=slot, link=FakeLink(),
                           stale_timeout_s=10.0)
        slot.put(frame(1, now_us()), now_us())
        loop.tick()
        good = loop.last_command
        assert good is not None
        bad = frame(2, now_us())
        bad.layers["height_mm"][4, 4] = np.nan
        slot.put(bad, now_us())
        loop.tick()
        assert loop.counters.frames_rejected == 1 and scene.frames_rejected == 1
        assert "NaN" in (loop.counters.last_reject_reason or "")
        assert scene.last_seq == 1 and loop.last_command is good
    finally:
        display.disconnect()


def test_a_slot_preparing_frames_for_another_scene_is_refused() -> None:
    from shared.errors import ConfigError

    display = open_display("sim", connect=False)
    with pytest.raises(ConfigError, match="another scene"):
        DisplayLoop(display, Renderer(), TactileFrameScene(), positions=lambda: SAMPLE,
                    platform_ok=lambda: True, frames=FrameSlot(TactileFrameScene().prepare),
                    link=FakeLink())
