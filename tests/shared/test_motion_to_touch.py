"""Motion-to-touch stage tracing against hand-computed stage durations."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from shared.motion_to_touch import (
    END_TO_END,
    FROM_CAPTURE,
    INCOMPLETE,
    STAGES,
    UNALIGNED,
    MotionToTouchLedger,
    trace_hops,
)
from shared.protocol import (
    MOTION_CARRY_MAX_US,
    Hop,
    PlatformState,
    TactileFrame,
    carry_motion,
    carry_motion_hops,
)
from shared.protocol.tactile_codec import CodecSettings, TactileEncoder
from tests.support import motion_frame, motion_of, motion_state

# true times on the relay clock (us) of each stamp of one loop
TRUE = [("local", "motion", -4_000), ("local", "capture", 0), ("relay", "relay_in", 10_000),
        ("relay", "relay_out", 10_050),
        ("remote", "station_rx", 20_050), ("remote", "arm_command", 20_100),
        ("remote", "sensor_frame", 28_000), ("remote", "sensor_arrival", 28_300),
        ("remote", "tactile_ready", 30_500),
        ("relay", "relay_in", 40_500), ("relay", "relay_out", 40_560),
        ("local", "station_rx", 50_560), ("local", "rendered", 51_000)]


def stamped(offsets: dict[str, int]) -> list[Hop]:
    return [Hop(c, s, t + (0 if c == "relay" else offsets[c])) for c, s, t in TRUE]


@given(st.integers(-10**9, 10**9), st.integers(-10**9, 10**9))
def test_offsets_are_removed(off_local: int, off_remote: int) -> None:
    offsets = {"local": off_local, "remote": off_remote}
    trace = trace_hops(stamped(offsets), offsets)
    assert trace.end_to_end_us == 55_000
    assert trace.from_capture_us == 51_000  # without the sampling wait
    assert dict(trace.stages_us) == {
        "uplink_sampling": 4_000, "uplink_local_to_relay": 10_000, "relay_forward_platform": 50,
        "relay_to_remote": 10_000,
        "remote_dispatch": 50, "arm_and_sensor": 7_900, "sensor_delivery": 300,
        "reconstruction_and_stiffness": 2_200,
        "uplink_remote_to_relay": 10_000, "relay_forward_tactile": 60, "relay_to_local": 10_000,
        "render": 440}
    assert sum(d for _, d in trace.stages_us) == trace.end_to_end_us


@given(st.booleans(), st.booleans())
def test_a_clustered_relays_hop_between_workers_lies_inside_the_forwarding_stage(
        out_leg: bool, back_leg: bool) -> None:
    # relay workers joined by NATS stamp relay_in, nats_out, nats_in, relay_out: the frame is
    # still aligned, with the same stages, the hop inside relay_forward_*
    hops: list[Hop] = []
    for hop in stamped({"local": 0, "remote": 0}):
        hops.append(hop)
        if hop.clock == "relay" and hop.stage == "relay_in" and (
                out_leg if hop.t_us < 20_000 else back_leg):
            hops += [Hop("relay", "nats_out", hop.t_us + 10),
                     Hop("relay", "nats_in", hop.t_us + 30)]
    trace = trace_hops(hops, {"local": 0, "remote": 0})
    plain = trace_hops(stamped({"local": 0, "remote": 0}), {"local": 0, "remote": 0})
    assert trace.skipped is None
    assert trace == plain
    assert dict(trace.stages_us)["relay_forward_platform"] == 50


@pytest.mark.parametrize("where", ["after_station_rx", "without_relay_in", "alone"])
def test_nats_stamps_out_of_place_break_the_sequence(where: str) -> None:
    hops = stamped({"local": 0, "remote": 0})
    k = next(i for i, h in enumerate(hops) if h.stage == "station_rx")
    nats = [Hop("relay", "nats_out", 20_060), Hop("relay", "nats_in", 20_070)]
    if where == "after_station_rx":
        hops = [*hops[:k + 1], *nats, *hops[k + 1:]]
    elif where == "without_relay_in":  # the leg stands in for relay_in
        r = next(i for i, h in enumerate(hops) if h.stage == "relay_in")
        hops = [*hops[:r], *nats, *hops[r + 1:]]
    else:  # a nats_in without its nats_out
        r = next(i for i, h in enumerate(hops) if h.stage == "relay_in")
        hops = [*hops[:r + 1], nats[1], *hops[r + 1:]]
    trace = trace_hops(hops, {"local": 0, "remote": 0})
    assert trace.skipped == INCOMPLETE and trace.stages_us == ()


def test_a_nats_leg_that_ends_before_it_began_shows_the_workers_clocks_out_of_step() -> None:
    hops = []
    for hop in stamped({"local": 0, "remote": 0}):
        hops.append(hop)
        if hop.stage == "relay_in" and hop.t_us < 20_000:  # worker B 5 ms behind worker A
            hops += [Hop("relay", "nats_out", hop.t_us + 10),
                     Hop("relay", "nats_in", hop.t_us + 10 - 5_000)]
    trace = trace_hops(hops, {"local": 0, "remote": 0})
    assert trace.skipped == UNALIGNED and trace.stages_us == ()


def test_unknown_offset_counts_the_frame_apart_without_merged_stages() -> None:
    offsets = {"local": 5, "remote": None}
    trace = trace_hops(stamped({"local": 5, "remote": 777}), offsets)
    assert trace.stages_us == ()
    assert trace.skipped == UNALIGNED
    assert trace.end_to_end_us == 55_000  # both of its stamps are on the local clock
    assert trace.from_capture_us == 51_000  # so are these
    ledger = MotionToTouchLedger()
    ledger.add(trace)
    ledger.add_hops(stamped({"local": 5, "remote": 777}), {"local": 5, "remote": 777})
    summary = ledger.summary_ms()
    assert summary[UNALIGNED]["count"] == 1
    assert summary["render"]["count"] == 1
    assert summary[END_TO_END]["count"] == 2 and summary[FROM_CAPTURE]["count"] == 2
    assert summary[FROM_CAPTURE]["p50"] == 51.0
    assert not [name for name in summary if ">" in name]


@given(st.sets(st.integers(1, len(TRUE) - 2), min_size=1))
def test_a_missing_stamp_never_yields_a_merged_stage(dropped: set[int]) -> None:
    hops = [h for i, h in enumerate(stamped({"local": 0, "remote": 0})) if i not in dropped]
    trace = trace_hops(hops, {"local": 0, "remote": 0})
    assert trace.stages_us == ()
    assert trace.skipped == INCOMPLETE
    assert trace.end_to_end_us == 55_000
    # local.capture is TRUE's second stamp: without it there is no figure from the capture
    assert trace.from_capture_us == (None if 1 in dropped else 51_000)


def test_a_first_message_without_motion_stamp_counts_from_its_capture() -> None:
    # the first platform_state of a link session has no previous message: no local.motion
    hops = stamped({"local": 0, "remote": 0})[1:]
    trace = trace_hops(hops, {"local": 0, "remote": 0})
    assert trace.skipped is None
    assert trace.end_to_end_us == trace.from_capture_us == 51_000
    assert [n for n, _ in trace.stages_us] == list(STAGES[1:])
    assert sum(d for _, d in trace.stages_us) == trace.end_to_end_us
    ledger = MotionToTouchLedger()
    ledger.add(trace)
    assert ledger.frames == 1
    assert ledger.tail_ms() is None  # counted, but not a complete frame for the tail


def test_missing_render_stamp_gives_no_end_to_end() -> None:
    trace = trace_hops(stamped({"local": 0, "remote": 0})[:-1], {"local": 0, "remote": 0})
    assert trace.end_to_end_us is None


def test_ledger_summary_in_ms() -> None:
    ledger = MotionToTouchLedger()
    for shift in range(100):
        hops = [Hop(c, s, t + (shift * 10 if s == "rendered" else 0)) for c, s, t in TRUE]
        ledger.add_hops(hops, {"local": 0, "remote": 0})
    summary = ledger.summary_ms()
    assert ledger.frames == 100
    assert summary[END_TO_END]["max"] == 55.0 + 0.99
    p50 = summary[END_TO_END]["p50"]
    assert p50 is not None and 55.4 <= p50 <= 55.6
    assert summary["relay_to_local"]["p99"] == 10.0


def test_a_frame_without_its_platform_part_still_has_stages() -> None:
    hops = stamped({"local": 0, "remote": 0})[6:]  # from remote.sensor_frame on
    trace = trace_hops(hops, {"local": 0, "remote": 0})
    assert trace.skipped is None and trace.end_to_end_us is None
    assert [n for n, _ in trace.stages_us] == [
        "sensor_delivery", "reconstruction_and_stiffness", "uplink_remote_to_relay",
        "relay_forward_tactile", "relay_to_local", "render"]


def _loop_hops(durations_us: list[int]) -> list[Hop]:
    """One loop's stamps, on one clock (offsets 0), with these stage durations."""
    t, hops = 0, []
    for (clock, stage, _), d in zip(TRUE, [0, *durations_us], strict=True):
        t += d
        hops.append(Hop(clock, stage, t))
    return hops


