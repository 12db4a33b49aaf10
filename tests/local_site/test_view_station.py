"""The local station's live view: the agent with --view against a relay and a fake remote."""

from __future__ import annotations

import asyncio
import json
import math
import os
import struct
import threading
from types import SimpleNamespace
from typing import Any, cast

import numpy as np
import pytest
from websockets.asyncio.client import connect

from local_site.agent.display_loop import DisplayLoop, FrameSlot, PinState, SameClockLink
from local_site.devices import open_display
from local_site.platform.base import PlatformSample
from local_site.render import Renderer
from local_site.scenes import TactileFrameScene
from local_site.view import StationView
from local_site.view.analysis import LiveAnalysis, LiveAnalysisConfig, _confidence, encode_map
from shared.errors import ConfigError
from shared.protocol import TactileFrame
from shared.timebase import now_us
from shared.view import ViewAddress
from shared.workspace import WorkspaceConfig
from tests.local_site.agent_support import FRAME_SHAPE, FakeRemote, loop_of, relay_agent
from tests.relay_server.relay_clients import running_relay
from tests.support import scaled, wait_until


async def _until(ws: Any, predicate: Any, what: str, timeout_s: float = 10.0,
                 trail: list[list[float]] | None = None) -> dict[str, Any]:
    """The first snapshot whose ``live`` matches; ``trail`` collects every trajectory point
    received on the way (a snapshot carries only the points its browser has not had yet)."""
    try:
        async with asyncio.timeout(scaled(timeout_s)):
            while True:
                msg = json.loads(await ws.recv())
                if trail is not None:
                    trail.extend(msg["trail"]["points"])
                live = msg["live"]
                # every snapshot is of one moment: never a command beside the safe state
                # that withdrew it (issue 9 under load)
                assert live["safe"]["reason"] is None or live["pins"]["commanded_mm"] is None, \
                    f"snapshot {msg['seq']}: commanded pins in the safe state {live['safe']}"
                if predicate(live):
                    return dict(msg)
    except TimeoutError as err:
        raise AssertionError(f"no snapshot with {what} in {scaled(timeout_s):.0f} s") from err


async def test_the_view_shows_pins_patch_probe_link_and_latency_then_safe_state() -> None:
    async with running_relay() as relay:
        url = f"ws://127.0.0.1:{relay.ws_port}/"
        agent = relay_agent(url)
        agent.view_address = ViewAddress("127.0.0.1", 0)
        async with FakeRemote(url, height_mm=2.0) as remote:
            run = asyncio.create_task(agent.run())
            try:
                await asyncio.to_thread(wait_until, lambda: agent.view_url is not None, 10,
                                        "the view listening")
                assert agent.view_server is not None
                async with connect(f"ws://127.0.0.1:{agent.view_server.port}/ws",
                                   max_size=None) as ws:
                    trail: list[list[float]] = []
                    msg = await _until(ws, lambda live: live["pins"]["measured_mm"] is not None
                                       and live["latency"] is not None
                                       # every stamp usable once both clock offsets are known
                                       and "render" in live["latency"]["stages_ms"]
                                       and live["patch"] is not None
                                       # rendering (a loaded machine may starve the
                                       # simulated platform for a moment: platform_lost)
                                       and live["safe"]["reason"] is None,
                                       "pins and a patch", timeout_s=20.0, trail=trail)
                    live = msg["live"]
                    assert live["station"] == "local" and live["link"]["state"] == "up"
                    assert live["safe"]["reason"] is None
                    # the fake remote's frames are a flat 2 mm: so are the commanded pins
                    assert np.allclose(live["pins"]["commanded_mm"], 2.0, atol=0.05)
                    assert np.allclose(live["pins"]["stiffness_k"], 0.8, atol=0.01)
                    assert (live["patch"]["w"], live["patch"]["h"]) == FRAME_SHAPE[::-1]
                    # platform held at (30, 30): the pins' window sits on the patch centre
                    c0, r0, c1, r1 = live["patch"]["window"]
                    assert math.isclose((c0 + c1) / 2, 4.0, abs_tol=0.2)
                    assert math.isclose((r0 + r1) / 2, 4.0, abs_tol=0.2)
                    assert np.allclose(live["probe"]["platform_mm"][:2], 30.0, atol=0.05)
                    assert np.allclose(live["probe"]["phantom_mm"][:2], 0.0, atol=0.05)
                    assert "render" in live["latency"]["stages_ms"]
                    assert live["latency"]["end_to_end_ms"] > 0
                    # (in this snapshot or an earlier one: a platform sample that did not
                    # change between two snapshots adds no point, under load it happens)
                    assert trail, "the trajectory has its first point"
                    remote.paused = True  # no frames: the pins go safe, the view says so
                    msg = await _until(ws, lambda live: live["safe"]["reason"] is not None,
                                       "the safe state")
                    assert msg["live"]["safe"]["reason"] == "stale_scene"
                    assert msg["live"]["pins"]["commanded_mm"] is None
                    # shown as old, not fresh: at least the stale timeout that made it safe
                    stale_ms = agent.config.stale_frame_timeout_s * 1e3
                    assert msg["live"]["patch"]["age_ms"] > stale_ms
            finally:
                agent.request_stop()
                await run
        assert loop_of(agent).frame_listener is None
        assert agent.view is not None and not agent.view._analysis.alive  # type: ignore[union-attr]


