"""SafeArm under faults: a halt the force limit must not undo, a sideways slide onto stiffer
tissue at the limit, non-finite readings, and bad or old set_force_limit commands."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence

import pytest

from remote_site.arm import SafeArm, SafetyConfig
from remote_site.arm.base import ArmReading
from remote_site.arm.sim import SimArm, SimArmConfig
from shared.errors import FieldError
from shared.protocol.messages import ArmCommand
from tests.remote_site.test_arm_safety import FakeClock


class Spring:
    """A flat surface at z = 0, ``k`` N/mm deep; ``k_right`` beyond ``edge_x_mm`` (an
    inclusion, stiffer tissue)."""

    def __init__(self, k: float, k_right: float | None = None, edge_x_mm: float = 5.0) -> None:
        self.k, self.k_right, self.edge_x_mm = k, k_right, edge_x_mm

    def force_n(self, position_mm: Sequence[float]) -> float:
        x, z = position_mm[0], position_mm[2]
        k = self.k_right if self.k_right is not None and x > self.edge_x_mm else self.k
        return k * max(0.0, -z)


def make(world: Spring | None, config: SafetyConfig | None = None
         ) -> tuple[SafeArm, SimArm, FakeClock]:
    clock = FakeClock()
    arm = SimArm(world, SimArmConfig(realtime=False))
    arm.connect()
    return SafeArm(arm, config, wall_clock_us=clock.wall_us, monotonic=clock.mono), arm, clock


def press_sideways_until_the_limit(safe: SafeArm, arm: SimArm) -> None:
    """At the surface, then a deep target 20 mm to the side, until the force limit trips."""
    safe.move((0.0, 0.0, 0.0))
    arm.advance(1.0)
    assert safe.move((20.0, 0.0, -3.0)).accepted
    for _ in range(500):
        arm.advance(0.001)
        if arm.state().force_n >= safe.force_limit_n:
            return
    raise AssertionError("the force limit never tripped")


def test_a_stopped_arm_at_the_force_limit_is_backed_off_where_it_is() -> None:
    """A stop while the force limit holds: the next polls lift the arm where it is, and do
    not send it on to its old target (the backends take any move as the end of a halt)."""
    cfg = SafetyConfig(force_limit_n=2.0, press_zone_z_mm=-100.0)  # no press-rate steps
    safe, arm, _ = make(Spring(5.0), cfg)
    press_sideways_until_the_limit(safe, arm)
    x_stop, _, z_stop = arm.true_position_mm()
    safe.stop()
    for _ in range(200):
        assert safe.poll().status == "halted"
        arm.advance(0.005)
    x, _, z = arm.true_position_mm()
    assert safe.halted
    assert x < x_stop + 0.5  # it was heading for x = 20 mm
    assert z > z_stop  # backed off, not pressed on
    assert arm.state().force_n < safe.force_limit_n


def test_a_watchdog_halt_at_the_force_limit_is_not_undone() -> None:
    """The link goes silent while the arm slides at depth; the watchdog halts it and the
    force limit trips while it brakes: the arm stops short of its old target."""
    cfg = SafetyConfig(force_limit_n=2.0, press_zone_z_mm=-100.0)
    safe, arm, clock = make(Spring(5.0), cfg)
    safe._check_period_ms = 5.0  # as start_watchdog(0.005) sets it
    safe.move((0.0, 0.0, 0.0))
    arm.advance(1.0)
    clock.t_s += 1.0
    safe.move((20.0, 0.0, -0.5))  # the last command
    for _ in range(400):  # the watchdog thread's checks
        arm.advance(0.005)
        clock.t_s += 0.005
        safe.poll()
    assert safe.halted and safe.counters.watchdog_halts == 1
    assert safe.counters.force_limited >= 1  # the limit did act while halted
    assert arm.true_position_mm()[0] < 19.0
    target = arm.state().target_mm
    assert target is not None and target[0] < 19.0


def test_sliding_sideways_at_the_limit_onto_stiffer_tissue_backs_off() -> None:
    """Pressed to the limit on soft tissue, then slid sideways at the same depth onto an
    inclusion ten times stiffer: the hold depth rises while the force is at or above the
    limit, so the arm backs off and the force comes back below the limit (holding the depth
    alone left it at 100 N against a 10 N limit)."""
    safe, arm, _ = make(Spring(5.0, 50.0))
    safe.move((0.0, 0.0, 0.0))
    arm.advance(1.0)
    for _ in range(200):  # press down to the limit at x = 0
        z = arm.state().position_mm[2]
        safe.move((0.0, 0.0, z - 1.0))
        arm.advance(0.004)
        safe.poll()
    assert safe.poll().status == "force_limit"
    lifted = False
    for i in range(250):  # slide at the current depth, 10 mm/s
        z = arm.state().position_mm[2]
        res = safe.move((0.04 * i, 0.0, z))
        assert res.accepted and res.applied_mm is not None
        lifted |= res.status == "force_limit" and res.applied_mm[2] > z
        arm.advance(0.004)
        reading = safe.poll()
    assert lifted  # sideways targets get the hold depth too
    assert reading.position_mm[0] > 9.0  # it did slide onto the inclusion
    assert reading.force_n < safe.force_limit_n
    for _ in range(50):  # and stays there while the operator holds the depth
        safe.move((10.0, 0.0, arm.state().position_mm[2]))
        arm.advance(0.004)
        assert safe.poll().force_n < safe.force_limit_n


def test_the_hold_depth_rises_by_at_most_the_back_off_and_never_falls() -> None:
    safe, _, _ = make(None)
    cfg = safe.config
    readings = [ArmReading((0.0, 0.0, -2.0), (0.0, 0.0, 0.0), 12.0, "ok", None, 0.0),
                ArmReading((0.0, 0.0, -2.5), (0.0, 0.0, 0.0), 12.0, "ok", None, 0.0),
                ArmReading((0.0, 0.0, -1.5), (0.0, 0.0, 0.0), 9.0, "ok", None, 0.0)]
    holds = []
    for reading in readings:
        assert safe._update_force_limit(reading)
        holds.append(safe._limit_hold_z)
    step = cfg.force_backoff_mm * 12.0 / cfg.force_limit_n  # in proportion to the force
    assert holds == [pytest.approx(-2.0 + step)] * 3  # deeper, then below the limit: kept
    safe._update_force_limit(ArmReading((0.0, 0.0, -1.5), (0.0, 0.0, 0.0), 11.0, "ok", None,
                                        0.0))
    assert safe._limit_hold_z == pytest.approx(-1.5 + cfg.force_backoff_mm * 11.0 / 10.0)


@pytest.mark.parametrize("bad", ["force", "position"])
def test_a_non_finite_reading_halts_the_arm_and_refuses_moves(
        bad: str, caplog: pytest.LogCaptureFixture) -> None:
    """A NaN force (or position) cannot be judged against the force limit: the arm halts
    (counted, logged once), poll reports ``fault`` and moves are refused until the readings
    are finite again; the next move then resumes."""
    safe, arm, _ = make(Spring(40.0))
    real_state = arm.state
    broken = [False]

    def state() -> ArmReading:
        reading = real_state()
        if not broken[0]:
            return reading
        if bad == "force":
            return dataclasses.replace(reading, force_n=math.nan)
        return dataclasses.replace(reading, position_mm=(0.0, math.nan, 0.0))

    arm.state = state  # type: ignore[method-assign]
    assert safe.move((0.0, 0.0, 1.0)).accepted
    arm.advance(1.0)
    assert safe.move((0.0, 0.0, -3.0)).accepted  # pressing (in press-rate steps)
    broken[0] = True
    with caplog.at_level(logging.WARNING, logger="remote_site.arm.safety"):
        for _ in range(5):
            assert safe.poll().status == "fault"
            res = safe.move((0.0, 0.0, -3.0))
            assert (res.accepted, res.applied_mm, res.status) == (False, None, "fault")
            arm.advance(0.01)
    assert safe.halted and safe.counters.fault_halts == 1
    assert len([r for r in caplog.records if "not finite" in r.getMessage()]) == 1
    assert real_state().status == "halted"  # the arm itself was told to stop
    broken[0] = False
    assert safe.poll().status == "halted"  # finite again: halted until a move is accepted
    res = safe.move((0.0, 0.0, 1.0))
    assert res.accepted and res.status == "moving" and not safe.halted


def test_a_zero_or_negative_force_limit_is_refused_on_the_wire() -> None:
    wire = ArmCommand(seq=1, ts_us=5, action="set_force_limit", force_limit_n=4.0).to_wire()
    assert ArmCommand.from_wire(wire).force_limit_n == 4.0
    for bad in (0.0, 0, -1.0):
        with pytest.raises(FieldError, match="force_limit_n"):
            ArmCommand.from_wire({**wire, "force_limit_n": bad})
    # on any other action the field means nothing: a stop is never refused for it (found by
    # review: the first version refused a stop carrying force_limit_n 0)
    for action in ("stop", "home"):
        stop = ArmCommand.from_wire({**wire, "action": action, "force_limit_n": 0.0})
        assert stop.action == action


def test_set_force_limit_commands_are_age_checked_and_never_raise() -> None:
    safe, _, clock = make(None)
    now = clock.wall_us()

    def limit(value: float | None, ts_us: int = now, **clock_kw: float | None) -> str:
        cmd = ArmCommand(seq=1, ts_us=ts_us, action="set_force_limit", force_limit_n=value)
        res = safe.handle(cmd, **clock_kw)  # type: ignore[arg-type]
        return res.status if res.accepted or res.refused is None else res.refused

    for bad in (0.0, -1.0, math.nan, math.inf, None):  # refused, never a ConfigError
        assert limit(bad) == "fault"
    assert safe.force_limit_n == 10.0
    assert limit(2.0, now - 5_000_000) == "stale"
    assert limit(2.0, clock_offset_us=None) == "unknown_clock"
    assert limit(2.0, offset_uncertainty_us=50_000.0) == "uncertain_clock"
    assert safe.force_limit_n == 10.0 and safe.counters.dropped_stale == 1
    assert safe.counters.dropped_clock == 2
    assert limit(2.0) == "ok" and safe.force_limit_n == 2.0
    # home is age-checked like any move
    home = ArmCommand(seq=2, ts_us=now - 5_000_000, action="home")
    assert safe.handle(home).refused == "stale"
    assert safe.handle(dataclasses.replace(home, ts_us=now), clock_offset_us=None
                       ).refused == "unknown_clock"
    assert safe.handle(dataclasses.replace(home, ts_us=now)).accepted


@pytest.mark.parametrize("stiffness", [5.0, 10.0, 50.0])
def test_a_press_held_at_the_limit_stays_held_however_stiff_the_tissue(
        stiffness: float) -> None:
    """Found by review of the back-off: released at each back-off, a press the operator
    holds deeper than the limit allows pressed again, and the force buzzed around the limit
    (7.8-10.3 N on 10 N/mm, 5.3-12.1 N on 50 N/mm, 65 releases in 2 s). The limit now stays
    engaged while the commands ask for a depth below the hold: the force settles below it."""
    clock = [1000.0]
    arm = SimArm(Spring(stiffness), SimArmConfig(realtime=False))
    arm.connect()
    safe = SafeArm(arm, SafetyConfig(), wall_clock_us=lambda: int(clock[0] * 1e6),
                   monotonic=lambda: clock[0])
    safe.move((0.0, 0.0, 0.0))
    arm.advance(1.0)
    forces, releases, engaged = [], 0, False
    for i in range(2000):  # 2 s of polls at 1 kHz; the operator asks 1 mm deeper at 250 Hz
        if i % 4 == 0:
            safe.move((0.0, 0.0, arm.state().position_mm[2] - 1.0))
        arm.advance(0.001)
        clock[0] += 0.001
        forces.append(safe.poll().force_n)
        held = safe._limit_hold_z is not None
        releases += engaged and not held
        engaged = held
    last = forces[1000:]
    limit = safe.config.force_limit_n
    assert releases == 0
    assert max(last) <= limit and min(last) >= limit - stiffness * safe.config.force_backoff_mm


def _glitch_once(arm: SimArm, force_n: float) -> None:
    real = arm._read
    once = [True]

    def glitch() -> ArmReading:
        reading = real()
        if once[0]:
            once[0] = False
            return dataclasses.replace(reading, force_n=force_n)
        return reading

    arm._read = glitch  # type: ignore[method-assign]


@pytest.mark.parametrize(("limit", "spike", "z0"), [(None, 10.5, 14.5), (None, 1000.0, 3.0),
                                                      (1.0, 1000.0, 0.0)])
def test_one_wild_reading_neither_lifts_the_arm_far_nor_holds_it_for_good(
        limit: float | None, spike: float, z0: float) -> None:
    """Found by review of the back-off: one 1000 N glitch lifted the hold 5 mm (50 mm at a
    1 N limit), and a hold above the box top could never be released by a command (the
    commands are clamped to the box), so the arm stayed held until a halt."""
    clock = [1000.0]
    arm = SimArm(Spring(10.0), SimArmConfig(realtime=False))
    arm.connect()
    safe = SafeArm(arm, SafetyConfig(), bounds_mm=((-50.0, -50.0, -4.0), (50.0, 50.0, 14.5)),
                   wall_clock_us=lambda: int(clock[0] * 1e6), monotonic=lambda: clock[0])
    if limit is not None:
        safe.set_force_limit(limit)

    def stream(target: tuple[float, float, float], n: int = 300) -> None:
        for _ in range(n):
            safe.move(target, sent_ts_us=int(clock[0] * 1e6))
            for _ in range(4):
                arm.advance(0.001)
                clock[0] += 0.001
                safe.poll()

    stream((0.0, 0.0, z0))
    _glitch_once(arm, spike)
    safe.poll()
    hold = safe._limit_hold_z
    assert hold is not None
    assert hold <= min(z0 + safe.config.max_press_step_mm, 14.5) + 1e-9
    stream((0.0, 0.0, 14.5))  # the operator lifts to the box top: released
    assert safe._limit_hold_z is None
    stream((0.0, 0.0, 0.5))  # and may come down again
    assert arm.state().position_mm[2] == pytest.approx(0.5, abs=0.05)