@given(st.lists(st.lists(st.integers(0, 50_000), min_size=len(STAGES), max_size=len(STAGES)),
                min_size=1, max_size=200),
       st.floats(0.5, 0.99))
def test_the_tails_stage_excesses_add_up_to_its_end_to_end_excess(
        frames: list[list[int]], quantile: float) -> None:
    ledger = MotionToTouchLedger()
    for durations in frames:
        ledger.add_hops(_loop_hops(durations), {"local": 0, "remote": 0})
    tail = ledger.tail_ms(quantile)
    assert tail is not None and tail["of"] == len(frames)
    data = np.asarray(frames, np.float64) / 1e3
    e2e = data.sum(axis=1)
    chosen = data[e2e >= np.quantile(e2e, quantile)]  # an independent reckoning
    assert tail["frames"] == chosen.shape[0] >= 1
    stages = tail["stages"]
    for i, name in enumerate(STAGES):
        assert stages[name]["tail_mean"] == pytest.approx(chosen[:, i].mean(), abs=1e-9)
        assert stages[name]["p50"] == pytest.approx(np.median(data[:, i]), abs=1e-9)
    excess = sum(s["excess"] for s in stages.values())
    assert excess == pytest.approx(tail["end_to_end"]["tail_mean"]
                                   - sum(s["p50"] for s in stages.values()), abs=1e-6)
    shares = [s["share"] for s in stages.values()]
    if excess > 1e-3:
        assert sum(shares) == pytest.approx(1.0)
    else:  # no slower than the rest: no shares of rounding noise
        assert shares == [None] * len(STAGES)


