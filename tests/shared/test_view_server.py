"""The view server over real sockets: page, snapshots, trail, limits, bad clients, tokens."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import time
import urllib.error
import urllib.request
from typing import Any

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.protocol import State

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
            writer.write(b"GET /ws HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: Upgrade\r\n"
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


# ---------------------------------------------------------------- who may connect (audit)

_KEY = "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ=="


async def _upgrade_status(port: int, *headers: str) -> int:
    """Send a WebSocket upgrade of /ws with ``headers`` over a raw socket: the status code."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        lines = ["GET /ws HTTP/1.1", *headers, "Upgrade: websocket", _KEY,
                 "Sec-WebSocket-Version: 13"]
        writer.write(("\r\n".join(lines) + "\r\n\r\n").encode())
        await writer.drain()
        async with asyncio.timeout(scaled(5)):
            status = await reader.readline()
    finally:
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()
    return int(status.split()[1])


def _accept_s1(session: str, token: str) -> bool:
    return session == "s1" and token == "good"


async def test_a_page_of_another_site_cannot_open_the_view_or_send_control() -> None:
    got: list[Any] = []
    server = ViewServer(FakeSource(), ViewServerConfig(rate_hz=60.0), control=got.append)
    await server.start("127.0.0.1", 0)
    port = server.port
    assert port is not None
    url = f"ws://127.0.0.1:{port}/ws"
    try:
        for origin in ("https://evil.example", f"http://evil.example:{port}", "null",
                       f"http://127.0.0.1:{port + 1}", f"http://localhost:{port}",
                       f"file://127.0.0.1:{port}"):
            with pytest.raises(InvalidStatus) as err:
                async with connect(url, origin=origin) as ws:  # type: ignore[arg-type]
                    await ws.send(json.dumps({"type": "control", "action": "pause"}))
            assert err.value.response.status_code == 403, origin
        assert server.counters["ws_forbidden_origin"] == 6 and got == []
        # the page itself (same origin) and a client that sends no Origin are served
        for same in (f"http://127.0.0.1:{port}", None):
            async with connect(url, origin=same) as ws:  # type: ignore[arg-type]
                assert json.loads(await ws.recv())["type"] == "snapshot"
        assert await _upgrade_status(port, f"Host: localhost:{port}",
                                     f"Origin: http://LOCALHOST:{port}",
                                     "Connection: Upgrade") == 101
    finally:
        await server.close()


async def test_a_view_without_token_answers_only_its_own_host_names() -> None:
    """DNS rebinding: a page of evil.example whose name now points at 127.0.0.1 is same-origin
    with itself, but its Host header names evil.example: refused."""
    server = await _server(FakeSource(), allowed_hosts=("lab-pc.example",))
    port = server.port
    assert port is not None
    try:
        for host, code in ((f"evil.example:{port}", 403), ("evil.example", 403),
                           ("bad host", 403), (f"127.0.0.1:{port}", 101),
                           (f"localhost:{port}", 101), (f"[::1]:{port}", 101),
                           (f"LAB-PC.example:{port}", 101)):
            assert await _upgrade_status(port, f"Host: {host}", f"Origin: http://{host}",
                                         "Connection: Upgrade") == code, host
        assert await _upgrade_status(port, "Connection: Upgrade") == 403  # no Host at all
        assert server.counters["ws_forbidden_host"] == 3  # "bad host": a malformed origin
        assert server.counters["ws_forbidden_origin"] == 1
    finally:
        await server.close()
    # a token-protected view (the relay's) is reached by its public name: any host name,
    # as long as the Origin matches it
    server = ViewServer(FakeSource(), ViewServerConfig(rate_hz=60.0), authorize=_accept_s1)
    await server.start("127.0.0.1", 0)
    port = server.port
    assert port is not None
    try:
        public = f"relay.example.org:{port}"
        assert await _upgrade_status(port, f"Host: {public}", f"Origin: http://{public}",
                                     "Connection: Upgrade") == 101
        assert await _upgrade_status(port, f"Host: {public}", "Origin: https://evil.example",
                                     "Connection: Upgrade") == 403
        # behind a TLS proxy that keeps the Host: https://relay.example.org -> default ports
        assert await _upgrade_status(port, "Host: relay.example.org",
                                     "Origin: https://relay.example.org",
                                     "Connection: Upgrade") == 101
    finally:
        await server.close()


