"""The local agent without a relay (--scene), a platform that disappears, and its parts."""

from __future__ import annotations

import asyncio
import re
from pathlib import Path
from typing import cast

import numpy as np
import pytest

from local_site.agent import LocalAgent, LocalAgentConfig
from local_site.agent.period_stats import PeriodStats
from local_site.agent.station import place_shape_spec
from local_site.platform.motion import HoldMotion, RandomWalk, RasterSweep, ReplayMotion
from local_site.platform.motion_spec import parse_motion_spec
from local_site.recording import SessionRecorder, load_recording
from shared.config import resolve_config
from shared.errors import ConfigError
from shared.protocol import Hop, PlatformState, TactileFrame
from tests.local_site.agent_support import loop_of, make_frame, reader_of, wait_for
from tests.support import MachineStalls, scaled

DEPLOY_LOCAL = Path(__file__).resolve().parents[2] / "deploy" / "config" / "local.toml"


@pytest.mark.parametrize("platform", ["sim", "sim-process"])
async def test_scene_mode_renders_the_hemisphere_and_survives_an_unplugged_platform(
        platform: str) -> None:
    # The platform's read timeout is a product timeout under test: scaled, so a loaded
    # machine does not report a spurious loss. A stall of the whole machine about as long
    # (the last sample as old as that when the loop runs again) is a loss the pins rightly
    # take: each such stall is allowed one more "platform_lost".
    read_timeout_s = scaled(0.25)
    agent = LocalAgent(LocalAgentConfig(scene="hemisphere", motion="hold:x=30,y=30,z=100",
                                        platform=platform, device_retry_min_s=0.05,
                                        platform_read_timeout_s=read_timeout_s))
    stalls = MachineStalls().start()
    run = asyncio.create_task(agent.run())
    try:
        # hemisphere r = 4.5 mm placed at the workspace centre, platform on its top:
        # pins at (+-0.85, +-0.85) -> 4.34 mm, corners (+-2.55, +-2.55) -> 2.69 mm
        await wait_for(lambda: agent.loop is not None and
                       (fb := loop_of(agent).display.latest_feedback()) is not None
                       and abs(float(fb.position_mm.max()) - 4.34) < 0.1
                       and abs(float(fb.position_mm.min()) - 2.69) < 0.1, 6.0,
                       "pins showing the hemisphere")
        assert agent.link is None and loop_of(agent).safe_reason is None
        # The display loop starts beside the platform reader: when the display is ready
        # first (a loaded machine), the pins wait in the safe state for the platform's first
        # sample, counted as one "platform_lost" at start. Count the unplug on top of that.
        at_start = dict(loop_of(agent).counters.safe_entries)
        assert set(at_start) <= {"platform_lost"} and reader_of(agent).errors == 0, at_start
        assert at_start.get("platform_lost", 0) <= 1 + stalls.count(read_timeout_s / 2), \
            (at_start, stalls.stalls_s)
        reader_of(agent).platform.unplug()  # type: ignore[attr-defined]
        await wait_for(lambda: loop_of(agent).safe_reason == "platform_lost", 2.0, "safe state")
        await wait_for(lambda: reader_of(agent).reconnects >= 1
                       and loop_of(agent).safe_reason is None,
                       4.0, "platform reopened and rendering again")
    finally:
        agent.request_stop("test")
        try:
            assert await run == 0
        finally:
            stalls.stop()
    s = agent.summary
    assert s is not None and s["mode"] == "scene" and s["link"] is None
    entries = s["safe_state"]["entries"]
    assert set(entries) == {"platform_lost"}, entries
    lost = entries["platform_lost"] - at_start.get("platform_lost", 0)
    assert 1 <= lost <= 1 + stalls.count(read_timeout_s / 2), (entries, stalls.stalls_s)
    assert s["platform"]["errors"] >= 1 and s["platform"]["reconnects"] >= 1
    assert s["display"]["commands_sent"] >= 2 and s["display"]["errors"] == 0
    assert s["display"]["driver"]["safe_states_sent"] >= 2  # the loss, and the shutdown


