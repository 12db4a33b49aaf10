"""The view server over real sockets: page, snapshots, trail, limits, bad clients, tokens."""

from __future__ import annotations

import asyncio
import itertools
import json
import urllib.error
import urllib.request
from typing import Any

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from shared.errors import ConfigError
from shared.view import ViewServer, ViewServerConfig, parse_view_address
from tests.support import async_wait_until, scaled


class FakeSource:
    """A view source whose trail grows by one point per live() call."""

    def __init__(self, pad_bytes: int = 0) -> None:
        self.pad = "p" * pad_bytes
        self.calls = 0
        self.trail: list[list[float]] = []
        self.version = 0
        self.result: dict[str, Any] | None = None
        self.fail = False

    def live(self) -> dict[str, Any]:
        if self.fail:
            raise RuntimeError("broken source")
        self.calls += 1
        self.trail.append([float(self.calls), 0.0, 0.0, 1.0])
        return {"station": "test", "calls": self.calls, "pad": self.pad}

    def trail_since(self, start: int, limit: int) -> tuple[int, list[list[float]]]:
        return start, self.trail[start:start + limit]

    def analysis(self) -> tuple[int, dict[str, Any] | None]:
        return self.version, self.result


async def _server(source: FakeSource, **cfg: Any) -> ViewServer:
    server = ViewServer(source, ViewServerConfig(**{"rate_hz": 60.0, **cfg}))
    await server.start("127.0.0.1", 0)
    return server


def _get(url: str) -> tuple[int, str, str]:
    try:
        with urllib.request.urlopen(url, timeout=scaled(5)) as resp:
            return resp.status, resp.headers["Content-Type"], resp.read().decode()
    except urllib.error.HTTPError as err:
        return err.code, err.headers["Content-Type"], err.read().decode()


async def test_serves_the_page_and_refuses_other_paths() -> None:
    server = await _server(FakeSource())
    try:
        base = f"http://127.0.0.1:{server.port}/"
        status, ctype, body = await asyncio.to_thread(_get, base)
        assert status == 200 and ctype.startswith("text/html") and "view.js" in body
        status, ctype, body = await asyncio.to_thread(_get, base + "view.js")
        assert status == 200 and ctype.startswith("text/javascript") and "WebSocket" in body
        assert (await asyncio.to_thread(_get, base + "../etc/passwd"))[0] == 404
        assert (await asyncio.to_thread(_get, base + "ws"))[0] == 426
    finally:
        await server.close()


async def test_snapshots_carry_live_state_the_whole_trail_and_analysis_once() -> None:
    source = FakeSource()
    server = await _server(source)
    try:
        async with connect(f"ws://127.0.0.1:{server.port}/ws") as ws:
            first = json.loads(await ws.recv())
            assert first["type"] == "snapshot" and first["live"]["station"] == "test"
            assert "analysis" not in first  # none yet
            source.result = {"findings": [{"kind": "benign"}]}
            source.version = 1
            got_analysis = 0
            points: list[list[float]] = list(first["trail"]["points"])
            nxt = first["trail"]["from"] + len(points)
            for _ in range(10):
                msg = json.loads(await ws.recv())
                assert msg["trail"]["from"] == nxt  # contiguous: nothing lost, nothing twice
                points += msg["trail"]["points"]
                nxt += len(msg["trail"]["points"])
                got_analysis += "analysis" in msg
            assert got_analysis == 1
            assert msg["live"]["view"]["clients"] == 1
            assert [p[0] for p in points] == [float(i + 1) for i in range(len(points))]
    finally:
        await server.close()