def test_the_stage_with_the_heavy_tail_takes_the_tails_share() -> None:
    ledger = MotionToTouchLedger()
    rng = np.random.default_rng(1)
    k = STAGES.index("arm_and_sensor")
    for i in range(1000):
        durations = [int(v) for v in rng.integers(900, 1100, len(STAGES))]
        if i % 20 == 0:
            durations[k] += 20_000  # one frame in 20 waits 20 ms for the sensor
        ledger.add_hops(_loop_hops(durations), {"local": 0, "remote": 0})
    tail = ledger.tail_ms(0.95)
    assert tail is not None and tail["frames"] == 50
    assert tail["stages"]["arm_and_sensor"]["share"] > 0.95
    assert tail["stages"]["arm_and_sensor"]["excess"] == pytest.approx(20.0, abs=0.5)


def test_equal_frames_have_no_tail_shares() -> None:
    ledger = MotionToTouchLedger()
    for _ in range(50):
        ledger.add_hops(_loop_hops([1234] * len(STAGES)), {"local": 0, "remote": 0})
    tail = ledger.tail_ms()
    assert tail is not None and tail["frames"] == tail["of"] == 50
    assert all(s["share"] is None and abs(s["excess"]) < 1e-9 for s in tail["stages"].values())


def test_the_tail_needs_complete_frames_and_a_quantile_inside_0_1() -> None:
    ledger = MotionToTouchLedger()
    assert ledger.tail_ms() is None
    ledger.add_hops(_loop_hops([1000] * len(STAGES))[5:], {"local": 0, "remote": 0})
    assert ledger.tail_ms() is None  # no platform part: not a complete frame
    for q in (0.0, 1.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="quantile"):
            ledger.tail_ms(q)




