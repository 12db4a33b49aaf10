"""Link emulator: the pure delay model, then real sockets through the proxy."""

from __future__ import annotations

import asyncio
import contextlib
import json
import random
import socket
import struct
from collections.abc import AsyncIterator

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lab.linkemu import (
    PROFILES,
    DirectionStats,
    LinkEmulator,
    LinkProfile,
    _Impairment,
    get_profile,
)
from shared.errors import ConfigError
from tests.support import MachineStalls, free_tcp_port, scaled

RECORD = struct.Struct(">Id")  # sequence number, send time (loop clock, s)


class Sink:
    """A TCP target that timestamps every fixed-size record it receives."""

    def __init__(self) -> None:
        self.arrivals: list[tuple[int, float, float]] = []  # (seq, sent_s, arrived_s)
        self.raw = bytearray()
        self.chunk_times: list[float] = []
        self._server: asyncio.Server | None = None
        self._writers: list[asyncio.StreamWriter] = []

    async def __aenter__(self) -> Sink:
        self._server = await asyncio.start_server(self._handle, "127.0.0.1", 0)
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self._server is not None
        self._server.close()
        for w in self._writers:
            w.close()
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(self._server.wait_closed(), scaled(1.0))

    @property
    def address(self) -> tuple[str, int]:
        assert self._server is not None
        return "127.0.0.1", self._server.sockets[0].getsockname()[1]

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._writers.append(writer)
        with contextlib.suppress(ConnectionError):
            await self._read(reader)
        writer.close()

    async def _read(self, reader: asyncio.StreamReader) -> None:
        loop = asyncio.get_running_loop()
        pending = b""
        while data := await reader.read(65536):
            now = loop.time()
            self.raw += data
            self.chunk_times.append(now)
            pending += data
            while len(pending) >= RECORD.size:
                seq, sent = RECORD.unpack_from(pending)
                self.arrivals.append((seq, sent, now))
                pending = pending[RECORD.size:]


@pytest.fixture
async def sink() -> AsyncIterator[Sink]:
    async with Sink() as s:
        yield s


async def _send_records(port: int, n: int, interval_s: float) -> None:
    loop = asyncio.get_running_loop()
    _reader, writer = await asyncio.open_connection("127.0.0.1", port)
    start = loop.time()
    for i in range(n):
        # pace against the start time so timer error does not accumulate
        await asyncio.sleep(max(0.0, start + i * interval_s - loop.time()))
        writer.write(RECORD.pack(i, loop.time()))
        await writer.drain()
    writer.close()
    await writer.wait_closed()


async def _wait_for(predicate: object, timeout_s: float) -> None:
    async with asyncio.timeout(scaled(timeout_s)):
        while not predicate():  # type: ignore[operator]
            await asyncio.sleep(0.005)


# --------------------------------------------------------------------------- pure model


def test_profiles_match_the_issue() -> None:
    assert set(PROFILES) >= {"lan", "city-1000km", "intercontinental", "bad-wifi"}
    assert PROFILES["lan"].round_trip_ms < 1.0
    assert 18.0 <= PROFILES["city-1000km"].round_trip_ms <= 22.0
    assert 0 < PROFILES["city-1000km"].loss < 1e-3
    assert 170.0 <= PROFILES["intercontinental"].round_trip_ms <= 190.0
    assert PROFILES["bad-wifi"].loss_burst_len > 1 and PROFILES["bad-wifi"].jitter_ms >= 3
    with pytest.raises(ConfigError):
        get_profile("moon")
    for bad in ({"delay_ms": -1}, {"loss": 1.0}, {"loss_burst_len": 0.5},
                {"bandwidth_mbps": 0}, {"jitter_ms": float("nan")}, {"outages": ((1, 0),)}):
        with pytest.raises(ConfigError):
            LinkProfile(**bad)


