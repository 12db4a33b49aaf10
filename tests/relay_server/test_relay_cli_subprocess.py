"""`teletouch relay` as a real process: /status over HTTP, a malformed client rejected."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import signal
import sys

from websockets.asyncio.client import connect

from relay_server.auth import derive_token
from shared.protocol import ArmCommand, Hello, ProtocolConnection, decode
from tests.relay_server.test_relay_isolation_and_status import http_get
from tests.support import free_tcp_port, scaled


def memlock_refusal() -> str | None:
    """Why a process of this user may not lock its memory (None: it may), as the relay
    judges it."""
    from shared.memlock import _refusal

    return _refusal()


def locked_kib(pid: int) -> int:
    """``VmLck`` of a process (kB)."""
    with open(f"/proc/{pid}/status", encoding="ascii") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmLck:"))


async def test_teletouch_relay_subprocess() -> None:
    port, tcp_port = free_tcp_port(), free_tcp_port()
    exe = shutil.which("teletouch")
    cmd = [exe] if exe else [sys.executable, "-m", "lab.cli"]
    env = dict(os.environ, TELETOUCH_RELAY_SECRET="cli-secret-0123456789abcdef0123456789")
    proc = await asyncio.create_subprocess_exec(
        *cmd, "relay", "--host", "127.0.0.1", "--port", str(port), "--tcp-port", str(tcp_port),
        env=env, stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
    try:
        async with asyncio.timeout(scaled(20.0)):
            while True:
                with contextlib.suppress(OSError):
                    code, _, body = await http_get(port, "/status")
                    if code == 200:
                        break
                await asyncio.sleep(0.1)
        assert json.loads(body)["ports"] == {"ws": port, "tcp": tcp_port}
        # the relay locks its memory where that is safe, as the stations do, and says so
        lock = json.loads(body)["memory_lock"]
        refusal = memlock_refusal()
        assert lock == {"locked": refusal is None, "reason": refusal}
        if refusal is None:
            assert locked_kib(proc.pid) > 0
        token = derive_token("cli-secret-0123456789abcdef0123456789", "demo")
        conn = ProtocolConnection("ws")
        async with connect(f"ws://127.0.0.1:{port}") as local, \
                connect(f"ws://127.0.0.1:{port}") as remote, \
                connect(f"ws://127.0.0.1:{port}") as bad:
            for ws, role in ((local, "local"), (remote, "remote")):
                await ws.send(conn.encode(Hello(role=role, session="demo", token=token)))
                assert decode(await ws.recv(decode=False)).TYPE == "welcome"
            await bad.send(b"this is not msgpack")
            err = decode(await bad.recv(decode=False))
            assert (err.code, err.fatal) == ("malformed", True)  # type: ignore[attr-defined]
            await bad.wait_closed()
            assert bad.close_code == 1007
            await local.send(conn.encode(ArmCommand(seq=1, ts_us=1, action="home")))
            async with asyncio.timeout(scaled(5.0)):
                while True:
                    msg = decode(await remote.recv(decode=False))
                    if msg.TYPE == "arm_command":
                        break
            assert msg.action == "home"  # type: ignore[attr-defined]
            _, _, body = await http_get(port, "/status")
            doc = json.loads(body)
            assert doc["sessions"]["demo"]["forwarded"]["local_to_remote"] == 1
            assert doc["counters"]["fatal_malformed"] == 1
        proc.send_signal(signal.SIGTERM)
        async with asyncio.timeout(scaled(10.0)):
            rc = await proc.wait()
        assert rc == 0
        assert proc.stderr is not None
        log_text = (await proc.stderr.read()).decode()
        assert log_text.count("WARNING") == 1 and "Traceback" not in log_text
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