async def test_a_busy_view_port_stops_the_agent_with_a_config_error() -> None:
    async with running_relay() as relay:
        agent = relay_agent(f"ws://127.0.0.1:{relay.ws_port}/")
        agent.view_address = ViewAddress("127.0.0.1", relay.ws_port)
        with pytest.raises(ConfigError, match="cannot listen"):
            await agent.run()


def _pad_frame(seq: int, x_mm: float, depth_mm: float) -> TactileFrame:
    offs = (np.arange(15) - 7) * 0.5
    pad = np.exp(-(offs[None, :] ** 2 + offs[:, None] ** 2) / 6.0).astype(np.float32)
    return TactileFrame(seq=seq, ts_us=0, center_mm=(x_mm, 30.0), pitch_mm=0.5,
                        layers={"height_mm": pad * depth_mm}, contact=depth_mm > 0,
                        force_n=2.0 * depth_mm, indentation_mm=depth_mm)


def test_live_analysis_waits_for_presses_then_builds_maps_in_its_process() -> None:
    analysis = LiveAnalysis(WorkspaceConfig(), LiveAnalysisConfig(interval_s=0.1, nice=0))
    try:
        for i in range(5):
            analysis.add(_pad_frame(i, 30.0, 0.0))  # touching, not pressed
        wait_until(lambda: analysis.poll() or analysis.result is not None, 60,
                   "the first analysis result")
        assert analysis.result is not None and analysis.result["state"] == "waiting"
        assert "nothing was palpated" in analysis.result["reason"]
        for i in range(40):
            analysis.add(_pad_frame(100 + i, 20.0 + i * 0.5, 1.5))
        wait_until(lambda: analysis.poll() and analysis.result is not None
                   and analysis.result["state"] == "ok", 60, "maps")
        result = analysis.result
        assert result["frames"] == 45 and result["frames_used"] == 40
        relief = result["relief"]
        assert relief["w"] > 0 and relief["h"] > 0
        assert isinstance(result["findings"], list)
    finally:
        analysis.close()
    assert not analysis.alive


def test_closing_after_the_child_died_mid_result_does_not_wait_for_the_rest() -> None:
    # issue 9: a replay's Ctrl-C hung after "the view's analysis process is busy;
    # terminating it": the child, cut short while writing a large result, left half a
    # message in the result pipe, and close() read it back, waiting for the rest for ever
    # (this process holds the pipe's write end too: no end-of-file)
    analysis = LiveAnalysis(WorkspaceConfig(), LiveAnalysisConfig(interval_s=0.1, nice=0))
    child = analysis._proc
    child.terminate()  # as close() does to a busy child (it may still be starting)
    child.join(scaled(10.0))
    assert not analysis.alive and child.exitcode != 0
    # the tail of its last result: a length header promising 1 MB, then 3 bytes
    writer = analysis._outbox._writer  # type: ignore[attr-defined]
    os.write(writer.fileno(), struct.pack("!i", 1 << 20) + b"abc")
    closer = threading.Thread(target=analysis.close, name="close-after-half-result",
                              daemon=True)
    closer.start()
    closer.join(scaled(10.0))
    assert not closer.is_alive(), "close() waits for the rest of a half-written result"


def test_confidence_is_the_share_of_recent_runs_that_found_it() -> None:
    a = {"center_mm": [0.0, 0.0], "equivalent_radius_mm": 2.0}
    near = {"center_mm": [2.5, 0.0], "equivalent_radius_mm": 2.0}
    far = {"center_mm": [10.0, 0.0], "equivalent_radius_mm": 2.0}
    current = [dict(a)]
    _confidence(current, [[far], [near], [a]], history=5)
    assert current[0]["confidence"] == pytest.approx(2 / 5)


def test_encode_map_marks_missing_cells_and_spans_the_range() -> None:
    values = np.array([[np.nan, 0.0], [1.0, 2.0]])
    enc = encode_map(values)
    import base64
    raw = np.frombuffer(base64.b64decode(enc["data"]), np.uint8).reshape(2, 2)
    assert raw[0, 0] == 0 and raw[0, 1] == 1 and raw[1, 1] == 255
    assert enc["lo"] == pytest.approx(0.02) and enc["hi"] == pytest.approx(1.98)
    assert encode_map(np.full((2, 3), np.nan))["lo"] is None


# ---------------------------------------------------------------- one pin state per snapshot
# (issue 9: under load a snapshot showed the commanded pins together with the safe state)