async def test_repeated_headers_get_400_not_a_server_error(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    server = await _server(FakeSource())
    port = server.port
    assert port is not None
    host = f"Host: 127.0.0.1:{port}"
    try:
        assert await _upgrade_status(port, host, host, "Connection: Upgrade") == 400
        assert await _upgrade_status(port, host, f"Origin: http://127.0.0.1:{port}",
                                     "Origin: https://evil.example",
                                     "Connection: Upgrade") == 400
        # Connection is a list header: two lines are one list, and the upgrade goes through
        assert await _upgrade_status(port, host, "Connection: keep-alive",
                                     "Connection: Upgrade") == 101
        assert server.counters["http_bad_request"] == 2
        async with connect(f"ws://127.0.0.1:{port}/ws") as ws:  # still serving
            assert json.loads(await ws.recv())["type"] == "snapshot"
    finally:
        await server.close()
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


async def test_a_deeply_nested_hello_or_control_message_is_refused_cleanly(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    nested = "[" * 2000 + "]" * 2000  # < 4 KiB, deeper than Python's recursion limit
    server = ViewServer(FakeSource(), ViewServerConfig(rate_hz=60.0), authorize=_accept_s1)
    await server.start("127.0.0.1", 0)
    got: list[Any] = []
    replay = ViewServer(FakeSource(), ViewServerConfig(rate_hz=60.0), control=got.append)
    await replay.start("127.0.0.1", 0)
    try:
        async with connect(f"ws://127.0.0.1:{server.port}/ws") as ws:
            await ws.send(nested)
            with pytest.raises(ConnectionClosed) as err:
                await ws.recv()
            assert err.value.rcvd is not None and err.value.rcvd.code == 4001
        async with connect(f"ws://127.0.0.1:{replay.port}/ws") as ws:
            await ws.recv()
            await ws.send(nested)
            await async_wait_until(lambda: replay.counters["client_messages_ignored"] >= 1, 5,
                                   "the nested message read and ignored")
            for _ in range(3):  # still served
                assert json.loads(await ws.recv())["type"] == "snapshot"
    finally:
        await server.close()
        await replay.close()
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


async def test_a_non_finite_analysis_is_dropped_and_the_live_stream_goes_on() -> None:
    source = FakeSource()
    server = await _server(source)
    url = f"ws://127.0.0.1:{server.port}/ws"
    try:
        source.result, source.version = {"map": [1.0, float("nan")]}, 1
        async with connect(url) as ws:
            for _ in range(10):
                msg = json.loads(await ws.recv())
                assert msg["type"] == "snapshot" and "analysis" not in msg
            assert server.counters["analysis_dropped"] == 1  # encoded once, not per message
            source.result, source.version = {"map": [1.0, 2.0]}, 2
            msg = await _first(ws, lambda m: "analysis" in m)
            assert msg["analysis"] == {"map": [1.0, 2.0]}
        async with connect(url) as ws:  # a browser that comes later gets it too
            assert (await _first(ws, lambda m: "analysis" in m))["analysis"]["map"] == [1, 2]
        assert server.counters["analysis_dropped"] == 1
    finally:
        await server.close()


async def _first(ws: Any, predicate: Any) -> dict[str, Any]:
    async with asyncio.timeout(scaled(5)):
        while True:
            msg = json.loads(await ws.recv())
            if predicate(msg):
                return dict(msg)


async def _closed_by_server(ws: Any) -> bool:
    """True once the server closed ``ws`` (a connected WebSocket that sent nothing)."""
    try:
        async with asyncio.timeout(scaled(5)):
            await ws.recv()
    except ConnectionClosed:
        return True
    except TimeoutError:
        return False
    return False


async def test_silent_sockets_from_one_address_cannot_lock_an_observer_out() -> None:
    """Behind a proxy every browser has the proxy's address: silent sockets from that
    address (no hello) used to get the observer HTTP 429; now the oldest gives way."""
    config = ViewServerConfig(rate_hz=60.0, max_clients=2, max_pending_per_address=3,
                              hello_timeout_s=scaled(30))
    server = ViewServer(FakeSource(), config, authorize=_accept_s1)
    await server.start("127.0.0.1", 0)
    url = f"ws://127.0.0.1:{server.port}/ws"
    hello = json.dumps({"type": "hello", "session": "s1", "token": "good"})
    try:
        async with contextlib.AsyncExitStack() as stack:
            silent = [await stack.enter_async_context(connect(url)) for _ in range(3)]
            await async_wait_until(lambda: server.pending == 3, 5,
                                   "3 connections waiting for their hello")
            # an observer from the same address: served; the oldest silent socket is closed
            ws = await stack.enter_async_context(connect(url))
            await ws.send(hello)
            assert json.loads(await ws.recv())["type"] == "snapshot"
            assert await _closed_by_server(silent[0])
            assert server.counters["pending_evicted_address"] == 1
            assert server.counters["clients_unauthorized"] == 0  # an eviction is no refusal
            await async_wait_until(lambda: server.pending == 2, 5, "2 silent sockets left")
            assert server.clients == 1
            # the other silent sockets are left alone until a newer one needs room
            assert silent[1].state is State.OPEN and silent[2].state is State.OPEN
            ws2 = await stack.enter_async_context(connect(url, local_addr=("127.0.0.2", 0)))
            await ws2.send(hello)
            assert json.loads(await ws2.recv())["type"] == "snapshot"
            assert server.clients == 2
            with pytest.raises(InvalidStatus) as err:  # max_clients counts the observers
                async with connect(url, local_addr=("127.0.0.3", 0)):
                    pass
            assert err.value.response.status_code == 503
    finally:
        await server.close()


async def test_the_global_pending_cap_closes_the_oldest_of_all() -> None:
    config = ViewServerConfig(rate_hz=60.0, max_pending=4, max_pending_per_address=3,
                              hello_timeout_s=scaled(30))
    server = ViewServer(FakeSource(), config, authorize=_accept_s1)
    await server.start("127.0.0.1", 0)
    url = f"ws://127.0.0.1:{server.port}/ws"
    hello = json.dumps({"type": "hello", "session": "s1", "token": "good"})
    try:
        async with contextlib.AsyncExitStack() as stack:
            first = [await stack.enter_async_context(connect(url)) for _ in range(3)]
            await stack.enter_async_context(connect(url, local_addr=("127.0.0.2", 0)))
            await async_wait_until(lambda: server.pending == 4, 5, "4 pending connections")
            ws = await stack.enter_async_context(connect(url, local_addr=("127.0.0.3", 0)))
            await ws.send(hello)
            assert json.loads(await ws.recv())["type"] == "snapshot"
            assert await _closed_by_server(first[0])
            assert server.counters["pending_evicted"] == 1
    finally:
        await server.close()


async def _server_closes(reader: asyncio.StreamReader, timeout_s: float) -> bool:
    """True when the server closes a raw connection (EOF or reset) within ``timeout_s``."""
    try:
        async with asyncio.timeout(timeout_s):
            return await reader.read(4096) == b""
    except (ConnectionResetError, BrokenPipeError):
        return True
    except TimeoutError:
        return False


@pytest.mark.parametrize("token", [False, True])
async def test_sockets_that_never_send_their_request_are_capped(token: bool) -> None:
    """Raw TCP connections that send nothing were held 10 s each without a cap (400 held
    400 descriptors); they count as pending now: beyond the cap the oldest are closed, and a
    browser from the same address is still served."""
    config = ViewServerConfig(rate_hz=60.0, max_pending_per_address=3,
                              open_timeout_s=scaled(30), hello_timeout_s=scaled(30))
    server = ViewServer(FakeSource(), config, authorize=_accept_s1 if token else None)
    await server.start("127.0.0.1", 0)
    writers = []
    try:
        conns = []
        for _ in range(10):
            reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
            conns.append(reader)
            writers.append(writer)
        closed = [await _server_closes(r, scaled(5)) for r in conns[:7]]
        assert closed == [True] * 7
        assert not any([await _server_closes(r, 0.2) for r in conns[7:]])
        assert server.pending == 3
        assert server.counters["pending_evicted_address"] == 7
        status, _, body = await asyncio.to_thread(_get, f"http://127.0.0.1:{server.port}/")
        assert status == 200 and "<html" in body.lower()
        async with connect(f"ws://127.0.0.1:{server.port}/ws") as ws:
            if token:
                await ws.send(json.dumps({"type": "hello", "session": "s1", "token": "good"}))
            assert json.loads(await ws.recv())["type"] == "snapshot"
    finally:
        for writer in writers:
            writer.close()
        await server.close()


async def test_a_socket_that_never_sends_its_request_is_cut_after_open_timeout() -> None:
    assert ViewServerConfig().open_timeout_s <= 3.0  # websockets' default was 10 s
    assert ViewServerConfig().hello_timeout_s <= 2.0  # the page sends its hello at once
    server = await _server(FakeSource(), open_timeout_s=0.3)
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        t0 = time.monotonic()
        assert await _server_closes(reader, scaled(5))
        assert time.monotonic() - t0 >= 0.25
        writer.close()
        await async_wait_until(lambda: server.pending == 0, 5, "no pending connection")
    finally:
        await server.close()


@pytest.mark.parametrize(("peer", "key"), [
    (("203.0.113.7", 5000), "203.0.113.7"),
    (("2001:db8:1:2:aaaa::1", 5000, 0, 0), "2001:db8:1:2::/64"),
    (("2001:db8:1:2:bbbb::9", 5000, 0, 0), "2001:db8:1:2::/64"),
    (("fe80::1%eth0", 5000, 0, 2), "fe80::/64"),
    (("::ffff:198.51.100.4", 5000, 0, 0), "198.51.100.4"),
    ("run/view.sock", "run/view.sock"),  # a unix socket peer: not an IP address
])
def test_the_per_address_cap_keys_ipv6_by_its_64(peer: Any, key: str) -> None:
    from shared.view.server import _address_key
    assert _address_key(peer) == key


async def test_a_refused_socket_that_never_answers_the_close_is_cut_soon() -> None:
    config = ViewServerConfig(rate_hz=60.0, hello_timeout_s=0.2, refuse_close_timeout_s=0.3)
    server = ViewServer(FakeSource(), config, authorize=_accept_s1)
    await server.start("127.0.0.1", 0)
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        writer.write(f"GET /ws HTTP/1.1\r\nHost: x\r\nConnection: Upgrade\r\nUpgrade: "
                     f"websocket\r\n{_KEY}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
        await writer.drain()
        t0 = time.monotonic()
        async with asyncio.timeout(20):
            while await reader.read(4096):  # never answers the close frame
                pass
        # the default close timeout is 10 s; 0.2 s hello + 0.3 s close here (8 s: load)
        assert time.monotonic() - t0 < 8.0
        assert not server._pending
        writer.close()
    finally:
        await server.close()


async def test_a_token_that_expires_closes_its_browser_with_4001() -> None:
    expiry: list[float] = []

    def authorize(session: str, token: str) -> float:
        return expiry[-1]

    server = ViewServer(FakeSource(), ViewServerConfig(rate_hz=60.0), authorize=authorize)
    await server.start("127.0.0.1", 0)
    url = f"ws://127.0.0.1:{server.port}/ws"
    hello = json.dumps({"type": "hello", "session": "s1", "token": "t"})
    try:
        expiry.append(time.time() - 1)  # expired already
        async with connect(url) as ws:
            await ws.send(hello)
            with pytest.raises(ConnectionClosed) as err:
                await ws.recv()
            assert err.value.rcvd is not None and err.value.rcvd.code == 4001
        expiry.append(time.time() + scaled(1.0))
        async with connect(url) as ws:
            await ws.send(hello)
            assert json.loads(await ws.recv())["type"] == "snapshot"  # valid for now
            with pytest.raises(ConnectionClosed) as err:
                async with asyncio.timeout(scaled(1.0) + scaled(5)):
                    while True:
                        await ws.recv()
            assert err.value.rcvd is not None and err.value.rcvd.code == 4001
            assert time.time() >= expiry[-1]
        assert server.counters["clients_expired"] == 1
    finally:
        await server.close()
