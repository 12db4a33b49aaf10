"""Helpers for the local-agent tests: a fake remote station on StationLink, agent builders."""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path
from typing import Any

import numpy as np

from local_site.agent import LocalAgent, LocalAgentConfig
from local_site.agent.display_loop import DisplayLoop
from local_site.agent.display_process import DisplayProcess
from local_site.agent.platform_reader import PlatformReader
from relay_server.auth import derive_token
from shared.client import StationLink, StationLinkConfig
from shared.protocol import Hop, PlatformState, TactileFrame
from shared.timebase import now_us
from tests.relay_server.relay_clients import SECRET
from tests.support import async_wait_until, scaled

SESSION = "agent-test"
TOKEN = derive_token(SECRET, SESSION)
FRAME_SHAPE = (9, 9)


def make_frame(seq: int, state: PlatformState | None, height_mm: float = 2.0,
               k: float = 0.8) -> TactileFrame:
    """A tactile frame answering ``state`` (contract hops), uniform height and stiffness."""
    t = now_us()
    hops = (*state.hops, Hop("remote", "arm_command", t), Hop("remote", "sensor_frame", t),
            Hop("remote", "sensor_arrival", t),
            Hop("remote", "tactile_ready", t)) if state is not None else ()
    center = state.position_mm[:2] if state is not None else (30.0, 30.0)
    return TactileFrame(
        seq=seq, ts_us=t, hops=hops, center_mm=(float(center[0]), float(center[1])),
        pitch_mm=1.0, layers={"height_mm": np.full(FRAME_SHAPE, height_mm, np.float32),
                              "stiffness_k": np.full(FRAME_SHAPE, k, np.float32),
                              "stiffness_n_per_mm": np.full(FRAME_SHAPE, 0.7, np.float32)},
        contact=True, force_n=1.5, indentation_mm=0.4,
        source_seq=state.seq if state is not None else None,
        source_ts_us=state.ts_us if state is not None else None)


class FakeRemote:
    """A remote station: receives platform_state, answers with tactile frames at a rate."""

    def __init__(self, url: str, *, rate_hz: float = 60.0, height_mm: float = 2.0) -> None:
        self.link = StationLink(url, session=SESSION, role="remote", token=TOKEN,
                                reconnect_min_s=0.05, reconnect_max_s=0.2, seed=1)
        self.rate_hz = rate_hz
        self.height_mm = height_mm
        self.paused = False
        self.states: list[PlatformState] = []
        self.frames_sent = 0
        self._tasks: list[asyncio.Task[None]] = []

    async def __aenter__(self) -> FakeRemote:
        self.link.start()
        self._tasks = [asyncio.create_task(self._rx()), asyncio.create_task(self._tx())]
        return self

    async def __aexit__(self, *exc: object) -> None:
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self.link.close()

    async def _rx(self) -> None:
        async for msg in self.link.messages():
            if isinstance(msg, PlatformState):
                self.states.append(msg)

    async def _tx(self) -> None:
        while True:
            await asyncio.sleep(1.0 / self.rate_hz)
            if self.paused or not self.link.is_connected or not self.states:
                continue
            self.frames_sent += 1
            with contextlib.suppress(Exception):
                await self.link.send(make_frame(self.frames_sent, self.states[-1],
                                                self.height_mm))


def relay_agent(url: str, tmp_path: Path | None = None, **overrides: Any) -> LocalAgent:
    """An in-process agent on the sim devices, platform held at (30, 30, 100) mm."""
    # frames made in this process are young unless the machine is loaded: the age bound is
    # the subject of tests/local_site/test_display_loop_age.py, not of these
    settings: dict[str, Any] = dict(motion="hold:x=30,y=30,z=100", status_interval_s=0.25,
                                    max_frame_age_s=min(scaled(0.5), 5.0))  # 5 s: the most allowed
    settings.update(overrides)
    link = StationLinkConfig(url=url, session=SESSION, token=TOKEN, reconnect_min_s=0.05,
                             reconnect_max_s=0.3)
    return LocalAgent(LocalAgentConfig(**settings), link_config=link,
                      record_path=None if tmp_path is None else tmp_path / "rec.mcap",
                      summary_path=None if tmp_path is None else tmp_path / "summary.json")


async def wait_for(predicate: Any, timeout_s: float, what: str) -> None:
    """Poll ``predicate()`` every 10 ms until true; fail after ``scaled(timeout_s)``."""
    await async_wait_until(predicate, timeout_s, what, poll_s=0.01)


def loop_of(agent: LocalAgent) -> DisplayLoop:
    """The agent's display loop; fails the test when the agent has not opened it (or runs
    it in a process of its own: :func:`any_loop_of`)."""
    if not isinstance(agent.loop, DisplayLoop):
        raise AssertionError(f"the agent's display loop is not running in-process: "
                             f"{agent.loop!r}")
    return agent.loop


def any_loop_of(agent: LocalAgent) -> DisplayLoop | DisplayProcess:
    """The agent's display loop, in-process or in a process of its own (what the station
    reads of it is the same)."""
    if agent.loop is None:
        raise AssertionError("the agent's display loop is not running")
    return agent.loop


def reader_of(agent: LocalAgent) -> PlatformReader:
    """The agent's in-process platform reader; fails the test when the agent has not opened
    it (or reads its platform in a process of its own)."""
    if not isinstance(agent.reader, PlatformReader):
        raise AssertionError(f"the agent's platform reader is not running in-process: "
                             f"{agent.reader!r}")
    return agent.reader


def link_of(agent: LocalAgent) -> StationLink:
    """The agent's relay link; fails the test when the agent has none."""
    if agent.link is None:
        raise AssertionError("the agent has no relay link")
    return agent.link
