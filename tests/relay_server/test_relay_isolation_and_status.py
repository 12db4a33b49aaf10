"""A stalled consumer does not delay another session; /status and /metrics; shutdown."""

from __future__ import annotations

import asyncio
import contextlib
import json
import time

import numpy as np

from shared.protocol import ArmCommand, ArmState, TactileFrame
from tests.relay_server.relay_clients import Client, clients, running_relay
from tests.support import MachineStalls, scaled


async def http_get(port: int, path: str) -> tuple[int, dict[str, str], str]:
    """Plain HTTP/1.1 GET on 127.0.0.1 (the relay closes after the response)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
        await writer.drain()
        async with asyncio.timeout(scaled(5.0)):
            data = await reader.read()
    finally:
        writer.close()
        await writer.wait_closed()
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode().split("\r\n")
    headers = dict(line.split(": ", 1) for line in lines[1:])
    return int(lines[0].split()[1]), headers, body.decode()


async def wait_relay_ready(port: int, timeout_s: float = 20.0) -> None:
    """Wait (scaled) until a relay process answers ``GET /status`` on ``port``."""
    async with asyncio.timeout(scaled(timeout_s)):
        while True:
            with contextlib.suppress(OSError):
                if (await http_get(port, "/status"))[0] == 200:
                    return
            await asyncio.sleep(0.1)


async def round_trip_ms(local: Client, remote: Client, seq: int) -> float:
    t0 = time.perf_counter()
    await local.send(ArmCommand(seq=seq, ts_us=local.now(), action="stop"))
    await remote.expect("arm_command", skip=("clock_ping", "stats", "arm_state"))
    await remote.send(ArmState(seq=seq, ts_us=remote.now(), position_mm=(0.0, 0.0, 0.0)))
    await local.expect("arm_state", skip=("clock_ping", "stats", "tactile_frame"))
    return (time.perf_counter() - t0) * 1e3


async def test_stalled_consumer_does_not_delay_another_session() -> None:
    async with running_relay() as relay, clients(("tcp", 0), ("tcp", 0), ("ws", 0),
                                                 ("ws", 0)) as (stalled, flooder, l2, r2):
        await stalled.connect(relay)
        await flooder.connect(relay)
        await stalled.hello("local", "stuck")  # then never reads again
        await flooder.hello("remote", "stuck")
        await l2.connect(relay)
        await r2.connect(relay)
        await l2.hello("local", "fine")
        await r2.hello("remote", "fine")
        baseline = [await round_trip_ms(l2, r2, i) for i in range(20)]
        layer = np.zeros((128, 128), np.float32)  # 64 KiB per frame
        frame = TactileFrame(seq=0, ts_us=0, layers={"height_mm": layer})
        flood_bytes = 0
        during = []
        with MachineStalls() as stalls:  # a stall of the machine lengthens a round trip
            for seq in range(1, 201):  # ~13 MB at a consumer that reads nothing
                data = flooder.conn.encode(TactileFrame(seq=seq, ts_us=flooder.now(),
                                                        layers=frame.layers))
                flood_bytes += len(data)
                await flooder.send_raw(data)
                if seq % 10 == 0:
                    during.append(await round_trip_ms(l2, r2, 1000 + seq))
        assert flood_bytes > 10_000_000
        status = relay.status()["sessions"]["stuck"]
        drops = status["drops"]["remote_to_local"]["latest_wins"]
        assert drops > 0  # the stalled reader's socket is full: frames replaced unsent
        # bounded by construction: one slot per state stream towards the local station
        # (tactile_frame, arm_state) and per periodic control message (stats, clock_ping)
        assert status["queue_depth"]["local"] <= 4
        # the other session's round trip stays small (not seconds of queued frames)
        assert max(during) < max(scaled(250.0), 10 * float(np.median(baseline))) + \
            1000 * stalls.total_s, (during, stalls.stalls_s)
        fine = relay.status()["sessions"]["fine"]
        assert fine["drops"]["local_to_remote"]["queue_full"] == 0


async def test_status_and_metrics_endpoints() -> None:
    async with running_relay() as relay, clients(("ws", 0), ("tcp", 0)) as (local, remote):
        await local.connect(relay)
        await remote.connect(relay)
        await local.hello("local", "stat")
        await remote.hello("remote", "stat")
        for i in range(5):
            await round_trip_ms(local, remote, i)
        code, headers, body = await http_get(relay.ws_port, "/status")
        assert code == 200 and headers["Content-Type"] == "application/json"
        doc = json.loads(body)
        s = doc["sessions"]["stat"]
        assert s["forwarded"] == {"local_to_remote": 5, "remote_to_local": 5}
        assert {p["role"] for p in s["peers"]} == {"local", "remote"}
        assert s["delay_us"]["local_to_remote"]["relay"]["p50"] is not None
        assert "arm_command" in s["streams"]["local_to_remote"]
        code, headers, text = await http_get(relay.ws_port, "/metrics")
        assert code == 200 and headers["Content-Type"].startswith("text/plain")
        assert "# TYPE teletouch_relay_forwarded_total counter" in text
        assert 'teletouch_relay_forwarded_total{session="stat",direction="local_to_remote"} 5' \
            in text
        assert 'leg="relay",quantile="0.99"' in text
        code, _, _ = await http_get(relay.ws_port, "/nope")
        assert code == 404


async def test_shutdown_says_bye_and_closes_1001() -> None:
    async with running_relay() as relay, clients(("ws", 0), ("tcp", 0)) as (ws, tcp):
        await ws.connect(relay)
        await tcp.connect(relay)
        await ws.hello("local", "bye")
        await tcp.hello("remote", "bye")
        await relay.close()
        assert (await ws.expect("bye")).reason == "relay shutting down"
        assert await ws.expect_closed() == 1001
        assert (await tcp.expect("bye")).reason == "relay shutting down"
        await tcp.expect_closed()
        assert relay.sessions == {}
