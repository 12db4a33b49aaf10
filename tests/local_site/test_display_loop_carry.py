"""A tactile frame replaced in the display loop's frame slot hands its start on
(``carry_motion``) while the loop renders; while the pins are safe the touch path is out,
not slow, and nothing is handed on."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

from local_site.agent.display_loop import DisplayLoop, FrameSlot
from local_site.devices import open_display
from local_site.render import Renderer
from local_site.scenes import TactileFrameScene
from shared.errors import DeviceError
from shared.motion_to_touch import MotionToTouchLedger, StageTrace
from shared.protocol import Hop, TactileFrame
from shared.timebase import now_us
from tests.local_site.test_display_loop_age import SAMPLE, FakeLink
from tests.support import motion_frame, motion_of


def _frame(seq: int, motion_us: int, capture_us: int) -> TactileFrame:
    f = motion_frame(seq, motion_us, capture_us)
    return TactileFrame(seq=seq, ts_us=f.ts_us, hops=f.hops, center_mm=(30.0, 30.0),
                        pitch_mm=1.0, contact=True,
                        layers={"height_mm": np.full((9, 9), 2.0, np.float32)})


class _Ledger(MotionToTouchLedger):
    def __init__(self) -> None:
        super().__init__()
        self.hops: list[tuple[Hop, ...]] = []

    def add_hops(self, hops: Iterable[Hop], offsets_us: Mapping[str, float | None]) -> StageTrace:
        hops = tuple(hops)
        self.hops.append(hops)
        return super().add_hops(hops, offsets_us)


def test_a_frame_the_loop_never_took_hands_its_start_on_while_the_loop_renders() -> None:
    slot = FrameSlot()
    slot.rendering = True
    for seq in (1, 2, 3):
        slot.put(motion_frame(seq, seq * 10_000 - 4_000, seq * 10_000), seq)
    item = slot.take()
    assert item is not None and slot.superseded == 2
    taken = item[0]
    assert taken.seq == 3 and motion_of(taken) == 6_000
    assert taken.hops[1:] == motion_frame(3, 26_000, 30_000).hops[1:]
    slot.put(motion_frame(4, 36_000, 40_000), 4)
    item = slot.take()
    assert item is not None and motion_of(item[0]) == 36_000  # its predecessor was taken
    # the loop not rendering (not begun, or the pins safe): the touch path is out, not slow
    slot.rendering = False
    for seq in (5, 6):
        slot.put(motion_frame(seq, seq * 10_000 - 4_000, seq * 10_000), seq)
    item = slot.take()
    assert item is not None and slot.superseded == 3 and motion_of(item[0]) == 56_000


def test_the_loop_lets_its_slot_carry_only_while_it_renders() -> None:
    platform = {"ok": False}
    ledger = _Ledger()
    slot = FrameSlot()
    loop = DisplayLoop(open_display("sim"), Renderer(), TactileFrameScene(),
                       positions=lambda: SAMPLE, platform_ok=lambda: platform["ok"],
                       frames=slot, link=FakeLink(), stale_timeout_s=10.0, ledger=ledger)
    try:
        t = now_us()
        # the platform is lost: each frame is accepted, the pins stay safe, nothing is
        # rendered, and nothing is handed on (an outage, not a latency)
        for seq, back_ms in ((1, 80), (2, 70)):
            slot.put(_frame(seq, t - back_ms * 1_000, t - (back_ms - 10) * 1_000), t)
            loop.tick()
            assert not slot.rendering
        slot.put(_frame(3, t - 60_000, t - 50_000), t)
        slot.put(_frame(4, t - 50_000, t - 40_000), t)  # replaced in the slot meanwhile
        assert loop.counters.frames_accepted == 2 and ledger.hops == []
        platform["ok"] = True
        loop.tick()
        counters = loop.counters
        assert counters.frames_rendered == 1 and counters.frames_superseded_unrendered == 2
        assert slot.rendering
        assert [h[0].t_us for h in ledger.hops] == [t - 50_000]  # its own start
        # rendering: two frames before the next tick, the second shows the first's first
        slot.put(_frame(5, t - 40_000, t - 30_000), t)
        slot.put(_frame(6, t - 30_000, t - 20_000), t)
        loop.tick()
        assert [h[0].t_us for h in ledger.hops] == [t - 50_000, t - 40_000]
        assert ledger.hops[-1][1:-1] == _frame(6, t - 30_000, t - 20_000).hops[1:]
        assert ledger.hops[-1][-1].stage == "rendered"
        platform["ok"] = False  # lost again: the slot stops carrying at once
        loop.tick()
        assert not slot.rendering and loop.safe_reason == "platform_lost"
        platform["ok"] = True
        slot.put(_frame(7, t - 20_000, t - 10_000), now_us())
        loop.tick()
        assert slot.rendering and loop.safe_reason is None
        # the display fails: nothing renders until it is reopened (the runner's path; the
        # pins keep their last command meanwhile, so only this tells the slot)
        assert not loop._display_failed(DeviceError("unplugged"), stop=lambda _s: True)
        assert not slot.rendering
        # reopened (the runner's path when it may go on): the slot stays out until the loop
        # renders again, and carries again from then on
        assert loop._display_failed(DeviceError("unplugged"), stop=lambda _s: False)
        t = now_us()
        slot.put(_frame(8, t - 20_000, t - 15_000), t)
        slot.put(_frame(9, t - 15_000, t - 10_000), t)  # replaced before the loop renders
        loop.tick()
        assert slot.rendering and loop.safe_reason is None
        assert ledger.hops[-1][0].t_us == t - 15_000  # its own start: nothing handed on
        slot.put(_frame(10, t - 10_000, t - 5_000), t)
        slot.put(_frame(11, t - 5_000, t - 2_000), t)  # replaced while the loop renders
        loop.tick()
        assert ledger.hops[-1][0].t_us == t - 10_000  # the replaced frame's start
    finally:
        loop.display.disconnect()
