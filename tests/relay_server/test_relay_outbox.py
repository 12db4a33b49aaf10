"""Outbox bounds: a peer that never drains holds one entry per stream and periodic message."""

from __future__ import annotations

from shared.protocol import ArmCommand, ClockPing, PlatformState, Stats
from shared.protocol.peer_session import Outbox


def test_periodic_control_replaces_unsent_and_stays_bounded() -> None:
    box = Outbox(ordered_limit=8)
    for i in range(100):  # 100 s of a stalled peer: stats and pings every second
        box.put_control_latest("stats", Stats(scope="relay", time_us=i, metrics={"i": i}))
        box.put_control_latest("clock_ping", ClockPing(), build=lambda t: ClockPing(t0_us=t))
        box.put_latest("local_to_remote:platform_state", PlatformState(seq=i), t_in_us=i)
    assert len(box) == 3
    taken = box.take()
    stats = [p.message for p in taken if isinstance(p.message, Stats)]
    assert [s.time_us for s in stats] == [99]  # only the newest survives
    assert len(box) == 0


def test_ordered_commands_are_never_replaced() -> None:
    box = Outbox(ordered_limit=3)
    assert all(box.put_ordered(ArmCommand(seq=i)) for i in range(3))
    assert not box.put_ordered(ArmCommand(seq=3))  # full: refused, caller reports it
    box.put_control_latest("stats", Stats(scope="relay", time_us=1, metrics={}))
    assert [p.message.seq for p in box.take() if isinstance(p.message, ArmCommand)] == [0, 1, 2]
