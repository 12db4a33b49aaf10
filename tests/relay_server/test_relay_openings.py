"""Openings under way (accepted, not yet open: a TLS handshake, a WebSocket opening) are
bounded per address and in total from the accept, before any TLS work: a flood of sockets
that never finish their opening holds at most ``max_connections_per_ip`` of them, the next
one is dropped at once, and the relay serves again as soon as they go (real sockets, a real
TLS relay)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import shutil
import ssl
from collections.abc import AsyncIterator
from pathlib import Path

import msgpack
import pytest

from relay_server import server as relay_module
from relay_server.auth import derive_token
from relay_server.server import RelayServer
from relay_server.wire import Admission
from shared.protocol import Hello
from shared.protocol.codec import encode
from shared.protocol.framing import LengthPrefixDecoder, frame
from tests.relay_server.relay_clients import SECRET, Client, running_relay
from tests.relay_server.test_relay_tls import lab_pki  # noqa: F401  (the fixture)
from tests.relay_server.test_relay_ws_open_timeout import _closed_after
from tests.support import async_wait_until, scaled

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")

#: the ports and schemes whose opening takes time: plain WebSocket (the upgrade), and both
#: ports with TLS (plain TCP is open at the accept: nothing to bound)
KINDS = [("ws", False), ("ws", True), ("tcp", True)]


def _port(relay: RelayServer, kind: str) -> int:
    return relay.ws_port if kind == "ws" else relay.tcp_port


async def _silent(relay: RelayServer, kind: str) -> asyncio.StreamWriter:
    """A socket that connects and says nothing (its opening never finishes)."""
    _, writer = await asyncio.open_connection("127.0.0.1", _port(relay, kind))
    return writer


async def _served(relay: RelayServer, kind: str, tls: ssl.SSLContext | None,
                  session: str) -> None:
    """A station's opening and hello on ``kind`` get the relay's welcome."""
    if tls is None:
        c = Client(kind)
        try:
            await c.connect(relay)
            await c.hello("local", session)
        finally:
            await c.close()
        return
    reader, writer = await asyncio.open_connection(
        "127.0.0.1", _port(relay, kind), ssl=tls, server_hostname="127.0.0.1")
    try:
        if kind == "ws":  # the relay's answer over TLS: its HTTP side, past the opening
            writer.write(b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            async with asyncio.timeout(scaled(5.0)):
                head = await reader.readuntil(b"\r\n\r\n")
            assert head.startswith(b"HTTP/1.1 200"), head[:40]
            return
        writer.write(frame(encode(Hello(role="local", session=session,
                                        token=derive_token(SECRET, session)))))
        decoder = LengthPrefixDecoder(2**20)
        types: list[str] = []
        async with asyncio.timeout(scaled(5.0)):
            while "welcome" not in types:
                data = await reader.read(65536)
                assert data, f"the relay closed before its welcome (got {types})"
                types += [msgpack.unpackb(m)["type"] for m in decoder.feed(data)]
    finally:
        writer.close()


@contextlib.asynccontextmanager
async def _relay(pki: dict[str, Path], tls: bool, **limits: int
                 ) -> AsyncIterator[tuple[RelayServer, ssl.SSLContext | None]]:
    files = {"tls_cert": pki["relay.crt"], "tls_key": pki["relay.key"]} if tls else {}
    async with running_relay(**files, **limits) as relay:
        yield relay, (ssl.create_default_context(cafile=str(pki["ca.crt"])) if tls else None)


@pytest.mark.parametrize(("kind", "tls"), KINDS)
async def test_openings_from_one_address_are_bounded_at_accept(
        lab_pki: dict[str, Path], kind: str, tls: bool,  # noqa: F811
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    # the open timeout far away: what ends a socket below is the bound, not the timeout
    monkeypatch.setattr(relay_module, "_OPEN_TIMEOUT_S", scaled(120.0))
    caplog.set_level(logging.WARNING)
    async with _relay(lab_pki, tls, max_connections_per_ip=3) as (relay, ctx):
        held = [await _silent(relay, kind) for _ in range(3)]
        try:
            await async_wait_until(lambda: relay._admission.opening_total == 3, 5.0,
                                   "three openings under way")
            for n in (1, 2):  # the next ones are dropped at once; one warning for both
                reader, writer = await asyncio.open_connection("127.0.0.1", _port(relay, kind))
                try:
                    await _closed_after(reader, scaled(10.0))
                finally:
                    writer.close()
                assert relay.counters["refused_at_accept"] == n
            assert relay._admission.openings == {"127.0.0.1": 3}
            warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING
                        and "dropped at accept" in r.getMessage()]
            assert len(warnings) == 1 and "127.0.0.1" in warnings[0], warnings
        finally:
            for writer in held:
                writer.close()
        await async_wait_until(lambda: relay._admission.opening_total == 0, 5.0,
                               "the openings released")
        await _served(relay, kind, ctx, "after-flood")
        assert relay.counters["refused_at_accept"] == 2


async def test_openings_in_total_are_bounded(lab_pki: dict[str, Path],  # noqa: F811
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(relay_module, "_OPEN_TIMEOUT_S", scaled(120.0))
    async with _relay(lab_pki, True, max_connections=2) as (relay, ctx):
        held = [await _silent(relay, "ws"), await _silent(relay, "tcp")]
        try:
            await async_wait_until(lambda: relay._admission.opening_total == 2, 5.0,
                                   "two openings under way")
            reader, writer = await asyncio.open_connection("127.0.0.1", relay.tcp_port)
            try:
                await _closed_after(reader, scaled(10.0))
            finally:
                writer.close()
            assert relay.counters["refused_at_accept"] == 1
        finally:
            for w in held:
                w.close()
        await async_wait_until(lambda: relay._admission.opening_total == 0, 5.0,
                               "the openings released")
        await _served(relay, "tcp", ctx, "after-total")


@pytest.mark.parametrize(("kind", "tls"), KINDS)
async def test_every_way_an_opening_ends_releases_it(
        lab_pki: dict[str, Path], kind: str, tls: bool,  # noqa: F811
        monkeypatch: pytest.MonkeyPatch) -> None:
    open_timeout_s = scaled(0.5)
    monkeypatch.setattr(relay_module, "_OPEN_TIMEOUT_S", open_timeout_s)
    async with _relay(lab_pki, tls, max_connections_per_ip=2) as (relay, _):
        # silent until the open timeout cuts it
        reader, writer = await asyncio.open_connection("127.0.0.1", _port(relay, kind))
        await _closed_after(reader, open_timeout_s + scaled(5.0))
        writer.close()
        await async_wait_until(lambda: relay._admission.opening_total == 0, 5.0,
                               "the cut opening released")
    monkeypatch.setattr(relay_module, "_OPEN_TIMEOUT_S", scaled(120.0))
    async with _relay(lab_pki, tls, max_connections_per_ip=2) as (relay, ctx):
        port = _port(relay, kind)
        # a whole bad TLS record, or plain HTTP, where TLS or an upgrade is due: the relay
        # ends them at once
        for blob in (b"\x16\x03\x01\x00\x05hello\r\n\r\n", b"GET /nothing HTTP/1.1\r\n\r\n"):
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(blob)
            await _closed_after(reader, scaled(5.0))
            writer.close()
        # the client goes first, mid-opening
        _, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(b"\x16\x03\x01" if tls else b"GET / HTTP/1.1\r\nHo")
        await writer.drain()
        writer.close()
        # opened, then served
        await _served(relay, kind, ctx, "served-1")
        await async_wait_until(lambda: relay._admission.opening_total == 0, 5.0,
                               "every opening released")
        assert relay._admission.openings == {}
        assert relay.counters["refused_at_accept"] == 0
        # so the bound of two still admits two at a time, again and again
        for session in ("served-2", "served-3"):
            await _served(relay, kind, ctx, session)


@pytest.mark.parametrize(("kind", "tls"), KINDS)
async def test_the_relays_close_ends_openings_under_way(
        lab_pki: dict[str, Path], kind: str, tls: bool,  # noqa: F811
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(relay_module, "_OPEN_TIMEOUT_S", scaled(120.0))
    async with _relay(lab_pki, tls) as (relay, _):
        reader, writer = await asyncio.open_connection("127.0.0.1", _port(relay, kind))
        await async_wait_until(lambda: relay._admission.opening_total == 1, 5.0,
                               "one opening under way")
        wires = set(relay._wires)
    # close() has returned: the socket is gone (not only at the open timeout, far away),
    # and with it the opening and the handshake's task
    assert all(w.ended.is_set() for w in wires)
    assert relay._admission.opening_total == 0
    tasks = [w._tls_task for w in wires if w._tls_task is not None]
    assert len(tasks) == (1 if tls else 0)
    await asyncio.sleep(0)  # the task's last step (its socket is already gone)
    assert all(t.done() for t in tasks)
    try:
        await _closed_after(reader, scaled(5.0))
    finally:
        writer.close()


async def test_a_plain_tcp_station_is_not_held_up_by_openings(
        lab_pki: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: F811
    # plain TCP is open at the accept: the openings' bound does not apply to it
    monkeypatch.setattr(relay_module, "_OPEN_TIMEOUT_S", scaled(120.0))
    async with _relay(lab_pki, False, max_connections_per_ip=2) as (relay, ctx):
        held = [await _silent(relay, "ws") for _ in range(2)]
        try:
            await async_wait_until(lambda: relay._admission.opening_total == 2, 5.0,
                                   "two openings under way")
            await _served(relay, "tcp", ctx, "tcp-beside")
            assert relay.counters["refused_at_accept"] == 0
        finally:
            for writer in held:
                writer.close()


def test_drops_are_warned_at_most_once_a_minute_with_their_count(
        caplog: pytest.LogCaptureFixture) -> None:
    now = [100.0]
    refused: list[int] = []
    admission = Admission(per_address=1, total=2, open_timeout_s=10.0,
                          on_refused=lambda: refused.append(1), clock=lambda: now[0])
    caplog.set_level(logging.WARNING, logger="relay_server.wire")
    assert admission.admit("10.0.0.1") and admission.admit("10.0.0.2")
    # the total bound, from many addresses: one warning, however many addresses
    for i in range(50):
        assert not admission.admit(f"2001:db8::{i}")
    now[0] += 59.0
    assert not admission.admit("10.0.0.1")  # the per-address bound
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1 and warnings[0].startswith("1 connection(s)"), warnings
    now[0] += 1.0  # a minute after the first: the 51 since then, in one line
    assert not admission.admit("10.0.0.3")
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 2 and warnings[1].startswith("51 connection(s)"), warnings
    assert "10.0.0.3" in warnings[1] and "in all" in warnings[1]
    assert len(refused) == 52
    admission.release("10.0.0.1")
    admission.release("10.0.0.2")
    assert (admission.opening_total, admission.openings) == (0, {})
    assert admission.admit("10.0.0.1")