def _rendering_view() -> tuple[DisplayLoop, StationView]:
    """A display loop rendering a fresh frame, and a station view over it (no analysis)."""
    sample = PlatformSample(position_mm=(30.0, 30.0, 100.0), velocity_mm_s=(0.0, 0.0, 0.0),
                            t_us=0, seq=1, board_t_us=0)
    slot = FrameSlot()
    link = SameClockLink(offset_bound_us=500)
    loop = DisplayLoop(open_display("sim"), Renderer(), TactileFrameScene(),
                       positions=lambda: sample, platform_ok=lambda: True, frames=slot,
                       link=link, stale_timeout_s=10.0)
    slot.put(TactileFrame(seq=1, ts_us=now_us(), center_mm=(30.0, 30.0), pitch_mm=1.0,
                          layers={"height_mm": np.full((9, 9), 2.0, np.float32)},
                          contact=True), now_us())
    loop.tick()
    assert loop.last_command is not None and loop.safe_reason is None
    agent = SimpleNamespace(loop=loop, reader=SimpleNamespace(latest=sample),
                            workspace=WorkspaceConfig(), render_config=None,
                            remote_mode=False, last_arm_state=None, link=link)
    return loop, StationView(cast(Any, agent), analysis=None)


def test_a_snapshot_taken_while_the_loop_goes_safe_shows_one_consistent_pin_state() -> None:
    # the display loop runs in its own thread: it can go safe while the view's thread is
    # half-way through a snapshot. Make it happen there, deterministically: the view reads
    # the board's feedback after the command and before the safe reason
    loop, view = _rendering_view()
    try:
        read_feedback = loop.display.latest_feedback

        def going_safe_meanwhile() -> Any:
            loop.enter_safe_state("stale_scene")
            return read_feedback()

        cast(Any, loop.display).latest_feedback = going_safe_meanwhile
        during = view.live()
        cast(Any, loop.display).latest_feedback = read_feedback
        after = view.live()
    finally:
        loop.display.disconnect()
    # the snapshot is of the moment before the safe state, whole: a command, no reason
    assert during["safe"]["reason"] is None and during["pins"]["commanded_mm"] is not None
    assert after["safe"]["reason"] == "stale_scene"
    assert after["pins"]["commanded_mm"] is None
    assert after["safe"]["seq"] > during["safe"]["seq"]  # the snapshot says which state


def test_the_loop_withdraws_the_command_before_it_tells_the_board() -> None:
    # what another thread could read at each step of entering the safe state: never the
    # command together with the reason, and no command from the moment the board is told
    loop, _ = _rendering_view()
    seen: list[PinState] = []
    try:
        send_safe = loop.display.safe_state
        read_link = cast(SameClockLink, loop.link).link_down_for_s

        def safe_state(mode: Any) -> Any:
            seen.append(loop.pin_state)
            return send_safe(mode)

        def link_down_for_s(now_s: float | None = None) -> float:
            seen.append(loop.pin_state)
            return read_link(now_s)

        cast(Any, loop.display).safe_state = safe_state
        cast(Any, loop.link).link_down_for_s = link_down_for_s
        loop.enter_safe_state("stale_scene")
        seen.append(loop.pin_state)
    finally:
        loop.display.disconnect()
    assert seen and all(s.command is None and s.safe_reason == "stale_scene" for s in seen)
    assert loop.last_command is None and loop.safe_reason == "stale_scene"


# ---------------------------------------------------------------- the probe position's age
# (the page draws the probe hollow and STALE past 500 ms; the station sent no age at all)


def test_the_probe_position_carries_the_age_of_its_platform_sample() -> None:
    loop, view = _rendering_view()
    reader = cast(Any, view.agent.reader)
    try:
        # the platform's newest sample stopped coming 0.8 s ago (board hung, link lost)
        reader.latest = PlatformSample(position_mm=(30.0, 30.0, 100.0),
                                       velocity_mm_s=(0.0, 0.0, 0.0),
                                       t_us=now_us() - 800_000, seq=2, board_t_us=0)
        old = view.live()["probe"]
        reader.latest = PlatformSample(position_mm=(30.0, 30.0, 100.0),
                                       velocity_mm_s=(0.0, 0.0, 0.0),
                                       t_us=now_us(), seq=3, board_t_us=0)
        fresh = view.live()["probe"]
        reader.latest = None
        none = view.live()["probe"]
    finally:
        loop.display.disconnect()
    assert old["phantom_mm"] is not None
    assert 800.0 <= old["platform_age_ms"] < 800.0 + scaled(5.0) * 1e3
    assert 0.0 <= fresh["platform_age_ms"] < scaled(5.0) * 1e3
    assert fresh["platform_age_ms"] < old["platform_age_ms"]
    # no sample: no position and no age
    assert none["phantom_mm"] is None and none["platform_age_ms"] is None
