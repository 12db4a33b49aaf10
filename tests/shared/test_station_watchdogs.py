"""The stations' own event-loop watchdogs (``hang_timeout_s``, :mod:`shared.loop_watchdog`):
a real ``teletouch local`` and ``teletouch remote`` whose loop a bug blocks (put in by the
test), or a remote whose frame call in the pipeline's thread never returns, write every
thread's stack and exit with code 1, for systemd or a container's ``restart: on-failure`` to
start them again. The relay's: ``test_relay_health.py``."""

from __future__ import annotations

import asyncio
import os
import sys

import pytest

from tests.support import assert_ended_by_loop_watchdog, scaled

pytestmark = pytest.mark.slow

#: ``teletouch`` with a bug put into a station: its status coroutine blocks the event loop
_WITH_A_BLOCKING_STATUS = """
import asyncio, sys, time
import local_site.agent.station as local_station
import remote_site.agent.station as remote_station

def _a_status_loop_that_blocks():
    time.sleep(3600)

async def _status(self):
    await asyncio.sleep(0.5)
    _a_status_loop_that_blocks()

local_station.LocalAgent._status = _status
remote_station.RemoteStation._status_loop = _status
from lab.cli import main
sys.exit(main(sys.argv[1:]))
"""

#: ``teletouch`` with a remote whose fourth frame's processing (in the pipeline's thread)
#: never returns (as a hung sensor driver's read would not); its event loop turns on
_WITH_A_FRAME_THAT_HANGS = """
import sys, time
from remote_site.agent.pipeline import FramePipeline

_process = FramePipeline.process
_calls = []

def _a_frame_call_that_hangs():
    time.sleep(3600)

def process(self, seq, source):
    _calls.append(seq)
    if len(_calls) == 4:
        print("hanging", file=sys.stderr, flush=True)
        _a_frame_call_that_hangs()
    return _process(self, seq, source)

FramePipeline.process = process
from lab.cli import main
sys.exit(main(sys.argv[1:]))
"""

_COMMANDS = {
    "local": ["local", "--scene", "hemisphere:radius_mm=8", "--platform", "sim", "--display",
              "sim", "--motion", "raster:x0=26,x1=34,y0=30,y1=30,press_depth=0,pause=0",
              "--no-lock-memory"],
    # no relay: the station serves on while its link retries (a station never gives up)
    "remote": ["remote", "--relay", "tcp://127.0.0.1:9", "--session", "s1", "--arm", "sim",
               "--sensor", "sim", "--phantom", "severity", "--seed", "2", "--ideal"],
}


async def _station(program: str, role: str) -> asyncio.subprocess.Process:
    """``teletouch`` with a bug put in (``program``) as a station with a 3 s (scaled) hang
    timeout; its standard error piped."""
    env = {**os.environ, f"TELETOUCH_{role.upper()}_AGENT_HANG_TIMEOUT_S": str(scaled(3.0)),
           "TELETOUCH_REMOTE_LINK_TOKEN": "x"}
    return await asyncio.create_subprocess_exec(
        sys.executable, "-c", program, "--log-level", "WARNING", *_COMMANDS[role], env=env,
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)


@pytest.mark.parametrize("role", ["local", "remote"])
async def test_a_station_whose_loop_is_stuck_writes_its_stacks_and_exits(role: str) -> None:
    proc = await _station(_WITH_A_BLOCKING_STATUS, role)
    try:
        _, stderr = await asyncio.wait_for(proc.communicate(), scaled(90.0))
        assert_ended_by_loop_watchdog(proc.returncode, stderr.decode(errors="replace"),
                                      "_a_status_loop_that_blocks",
                                      stuck="the event loop has not turned for ")
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


async def test_a_remote_whose_frame_call_hangs_writes_its_stacks_and_exits() -> None:
    """The loop turns on (the status loop, the arm), but a frame never comes: the station
    ends as for a stuck loop, after a WARNING naming the call at half the timeout."""
    proc = await _station(_WITH_A_FRAME_THAT_HANGS, "remote")
    try:
        _, stderr = await asyncio.wait_for(proc.communicate(), scaled(90.0))
        text = stderr.decode(errors="replace")
        assert_ended_by_loop_watchdog(
            proc.returncode, text, "_a_frame_call_that_hangs",
            stuck="a frame's capture and processing has not returned for ")
        assert "a frame's capture and processing has not returned for" in text, text[-3000:]
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


async def test_a_remote_stopped_while_a_frame_call_hangs_still_ends() -> None:
    """SIGTERM while the frame call hangs: the station's close-down waits for the
    pipeline's thread, so the watch holds until it has ended, and the station ends with
    its stacks instead of waiting for that thread for ever."""
    proc = await _station(_WITH_A_FRAME_THAT_HANGS, "remote")
    assert proc.stderr is not None
    try:
        lines: list[bytes] = []
        async with asyncio.timeout(scaled(60.0)):
            while not lines or lines[-1] != b"hanging\n":
                lines.append(await proc.stderr.readline())
                assert lines[-1], b"".join(lines)[-3000:]
        proc.terminate()
        rest = await asyncio.wait_for(proc.stderr.read(), scaled(60.0))
        await proc.wait()
        text = (b"".join(lines) + rest).decode(errors="replace")
        assert_ended_by_loop_watchdog(proc.returncode, text, "_a_frame_call_that_hangs")
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
