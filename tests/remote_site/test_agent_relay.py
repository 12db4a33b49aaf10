"""The remote agent against the real relay (in-process RelayServer) and a fake local station.

The fake local station is a real StationLink sending platform states that press a known
tumor of the phantom; it checks what comes back: tactile frames with the contract's hops,
contact while pressing, a stiffness layer near the phantom's ground truth, arm state.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import cv2
import pytest

from lab.ground_truth import write_ground_truth
from relay_server.config import RelayConfig
from relay_server.server import RelayServer
from remote_site.agent.app import AgentOptions, run_agent
from remote_site.agent.world import build_world
from remote_site.phantom.scenes import make_scene
from shared.client import StationLink
from shared.protocol import ArmState, PlatformState, TactileCompact, TactileFrame
from shared.protocol.tactile_codec import TactileDecoder
from shared.timebase import now_us
from shared.workspace import WorkspaceMap
from tests.support import free_tcp_port, scaled

TOKEN = "palpate"
SESSION = "lab1"
CONTRACT_STAMPS = ["local.capture", "relay.relay_in", "relay.relay_out", "remote.station_rx",
                   "remote.arm_command", "remote.sensor_frame", "remote.sensor_arrival",
                   "remote.tactile_ready",
                   "relay.relay_in", "relay.relay_out", "local.station_rx"]


def press_profile_mm(t_s: float, depth_mm: float = 3.0) -> float:
    """Phantom z of the scripted press: hover, descend, hold, lift (mm)."""
    if t_s < 0.4:
        return 2.0
    if t_s < 1.9:
        return 2.0 - (2.0 + depth_mm) * (t_s - 0.4) / 1.5
    if t_s < 2.4:
        return -depth_mm
    return 2.0


async def fake_local(url: str, target_xy_mm: tuple[float, float], duration_s: float,
                     token: str = TOKEN) -> dict[str, list[Any]]:
    """Press ``target_xy_mm`` (phantom) through the relay; collect what comes back."""
    ws = WorkspaceMap()
    got: dict[str, list[Any]] = {"frames": [], "arm_states": [], "compact": []}
    decoder = TactileDecoder()  # the remote sends compact frames (protocol v2) by default
    async with StationLink(url, session=SESSION, role="local", token=token) as link:
        await link.wait_connected(timeout_s=scaled(10.0))

        remote_ready = asyncio.Event()  # set by the first tactile frame: the remote is up

        async def send_states() -> None:
            seq = 0
            t0: float | None = None
            while True:
                if t0 is None and remote_ready.is_set():
                    t0 = time.monotonic()  # press only once the remote processes frames
                z = press_profile_mm(0.0 if t0 is None else time.monotonic() - t0)
                p = ws.inverse([target_xy_mm[0], target_xy_mm[1], z])
                seq += 1
                ts = now_us()
                state = PlatformState(seq=seq, ts_us=ts, position_mm=(float(p[0]), float(p[1]),
                                                                      float(p[2])))
                await link.send(state.with_hop("local", "capture", ts))
                await asyncio.sleep(0.004)

        sender = asyncio.create_task(send_states())
        try:
            end: float | None = None  # duration_s counts from the remote's first frame
            start_deadline = time.monotonic() + scaled(30.0)
            while end is None or time.monotonic() < end:
                if end is None and time.monotonic() > start_deadline:
                    raise AssertionError("the remote station sent no tactile frame in time")
                try:
                    msg = await link.recv(timeout_s=0.2)
                except TimeoutError:
                    continue
                if isinstance(msg, TactileCompact):
                    got["compact"].append(msg)
                    decoded = decoder.decode(msg)
                    if decoded is None:
                        continue
                    msg = decoded
                if isinstance(msg, TactileFrame):
                    if end is None:
                        end = time.monotonic() + duration_s
                        remote_ready.set()
                    got["frames"].append(msg)
                elif isinstance(msg, ArmState):
                    got["arm_states"].append(msg)
        finally:
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sender
    return got


@pytest.fixture
async def relay() -> AsyncIterator[RelayServer]:
    server = RelayServer(RelayConfig(host="127.0.0.1", port=free_tcp_port(),
                                     tcp_port=free_tcp_port(), tokens={SESSION: TOKEN},
                                     stats_interval_s=0.1, ping_interval_s=0.2,
                                     ping_burst_spacing_s=0.005))
    await server.start()
    try:
        yield server
    finally:
        await server.close()


def check_press_result(got: dict[str, list[Any]], truth: dict[str, Any], tumor_id: str) -> None:
    """Shared checks: hops, contact, stiffness near ground truth, arm state."""
    frames: list[TactileFrame] = got["frames"]
    assert len(frames) > 30
    # frames that answer a command (an idle frame repeats its command without the stamps)
    answered = [f for f in frames if f.source_seq is not None
                and any(h.clock == "local" for h in f.hops)]
    assert answered
    stamps = [f"{h.clock}.{h.stage}" for h in answered[-1].hops]
    assert stamps == CONTRACT_STAMPS
    times = [h.t_us for h in answered[-1].hops if h.clock == "remote"]
    assert times == sorted(times)
    assert answered[-1].ts_us == answered[-1].hops[5].t_us
    pressing = [f for f in frames if f.contact]
    assert pressing and not frames[0].contact
    deepest = max(pressing, key=lambda f: f.force_n)
    assert deepest.indentation_mm == pytest.approx(3.0, abs=0.3)
    assert deepest.layers["height_mm"].shape == (30, 40)
    assert deepest.layers["height_mm"].max() > 0.1
    tumor = next(t for t in truth["tumors"] if t["id"] == tumor_id)
    # the probe centre maps back to the tumor in platform coordinates
    assert deepest.center_mm == pytest.approx(tumor["center_platform_mm"], abs=0.2)
    with_k = [f for f in frames if "stiffness_n_per_mm" in f.layers]
    assert with_k, "no stiffness estimate reached the local station"
    k_patch = with_k[-1].layers["stiffness_n_per_mm"]
    k_centre = float(k_patch[15, 20])
    assert k_centre == pytest.approx(tumor["stiffness_n_per_mm"], rel=0.05)
    assert 0.5 <= float(with_k[-1].layers["stiffness_k"].min()) <= 1.0
    assert got["arm_states"] and got["arm_states"][-1].source_seq is not None


async def test_agent_follows_a_press_and_streams_tactile_frames(
        relay: RelayServer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # the arm's command age limit and command timeout are product timeouts under test:
    # scaled, so a loaded machine's queueing delays do not read as stale commands
    monkeypatch.setenv("TELETOUCH_ARM_SAFETY_MAX_COMMAND_AGE_MS", str(scaled(100.0)))
    monkeypatch.setenv("TELETOUCH_ARM_SAFETY_COMMAND_TIMEOUT_MS", str(scaled(100.0)))
    monkeypatch.setenv("TELETOUCH_REMOTE_AGENT_GIL_SWITCH_INTERVAL_S", "0.003")
    switch_before = sys.getswitchinterval()
    url = f"ws://127.0.0.1:{relay.ws_port}/"
    truth_path = tmp_path / "truth.json"
    write_ground_truth(build_world("breast", 5, ideal=True), truth_path, WorkspaceMap())
    options = AgentOptions(relay=url, session=SESSION, token=TOKEN, phantom="breast", seed=5,
                           ideal=True,
                           frame_rate_hz=60.0)
    stop = asyncio.Event()
    cv2.setNumThreads(2)  # OpenCV's pool, as a process with 2 cores starts with
    agent = asyncio.create_task(run_agent(options, stop))
    try:
        async with asyncio.timeout(scaled(20.0)):  # the station has opened its devices
            while not any(p["role"] == "remote" for p in relay.status()["sessions"].get(
                    SESSION, {}).get("peers", [])):
                await asyncio.sleep(0.05)
        # while the station runs, OpenCV works in the calling thread (opencv_threads = 1)
        assert cv2.getNumThreads() == 1
        truth = json.loads(truth_path.read_text())
        malignant = next(t for t in truth["tumors"] if t["id"] == "malignant")
        got = await fake_local(url, tuple(malignant["center_mm"]), duration_s=scaled(3.2))
        # then the relay goes away: the arm must be halted for link loss
        await relay.close()
        await asyncio.sleep(scaled(0.4))  # the agent notices the loss and halts the arm
    finally:
        stop.set()
        summary = await asyncio.wait_for(agent, scaled(10.0))
    assert cv2.getNumThreads() == 2  # and gets its pool back when it stops
    # the GIL switch interval in force while it ran is reported, and restored after
    assert summary["gil_switch_interval_s"] == pytest.approx(0.003)
    assert sys.getswitchinterval() == pytest.approx(switch_before)
    check_press_result(got, truth, "malignant")
    # compact frames through the real relay: key frames and deltas, every one decoded
    compact = got["compact"]
    assert summary["frames"]["codec"] == "compact"
    assert any(m.key for m in compact) and sum(not m.key for m in compact) > len(compact) // 2
    assert len(got["frames"]) == len(compact) - next(i for i, m in enumerate(compact) if m.key)
    phantom = make_scene("breast", 5)
    assert truth["tumors"][1]["stiffness_n_per_mm"] == pytest.approx(
        phantom.tissue_stiffness_n_per_mm(*phantom.tumors[1].center_mm))
    assert summary["frames"]["sent"] >= len(got["frames"])
    assert summary["frames"]["skipped_integration_no_contact"] > 0
    assert summary["stiffness"]["estimates_valid"] >= 1
    assert summary["stiffness"]["samples_skipped_not_loading"] > 0
    assert summary["platform_states"]["applied"] > 100
    # a wrong clock correction would make most states stale; a start-up stall (first JIT
    # compile) may legitimately age a few queued ones past 100 ms
    assert summary["platform_states"]["dropped_stale"] <= 0.05 * summary["platform_states"][
        "applied"]
    assert summary["arm"]["link_loss_halts"] == 1
    assert summary["link"]["pongs_sent"] > 0
    assert summary["latency_ms"]["sensor_frame_to_tactile_ready"]["p50"] > 0
    assert summary["latency_ms"]["sensor_delivery"]["max"] == 0.0  # the simulator, on demand
    json.dumps(summary, allow_nan=False)


async def test_agent_with_a_wrong_token_stops_with_auth_error(relay: RelayServer) -> None:
    from shared.errors import AuthError

    options = AgentOptions(relay=f"tcp://127.0.0.1:{relay.tcp_port}", session=SESSION,
                           token="wrong", duration_s=scaled(10.0))
    summaries: list[dict[str, Any]] = []
    with pytest.raises(AuthError):
        await asyncio.wait_for(run_agent(options, asyncio.Event(), on_summary=summaries.append),
                               scaled(10.0))
    assert summaries and summaries[0]["frames"]["sent"] == 0


@pytest.mark.parametrize("threads", [-1, 257, 1.5, True, "2"])
def test_opencv_threads_must_be_a_small_integer(threads: Any) -> None:
    from remote_site.agent.config import RemoteAgentConfig
    from shared.errors import ConfigError

    with pytest.raises(ConfigError, match="opencv_threads"):
        RemoteAgentConfig(opencv_threads=threads)
    assert RemoteAgentConfig(opencv_threads=0).opencv_threads == 0  # 0: OpenCV's own setting
