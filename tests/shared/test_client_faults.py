"""StationLink under faults: a relay certificate that fails for a while, a relay that pings
slowly, a relay that welcomes and hangs up at once, a hello the relay could never accept, a
half-open connection, a secret in the relay URL, a connect that times out, an unforeseen
error in the link's loop, bad numbers given to the constructor, and ``replaced`` over raw TCP.

Real sockets on 127.0.0.1: the fake relay of ``test_client``, the real relay in-process, small
asyncio servers and the link emulator.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import shutil
import subprocess
from collections.abc import AsyncIterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from shared.client import StationLink
from shared.errors import (
    ConfigError,
    InvalidHelloError,
    ReplacedError,
    SessionError,
    TlsCertificateError,
    TokenExpiredError,
)
from shared.link_settings import client_tls_context
from shared.protocol import Hello, MessageReceived, ProtocolConnection, Welcome
from shared.timebase import monotonic_s, now_us
from tests.shared.test_client import TOKEN, FakeRelay, _link, _real_relay
from tests.support import MachineStalls, async_wait_until, free_tcp_port, scaled


@contextlib.asynccontextmanager
async def _tcp_server(handler: Any) -> AsyncIterator[int]:
    """A plain asyncio TCP server on 127.0.0.1; yields its port."""
    tasks: set[asyncio.Task[Any]] = set()

    async def tracked(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        tasks.add(task)
        try:
            await handler(reader, writer)
        except (OSError, asyncio.IncompleteReadError):
            pass
        finally:
            writer.close()
            tasks.discard(task)

    server = await asyncio.start_server(tracked, "127.0.0.1", 0)
    try:
        yield server.sockets[0].getsockname()[1]
    finally:
        server.close()
        for task in list(tasks):
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(server.wait_closed(), scaled(1.0))


# --------------------------------------------------------------------------- TLS (issue 3)


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """A lab CA, a relay certificate it signed for 127.0.0.1, and a self-signed one."""
    if shutil.which("openssl") is None:
        pytest.skip("needs openssl")
    d = tmp_path_factory.mktemp("pki")
    ec = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes")
    _openssl("req", "-x509", *ec, "-keyout", "ca.key", "-out", "ca.crt", "-days", "2",
             "-subj", "/CN=test CA", cwd=d)
    _openssl("req", *ec, "-keyout", "good.key", "-out", "good.csr", "-subj", "/CN=relay",
             cwd=d)
    (d / "san.ext").write_text("subjectAltName = IP:127.0.0.1\nextendedKeyUsage = serverAuth\n")
    _openssl("x509", "-req", "-in", "good.csr", "-CA", "ca.crt", "-CAkey", "ca.key",
             "-CAcreateserial", "-out", "good.crt", "-days", "2", "-extfile", "san.ext", cwd=d)
    _openssl("req", "-x509", *ec, "-keyout", "bad.key", "-out", "bad.crt", "-days", "2",
             "-subj", "/CN=not the relay", "-addext", "subjectAltName = IP:127.0.0.1", cwd=d)
    return {name: str(d / name) for name in ("ca.crt", "good.crt", "good.key", "bad.crt",
                                             "bad.key")}


@contextlib.asynccontextmanager
async def _tls_relay(ws_port: int, tcp_port: int, cert: str, key: str) -> AsyncIterator[Any]:
    from relay_server.config import RelayConfig
    from relay_server.server import RelayServer

    relay = RelayServer(RelayConfig(host="127.0.0.1", port=ws_port, tcp_port=tcp_port,
                                    tokens={"lab1": TOKEN}, tls_cert=Path(cert),
                                    tls_key=Path(key),
                                    hello_timeout_s=scaled(2.0)))
    await relay.start()
    try:
        yield relay
    finally:
        await relay.close()


@pytest.mark.parametrize("scheme", ["wss", "tls"])
async def test_a_certificate_failure_is_retried_until_the_relay_presents_a_good_one(
        pki: dict[str, str], scheme: str, caplog: pytest.LogCaptureFixture) -> None:
    """A relay restarted with the wrong certificate for a while (a certificate swapped
    during a restart, a station clock wrong at boot): the link keeps the error visible,
    logs it once (not at every attempt), keeps retrying with backoff, and connects as soon
    as the relay presents a certificate the station trusts."""
    caplog.set_level(logging.INFO, logger="shared.client")
    ws_port, tcp_port = free_tcp_port(), free_tcp_port()
    url = f"wss://127.0.0.1:{ws_port}/" if scheme == "wss" else f"tls://127.0.0.1:{tcp_port}"
    link = _link(url, ssl_context=client_tls_context(pki["ca.crt"]), reconnect_min_s=0.01,
                 reconnect_max_s=0.02)
    async with link:
        async with _tls_relay(ws_port, tcp_port, pki["bad.crt"], pki["bad.key"]) as relay:
            with pytest.raises(TlsCertificateError, match="not trusted"):
                await link.wait_connected(scaled(5.0))
            await async_wait_until(lambda: len(link.backoff_history_s) >= 4, 5.0,
                                   "four attempts on the bad certificate")
            assert link.final_error is None and link._task is not None \
                and not link._task.done()
            assert isinstance(link.last_error, TlsCertificateError)
            assert not link.is_connected and relay.counters["joined"] == 0
            # the delays grow (capped): a misconfigured station does not hammer the relay
            history = list(link.backoff_history_s)
            assert history[3] > history[0]
        async with _tls_relay(ws_port, tcp_port, pki["good.crt"], pki["good.key"]):
            welcome = await link.wait_connected(scaled(10.0))
            assert welcome.session == "lab1" and link.last_error is None
    tls_logs = [r for r in caplog.records if "TlsCertificateError" in r.getMessage()]
    assert len(tls_logs) == 1 and tls_logs[0].levelno == logging.ERROR, \
        [r.getMessage() for r in tls_logs]


async def test_a_failure_that_persists_is_logged_again_periodically(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """Logged at the first failure, then at most once per REPEAT_LOG_S with the number of
    failures since: an operator who looks later still sees why the link is down."""
    monkeypatch.setattr("shared.client.REPEAT_LOG_S", scaled(0.3))
    caplog.set_level(logging.WARNING, logger="shared.client")
    async with _link(f"tcp://127.0.0.1:{free_tcp_port()}", reconnect_min_s=0.005,
                     reconnect_max_s=0.01) as link:
        await async_wait_until(lambda: len(link.backoff_history_s) >= 40, 5.0, "40 attempts")
        await async_wait_until(
            lambda: sum("unavailable" in r.getMessage() for r in caplog.records) >= 2, 2.0,
            "the failure logged again")
        attempts = len(link.backoff_history_s)
    logged = [r.getMessage() for r in caplog.records if "unavailable" in r.getMessage()]
    assert len(logged) < attempts / 4, (len(logged), attempts)
    assert "again:" in logged[1] and "such failures" in logged[1]


# --------------------------------------------------------------------------- liveness (issue 4)


async def test_an_idle_link_does_not_flap_when_the_relay_pings_slowly(
        caplog: pytest.LogCaptureFixture) -> None:
    """The relay pings every 0.4 s and the station's silence limit is 0.15 s: the link
    presumes it dead only after 2.5 of the relay's announced intervals."""
    caplog.set_level(logging.INFO, logger="shared.client")
    ping_s = scaled(0.4)
    welcome = await _idle_link_holds("remote", ping_s=ping_s, stats_s=60.0, period_s=ping_s)
    assert welcome.ping_interval_s == pytest.approx(ping_s)
    said = [r for r in caplog.records if "presumed dead after" in r.getMessage()]
    assert len(said) == 1