async def test_a_slow_browser_skips_snapshots_but_gets_every_trail_point() -> None:
    source = FakeSource(pad_bytes=256 * 1024)  # big snapshots fill the socket buffers soon
    server = await _server(source, rate_hz=100.0, trail_batch=7)
    try:
        async with connect(f"ws://127.0.0.1:{server.port}/ws", max_size=None) as ws:
            first = json.loads(await ws.recv())
            calls = source.calls
            # not reading: the server must keep publishing (latest wins), not wait for us
            await async_wait_until(lambda: source.calls >= calls + 100, 10,
                                   "100 more snapshots published while the browser is idle")
            points = list(first["trail"]["points"])
            nxt = first["trail"]["from"] + len(points)
            seqs = [first["seq"]]
            while nxt < source.calls - 5:
                msg = json.loads(await ws.recv())
                assert msg["trail"]["from"] == nxt and len(msg["trail"]["points"]) <= 7
                points += msg["trail"]["points"]
                nxt += len(msg["trail"]["points"])
                seqs.append(msg["seq"])
            assert [p[0] for p in points] == [float(i + 1) for i in range(len(points))]
            # the snapshots published while the buffers were full were skipped, not queued
            assert max(b - a for a, b in itertools.pairwise(seqs)) > 1
            assert server.counters["snapshots_skipped"] > 0
    finally:
        await server.close()


async def test_too_many_browsers_get_503_and_the_others_keep_their_stream() -> None:
    server = await _server(FakeSource(), max_clients=2)
    url = f"ws://127.0.0.1:{server.port}/ws"
    try:
        async with connect(url) as a, connect(url) as b:
            await a.recv()
            await b.recv()
            with pytest.raises(InvalidStatus) as err:
                async with connect(url):
                    pass
            assert err.value.response.status_code == 503
            assert server.counters["clients_refused"] == 1
            await a.recv()
            await b.recv()
        await async_wait_until(lambda: server.clients == 0, 5, "both browsers gone")
        async with connect(url) as c:  # slots are given back
            await c.recv()
    finally:
        await server.close()


async def test_garbage_and_oversized_messages_hurt_only_their_sender() -> None:
    server = await _server(FakeSource(), max_message_bytes=256)
    url = f"ws://127.0.0.1:{server.port}/ws"
    try:
        async with connect(url) as good, connect(url) as bad:
            await bad.send(b"\xff\x00garbage")
            await bad.send("{not json")
            await bad.send(json.dumps({"type": "hello", "token": 5}))
            await bad.recv()  # still served: what a browser sends is ignored
            await async_wait_until(
                lambda: server.counters["client_messages_ignored"] >= 3, 5, "3 ignored")
            await bad.send("x" * 10_000)
            with pytest.raises(ConnectionClosed) as err:
                for _ in range(1000):
                    await bad.recv()
            assert err.value.rcvd is not None and err.value.rcvd.code == 1009
            for _ in range(3):
                assert json.loads(await good.recv())["type"] == "snapshot"
    finally:
        await server.close()


async def test_a_failing_source_is_logged_and_the_server_recovers() -> None:
    source = FakeSource()
    server = await _server(source)
    try:
        async with connect(f"ws://127.0.0.1:{server.port}/ws") as ws:
            await ws.recv()
            source.fail = True
            await async_wait_until(lambda: server.counters["source_errors"] >= 3, 5,
                                   "failed snapshots")
            source.fail = False
            calls = source.calls
            await async_wait_until(lambda: source.calls > calls + 2, 5, "snapshots again")
            msg = json.loads(await ws.recv())
            assert msg["live"]["calls"] > 0
    finally:
        await server.close()


async def test_with_an_authorizer_the_hello_must_carry_a_valid_token() -> None:
    def authorize(session: str, token: str) -> bool:
        return session == "s1" and token == "good"

    server = ViewServer(FakeSource(), ViewServerConfig(rate_hz=60.0, hello_timeout_s=0.5),
                        authorize=authorize)
    await server.start("127.0.0.1", 0)
    url = f"ws://127.0.0.1:{server.port}/ws"
    try:
        for hello in ({"type": "hello", "session": "s1", "token": "bad"},
                      {"type": "hello", "session": "s2", "token": "good"}, "junk", None):
            async with connect(url) as ws:
                if hello is not None:
                    await ws.send(hello if isinstance(hello, str) else json.dumps(hello))
                with pytest.raises(ConnectionClosed) as err:
                    await ws.recv()
                assert err.value.rcvd is not None and err.value.rcvd.code == 4001
        assert server.counters["clients_unauthorized"] == 4
        async with connect(url) as ws:
            await ws.send(json.dumps({"type": "hello", "session": "s1", "token": "good"}))
            assert json.loads(await ws.recv())["type"] == "snapshot"
    finally:
        await server.close()


