"""`teletouch relay` and `teletouch remote` as real processes, a fake local station in the test.

The remote presses a known tumor (found in the ground truth the lab writes for the same
phantom) for the fake local station, and on SIGTERM stops cleanly (exit 0) and writes
--summary-json.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
from pathlib import Path

import shared.memlock as memlock
from lab.ground_truth import write_ground_truth
from relay_server.auth import derive_token
from remote_site.agent.world import build_world
from shared.workspace import WorkspaceMap
from tests.relay_server.test_relay_isolation_and_status import http_get, wait_relay_ready
from tests.remote_site.test_agent_relay import SESSION, check_press_result, fake_local
from tests.support import NotifySocket, free_tcp_port, scaled, teletouch_cmd

SUMMARY_KEYS = {"role", "elapsed_s", "frames", "platform_states", "arm_commands", "arm",
                "stiffness", "latency_ms", "link", "session", "arm_backend", "sensor_backend",
                "phantom", "seed"}


async def _stop(proc: asyncio.subprocess.Process) -> None:
    if proc.returncode is None:
        proc.kill()
        await proc.wait()


async def _remote_joined(port: int) -> bool:
    with contextlib.suppress(OSError, ValueError):
        code, _, body = await http_get(port, "/status")
        session = json.loads(body).get("sessions", {}).get(SESSION, {})
        return code == 200 and any(p.get("role") == "remote" for p in session.get("peers", []))
    return False


async def test_relay_and_remote_as_processes(tmp_path: Path) -> None:
    """Also what systemd is told (``Type=notify``, ``WatchdogSec=``): each process is ready
    once it serves, pings its watchdog and says it stops, and nothing else speaks for it."""
    cmd = teletouch_cmd()
    port, tcp_port = free_tcp_port(), free_tcp_port()
    relay_notify, remote_notify = NotifySocket(), NotifySocket()  # closed in the finally
    secret = "sub-secret-0123456789abcdef0123456789"  # 32 characters at least
    env = dict(os.environ, TELETOUCH_RELAY_SECRET=secret, **relay_notify.env(200_000))
    token = derive_token(secret, SESSION)
    relay = await asyncio.create_subprocess_exec(
        *cmd, "relay", "--host", "127.0.0.1", "--port", str(port), "--tcp-port", str(tcp_port),
        "--stats-interval-s", "0.2", env=env, stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.DEVNULL)
    remote = None
    try:
        await wait_relay_ready(port)
        truth_path, summary_path = tmp_path / "truth.json", tmp_path / "summary.json"
        write_ground_truth(build_world("severity", 2, ideal=True), truth_path, WorkspaceMap())
        await relay_notify.wait_for(lambda got: bool(got), scaled(10.0))
        assert relay_notify.texts(relay.pid)[0] == (  # ready once it serves
            f"READY=1\nSTATUS=relay serving: WebSocket port {port}, TCP port {tcp_port}")
        remote_env = dict(os.environ, TELETOUCH_REMOTE_LINK_TOKEN=token,
                          **remote_notify.env(200_000))
        remote = await asyncio.create_subprocess_exec(
            *cmd, "remote", "--relay", f"tcp://127.0.0.1:{tcp_port}", "--session", SESSION,
            "--arm", "sim", "--sensor", "sim", "--phantom", "severity", "--seed", "2",
            "--ideal", "--frame-rate-hz", "60",
            "--summary-json", str(summary_path), env=remote_env,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        async with asyncio.timeout(scaled(30.0)):  # the remote has opened its devices
            while not await _remote_joined(port):
                await asyncio.sleep(0.1)
        await remote_notify.wait_for(lambda got: ("READY=1\nSTATUS=remote station running") in
                                     [t for _, t in got], scaled(30.0))
        truth = json.loads(truth_path.read_text())
        hardest = next(t for t in truth["tumors"] if t["id"] == truth["severity_order"][-1])
        got = await fake_local(f"ws://127.0.0.1:{port}/", tuple(hardest["center_mm"]),
                               duration_s=scaled(4.5), token=token)
        remote.send_signal(signal.SIGTERM)
        async with asyncio.timeout(scaled(15.0)):
            out, err = await remote.communicate()
        assert remote.returncode == 0, err.decode()[-2000:]
        await _told_systemd(remote_notify, remote.pid)
        check_press_result(got, truth, hardest["id"])
        summary = json.loads(summary_path.read_text())
        assert set(summary) >= SUMMARY_KEYS
        assert summary["phantom"] == "severity" and summary["seed"] == 2
        assert summary["frames"]["sent"] > 30
        assert summary["arm"]["applied"] > 0
        refusal = memlock._refusal()  # locked by default wherever it is safe
        assert summary["memory_lock"] == {"locked": refusal is None, "reason": refusal}
        assert "tactile frames sent" in out.decode()
        assert "Traceback" not in err.decode().split("remote station stopped")[0]
        relay.send_signal(signal.SIGTERM)
        async with asyncio.timeout(scaled(10.0)):
            await relay.wait()
        await _told_systemd(relay_notify, relay.pid)
    finally:
        relay_notify.close()
        remote_notify.close()
        if remote is not None:
            await _stop(remote)
        if relay.returncode is None:
            relay.send_signal(signal.SIGTERM)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(scaled(10.0)):
                    await relay.wait()
        await _stop(relay)


async def _told_systemd(notify: NotifySocket, pid: int) -> None:
    """``pid`` (ended) said it was ready, pinged its watchdog (every 0.1 s here) and said it
    was stopping, in that order; nothing else said anything."""
    await notify.wait_for(lambda got: bool(got) and got[-1][1] == "STOPPING=1", scaled(10.0))
    texts = notify.texts()
    assert notify.texts(pid) == texts, notify.messages  # not its children, nor its workers
    assert texts[0].startswith("READY=1\nSTATUS=") and texts[-1] == "STOPPING=1", texts
    assert set(texts[1:-1]) == {"WATCHDOG=1"} and len(texts) >= 4, texts
