"""`teletouch relay` and `teletouch local` as real processes, a fake remote in the test."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import sys
from pathlib import Path

import numpy as np

import shared.memlock as memlock
from local_site.recording import load_recording
from tests.local_site.agent_support import FakeRemote, wait_for
from tests.relay_server.relay_clients import SECRET
from tests.support import NotifySocket, free_tcp_port, scaled

EXE = shutil.which("teletouch")
CMD = [EXE] if EXE else [sys.executable, "-m", "lab.cli"]


async def _stop(proc: asyncio.subprocess.Process) -> int:
    if proc.returncode is None:
        proc.send_signal(signal.SIGTERM)
    try:
        async with asyncio.timeout(scaled(15.0)):
            return await proc.wait()
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


async def test_relay_and_local_processes_sigterm_writes_record_and_summary(tmp_path: Path) -> None:
    port, tcp_port = free_tcp_port(), free_tcp_port()
    env = dict(os.environ, TELETOUCH_RELAY_SECRET=SECRET)
    relay = await asyncio.create_subprocess_exec(
        *CMD, "relay", "--host", "127.0.0.1", "--port", str(port), "--tcp-port", str(tcp_port),
        env=env, stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL)
    local = None
    try:
        url = f"ws://127.0.0.1:{port}/"
        from relay_server.auth import derive_token
        summary, record = tmp_path / "summary.json", tmp_path / "run.mcap"
        local = await asyncio.create_subprocess_exec(
            *CMD, "local", "--relay", url, "--session", "agent-test",
            "--token", derive_token(SECRET, "agent-test"), "--platform", "sim", "--display",
            "sim", "--motion", "raster:x0=25,x1=35,y0=30,y1=31,spacing=1,press_depth=0",
            "--record", str(record), "--summary-json", str(summary), "--no-status",
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        assert local.stderr is not None and local.stdout is not None
        err_lines: list[str] = []

        async def read_stderr() -> None:
            assert local is not None and local.stderr is not None
            async for line in local.stderr:
                err_lines.append(line.decode(errors="replace"))

        reader = asyncio.create_task(read_stderr())
        async with FakeRemote(url) as remote:
            # start counting once the display is connected (the render loop runs from then
            # on): a cold start (first JIT compile of the plant) may take seconds
            await wait_for(lambda: any("ArrayTac on" in ln and "connected" in ln
                                       for ln in err_lines),
                           30.0, "the local station's display to connect")
            first = remote.frames_sent
            await wait_for(lambda: remote.frames_sent >= first + 180, 25.0,
                           "frames to the local process")
        assert await _stop(local) == 0
        await asyncio.wait_for(reader, scaled(10.0))
        err_text = "".join(err_lines)
        out_text = (await local.stdout.read()).decode()
        assert "Traceback" not in err_text, err_text[-2000:]
        assert "stopped (signal)" in out_text
        doc = json.loads(summary.read_text())
        assert doc["exit_reason"] == "signal" and doc["frames_rendered"] > 10
        assert doc["motion_to_touch_ms"]["end_to_end"]["count"] > 10
        assert doc["display"]["last_feedback_safe_state"] is not None
        # locked by default wherever it is safe (this test's user and limits are the child's)
        refusal = memlock._refusal()
        assert doc["memory_lock"] == {"locked": refusal is None, "reason": refusal}
        rec = load_recording(record)
        assert rec.frames == doc["frames_accepted"]
        xs = rec.platform_mm[:, 0]
        assert xs.min() < 27 and xs.max() > 33 and np.all(np.diff(rec.platform_t_us) > 0)
    finally:
        if local is not None:
            await _stop(local)
        assert await _stop(relay) == 0


async def test_scene_mode_process_until_motion_done(tmp_path: Path) -> None:
    """Also what systemd is told (``Type=notify``, ``WatchdogSec=``): ready once the loops
    run, watchdog pings, stopping; from the station's process alone (not its children)."""
    summary = tmp_path / "scene.json"
    notify = NotifySocket()
    proc = await asyncio.create_subprocess_exec(
        *CMD, "local", "--scene", "hemisphere:radius_mm=8", "--platform", "sim", "--display",
        "sim", "--motion", "raster:x0=26,x1=34,y0=30,y1=30,press_depth=0,pause=0,loop=0",
        "--until-motion-done", "--summary-json", str(summary), "--no-lock-memory",
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL,
        # a platform lost only when it is: not when the machine stalled the station longer
        # than the default read timeout (250 ms)
        env={**os.environ, **notify.env(100_000),
             "TELETOUCH_LOCAL_AGENT_PLATFORM_READ_TIMEOUT_S": "5",
             "TELETOUCH_LOCAL_AGENT_PLATFORM_REOPEN_AFTER_S": "5"})
    try:
        async with asyncio.timeout(scaled(20.0)):
            assert await proc.wait() == 0
        await notify.wait_for(lambda got: bool(got) and got[-1][1] == "STOPPING=1",
                              scaled(10.0))  # the reader thread has it too
        texts = notify.texts()
        assert notify.texts(proc.pid) == texts, notify.messages
    finally:
        notify.close()
        await _stop(proc)
    assert texts[0] == "READY=1\nSTATUS=local station running" and texts[-1] == "STOPPING=1"
    assert set(texts[1:-1]) == {"WATCHDOG=1"} and len(texts) >= 3, texts
    doc = json.loads(summary.read_text())
    assert doc["mode"] == "scene" and doc["exit_reason"] == "motion_done"
    assert doc["memory_lock"] == {"locked": False, "reason": "off (lock_memory = false)"}
    assert doc["display"]["commands_sent"] > 20 and doc["link"] is None
    # No loss during the run: no platform error, and at most the start-up wait for the
    # platform's first sample when the display is ready first (loaded machine).
    assert doc["platform"]["errors"] == 0
    assert doc["safe_state"]["entries"] in ({}, {"platform_lost": 1})