def test_a_replacement_starts_where_the_replaced_message_started() -> None:
    newer = motion_state(2, 2_000, 3_000)
    carried = carry_motion(motion_state(1, 1_000, 2_000), newer)
    assert isinstance(carried, PlatformState)
    assert carried.hops == (Hop("local", "motion", 1_000), Hop("local", "capture", 3_000))
    assert carried.seq == 2 and carried.ts_us == 3_000
    # the replaced one had no start (first of a session): the known part of its wait, from
    # its capture, is kept (here that is the successor's own start: the very message)
    assert carry_motion(motion_state(1, None, 2_000), newer) is newer
    carried = carry_motion(motion_state(1, None, 1_500), newer)
    assert carried.hops == (Hop("local", "motion", 1_500), Hop("local", "capture", 3_000))
    # a successor that its sender saw break the chain keeps what it has
    alone = motion_state(2, None, 3_000)
    assert carry_motion(motion_state(1, 1_000, 2_000), alone) is alone
    # nothing to change: the very message
    same = motion_state(2, 1_000, 3_000)
    assert carry_motion(motion_state(1, 1_000, 2_000), same) is same
    # only an earlier start is taken: a successor never counts less than its own wait
    early = motion_state(2, 500, 3_000)
    assert carry_motion(motion_state(1, 1_000, 2_000), early) is early
    # and none more than a second before the successor's own: an outage, not a latency
    late = motion_state(9, 1_000 + MOTION_CARRY_MAX_US + 1, 2_000_000_000)
    assert carry_motion(motion_state(1, 1_000, 2_000), late) is late
    edge = motion_state(9, 1_000 + MOTION_CARRY_MAX_US, 2_000_000_000)
    assert motion_of(carry_motion(motion_state(1, 1_000, 2_000), edge)) == 1_000


def test_a_tactile_frame_replaced_hands_its_start_on_to_a_tactile_frame_only() -> None:
    frame = motion_frame(2, 2_000, 3_000)
    carried = carry_motion(motion_frame(1, 1_000, 2_000), frame)
    assert isinstance(carried, TactileFrame) and carried.seq == 2
    assert carried.hops == (Hop("local", "motion", 1_000), *frame.hops[1:])
    # either encoding: a compact frame replaced by a compact frame
    encoder = TactileEncoder(CodecSettings())
    compact = [encoder.encode(motion_frame(seq, 1_000 * seq, 1_000 * seq + 1_000))
               for seq in (1, 2)]
    assert motion_of(carry_motion(compact[0], compact[1])) == 1_000
    # a frame after a state, a state after a frame: different streams, nothing changes
    assert carry_motion(motion_state(1, 1_000, 2_000), frame) is frame
    state = motion_state(2, 2_000, 3_000)
    assert carry_motion(motion_frame(1, 1_000, 2_000), state) is state
    # an idle frame (no platform stamps) shows nothing first: it hands nothing on and a
    # successor to one keeps its own start; an idle successor takes nothing
    idle = TactileFrame(seq=1, ts_us=2_500, layers=frame.layers, hops=frame.hops[-2:])
    assert carry_motion(idle, frame) is frame
    assert carry_motion(motion_frame(1, 1_000, 2_000), idle) is idle


@given(st.lists(st.tuples(st.sampled_from(["motion", "capture", "relay_in", "sensor_frame"]),
                          st.sampled_from(["local", "relay", "remote"]),
                          st.integers(0, 3_000_000)), max_size=6),
       st.lists(st.tuples(st.sampled_from(["motion", "capture", "relay_in", "sensor_frame"]),
                          st.sampled_from(["local", "relay", "remote"]),
                          st.integers(0, 3_000_000)), max_size=6))
def test_carried_hops_change_only_the_motion_stamp(
        replaced_raw: list[tuple[str, str, int]], newer_raw: list[tuple[str, str, int]]) -> None:
    replaced = tuple(Hop(c, s, t) for s, c, t in replaced_raw)
    newer = tuple(Hop(c, s, t) for s, c, t in newer_raw)
    out = carry_motion_hops(replaced, newer)

    def first(hops: tuple[Hop, ...], stage: str) -> int | None:
        return next((h.t_us for h in hops if h.clock == "local" and h.stage == stage), None)

    def others(hops: tuple[Hop, ...]) -> list[Hop]:
        return [h for h in hops if not (h.clock == "local" and h.stage == "motion")]

    theirs = first(replaced, "motion")
    theirs = first(replaced, "capture") if theirs is None else theirs
    mine = first(newer, "motion")
    if mine is None or theirs is None or not 0 < mine - theirs <= MOTION_CARRY_MAX_US:
        assert out is newer  # the very tuple: nothing re-encoded
    else:
        assert out[0] == Hop("local", "motion", theirs)
        assert others(out) == others(newer)  # every other stamp kept, in order
        assert sum(h.clock == "local" and h.stage == "motion" for h in out) == 1


def test_without_motion_drops_only_the_motion_stamp() -> None:
    from shared.protocol import without_motion

    stamped = motion_state(2, 1_000, 3_000)
    assert without_motion(stamped).hops == (Hop("local", "capture", 3_000),)
    assert without_motion(stamped).seq == 2
    alone = motion_state(2, None, 3_000)
    assert without_motion(alone) is alone
