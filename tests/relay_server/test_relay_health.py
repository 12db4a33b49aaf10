"""The relay's liveness probe (``GET /healthz``, ``teletouch relay --health-check``): what a
container's HEALTHCHECK runs, over plain HTTP and TLS, with and without a status token."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import sys
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from relay_server.config import RelayConfig
from relay_server.health import health_url, probe
from tests.relay_server.relay_clients import running_relay
from tests.relay_server.test_relay_tls import lab_pki  # noqa: F401 (a fixture)
from tests.support import (
    assert_ended_by_loop_watchdog,
    free_tcp_port,
    scaled,
    teletouch_cmd,
)


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


#: ``teletouch`` with a bug put into the relay: its /status handler blocks the event loop
_RELAY_WITH_A_BLOCKING_HANDLER = """
import sys, time
import relay_server.server as server

def _a_status_handler_that_blocks(self):
    time.sleep(3600)

server.RelayServer.status = _a_status_handler_that_blocks
from lab.cli import main
sys.exit(main(sys.argv[1:]))
"""


async def test_a_relay_whose_loop_is_stuck_writes_its_stacks_and_exits() -> None:
    """The relay's own watchdog (``hang_timeout_s``): a real ``teletouch relay`` whose event
    loop a request blocks (a bug put in its /status handler) writes every thread's stack and
    exits with code 1, for systemd, a container's ``restart: on-failure`` or the workers'
    supervisor to start it again."""
    port, tcp_port = free_tcp_port(), free_tcp_port()
    config = RelayConfig(host="127.0.0.1", port=port, tcp_port=tcp_port)
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-c", _RELAY_WITH_A_BLOCKING_HANDLER, "--log-level", "WARNING",
        "relay", "--host", "127.0.0.1", "--port", str(port), "--tcp-port", str(tcp_port),
        "--allow-any-token", "--hang-timeout-s", str(scaled(5.0)),
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
    writer = None
    try:
        async with asyncio.timeout(scaled(30.0)):
            while await asyncio.to_thread(probe, config, scaled(2.0)) is not None:
                assert proc.returncode is None
                await asyncio.sleep(0.1)
        _, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        await writer.drain()
        _, stderr = await asyncio.wait_for(proc.communicate(), scaled(30.0))
        assert_ended_by_loop_watchdog(proc.returncode, stderr.decode(errors="replace"),
                                      "_a_status_handler_that_blocks",
                                      stuck="the event loop has not turned for ")
    finally:
        if writer is not None:
            writer.close()
        if proc.returncode is None:
            proc.kill()
            await proc.wait()


async def test_a_relay_that_serves_is_not_ended_by_its_watchdog() -> None:
    """The control: a real relay with a short ``hang_timeout_s``, idle apart from health
    probes for three timeouts, serves on; on SIGTERM it stops cleanly (exit 0), its watchdog
    off before it closes its connections."""
    timeout_s = scaled(2.0)
    port, tcp_port = free_tcp_port(), free_tcp_port()
    config = RelayConfig(host="127.0.0.1", port=port, tcp_port=tcp_port)
    proc = await asyncio.create_subprocess_exec(
        *teletouch_cmd(), "--log-level", "WARNING", "relay", "--host", "127.0.0.1", "--port",
        str(port), "--tcp-port", str(tcp_port), "--allow-any-token", "--hang-timeout-s",
        str(timeout_s), stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
    try:
        async with asyncio.timeout(scaled(30.0)):
            while await asyncio.to_thread(probe, config, scaled(2.0)) is not None:
                assert proc.returncode is None
                await asyncio.sleep(0.1)
        end = asyncio.get_running_loop().time() + 3 * timeout_s
        while asyncio.get_running_loop().time() < end:  # the time itself is what is tested
            assert proc.returncode is None
            assert await asyncio.to_thread(probe, config, scaled(2.0)) is None
            await asyncio.sleep(0.2)
        proc.terminate()
        _, stderr = await asyncio.wait_for(proc.communicate(), scaled(30.0))
        text = stderr.decode(errors="replace")
        assert proc.returncode == 0 and "Timeout (" not in text and \
            "Event loop watchdog" not in text, (proc.returncode, text[-3000:])
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