def test_place_shape_spec_centres_shapes_only(tmp_path: Path) -> None:
    assert place_shape_spec("cone", (30.0, 20.0)) == "cone:x_mm=30.0,y_mm=20.0"
    assert place_shape_spec("cone:x_mm=5,k=0.7", (30.0, 20.0)) == \
        "cone:x_mm=5.0,k=0.7,y_mm=20.0"
    layer = tmp_path / "layers.npz"
    assert place_shape_spec(str(layer), (1.0, 1.0)) == str(layer)
    with pytest.raises(ConfigError):
        place_shape_spec("cone:radius", (0.0, 0.0))


def test_motion_specs() -> None:
    m = parse_motion_spec("raster:x0=5,x1=55,y0=5,y1=55,spacing=2,speed=20,press_depth=3,"
                          "press_every=4")
    assert isinstance(m, RasterSweep)
    p = m.params
    assert (p.origin_mm, p.size_mm, p.line_spacing_mm, p.speed_mm_s) == \
        ((5.0, 5.0), (50.0, 50.0), 2.0, 20.0)
    assert (p.press_depth_mm, p.press_spacing_mm) == (3.0, 4.0)
    once = parse_motion_spec("raster:x0=20,x1=30,y0=30,y1=30,loop=0,pause=0,press_depth=0")
    assert once.duration_s == pytest.approx(10.0 / 20.0 + 10.0 / 20.0)  # line, then back
    assert once.position_mm(100.0) == pytest.approx((20.0, 30.0, 100.0))  # holds: no loop
    walk = parse_motion_spec("random:seed=4,speed=5,x=10,y=10,z=50")
    assert isinstance(walk, RandomWalk) and walk.position_mm(0.0) == pytest.approx((10, 10, 50))
    assert walk.duration_s is None
    ending = parse_motion_spec("random:seed=4,speed=5,x=10,y=10,z=50,duration=2.5")
    assert isinstance(ending, RandomWalk) and ending.duration_s == 2.5
    hold = parse_motion_spec("hold:x=12")
    assert isinstance(hold, HoldMotion) and hold.position_mm(5.0) == (12.0, 30.0, 100.0)
    for bad in ("raster:spacing", "raster:x0=5,x0=6", "raster:speed=fast", "raster:bogus=1",
                "hold:w=1", "swim", "random:x=1", "raster:x0=50,x1=10", "replay:loop=1", "",
                "random:duration=0", "random:duration=inf", "random:duration=-1"):
        with pytest.raises(ConfigError):
            parse_motion_spec(bad)


@pytest.mark.parametrize("bad, named", [
    ("random:x=nan,y=1,z=1", "x='nan' is not a finite number"),  # accepted before
    ("random:seed=nan", "seed='nan' is not an integer"),  # ValueError before
    ("random:seed=1e400", "seed='1e400' is not an integer"),  # OverflowError before
    ("random:seed=2.5", "seed='2.5' is not an integer"),  # taken as 2 before
    ("random:seed=-1", "seed='-1' must be >= 0"),  # numpy's ValueError before
    ("hold:x=nan", "x='nan' is not a finite number"),  # InputDataError before
])
def test_motion_specs_refuse_non_finite_values_by_name(bad: str, named: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(named)):
        parse_motion_spec(bad)


def test_motion_spec_replay_file(tmp_path: Path) -> None:
    path = tmp_path / "walk.csv"
    ReplayMotion.save(path, np.array([0.0, 1.0]), np.array([[0, 0, 0], [10, 20, 30.0]]))
    for spec in (str(path), f"replay:file={path},loop=1"):
        m = parse_motion_spec(spec)
        assert m.position_mm(0.5) == pytest.approx((5.0, 10.0, 15.0))


