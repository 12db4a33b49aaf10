"""The relay's liveness probe (``GET /healthz``, ``teletouch relay --health-check``): what a
container's HEALTHCHECK runs, over plain HTTP and TLS, with and without a status token."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from relay_server.config import RelayConfig
from relay_server.health import health_url, probe
from tests.relay_server.relay_clients import running_relay
from tests.relay_server.test_relay_tls import lab_pki  # noqa: F401 (a fixture)
from tests.support import free_tcp_port, scaled, teletouch_cmd


async def test_healthz_needs_no_token_and_says_only_ok(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="relay_server")
    async with running_relay(status_token="s3cret") as relay:
        base = f"http://127.0.0.1:{relay.ws_port}"

        def get(path: str) -> tuple[int, bytes]:
            try:
                with urllib.request.urlopen(base + path, timeout=scaled(5.0)) as answer:
                    return answer.status, answer.read()
            except urllib.error.HTTPError as err:
                return err.code, err.read()

        assert await asyncio.to_thread(get, "/healthz") == (200, b"ok\n")
        config = dataclasses.replace(relay.config, port=relay.ws_port)
        assert await asyncio.to_thread(probe, config, scaled(5.0)) is None
        # a probe every 30 s leaves the log alone; other answers are still logged
        assert not [r for r in caplog.records if r.name.startswith("relay_server.websockets")]
        assert (await asyncio.to_thread(get, "/status"))[0] == 401  # the figures stay closed
        assert await asyncio.to_thread(get, "/nothing") == (
            404, b"Tele-Touch relay: WebSocket endpoint; see /status, /metrics and /healthz\n")
        assert any("HTTP response sent (401" in r.getMessage() for r in caplog.records)


async def test_the_probe_speaks_tls_to_a_tls_relay(lab_pki: dict[str, Path]) -> None:  # noqa: F811
    async with running_relay(tls_cert=lab_pki["relay.crt"],
                             tls_key=lab_pki["relay.key"]) as relay:
        config = dataclasses.replace(relay.config, port=relay.ws_port)
        assert health_url(config) == f"https://127.0.0.1:{relay.ws_port}/healthz"
        assert await asyncio.to_thread(probe, config, scaled(5.0)) is None
        # plain HTTP to the TLS port is no answer
        plain = dataclasses.replace(config, tls_cert=None, tls_key=None)
        error = await asyncio.to_thread(probe, plain, scaled(5.0))
        assert error is not None and error.startswith(f"http://127.0.0.1:{relay.ws_port}")


async def test_something_else_on_the_port_is_not_a_relay() -> None:
    async def answer(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.readuntil(b"\r\n\r\n")
        writer.write(b"HTTP/1.1 200 OK\r\nContent-Length: 5\r\nConnection: close\r\n\r\nhello")
        await writer.drain()
        writer.close()

    server = await asyncio.start_server(answer, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    async with server:
        error = await asyncio.to_thread(probe, RelayConfig(port=port), scaled(5.0))
    assert error == f"http://127.0.0.1:{port}/healthz: HTTP 200 b'hello', not a relay's 200 ok"


@pytest.mark.parametrize(("host", "url"), [("0.0.0.0", "http://127.0.0.1:9/healthz"),
                                           ("::", "http://[::1]:9/healthz"),
                                           ("10.1.2.3", "http://10.1.2.3:9/healthz")])
def test_the_probe_asks_where_the_relay_listens(host: str, url: str) -> None:
    assert health_url(RelayConfig(host=host, port=9)) == url


def test_health_check_exit_codes() -> None:
    """``teletouch relay --health-check`` (the image's HEALTHCHECK): 1 and the reason when
    nothing answers, 0 when the relay does (its port from the same configuration)."""
    import subprocess

    port = free_tcp_port()
    probe_cmd = [*teletouch_cmd(), "relay", "--port", str(port), "--health-check"]
    down = subprocess.run(probe_cmd, capture_output=True, text=True, timeout=scaled(60.0))
    assert down.returncode == 1, down
    assert f"relay not healthy: http://127.0.0.1:{port}/healthz: " in down.stderr, down.stderr
    relay = subprocess.Popen([*teletouch_cmd(), "relay", "--port", str(port), "--tcp-port",
                              str(free_tcp_port()), "--allow-any-token"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        assert relay.stderr is not None
        seen = []
        for line in relay.stderr:  # logged once the ports are bound: an event, not a sleep
            seen.append(line)
            if "relay listening" in line:
                break
        assert "relay listening" in seen[-1], "".join(seen)  # else: why it did not start
        up = subprocess.run(probe_cmd, capture_output=True, text=True, timeout=scaled(60.0))
        assert up.returncode == 0, up
        assert up.stdout.strip() == f"relay healthy: http://127.0.0.1:{port}/healthz"
    finally:
        relay.terminate()
        relay.wait(scaled(30.0))