@settings(max_examples=60, deadline=None)
@given(delay=st.floats(0, 200), jitter=st.floats(0, 50), loss=st.floats(0, 0.5),
       burst=st.floats(1, 10), bw=st.one_of(st.none(), st.floats(0.01, 1e4)),
       gaps=st.lists(st.floats(0, 0.05), min_size=1, max_size=200),
       sizes=st.lists(st.integers(1, 200_000), min_size=1, max_size=200),
       seed=st.integers(0, 2**32 - 1))
def test_delivery_times_are_monotone_and_never_early(delay: float, jitter: float, loss: float,
                                                     burst: float, bw: float | None,
                                                     gaps: list[float], sizes: list[int],
                                                     seed: int) -> None:
    profile = LinkProfile(delay_ms=delay, jitter_ms=jitter, loss=loss, loss_burst_len=burst,
                          bandwidth_mbps=bw)
    model = _Impairment(profile, random.Random(seed), 1448)
    stats = DirectionStats()
    t, last = 0.0, -1.0
    for gap, size in zip(gaps, sizes * (len(gaps) // len(sizes) + 1), strict=False):
        t += gap
        out = model.schedule(t, size, stats)
        assert np.isfinite(out)
        assert out >= last  # in order
        assert out >= t  # causality
        if bw is not None:  # serialization alone takes size*8/bw
            assert out >= t + size * 8 / (bw * 1e6) - 1e-12
        last = out


def test_loss_model_matches_rate_and_burst_length() -> None:
    profile = LinkProfile(loss=0.05, loss_burst_len=4.0, delay_ms=1.0)
    model = _Impairment(profile, random.Random(3), 1448)
    stats = DirectionStats()
    states = []
    for i in range(200_000):
        before = stats.lost_segments
        model.schedule(i * 1e-3, 100, stats)  # one segment per chunk
        states.append(stats.lost_segments > before)
    arr = np.array(states)
    assert arr.mean() == pytest.approx(0.05, abs=0.005)
    starts = np.flatnonzero(arr[1:] & ~arr[:-1])
    assert arr.sum() / max(1, len(starts)) == pytest.approx(4.0, rel=0.15)
    assert stats.delayed_by_loss == arr.sum()


def test_loss_penalty_defaults_to_rtt_plus_jitter() -> None:
    assert LinkProfile(delay_ms=10, jitter_ms=1).effective_loss_penalty_ms == 24.0
    assert LinkProfile(delay_ms=0.1).effective_loss_penalty_ms == 1.0
    assert LinkProfile(delay_ms=10, loss_penalty_ms=200).effective_loss_penalty_ms == 200


# --------------------------------------------------------------------------- real sockets


async def test_added_delay_and_jitter_match_the_profile(sink: Sink) -> None:
    profile = LinkProfile(name="test", delay_ms=20.0, jitter_ms=3.0)
    with MachineStalls() as stalls:  # a stall of the machine delays the records it spans
        async with LinkEmulator(target=sink.address, profile=profile, seed=7) as emu:
            n = 150
            await _send_records(emu.port, n, 0.01)
            await _wait_for(lambda: len(sink.arrivals) == n, 3.0)
            stats = emu.stats()
    assert [a[0] for a in sink.arrivals] == list(range(n))
    unstalled = [(sent, arr) for _, sent, arr in sink.arrivals
                 if not stalls.overlaps(sent, arr)]
    stalled = n - len(unstalled)
    assert len(unstalled) >= 100, f"the machine stalled too much to judge: {stalls.spans}"
    added_ms = np.array([(arr - sent) * 1000.0 for sent, arr in unstalled])
    p16, p50, p84 = np.percentile(added_ms, [16, 50, 84])
    tol = scaled(2.0)
    assert p50 == pytest.approx(20.0, abs=tol)
    # the 16-84 % spread of a normal is 2 sigma = 6 ms
    assert (p84 - p16) == pytest.approx(6.0, abs=tol)
    assert added_ms.min() >= 20.0 - 4 * 3.0 - 1.0  # no chunk faster than the model allows
    up = stats["up"]
    # one read per 10 ms record while the emulator keeps up; an emulator held up for 10 ms
    # reads the records that came meanwhile together (TCP coalesces them): a few such
    # hiccups happen on any machine (6 of 150 in a fresh-clone CI run at scale 1), so most
    # records, not all, must have been read alone (a scaled bound on a loaded machine)
    assert up["bytes"] == n * RECORD.size
    assert up["chunks"] >= 0.8 * n / max(1.0, scaled(1.0)) - stalled, (up, stalls.spans)
    assert up["planned_delay_ms"]["p50"] == pytest.approx(20.0, abs=1.5)
    assert stats["down"]["bytes"] == 0 and stats["connections_total"] == 1


async def test_byte_stream_stays_in_order_under_heavy_jitter(sink: Sink) -> None:
    profile = LinkProfile(delay_ms=5.0, jitter_ms=10.0, loss=0.05, loss_burst_len=3)
    async with LinkEmulator(target=sink.address, profile=profile, seed=1) as emu:
        n = 300
        await _send_records(emu.port, n, 0.001)
        await _wait_for(lambda: len(sink.arrivals) == n, 5.0)
        stats = emu.stats()
    assert [a[0] for a in sink.arrivals] == list(range(n))  # nothing reordered or lost
    assert sink.chunk_times == sorted(sink.chunk_times)
    assert stats["up"]["lost_segments"] > 0 and stats["up"]["delayed_by_loss"] > 0


async def test_bandwidth_cap_limits_throughput(sink: Sink) -> None:
    profile = LinkProfile(bandwidth_mbps=8.0)  # 1 MB/s
    payload = bytes(range(256)) * 2000  # 512,000 bytes
    with MachineStalls() as stalls:  # a stall of the machine lengthens the transfer
        async with LinkEmulator(target=sink.address, profile=profile) as emu:
            loop = asyncio.get_running_loop()
            _reader, writer = await asyncio.open_connection("127.0.0.1", emu.port)
            t0 = loop.time()
            writer.write(payload)
            await writer.drain()
            await _wait_for(lambda: len(sink.raw) == len(payload), 3.0)
            elapsed_s = sink.chunk_times[-1] - t0
            writer.close()
            await writer.wait_closed()
    assert bytes(sink.raw) == payload
    assert 0.5 * 0.95 <= elapsed_s <= 0.5 + scaled(0.3) + stalls.total_s, (elapsed_s,
                                                                            stalls.stalls_s)


async def test_manual_outage_holds_data_then_delivers_it(sink: Sink) -> None:
    async with LinkEmulator(target=sink.address, profile="lan") as emu:
        sender = asyncio.create_task(_send_records(emu.port, 60, 0.01))
        await asyncio.sleep(0.15)
        emu.start_outage(0.3)
        assert not emu.stats()["link_up"]
        await sender
        await _wait_for(lambda: len(sink.arrivals) == 60, 3.0)
        assert emu.stats()["link_up"] and emu.outages_started == 1
    assert [a[0] for a in sink.arrivals] == list(range(60))
    gaps = np.diff(sink.chunk_times)
    assert gaps.max() >= 0.28  # nothing got through during the outage
    held = [a for a in sink.arrivals if a[2] - a[1] > 0.1]
    assert len(held) >= 20  # records sent during the outage waited for its end


async def test_scheduled_outage_with_close_resets_and_refuses(sink: Sink) -> None:
    # the second connection below must land inside the outage: its length scales
    profile = LinkProfile(outages=((0.1, scaled(0.3)),), close_on_outage=True)
    async with LinkEmulator(target=sink.address, profile=profile) as emu:
        reader, writer = await asyncio.open_connection("127.0.0.1", emu.port)
        async with asyncio.timeout(scaled(2.0)):
            try:
                data = await reader.read(10)  # reset at the outage start
            except ConnectionResetError:
                data = b""
        assert data == b""
        writer.close()
        # during the outage a new connection is accepted and closed at once
        r2, w2 = await asyncio.open_connection("127.0.0.1", emu.port)
        async with asyncio.timeout(scaled(2.0)):
            assert await r2.read(10) == b""
        w2.close()
        assert emu.connections_refused >= 1
        await _wait_for(emu.link_up.is_set, 2.0)
        await _send_records(emu.port, 5, 0.001)
        await _wait_for(lambda: len(sink.arrivals) == 5, 2.0)
        with contextlib.suppress(ConnectionError):
            await writer.wait_closed()
        with contextlib.suppress(ConnectionError):
            await w2.wait_closed()


async def test_websocket_round_trip_through_the_proxy() -> None:
    from websockets.asyncio.client import connect
    from websockets.asyncio.server import serve

    async def echo(ws: object) -> None:
        async for message in ws:  # type: ignore[attr-defined]
            await ws.send(message)  # type: ignore[attr-defined]

    async with serve(echo, "127.0.0.1", 0) as server:
        target = ("127.0.0.1", next(iter(server.sockets)).getsockname()[1])
        profile = LinkProfile(delay_ms=15.0, jitter_ms=0.5)
        async with LinkEmulator(target=target, profile=profile, seed=2) as emu:
            loop = asyncio.get_running_loop()
            async with connect(f"ws://127.0.0.1:{emu.port}/", compression=None) as ws:
                rtts = []
                for i in range(10):
                    t0 = loop.time()
                    await ws.send(bytes([i]) * 100)
                    assert await ws.recv() == bytes([i]) * 100
                    rtts.append((loop.time() - t0) * 1000.0)
            stats = emu.stats()
    # 2 x 15 ms; never faster, and late only by timer ticks and scheduling on a busy host
    assert 29.0 <= float(np.median(rtts)) <= 30.0 + scaled(6.0)
    assert stats["up"]["chunks"] >= 11 and stats["down"]["chunks"] >= 11


async def test_unreachable_target_closes_the_client() -> None:
    # a port bound but never listening refuses connections, and no other process can take it
    # while the test runs (a port merely found free could be, by a server of another test)
    with socket.socket() as refusing:
        refusing.bind(("127.0.0.1", 0))
        target = refusing.getsockname()
        async with LinkEmulator(target=target, profile="lan") as emu:
            reader, writer = await asyncio.open_connection("127.0.0.1", emu.port)
            async with asyncio.timeout(scaled(2.0)):
                assert await reader.read(10) == b""
            writer.close()
            assert emu.target_failures == 1


def test_cli_runs_for_a_duration_and_prints_json(capsys: pytest.CaptureFixture[str]) -> None:
    from lab.cli import main

    port = free_tcp_port()
    code = main(["link", "--listen", f"127.0.0.1:{port}", "--target", "127.0.0.1:1",
                 "--profile", "city-1000km", "--delay-ms", "12", "--outage", "0.05:0.05",
                 "--duration", "0.2", "--seed", "3", "--json"])
    assert code == 0
    out = capsys.readouterr().out.strip().splitlines()
    stats = json.loads(out[-1])
    assert stats["profile"] == "city-1000km" and stats["outages_started"] == 1
    assert "listening" in out[0] and "12.0 ms" in out[0]


def test_cli_sigusr1_starts_an_outage_of_the_given_length() -> None:
    import signal
    import subprocess
    import sys

    from tests.support import wait_until

    port = free_tcp_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "lab.cli", "link", "--listen", f"127.0.0.1:{port}", "--target",
         "127.0.0.1:1", "--outage-on-signal", "0.05", "--outage-close",
         "--duration", f"{scaled(3.0):g}", "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert "listening" in proc.stdout.readline()  # the handler is set right after
        wait_until(lambda: _port_accepts(port), 10.0, "the emulator's port")
        proc.send_signal(signal.SIGUSR1)
        out, err = proc.communicate(timeout=scaled(20.0))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert "outage of 0.050 s (SIGUSR1), connections reset" in err
    assert json.loads(out.strip().splitlines()[-1])["outages_started"] == 1


def _port_accepts(port: int) -> bool:
    import socket

    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.2):
            return True
    except OSError:
        return False


def test_cli_refuses_a_non_positive_signal_outage() -> None:
    from lab.cli import main

    assert main(["link", "--listen", f"127.0.0.1:{free_tcp_port()}", "--target",
                 "127.0.0.1:1", "--outage-on-signal", "0", "--duration", "0.1"]) == 1


@pytest.mark.parametrize(("flag", "value", "key"), [
    ("--stats-interval", "0", "link.stats_interval_s"),  # would spin the status loop
    ("--duration", "-1", "link.duration_s")])
def test_cli_refuses_a_status_period_or_duration_that_is_not_positive(
        flag: str, value: str, key: str, caplog: pytest.LogCaptureFixture) -> None:
    from lab.cli import main

    more = ["--duration", "0.1"] if flag != "--duration" else []
    assert main(["link", "--listen", f"127.0.0.1:{free_tcp_port()}", "--target",
                 "127.0.0.1:1", flag, value, *more]) == 1
    said = [r.getMessage() for r in caplog.records]
    assert any(f"{key} must be a finite number > 0, got" in m for m in said), said


def test_one_process_serves_both_legs_each_with_its_own_delay_and_stats() -> None:
    """Two --listen ports in one ``teletouch link`` process: the demo's two legs."""
    import socket
    import socketserver
    import subprocess
    import sys
    import threading
    import time

    class Echo(socketserver.BaseRequestHandler):
        def handle(self) -> None:
            while data := self.request.recv(4096):
                self.request.sendall(data)

    server = socketserver.ThreadingTCPServer(("127.0.0.1", 0), Echo)
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, daemon=True).start()
    ports = [free_tcp_port(), free_tcp_port()]
    one_way_ms = 15.0
    proc = subprocess.Popen(
        [sys.executable, "-m", "lab.cli", "link", "--listen", f"127.0.0.1:{ports[0]}",
         "--listen", f"127.0.0.1:{ports[1]}", "--target",
         f"127.0.0.1:{server.server_address[1]}", "--delay-ms", f"{one_way_ms:g}",
         "--jitter-ms", "0", "--seed", "4", "--duration", f"{scaled(4.0):g}", "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        listening = [proc.stdout.readline(), proc.stdout.readline()]
        assert all("listening" in line for line in listening)
        assert [f":{p} ->" in line for p, line in zip(ports, listening, strict=True)] == \
            [True, True]
        round_trips: dict[int, list[float]] = {}
        clients = [socket.create_connection(("127.0.0.1", p), timeout=scaled(5.0))
                   for p in ports]
        for i in range(3):
            for port, client in zip(ports, clients, strict=True):
                payload = f"leg {port} ping {i}".encode()
                t0 = time.monotonic()
                client.sendall(payload)
                got = b""
                while len(got) < len(payload):
                    got += client.recv(4096)
                round_trips.setdefault(port, []).append((time.monotonic() - t0) * 1e3)
                assert got == payload
        for client in clients:
            client.close()
        out, _err = proc.communicate(timeout=scaled(20.0))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        server.shutdown()
        server.server_close()
    # each leg delays both directions: one round trip through a leg is 2 x one-way
    for port in ports:
        assert min(round_trips[port]) >= 2 * one_way_ms - 1.0, round_trips
    legs = json.loads(out.strip().splitlines()[-1])["legs"]
    assert [leg["listen"] for leg in legs] == [f"127.0.0.1:{p}" for p in ports]
    for leg in legs:  # independent links: one connection and three requests each
        assert leg["connections_total"] == 1
        assert leg["up"]["chunks"] == 3 and leg["down"]["chunks"] == 3