async def _idle_link_holds(role: str, *, ping_s: float, stats_s: float,
                           period_s: float) -> Welcome:
    """An idle link of ``role`` with a 0.15 s silence limit to a relay pinging every
    ``ping_s`` and pushing stats every ``stats_s``: its limit is 2.5 periods of the relay's
    traffic it gets (``period_s``), and it holds for 4 of them."""
    async with (_real_relay(stats_interval_s=stats_s, ping_interval_s=ping_s) as relay,
                _link(f"ws://127.0.0.1:{relay.ws_port}/", role=role,
                      liveness_timeout_s=0.15) as link):
        welcome = await link.wait_connected(scaled(3.0))
        assert link.liveness_timeout_s == pytest.approx(2.5 * period_s)
        await asyncio.sleep(4 * period_s)  # idle: nothing but the relay's own traffic
        assert link.counters.connects == 1 and link.counters.connection_losses == 0
    return welcome


async def test_an_idle_observer_does_not_flap_when_the_relay_pushes_stats_slowly() -> None:
    """An observer is not pinged: in a quiet session the stats push (every 0.4 s here) is all
    it hears. Its silence limit followed the ping interval (0.05 s), so it presumed a healthy
    link dead between two pushes and reconnected over and over (found by review); the
    welcome now announces ``stats_interval_s`` and an observer waits 2.5 of those."""
    stats_s = scaled(0.4)
    welcome = await _idle_link_holds("observer", ping_s=0.05, stats_s=stats_s,
                                     period_s=stats_s)
    assert welcome.stats_interval_s == pytest.approx(stats_s)