def test_recorder_keeps_accepted_frames_of_the_first_shape(tmp_path: Path) -> None:
    rec = SessionRecorder(tmp_path / "r.mcap", {"session": "s"})
    rec.tap("tx", PlatformState(seq=1, ts_us=5, hops=(Hop("local", "capture", 5),),
                                position_mm=(1.0, 2.0, 3.0)), 5)
    frame = make_frame(1, None)
    no_k = make_frame(2, None)
    del no_k.layers["stiffness_k"], no_k.layers["stiffness_n_per_mm"]
    other = make_frame(3, None)
    cast(dict[str, np.ndarray], other.layers).update(
        {k: np.full((3, 3), 1.0 if k == "stiffness_k" else 0.0, np.float32)
         for k in other.layers})
    unaccepted = make_frame(4, None)
    for i, f in enumerate((frame, other, no_k, unaccepted)):
        rx = 100 + i
        received = f.with_hop("local", "station_rx", rx)
        assert isinstance(received, TactileFrame)
        rec.tap("rx", received, rx)
        if f is not unaccepted:
            rec.add_frame(received, rx)
    assert rec.close() == tmp_path / "r.mcap"
    out = load_recording(tmp_path / "r.mcap")
    assert out.frame_seq.tolist() == [1, 2] and out.frame_rx_us.tolist() == [100, 102]
    assert out.frame_stiffness_k is not None and out.frame_stiffness_n_per_mm is not None
    assert np.all(out.frame_stiffness_k[1] == 1.0)
    assert np.all(out.frame_stiffness_n_per_mm[1] == 0.0)
    assert out.platform_mm.tolist() == [[1.0, 2.0, 3.0]] and out.platform_t_us.tolist() == [5]
    assert out.meta["session"] == "s" and out.meta["layer_shape"] == [9, 9]
    assert out.meta["counts"]["frames_rejected_shape"] == 1 and out.meta["complete"]
    empty = SessionRecorder(tmp_path / "e.mcap")
    empty.close()
    loaded = load_recording(tmp_path / "e.mcap")
    assert loaded.frame_height_mm.shape == (0, 0, 0) and loaded.platform_mm.shape == (0, 3)


def test_period_stats_percentiles_against_numpy() -> None:
    stats = PeriodStats(0.001, capacity=64)
    rng = np.random.default_rng(0)
    starts = np.cumsum(0.001 + rng.uniform(-2e-4, 5e-4, 200))
    for t in starts:
        stats.tick(float(t))
    periods = np.diff(starts)[-64:]
    s = stats.summary()
    assert s["iterations"] == 200
    assert s["period_p99_ms"] == pytest.approx(np.percentile(periods, 99) * 1e3)
    assert s["jitter_p50_ms"] == pytest.approx(np.percentile(np.abs(periods - 1e-3), 50) * 1e3)


def test_config_validation_and_deploy_example() -> None:
    cfg = resolve_config(LocalAgentConfig, "local.agent", toml_path=DEPLOY_LOCAL, environ={})
    assert cfg.safe_state in ("flat", "hold") and cfg.render_rate_hz >= 500
    env = {"TELETOUCH_LOCAL_AGENT_SAFE_STATE": "hold",
           "TELETOUCH_LOCAL_AGENT_RENDER_RATE_HZ": "800"}
    cfg = resolve_config(LocalAgentConfig, "local.agent", environ=env)
    assert (cfg.safe_state, cfg.render_rate_hz) == ("hold", 800.0)
    for bad in ({"safe_state": "up"}, {"render_loop": "fiber"}, {"render_rate_hz": 0.0},
                {"link_loss_timeout_s": float("nan")}, {"interpolation_order": 2},
                {"device_retry_min_s": 2.0, "device_retry_max_s": 1.0}):
        with pytest.raises(ConfigError):
            LocalAgentConfig(**bad)
    with pytest.raises(ConfigError):
        LocalAgent(LocalAgentConfig())  # neither a relay nor a scene


async def test_display_loop_as_asyncio_task_renders_too() -> None:
    agent = LocalAgent(LocalAgentConfig(scene="cone:radius_mm=10,height_mm=3",
                                        motion="random:seed=2,speed=10", render_loop="asyncio",
                                        render_rate_hz=500.0), duration_s=1.5)
    assert await agent.run() == 0
    s = agent.summary
    assert s is not None and s["exit_reason"] == "duration"
    assert s["display_loop"]["mode"] == "asyncio" and s["display_loop"]["iterations"] > 100
    assert s["display_loop"]["target_hz"] == 500.0
    assert s["display"]["commands_sent"] > 10 and s["render"]["rendered"] > 10
