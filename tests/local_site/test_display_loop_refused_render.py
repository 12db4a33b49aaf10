"""A refused render never puts old touch back on the pins (found by review, 2026-12-07).

When the renderer refuses a tick (a non-finite platform sample), the loop keeps the pins'
command alive. It used to re-send whatever the driver sent last, under the newest frame's
deadline: the touch of a frame past its bound, or of one withdrawn by a safe state, went
back on the pins as fresh.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from local_site.agent.display_loop import DisplayLoop, FrameSlot, SameClockLink
from local_site.display import frames as fr
from local_site.platform.base import PlatformSample
from local_site.render import Renderer
from local_site.scenes import TactileFrameScene
from shared.errors import DeviceInitError, DeviceOperationError
from shared.protocol import TactileFrame
from shared.timebase import now_us
from tests.local_site.test_local_hot_paths import _CaptureDisplay
from tests.support import scaled, wait_until

MAX_AGE_S = 1.0
#: how long frame A stays fresh after it is made: the first tick must come within it (scaled:
#: a loaded machine may take a while), and the test then waits it out
FRESH_FOR_S = min(0.5, scaled(0.05))
GOOD = PlatformSample((30.0, 30.0, 0.0), (0.0, 0.0, 0.0), 0, 1, 0)
BAD = PlatformSample((float("nan"), 30.0, 0.0), (0.0, 0.0, 0.0), 0, 2, 0)


class CaptureDisplay(_CaptureDisplay):
    """The driver's own logic, its frames kept instead of written to a board; a 1 ms
    keepalive interval."""

    def __init__(self) -> None:
        super().__init__(keepalive_interval_s=0.001)

    def heights(self) -> list[str | float]:
        """Each frame sent: its first pin's height (mm), or "safe"."""
        return ["safe" if arb == fr.ARB_ID_SAFE_STATE
                else round(float(fr.decode_command(p).height_mm[0]), 3)
                for arb, p in self.sent]


def frame(seq: int, height_mm: float, age_s: float = 0.0) -> TactileFrame:
    return TactileFrame(seq=seq, ts_us=now_us() - int(age_s * 1e6), center_mm=(30.0, 30.0),
                        pitch_mm=1.0, layers={"height_mm": np.full((9, 9), height_mm,
                                                                   np.float32)})


def build() -> tuple[DisplayLoop, FrameSlot, CaptureDisplay, list[PlatformSample]]:
    display = CaptureDisplay()
    display.connect()
    slot = FrameSlot()
    sample = [GOOD]
    loop = DisplayLoop(display, Renderer(), TactileFrameScene(), positions=lambda: sample[0],
                       platform_ok=lambda: True, frames=slot, link=SameClockLink(),
                       max_frame_age_s=MAX_AGE_S, stale_timeout_s=10.0)
    return loop, slot, display, sample


def past(deadline_s: float) -> None:
    """Let the monotonic clock pass ``deadline_s`` (a few milliseconds here)."""
    while time.monotonic() <= deadline_s:
        time.sleep(0.001)


def test_a_refused_render_keeps_a_command_alive_only_while_its_own_frame_is_fresh() -> None:
    loop, slot, display, sample = build()
    made = time.monotonic()
    slot.put(frame(1, 3.0, age_s=MAX_AGE_S - FRESH_FOR_S), now_us())  # A: fresh a while more
    loop.tick()
    assert display.heights() == [3.0] and loop.pin_state.command is not None
    past(made + FRESH_FOR_S + 0.001)  # A is past its bound now
    sample[0] = BAD
    slot.put(frame(2, 0.5), now_us())  # B: fresh, but its render is refused
    loop.tick()
    assert loop.counters.render_rejected == 1
    # A's touch was not re-sent under B's deadline: refused at the driver, pins safe
    assert display.heights() == [3.0, "safe"]
    assert loop.safe_reason == "stale_frame" and loop.counters.late_sends_refused == 1


def test_a_refused_render_after_a_safe_state_sends_nothing() -> None:
    loop, slot, display, sample = build()
    made = time.monotonic()
    slot.put(frame(1, 3.0, age_s=MAX_AGE_S - FRESH_FOR_S), now_us())
    loop.tick()
    past(made + FRESH_FOR_S + 0.001)
    loop.tick()  # A aged out: the pins go safe
    assert display.heights() == [3.0, "safe"] and loop.safe_reason == "stale_frame"
    sample[0] = BAD
    slot.put(frame(2, 0.5), now_us())
    for _ in range(3):  # B is fresh, so the loop leaves the safe state; every render refused
        loop.tick()
    assert loop.counters.render_rejected == 3
    assert display.heights() == [3.0, "safe"]  # nothing after the safe state
    assert loop.pin_state.command is None


def test_a_refused_render_keeps_a_fresh_command_alive() -> None:
    # the rule the fix keeps: a transient refusal leaves the pins their (fresh) command
    loop, slot, display, sample = build()
    slot.put(frame(1, 3.0), now_us())
    loop.tick()
    sample[0] = BAD
    past(time.monotonic() + 0.002)  # the keepalive interval (1 ms) has passed
    loop.tick()
    assert loop.counters.render_rejected == 1 and loop.counters.keepalives_sent == 1
    assert display.heights() == [3.0, 3.0] and loop.safe_reason is None


class FlakyDisplay(CaptureDisplay):
    """A board whose link fails (and cannot be reopened) while ``fail`` is set."""

    def __init__(self) -> None:
        super().__init__()
        self.fail = False

    def _connect(self) -> None:
        if self.fail:
            raise DeviceInitError("board unplugged")

    def _send_frame(self, arb_id: int, payload: bytes) -> None:
        if self.fail:
            raise DeviceOperationError("link gone")
        super()._send_frame(arb_id, payload)


def test_while_the_board_is_away_no_command_is_shown_and_the_outage_counts_as_safe() -> None:
    # found by review: in thread mode the last command stayed in pin_state, shown as live,
    # until the board was back, and the outage was not counted in safe_time_s
    display = FlakyDisplay()
    display.connect()
    slot = FrameSlot()
    loop = DisplayLoop(display, Renderer(), TactileFrameScene(), positions=lambda: GOOD,
                       platform_ok=lambda: True, frames=slot, link=SameClockLink(),
                       stale_timeout_s=10.0, retry_min_s=0.01, retry_max_s=0.02)
    stop = threading.Event()
    runner = threading.Thread(target=loop.run_in_thread, args=(stop,), daemon=True)
    runner.start()
    try:
        def fresh() -> bool:
            slot.put(frame(0, 3.0), now_us())
            return loop.pin_state.command is not None

        wait_until(fresh, 5.0, "the loop renders")
        display.fail = True
        wait_until(lambda: loop.pin_state.safe_reason == "display_lost", 5.0,
                   "the display's loss published")
        assert loop.pin_state.command is None and loop.counters.display_errors == 1
        assert loop.counters.safe_entries.get("display_lost") == 1
        display.fail = False
        wait_until(lambda: loop.counters.display_reconnects >= 1, 5.0, "the display is back")
        assert loop.counters.safe_time_s > 0.0
        wait_until(fresh, 5.0, "the loop renders again")
    finally:
        stop.set()
        runner.join(10.0)