async def test_a_silence_limit_longer_than_the_relays_interval_is_kept(relay: FakeRelay) -> None:
    async with _link(relay.url("tcp"), liveness_timeout_s=0.15, reconnect_min_s=0.02) as link:
        await link.wait_connected(scaled(2.0))
        assert link.liveness_timeout_s == pytest.approx(0.15)  # 2.5 x 0.05 is shorter
        # the fake relay never sends anything: the link notices and reconnects
        await async_wait_until(lambda: link.counters.connects >= 2, 3.0, "a reconnect")


@pytest.fixture
async def relay() -> AsyncIterator[FakeRelay]:
    async with FakeRelay() as r:
        yield r


# --------------------------------------------------------------------------- backoff (issue 5)


def _welcome_then_close(hold_s: float, hellos: list[float]) -> Any:
    """A TCP relay that welcomes every hello and closes ``hold_s`` later."""

    async def handler(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        conn = ProtocolConnection("tcp")
        while True:
            data = await reader.read(65536)
            if not data:
                return
            conn.receive_data(data)
            hello = next((e.message for e in conn.events_received()
                          if isinstance(e, MessageReceived)), None)
            if isinstance(hello, Hello):
                break
        hellos.append(monotonic_s())
        conn.send(Welcome(session=hello.session, role=hello.role, server_time_us=now_us(),
                          max_message_bytes=1 << 20, ping_interval_s=0.0))
        for chunk in conn.data_to_send():
            writer.write(chunk)
        await writer.drain()
        await asyncio.sleep(hold_s)

    return handler


async def test_a_relay_that_welcomes_and_closes_at_once_gets_growing_delays() -> None:
    """Welcome, then close (the relay's rate limit closing a station at once): the welcome
    does not start the backoff afresh, the delays keep doubling to reconnect_max_s."""
    hellos: list[float] = []
    async with (_tcp_server(_welcome_then_close(0.0, hellos)) as port,
                _link(f"tcp://127.0.0.1:{port}", reconnect_min_s=0.02, reconnect_max_s=0.16,
                      reconnect_jitter=0.0) as link):
        await async_wait_until(lambda: len(link.backoff_history_s) >= 6, 10.0, "6 retries")
        history = list(link.backoff_history_s)[:6]
    assert link.counters.connects >= 5
    assert history == pytest.approx([0.02, 0.04, 0.08, 0.16, 0.16, 0.16])


async def test_a_connection_that_stayed_up_starts_the_backoff_afresh(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("shared.client.STABLE_CONNECTION_S", 0.1)
    hellos: list[float] = []
    async with (_tcp_server(_welcome_then_close(0.3, hellos)) as port,
                _link(f"tcp://127.0.0.1:{port}", reconnect_min_s=0.02, reconnect_max_s=0.05,
                      reconnect_jitter=0.0) as link):
        await async_wait_until(lambda: len(link.backoff_history_s) >= 3, 10.0, "3 retries")
        history = list(link.backoff_history_s)[:3]
    assert history == pytest.approx([0.02, 0.02, 0.02])


# --------------------------------------------------------------------------- hello (issue 6)


@pytest.mark.parametrize("field", ["session", "token", "name"])
async def test_a_hello_the_relay_can_never_accept_is_final(relay: FakeRelay, field: str,
                                                         caplog: pytest.LogCaptureFixture
                                                         ) -> None:
    caplog.set_level(logging.ERROR, logger="shared.client")
    bad = {"session": "lab 1", "token": "x" * 600, "name": "n" * 100}[field]
    hello: dict[str, Any] = {"session": "lab1", "token": TOKEN, "name": "", field: bad}
    link = StationLink(relay.url("ws"), role="local", reconnect_min_s=0.01, **hello)
    async with link:
        with pytest.raises(InvalidHelloError, match=f"hello.{field}"):
            await link.wait_connected(scaled(2.0))
        assert link._task is not None and link._task.done()
        with pytest.raises(InvalidHelloError):
            await link.recv(timeout_s=0.1)
        # refused before connecting: the relay never even saw a connection
        assert len(link.backoff_history_s) == 0 and relay.accepts_s == []
    assert len([r for r in caplog.records if "hello" in r.getMessage()]) == 1


# --------------------------------------------------------------------------- half-open (issue 7)


@pytest.mark.parametrize("scheme", ["ws", "tcp"])
async def test_a_half_open_connection_is_marked_down_at_the_liveness_timeout(
        scheme: str) -> None:
    """Blackholed both ways: the link is down as soon as the silence limit passes and its
    next attempt starts then, not after a graceful close that can never complete (the
    WebSocket close handshake waited its 2 s timeout)."""
    from lab.linkemu import LinkEmulator, LinkProfile

    liveness_s = scaled(0.4)
    async with _real_relay() as relay:
        target = relay.ws_port if scheme == "ws" else relay.tcp_port
        emu = LinkEmulator(listen=("127.0.0.1", 0), target=("127.0.0.1", target),
                           profile=LinkProfile(name="test", delay_ms=0.0))
        await emu.start()
        try:
            url = (f"ws://127.0.0.1:{emu.port}/" if scheme == "ws"
                   else f"tcp://127.0.0.1:{emu.port}")
            async with _link(url, liveness_timeout_s=liveness_s) as link:
                await link.wait_connected(scaled(3.0))
                await async_wait_until(lambda: link.silent_for_s() < 0.05, 2.0, "traffic")
                with MachineStalls() as stalls:
                    emu.start_outage(scaled(5.0))
                    await async_wait_until(lambda: len(link.backoff_history_s) >= 1,
                                           liveness_s + 3.0, "a retry")
                    retry_s = monotonic_s()
                assert not link.is_connected and link.link_down_since is not None
                last_rx = link.last_received_s
                assert last_rx is not None
                slack = scaled(0.5) + stalls.total_s
                assert link.link_down_since - last_rx <= liveness_s + slack, stalls.stalls_s
                assert retry_s - last_rx <= liveness_s + slack + 0.05, stalls.stalls_s
        finally:
            await emu.close()


# --------------------------------------------------------------------------- URL secret (issue 9)


def test_redact_url_hides_user_information() -> None:
    from shared.client import redact_url

    assert redact_url("ws://user:pw@relay:8765/x?y=1") == "ws://***@relay:8765/x?y=1"
    assert redact_url("tcp://relay:8766") == "tcp://relay:8766"


async def test_user_information_in_the_url_is_never_shown(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """The link settings refuse such a URL; the link itself, given one anyway, never shows
    the password in a log line or an error."""
    port = free_tcp_port()
    monkeypatch.setattr("shared.client.parse_link_url", lambda url: ("ws", "127.0.0.1", port))
    caplog.set_level(logging.DEBUG, logger="shared.client")
    async with _link(f"ws://relayuser:hunter2@127.0.0.1:{port}/", reconnect_min_s=0.01,
                     reconnect_max_s=0.02) as link:
        await async_wait_until(lambda: len(link.backoff_history_s) >= 2, 3.0, "2 attempts")
        with pytest.raises(TimeoutError) as info:
            await link.wait_connected(0.01)
    shown = [r.getMessage() for r in caplog.records] + [str(info.value)]
    assert any("***@127.0.0.1" in text for text in shown)
    assert not any("hunter2" in text or "relayuser" in text for text in shown), shown


# --------------------------------------------------------------------------- timeout text (12)


async def test_a_connect_timeout_says_what_timed_out(caplog: pytest.LogCaptureFixture) -> None:
    async def silent(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await asyncio.sleep(60)

    caplog.set_level(logging.WARNING, logger="shared.client")
    async with (_tcp_server(silent) as port,
                _link(f"ws://127.0.0.1:{port}/", connect_timeout_s=0.2) as link):
        await async_wait_until(lambda: len(link.backoff_history_s) >= 1, 3.0, "an attempt")
    logged = [r.getMessage() for r in caplog.records if "unavailable" in r.getMessage()]
    assert logged and "TimeoutError: no connection to ws://127.0.0.1" in logged[0], logged
    assert "within connect_timeout_s = 0.2 s" in logged[0] and "WebSocket handshake" in logged[0]


# --------------------------------------------------------------------------- suspected ones


async def test_an_unforeseen_error_in_the_link_loop_leaves_it_down_and_says_so(
        relay: FakeRelay, monkeypatch: pytest.MonkeyPatch) -> None:
    """An exception type the loop does not expect, raised while connected: the link is not
    left reporting connected, and recv / wait_connected raise instead of waiting forever."""
    async with _link(relay.url("tcp")) as link:
        await link.wait_connected(scaled(2.0))

        def boom(*args: object) -> None:
            raise RuntimeError("boom")

        monkeypatch.setattr("shared.client.refusal_for_close_code", boom)
        await relay.drop_all()
        assert link._task is not None
        await asyncio.wait_for(asyncio.shield(link._task), scaled(2.0))
        assert not link.is_connected and link.link_down_since is not None
        with pytest.raises(SessionError, match="boom"):
            await link.recv(timeout_s=scaled(1.0))


@pytest.mark.parametrize("setting", ["connect_timeout_s", "liveness_timeout_s",
                                     "reconnect_max_s"])
@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_non_finite_timeouts_are_config_errors(setting: str, value: float) -> None:
    settings: dict[str, Any] = {setting: value}
    with pytest.raises(ConfigError):
        StationLink("ws://127.0.0.1:9/", session="lab1", role="local", token="t", **settings)


@pytest.mark.parametrize("scheme", ["ws", "tcp"])
async def test_replaced_is_final_over_websocket_and_raw_tcp(scheme: str) -> None:
    """Another connection proved this connection's resume secret and replaced it: final on
    both transports (docs/safety.md), not retried over TCP for want of a close code."""
    async with _real_relay() as relay:
        url = (f"ws://127.0.0.1:{relay.ws_port}/" if scheme == "ws"
               else f"tcp://127.0.0.1:{relay.tcp_port}")
        async with _link(url, reconnect_min_s=0.01, reconnect_max_s=0.02) as first:
            welcome = await first.wait_connected(scaled(2.0))
            async with _link(f"ws://127.0.0.1:{relay.ws_port}/") as second:
                # a second station holding the first one's secret (a copied identity)
                second._session.hello = dataclasses.replace(second._session.hello,
                                                            resume=welcome.resume)
                await second.wait_connected(scaled(2.0))
                await async_wait_until(lambda: first.final_error is not None, 3.0,
                                       "the first link's final error")
                assert isinstance(first.final_error, ReplacedError)
                assert not first.is_connected and first.counters.role_taken_refusals == 0
                with pytest.raises(ReplacedError):
                    await first.wait_connected(scaled(1.0))
                assert second.is_connected


async def test_the_link_is_marked_down_before_its_connection_is_closed(
        relay: FakeRelay, monkeypatch: pytest.MonkeyPatch) -> None:
    """A graceful close may take its whole timeout: the link says it is down first."""
    from shared.transport import WsTransport

    seen: list[tuple[bool, float | None]] = []
    close = WsTransport.close

    async def observed_close(self: WsTransport, code: int = 1000, reason: str = "") -> None:
        seen.append((link.is_connected, link.link_down_since))
        await close(self, code, reason)

    monkeypatch.setattr(WsTransport, "close", observed_close)
    async with _link(relay.url("ws")) as link:
        await link.wait_connected(scaled(2.0))
        await relay.drop_all()
        await async_wait_until(lambda: bool(seen), 2.0, "the close")
    assert seen[0][0] is False and seen[0][1] is not None


# --------------------------------------------------------------------------- review of the above


async def test_a_relay_announcing_a_huge_ping_interval_does_not_stretch_liveness() -> None:
    """A welcome announcing pings every hour made a blackholed link go unnoticed for 2.5 h
    (found by review): the limit is bounded as the setting is (60 s)."""
    from shared.link_settings import MAX_LINK_TIMEOUT_S

    async def handler(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        conn = ProtocolConnection("tcp")
        hello = None
        while hello is None:
            data = await reader.read(65536)
            if not data:
                writer.close()
                return
            conn.receive_data(data)
            hello = next((e.message for e in conn.events_received()
                          if isinstance(e, MessageReceived)), None)
        assert isinstance(hello, Hello)
        conn.send(Welcome(session=hello.session, role=hello.role, server_time_us=now_us(),
                          max_message_bytes=1 << 20, ping_interval_s=3600.0))
        for chunk in conn.data_to_send():
            writer.write(chunk)
        await writer.drain()
        await reader.read()  # held open until the station leaves
        writer.close()

    server = await asyncio.start_server(handler, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        async with _link(f"tcp://127.0.0.1:{port}", liveness_timeout_s=3.0) as link:
            await link.wait_connected(scaled(3.0))
            assert link.liveness_timeout_s == pytest.approx(MAX_LINK_TIMEOUT_S)
    finally:
        server.close()
        await server.wait_closed()


@pytest.mark.parametrize("location", [b"ws://127.0.0.1:99999/", b"ws://127.0.0.1:abc/",
                                      b"ws://a..b/", b"ws://" + b"a" * 70 + b".example/"])
async def test_a_malformed_redirect_is_retried_not_final(location: bytes) -> None:
    """A proxy answering with a redirect whose Location does not parse (websockets raises
    ValueError or UnicodeError) ended the link for good, and the local station with it
    (found by review); it is the relay side's answer, retried like a refused connection."""

    async def handler(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.read(4096)
        writer.write(b"HTTP/1.1 302 Found\r\nLocation: " + location +
                     b"\r\nContent-Length: 0\r\n\r\n")
        await writer.drain()
        writer.close()

    server = await asyncio.start_server(handler, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        async with _link(f"ws://127.0.0.1:{port}/", reconnect_min_s=0.02,
                         reconnect_max_s=0.05) as link:
            await async_wait_until(lambda: len(link.backoff_history_s) >= 3, 5.0,
                                   "three attempts")
            assert link.final_error is None
            assert link._task is not None and not link._task.done()
            assert "cannot open the connection" in str(link.last_error)
    finally:
        server.close()
        await server.wait_closed()


# ---------------------------------------------------------------- a token the relay calls expired


@contextlib.asynccontextmanager
async def _relay_clock_ahead(monkeypatch: pytest.MonkeyPatch, ahead_s: list[float]
                             ) -> AsyncIterator[Any]:
    """A relay with a secret whose wall clock runs ``ahead_s[0]`` ahead (changeable)."""
    import time

    import relay_server.auth
    from tests.relay_server.relay_clients import running_relay

    real = time.time
    monkeypatch.setattr(relay_server.auth, "time",
                        SimpleNamespace(time=lambda: real() + ahead_s[0]))
    async with running_relay() as relay:
        yield relay


def _v2_token(expiry_in_s: float) -> str:
    import time

    from relay_server.auth import make_token
    from tests.relay_server.relay_clients import SECRET

    return make_token(SECRET, "lab1", "local", int(time.time() + expiry_in_s))


@pytest.mark.parametrize("scheme", ["ws", "tcp"])
async def test_a_token_the_relays_clock_calls_expired_is_retried_while_ours_says_valid(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture,
        scheme: str) -> None:
    """The relay's clock an hour ahead (wrong at its boot): it refuses a token valid for
    10 more minutes as expired. Before, ``auth`` was final and the station gave up for good;
    now it retries with backoff, logs the disagreement once, and connects once the relay's
    clock is set right."""
    caplog.set_level(logging.INFO, logger="shared.client")
    ahead_s = [3600.0]
    async with _relay_clock_ahead(monkeypatch, ahead_s) as relay:
        port = relay.ws_port if scheme == "ws" else relay.tcp_port
        url = f"ws://127.0.0.1:{port}/" if scheme == "ws" else f"tcp://127.0.0.1:{port}"
        link = _link(url, token=_v2_token(600), reconnect_min_s=0.01, reconnect_max_s=0.02)
        async with link:
            await async_wait_until(lambda: len(link.backoff_history_s) >= 3, 10.0,
                                   "three attempts refused as expired")
            assert link.final_error is None and isinstance(link.last_error, TokenExpiredError)
            ahead_s[0] = 0.0  # time sync sets the relay's clock right
            welcome = await link.wait_connected(scaled(10.0))
            assert welcome.session == "lab1"
    said = [r for r in caplog.records if "one of the two clocks is wrong" in r.getMessage()]
    assert len(said) == 1 and said[0].levelno == logging.ERROR


async def test_a_token_both_clocks_call_expired_is_final(
        monkeypatch: pytest.MonkeyPatch) -> None:
    async with _relay_clock_ahead(monkeypatch, [0.0]) as relay:
        link = _link(f"ws://127.0.0.1:{relay.ws_port}/", token=_v2_token(-5),
                     reconnect_min_s=0.01, reconnect_max_s=0.02)
        async with link:
            with pytest.raises(TokenExpiredError, match="expired"):
                await link.wait_connected(scaled(5.0))
            assert isinstance(link.final_error, TokenExpiredError)
