"""``tests.support.LoopStalls`` sees a stall of the event loop, with its length."""

from __future__ import annotations

import asyncio
import time

from tests.support import LoopStalls, scaled


async def test_a_blocked_loop_is_counted_as_one_stall_of_about_its_length() -> None:
    async with LoopStalls(tick_s=0.01, over_s=0.03) as stalls:
        await asyncio.sleep(0.05)  # the watch has ticked
        time.sleep(0.2)  # the loop blocked
        await asyncio.sleep(0.05)  # the watch has woken, late
    assert stalls.count(0.1) >= 1, stalls.stalls_s
    assert 0.15 <= max(stalls.stalls_s) <= 0.2 + scaled(0.3), stalls.stalls_s
    assert stalls.total_s >= max(stalls.stalls_s)
