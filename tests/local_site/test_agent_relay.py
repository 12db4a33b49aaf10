"""The local agent against a real (in-process) relay and a fake remote station."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from local_site.agent import LocalAgent
from local_site.platform.base import PlatformSample
from local_site.recording import load_recording
from local_site.scenes import TactileFrameScene
from shared.protocol import PlatformState, TactileFrame
from shared.recording import read_mcap
from shared.timebase import monotonic_s, now_us
from tests.local_site.agent_support import (
    FRAME_SHAPE,
    FakeRemote,
    any_loop_of,
    link_of,
    loop_of,
    make_frame,
    relay_agent,
    wait_for,
)
from tests.relay_server.relay_clients import running_relay
from tests.support import MachineStalls, free_tcp_port, motion_of, scaled


def _pins_near(agent: LocalAgent, height_mm: float, tol_mm: float = 0.15) -> bool:
    fb = any_loop_of(agent).display.latest_feedback()
    return fb is not None and not fb.safe_state and \
        bool(np.all(np.abs(fb.position_mm - height_mm) < tol_mm))


@pytest.mark.parametrize("render_loop", ["thread", "process"])
async def test_platform_state_and_frames_flow_record_and_summary(tmp_path: Path,
                                                                 render_loop: str) -> None:
    # "process": the display loop in a process of its own (local_site.agent.display_process),
    # read through the same attributes, recorded and summarised the same way
    async with running_relay() as relay:
        url = f"ws://127.0.0.1:{relay.ws_port}/"
        agent = relay_agent(url, tmp_path, render_loop=render_loop)
        switch_before = sys.getswitchinterval()
        run = asyncio.create_task(agent.run())
        async with FakeRemote(url) as remote:
            await wait_for(lambda: agent.loop is not None and _pins_near(agent, 2.0), 6.0,
                           "pins at the frames' 2 mm")
            # the station's GIL switch interval while it runs (0.2 ms), restored after; with
            # the loop in a process of its own, that process takes it and the station keeps
            # Python's
            assert sys.getswitchinterval() == pytest.approx(
                switch_before if render_loop == "process" else agent.config.gil_switch_interval_s)
            await wait_for(lambda: agent.ledger.frames >= 5, 3.0, "end-to-end latencies")
            await wait_for(lambda: any_loop_of(agent).periods.iterations > 300, 3.0,
                           "loop iterations")
            # asserted below: wait for it too (beside two CPU burners the other conditions
            # were met after 45 states)
            await wait_for(lambda: agent.platform_states_sent > 50, 3.0, "platform states sent")
            # and received: beside two CPU burners the station had sent 50 while the remote
            # had taken only 35 (the rest in flight, or replaced unsent in a slot on the way)
            await wait_for(lambda: len(remote.states) > 51, 3.0, "platform states received")
            agent.request_stop("test")
            assert await run == 0
    assert sys.getswitchinterval() == pytest.approx(switch_before)
    assert switch_before != pytest.approx(agent.config.gil_switch_interval_s)
    # platform_state: the previous message's sample (motion), capture hop = ts, then the
    # relay's stamps, then the remote's receipt; the first of the link session has no motion
    state = remote.states[-1]
    assert [f"{h.clock}.{h.stage}" for h in state.hops] == [
        "local.motion", "local.capture", "relay.relay_in", "relay.relay_out",
        "remote.station_rx"]
    assert state.hops[1].t_us == state.ts_us and state.hops[0].t_us < state.ts_us
    # motion is the previous message's sample (the relay forwards every state here)
    follow = [(s.hops[0].t_us, prev.ts_us) for prev, s in itertools.pairwise(remote.states)
              if s.hops[0].stage == "motion"]
    assert len(follow) >= 50 and sum(a == b for a, b in follow) >= 0.9 * len(follow)
    assert abs(state.position_mm[0] - 30.0) < 0.1 and abs(state.position_mm[2] - 100.0) < 0.1
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert agent.summary is not None
    assert summary == agent.summary | {"recording": summary["recording"]}
    assert summary["mode"] == "relay" and summary["exit_reason"] == "test"
    assert summary["frames_rendered"] > 0 and summary["frames_rejected"] == 0
    assert summary["frames_received"] >= summary["frames_accepted"] >= summary["frames_rendered"]
    e2e = summary["motion_to_touch_ms"]["end_to_end"]
    assert e2e["count"] >= 5 and 0 < e2e["p50"] < 1000
    assert "render" in summary["motion_to_touch_ms"]
    assert summary["display_loop"]["iterations"] > 100
    assert summary["display_loop"]["period_p50_ms"] is not None
    assert summary["display_loop"]["mode"] == render_loop
    assert summary["platform"]["process"] == (render_loop == "process")
    assert summary["link"]["connects"] == 1 and summary["uplink"]["platform_states_sent"] > 50
    assert summary["platform"]["read_rate_hz"] > 100
    rec = load_recording(tmp_path / "rec.mcap")
    assert rec.frames > 0
    n = rec.frame_seq.size
    assert n == summary["frames_accepted"] and n > 0
    assert rec.frame_height_mm.shape == (n, *FRAME_SHAPE)
    assert rec.frame_height_mm.dtype == np.float32
    assert rec.frame_stiffness_k is not None and rec.frame_stiffness_n_per_mm is not None
    assert np.allclose(rec.frame_height_mm, 2.0) and np.allclose(rec.frame_stiffness_k, 0.8)
    assert np.allclose(rec.frame_stiffness_n_per_mm, 0.7)
    assert rec.frame_rx_us.dtype == np.int64 and np.all(np.diff(rec.frame_rx_us) >= 0)
    assert rec.frame_center_mm.shape == (n, 2) and rec.frame_contact.all()
    assert rec.platform_mm.shape == (rec.platform_t_us.size, 3)
    assert rec.platform_t_us.size == summary["uplink"]["platform_states_sent"]
    assert rec.meta["session"] == "agent-test" and rec.meta["layer_shape"] == [9, 9]
    assert "workspace" in rec.meta and rec.meta["counts"]["frames"] == n
    assert rec.meta["complete"] and summary["recording"]["dropped_queue_full"] == 0
    mcap = read_mcap(tmp_path / "rec.mcap")
    pins = [m.json() for m in mcap.on("/local/pins")]
    assert pins and all(p["commanded_mm"] is None or len(p["commanded_mm"]) == 16
                        for p in pins)
    # a sample in the safe state has no command, a rendering one has one
    assert all((p["commanded_mm"] is None) == (p["safe_reason"] is not None) for p in pins)
    assert any(p["measured_mm"] is not None and p["safe_reason"] is None for p in pins)
    latency = [m.json() for m in mcap.on("/local/latency")]
    assert latency and all(m["type"] == "tactile_frame" for m in latency)
    assert {"capture_to_relay_in", "relay_in_to_relay_out", "relay_out_to_station_rx"} <= \
        set(latency[-1]["stages_ms"])


async def test_bad_frames_are_rejected_without_touching_the_pins() -> None:
    async with running_relay() as relay:
        url = f"ws://127.0.0.1:{relay.ws_port}/"
        # every timeout that would put the pins safe long: a stall of the machine must not
        # look like a change the bad frames made (5 s: the longest the settings allow)
        agent = relay_agent(url, stale_frame_timeout_s=5.0, max_frame_age_s=5.0,
                            platform_read_timeout_s=10.0, platform_reopen_after_s=10.0)
        run = asyncio.create_task(agent.run())
        try:
            async with FakeRemote(url, height_mm=3.0) as remote:
                await wait_for(lambda: agent.loop is not None and _pins_near(agent, 3.0), 6.0,
                               "pins at 3 mm")
                remote.paused = True
                loop = loop_of(agent)
                stream = loop.scene
                assert isinstance(stream, TactileFrameScene)
                await wait_for(lambda: stream.last_seq == remote.frames_sent, 2.0,
                               "the frames in flight to arrive")
                version = loop.scene.version
                sent = loop.counters.commands_sent
                command = loop.renderer.last_command
                nan = make_frame(900, None, 3.0)
                nan.layers["height_mm"][2, 3] = np.nan
                for bad in (nan, make_frame(901, None, 50.0),  # out of range
                            TactileFrame(seq=902, center_mm=(30.0, 30.0), layers={
                                "height_mm": np.ones((4, 4)), "friction": np.ones((3, 3))})):
                    agent.frames.put(bad, now_us())
                    await asyncio.sleep(0.02)
                await wait_for(lambda: loop.counters.frames_rejected >= 3, 2.0,
                               "the display loop to reject the bad frames")
                assert loop.counters.frames_rejected == 3
                assert loop.scene.version == version
                assert loop.counters.commands_sent == sent
                assert loop.renderer.last_command is command
                assert _pins_near(agent, 3.0) and loop.safe_reason is None
        finally:
            agent.request_stop("test")
            assert await run == 0
    assert agent.summary is not None and agent.summary["frames_rejected"] == 3


@pytest.mark.parametrize("render_loop", ["thread", "process"])
async def test_link_loss_goes_safe_then_reconnects_and_resumes(render_loop: str) -> None:
    port, tcp_port = free_tcp_port(), free_tcp_port()
    url = f"ws://127.0.0.1:{port}/"
    agent = relay_agent(url, safe_state="flat", render_loop=render_loop)
    run = asyncio.create_task(agent.run())
    # the link's losses (both relays' ends) watched for stalls of the machine: they hold up
    # the loops and this test's look alike
    stalls = MachineStalls()
    try:
        async with running_relay(port=port, tcp_port=tcp_port), FakeRemote(url) as remote:
            await wait_for(lambda: agent.loop is not None and _pins_near(agent, 2.0), 6.0,
                           "pins at 2 mm")
            rendered = any_loop_of(agent).counters.frames_rendered
            stalls.start()
        # relay gone: the link is down, the pins go flat within ~100 ms
        await wait_for(lambda: not link_of(agent).is_connected, 2.0, "link down")
        down_at = link_of(agent).link_down_since
        assert down_at is not None
        await wait_for(lambda: any_loop_of(agent).safe_reason is not None, 1.0, "safe state")
        reaction_s = monotonic_s() - down_at
        await wait_for(lambda: (fb := any_loop_of(agent).display.latest_feedback())
                       is not None and fb.safe_state and float(fb.position_mm.max()) < 0.3, 2.0,
                       "pins flat")
        async with running_relay(port=port, tcp_port=tcp_port), FakeRemote(url) as remote:
            await wait_for(lambda: link_of(agent).is_connected, 3.0, "reconnected")
            await wait_for(lambda: any_loop_of(agent).safe_reason is None
                           and _pins_near(agent, 2.0), 4.0, "rendering resumed")
            assert any_loop_of(agent).counters.frames_rendered > rendered
            assert remote.frames_sent > 0
    finally:
        agent.request_stop("test")
        try:
            assert await run == 0
        finally:
            stalls.stop()
    assert reaction_s < 0.1 + scaled(0.15) + stalls.total_s, (reaction_s, stalls.stalls_s)
    summary = agent.summary
    assert summary is not None
    assert summary["link"]["connects"] == 2 and summary["link"]["connection_losses"] >= 1
    entries = summary["safe_state"]["entries"]
    assert entries.get("link_lost", 0) + entries.get("stale_scene", 0) >= 1
    assert summary["safe_state"]["link_loss_to_safe_ms"]["max"] < \
        100 + scaled(150) + stalls.total_s * 1e3, stalls.stalls_s


async def test_compact_frames_render_only_once_their_key_frame_arrived() -> None:
    # a remote sending protocol-v2 compact frames, whose key frame the local station missed
    # (joined late): its deltas must render nothing until the next key frame
    from shared.client import StationLink
    from shared.protocol.tactile_codec import CodecSettings, TactileEncoder
    from tests.local_site.agent_support import SESSION, TOKEN

    async with running_relay() as relay:
        url = f"ws://127.0.0.1:{relay.ws_port}/"
        remote = StationLink(url, session=SESSION, role="remote", token=TOKEN)
        remote.start()
        await remote.wait_connected(timeout_s=scaled(10.0))
        agent = relay_agent(url, stale_frame_timeout_s=5.0)  # the longest allowed
        run = asyncio.create_task(agent.run())
        try:
            await wait_for(lambda: agent.loop is not None and agent.link is not None
                           and agent.link.is_connected, 10.0, "the local station's link")
            enc = TactileEncoder(CodecSettings(key_every=1000))
            enc.encode(make_frame(1, None, 3.0))  # the key frame the local never sees
            for seq in range(2, 12):
                frame = make_frame(seq, None, 3.0)
                frame.layers["height_mm"][4, 4] = 2.5  # a small change: a delta
                msg = enc.encode(frame)
                assert not msg.key
                await remote.send(msg)
                await asyncio.sleep(0.01)
            await wait_for(lambda: agent.tactile_decoder.counters.waiting_for_key >= 10, 5.0,
                           "the deltas to arrive")
            loop = loop_of(agent)
            assert loop.counters.frames_accepted == 0
            # the pins are safe: no frame was ever taken in (a loaded machine may also have
            # lost the platform for a moment, which takes precedence as the reason)
            assert loop.safe_reason in ("no_frames", "platform_lost")
            # a key frame, resent fresh every 0.3 s as a remote does on its key period: on a
            # loaded machine one copy may age past the display's bound before it is rendered
            deadline = monotonic_s() + scaled(6.0)
            seq = 20
            while not _pins_near(agent, 2.0):
                assert monotonic_s() < deadline, "pins never at the key frame's 2 mm"
                enc.reset()
                key = enc.encode(make_frame(seq, None, 2.0))
                assert key.key
                await remote.send(key)
                seq += 1
                with contextlib.suppress(AssertionError):
                    await wait_for(lambda: _pins_near(agent, 2.0), 0.3, "")
            assert 1 <= agent.tactile_decoder.counters.keys <= seq - 20
        finally:
            await remote.close()
            agent.request_stop("test")
            assert await run == 0


async def test_platform_samples_older_than_the_read_timeout_are_never_sent(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # a reader that resumes after a stall (a stopped or starved platform process) may first
    # publish samples the board latched long ago; the uplink must not send them as commands.
    # The clock the sample-age rule reads runs 1 s ahead: every sample is 1 s old.
    import local_site.agent.platform_reader as platform_reader

    monkeypatch.setattr(platform_reader, "now_us", lambda: now_us() + 1_000_000)
    async with running_relay() as relay:
        url = f"ws://127.0.0.1:{relay.ws_port}/"
        agent = relay_agent(url)
        run = asyncio.create_task(agent.run())
        async with FakeRemote(url) as remote:
            await wait_for(lambda: agent.platform_states_skipped_stale > 20, 10.0,
                           "samples skipped as stale")
            agent.request_stop("test")
            assert await run == 0
    assert agent.platform_states_sent == 0 and remote.states == []
    assert agent.summary is not None
    assert agent.summary["uplink"]["skipped_stale"] == agent.platform_states_skipped_stale


async def test_the_first_state_after_skipped_samples_has_no_motion_stamp(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # ``local.motion`` is the previous message's sample: the first message after samples
    # were skipped has none to name (its frames count from capture)
    import local_site.agent.platform_reader as platform_reader

    ahead_us = [0]  # 1 s: every sample 1 s old, skipped as stale
    monkeypatch.setattr(platform_reader, "now_us", lambda: now_us() + ahead_us[0])
    async with running_relay() as relay:
        url = f"ws://127.0.0.1:{relay.ws_port}/"
        agent = relay_agent(url)
        run = asyncio.create_task(agent.run())
        async with FakeRemote(url) as remote:
            await wait_for(lambda: len(remote.states) >= 3, 10.0, "states")
            ahead_us[0] = 1_000_000
            await wait_for(lambda: agent.platform_states_skipped_stale > 5, 10.0,
                           "samples skipped as stale")
            sent = agent.platform_states_sent
            ahead_us[0] = 0
            await wait_for(lambda: len(remote.states) >= sent + 3, 10.0, "states after")
            agent.request_stop("test")
            assert await run == 0
    # by seq: a state replaced unsent (a busy machine) leaves a gap, not a shift; the one
    # after it names what the replaced one would have (none, at the start of a stretch)
    by_seq = {s.seq: s for s in remote.states}
    stages = {seq: [h.stage for h in s.hops][:2] for seq, s in by_seq.items()}
    # (the first of the link session may go out before the remote joins: the relay drops it;
    # test_the_motion_stamp_names_the_previous_sample_but_never_spans_an_outage has it)
    after_skip = min(seq for seq in by_seq if seq > sent)
    if after_skip == sent + 1:  # the first after the skipped samples
        assert stages[after_skip] == ["capture", "relay_in"]
    else:  # replaced unsent on the way (a busy machine): its successor carries its capture,
        # a sample after the skipped ones, never one from before them
        last_before = by_seq[max(seq for seq in by_seq if seq <= sent)]
        motion = motion_of(by_seq[after_skip])
        assert motion is not None and motion > last_before.ts_us
    follows = [seq for seq in by_seq if seq - 1 in by_seq and seq - 1 != sent]
    assert len(follows) >= 2
    for seq in follows:  # its predecessor was written: it names that one's sample
        assert stages[seq] == ["motion", "capture"]
        assert by_seq[seq].hops[0].t_us == by_seq[seq - 1].ts_us


class _UplinkLink:
    """The link as the uplink sees it: every send kept (a message its queue replaces unsent
    is the queue's to carry: test_the_send_queue_carries_only_a_replaced_unsent_platform_state)."""

    is_connected = True

    def __init__(self) -> None:
        self.sent: list[PlatformState] = []

    async def send(self, msg: PlatformState) -> None:
        self.sent.append(msg)


def _sample(t_us: int) -> PlatformSample:
    return PlatformSample((0.0, 0.0, 100.0), (0.0, 0.0, 0.0), t_us, seq=t_us, board_t_us=t_us)


async def test_the_motion_stamp_names_the_previous_sample_but_never_spans_an_outage(
        ) -> None:
    # each message names the sample of the one before it; a platform lost for longer than
    # the read timeout is not an uplink wait
    agent = relay_agent("ws://127.0.0.1:9/")
    link, reader = _UplinkLink(), SimpleNamespace(latest=None)
    agent.link, agent.reader = link, reader  # type: ignore[assignment]
    task = asyncio.create_task(agent._uplink())
    try:
        async def offer(t_us: int) -> PlatformState:
            n = len(link.sent)
            reader.latest = _sample(t_us)
            await wait_for(lambda: len(link.sent) > n, 2.0, "a platform_state")
            return link.sent[-1]

        t0 = now_us()
        first = await offer(t0)
        assert motion_of(first) is None  # the first of the link session: nothing before it
        second = await offer(t0 + 3_000)
        assert motion_of(second) == t0
        third = await offer(t0 + 6_000)
        assert motion_of(third) == t0 + 3_000
        fourth = await offer(t0 + 9_000)
        assert motion_of(fourth) == t0 + 6_000
        # the same sample held through an outage longer than the read timeout, then a
        # fresh one (stamped now, so not stale): no motion stamp across the outage
        gap_us = int(agent.config.platform_read_timeout_s * 1e6) + 200_000
        await asyncio.sleep(gap_us / 1e6)
        after = await offer(max(now_us(), t0 + 9_000 + gap_us))
        assert motion_of(after) is None
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


@pytest.mark.parametrize("refusal", ["replaced", "invalid_hello"])
async def test_every_final_refusal_of_the_link_ends_the_station_with_exit_1(
        refusal: str) -> None:
    """Only a wrong token or a taken role ended the station; a connection replaced by another
    proving it (now final over raw TCP too) or a hello the relay can never accept ended the
    station's receive task silently, the station up with its link down for good."""
    from shared.errors import InvalidHelloError, ReplacedError

    error = ReplacedError("replaced by another connection") if refusal == "replaced" else \
        InvalidHelloError("the relay can never accept this station's hello")
    async with running_relay() as relay:
        agent = relay_agent(f"ws://127.0.0.1:{relay.ws_port}/")
        run = asyncio.create_task(agent.run())
        try:
            await wait_for(lambda: agent.link is not None and agent.link.is_connected, 10.0,
                           "the station's link")
            assert agent.link is not None
            agent.link._give_up(error)  # as the link's loop does on a final refusal
            assert await asyncio.wait_for(run, scaled(20.0)) == 1
        finally:
            if not run.done():
                agent.request_stop("test")
                await run
    assert agent.exit_reason == "link_refused"
