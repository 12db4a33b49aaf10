"""No secret in any log (issue 11 item 6) and /status, /metrics behind a token (item 3)."""

from __future__ import annotations

import asyncio
import json
import logging

import pytest
from websockets.asyncio.client import connect as websockets_connect
from websockets.exceptions import ConnectionClosed

from relay_server.auth import derive_token, make_token
from shared.client import StationLink
from shared.errors import AuthError
from shared.protocol import ArmCommand
from shared.timebase import now_us
from tests.relay_server.relay_clients import running_relay
from tests.relay_server.test_relay_isolation_and_status import http_get
from tests.support import scaled

SECRET = "SECRET-7f3a9c-recognisable-0123456789"
STATUS_TOKEN = "STATUS-b41d-recognisable"
#: the logger of the test's own browser (its DEBUG lines show the frames it sends)
_TEST_CLIENT_LOG = logging.getLogger("tests.view_browser")


async def _raw_get(port: int, path: str, auth: str | None, *headers: str) -> int:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        extra = f"Authorization: {auth}\r\n" if auth is not None else ""
        extra += "".join(f"{h}\r\n" for h in headers)
        writer.write(f"GET {path} HTTP/1.1\r\nHost: x\r\n{extra}\r\n".encode())
        await writer.drain()
        async with asyncio.timeout(scaled(5.0)):
            data = await reader.read()
    finally:
        writer.close()
        await writer.wait_closed()
    return int(data.split(b" ", 2)[1])


async def test_no_secret_or_token_in_any_log_at_debug(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    legacy = derive_token(SECRET, "sec")
    v2 = make_token(SECRET, "sec", "remote", int(now_us() / 1e6) + 600)
    wrong = "WRONG-TOKEN-5e2f-recognisable"
    expired = make_token(SECRET, "sec", "observer", 1)
    observer = make_token(SECRET, "sec", "observer", int(now_us() / 1e6) + 600)
    async with running_relay(secret=SECRET, status_token=STATUS_TOKEN,
                             view="127.0.0.1:0") as relay:
        url = f"ws://127.0.0.1:{relay.ws_port}/"
        tcp = f"tcp://127.0.0.1:{relay.tcp_port}"
        async with StationLink(url, session="sec", role="local", token=legacy) as local, \
                StationLink(tcp, session="sec", role="remote", token=v2) as remote:
            await local.wait_connected(scaled(5.0))
            await remote.wait_connected(scaled(5.0))
            await local.send(ArmCommand(seq=1, ts_us=now_us(), action="home"))
            while (await remote.recv(scaled(5.0))).TYPE != "arm_command":
                pass
            for tok, role in ((wrong, "observer"), (expired, "observer")):
                async with StationLink(url, session="sec", role=role, token=tok) as bad:
                    with pytest.raises(AuthError):
                        await bad.wait_connected(scaled(5.0))
            assert await _raw_get(relay.ws_port, "/status", f"Bearer {STATUS_TOKEN}") == 200
            # the observers' live view: a hello carries its token in a WebSocket frame
            assert relay.view_server is not None
            view_url = f"ws://127.0.0.1:{relay.view_server.port}/ws"
            for tok in (observer, wrong, legacy, expired):
                async with websockets_connect(view_url, logger=_TEST_CLIENT_LOG) as ws:
                    await ws.send(json.dumps({"type": "hello", "session": "sec",
                                              "token": tok}))
                    try:
                        reply = json.loads(await asyncio.wait_for(ws.recv(), scaled(5.0)))
                        assert tok == observer and reply["type"] == "snapshot"
                    except ConnectionClosed as err:
                        assert tok != observer and err.rcvd is not None
                        assert err.rcvd.code == 4001
    text = "\n".join(f"{r.name} {r.getMessage()} {r.exc_text or ''}" for r in caplog.records
                     if r.name != _TEST_CLIENT_LOG.name)  # the test's browser logs its frames
    assert "expired" in text and "wrong token" in text  # the refusals were logged ...
    tokens = (legacy, v2, wrong, expired, observer)
    # websockets shortens a logged frame to its head and tail: look for the tails as well
    for needle in (SECRET, STATUS_TOKEN, *tokens, *(t.rsplit(".", 1)[-1] for t in tokens),
                   *(t[-12:] for t in tokens)):
        assert needle not in text, needle  # ... without any secret
    assert "shared.view" in text  # the view was served and logged


async def test_status_and_metrics_need_the_bearer_token_when_set() -> None:
    async with running_relay(status_token=STATUS_TOKEN) as relay:
        port = relay.ws_port
        for path in ("/status", "/metrics"):
            assert await _raw_get(port, path, None) == 401
            assert await _raw_get(port, path, "Bearer nope") == 401
            assert await _raw_get(port, path, f"Basic {STATUS_TOKEN}") == 401
            assert await _raw_get(port, path, f"Bearer {STATUS_TOKEN}") == 200
        assert relay.counters["status_unauthorized"] == 6


async def test_repeated_headers_get_400_not_a_server_error(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    async with running_relay(status_token=STATUS_TOKEN) as relay:
        port = relay.ws_port
        bearer = f"Bearer {STATUS_TOKEN}"
        assert await _raw_get(port, "/status", bearer, f"Authorization: {bearer}") == 400
        assert await _raw_get(port, "/status", "Bearer nope", f"Authorization: {bearer}") == 400
        # Connection is a list header: two lines are one list (no upgrade here: 404)
        assert await _raw_get(port, "/", None, "Connection: keep-alive",
                              "Connection: close") == 404
        assert relay.counters["http_bad_request"] == 2
        assert await _raw_get(port, "/status", bearer) == 200  # still serving
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


async def test_public_status_is_announced_with_a_warning(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING)
    async with running_relay(host="0.0.0.0") as relay:  # reachable from outside
        code, _, _ = await http_get(relay.ws_port, "/status")
        assert code == 200
    assert any("/status and /metrics are public" in r.getMessage() for r in caplog.records)
    caplog.clear()
    async with running_relay(status_token=STATUS_TOKEN, host="0.0.0.0"):
        pass
    assert not any("are public" in r.getMessage() for r in caplog.records)


def test_a_hello_repr_hides_its_token() -> None:
    from shared.protocol import Hello

    assert "TOPSECRET" not in repr(Hello(role="local", session="s", token="TOPSECRET"))