def test_thread_mode_starts_serves_and_stops_cleanly() -> None:
    server = ViewServer(FakeSource(), ViewServerConfig(rate_hz=30.0))
    port = server.start_thread("127.0.0.1", 0)
    try:
        status, _, _ = _get(f"http://127.0.0.1:{port}/")
        assert status == 200
    finally:
        server.stop_thread()
    with pytest.raises(ConfigError, match="cannot listen"):
        other = ViewServer(FakeSource())
        busy = ViewServer(FakeSource())
        p = busy.start_thread("127.0.0.1", 0)
        try:
            other.start_thread("127.0.0.1", p)
        finally:
            busy.stop_thread()
            other.stop_thread()


@pytest.mark.parametrize(("text", "host", "port", "loopback"), [
    ("127.0.0.1:8780", "127.0.0.1", 8780, True), ("8780", "127.0.0.1", 8780, True),
    ("[::1]:0", "::1", 0, True), ("0.0.0.0:80", "0.0.0.0", 80, False),
    ("localhost:1", "localhost", 1, True), ("lab-pc:9", "lab-pc", 9, False)])
def test_parse_view_address(text: str, host: str, port: int, loopback: bool) -> None:
    address = parse_view_address(text)
    assert (address.host, address.port, address.is_loopback) == (host, port, loopback)


@pytest.mark.parametrize("text", ["host:", "host:abc", "1:70000", "h:-1"])
def test_parse_view_address_rejects_bad_input(text: str) -> None:
    with pytest.raises(ConfigError, match="--view"):
        parse_view_address(text)


async def test_failed_upgrades_never_hold_a_viewer_slot() -> None:
    server = await _server(FakeSource(), max_clients=2)
    try:
        for _ in range(5):  # an upgrade without a key fails the handshake (HTTP 400)
            reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
            writer.write(b"GET /ws HTTP/1.1\r\nHost: x\r\nConnection: Upgrade\r\n"
                         b"Upgrade: websocket\r\n\r\n")
            await writer.drain()
            status = await reader.readline()
            assert b" 400 " in status
            writer.close()
            await writer.wait_closed()
        url = f"ws://127.0.0.1:{server.port}/ws"
        async with connect(url) as a, connect(url) as b:
            await a.recv()
            await b.recv()
            assert server.clients == 2
    finally:
        await server.close()


async def test_control_messages_reach_the_callback_only_where_one_is_given() -> None:
    got: list[dict[str, Any]] = []

    def control(doc: Any) -> None:
        if doc.get("action") == "explode":
            raise ValueError("unknown control")
        got.append(dict(doc))

    source = FakeSource()
    server = ViewServer(source, ViewServerConfig(rate_hz=60.0), control=control)
    await server.start("127.0.0.1", 0)
    plain = await _server(FakeSource())  # a station's view: no callback
    try:
        async with connect(f"ws://127.0.0.1:{server.port}/ws") as ws, \
                connect(f"ws://127.0.0.1:{plain.port}/ws") as ws_plain:
            await ws.send(json.dumps({"type": "control", "action": "pause"}))
            await ws.send(json.dumps({"type": "control", "action": "explode"}))
            await ws.send(json.dumps({"type": "hello"}))  # not a control: ignored
            await ws.send("{not json")
            await ws_plain.send(json.dumps({"type": "control", "action": "pause"}))
            await async_wait_until(lambda: server.counters["client_messages_ignored"] >= 3
                                   and plain.counters["client_messages_ignored"] >= 1, 5,
                                   "the messages read")
            assert got == [{"type": "control", "action": "pause"}]
            assert server.counters["control_messages"] == 1
            assert server.counters["control_errors"] == 1
            assert plain.counters["control_messages"] == 0
            assert json.loads(await ws.recv())["type"] == "snapshot"  # still served
    finally:
        await server.close()
        await plain.close()
