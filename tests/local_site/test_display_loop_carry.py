"""A tactile frame replaced before the pins showed it hands its start on (``carry_motion``):
in the display process's frame slot and as the loop's frame accepted but not yet rendered."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

from local_site.agent.display_loop import DisplayLoop, FrameSlot
from local_site.devices import open_display
from local_site.render import Renderer
from local_site.scenes import TactileFrameScene
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


def test_a_frame_the_loop_never_took_hands_its_start_on() -> None:
    slot = FrameSlot()
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


def test_a_frame_accepted_but_never_rendered_hands_its_start_on() -> None:
    platform = {"ok": False}
    ledger = _Ledger()
    slot = FrameSlot()
    loop = DisplayLoop(open_display("sim"), Renderer(), TactileFrameScene(),
                       positions=lambda: SAMPLE, platform_ok=lambda: platform["ok"],
                       frames=slot, link=FakeLink(), stale_timeout_s=10.0, ledger=ledger)
    try:
        t = now_us()
        # the platform is lost: each frame is accepted, the pins stay safe, nothing rendered
        for seq, back_ms in ((1, 60), (2, 40)):
            slot.put(_frame(seq, t - back_ms * 1_000, t - (back_ms - 10) * 1_000), t)
            loop.tick()
        assert loop.counters.frames_accepted == 2 and loop.counters.frames_rendered == 0
        assert loop.counters.frames_superseded_unrendered == 1 and ledger.hops == []
        platform["ok"] = True
        loop.tick()
        assert loop.counters.frames_rendered == 1
        (hops,) = ledger.hops
        assert hops[0] == Hop("local", "motion", t - 60_000)  # the first frame's start
        assert hops[1:-1] == _frame(2, t - 40_000, t - 30_000).hops[1:]
        assert hops[-1].stage == "rendered"
        # the next frame follows a rendered one: its own start
        slot.put(_frame(3, t - 20_000, t - 10_000), now_us())
        loop.tick()
        assert [h[0].t_us for h in ledger.hops] == [t - 60_000, t - 20_000]
    finally:
        loop.display.disconnect()
