"""StationLink against a small in-test relay built from the same sans-I/O ProtocolConnection.

The fake relay speaks both framings (WebSocket on one port, length-prefixed TCP on another),
checks the token, answers hello with welcome or error + close code, can ping, push stats,
stall (stop reading) and drop every connection. The last tests run the same link against
the real relay (``relay_server.server.RelayServer`` on free ports), directly and through
the link emulator.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest

from shared.client import LATEST_WINS_TYPES, StationLink, backoff_delay_s, parse_link_url
from shared.errors import AuthError, ConfigError, LocalProtocolError
from shared.protocol import (
    ArmCommand,
    ClockPing,
    ClockPong,
    Error,
    Hello,
    Message,
    MessageReceived,
    PlatformState,
    ProtocolConnection,
    Stats,
    TactileFrame,
    Welcome,
)
from shared.timebase import monotonic_s, now_us
from shared.transport import TcpTransport, TransportClosed, WsTransport
from tests.support import MachineStalls, free_tcp_port, motion_of, motion_state, scaled

TOKEN = "s3cret"


class _Peer:
    """One accepted connection of the fake relay (either framing)."""

    def __init__(self, framing: str, send_raw: Any, recv_raw: Any, close: Any) -> None:
        self.conn = ProtocolConnection(framing)  # type: ignore[arg-type]
        self._send_raw, self._recv_raw, self._close = send_raw, recv_raw, close
        self.hello: Hello | None = None

    async def send(self, msg: Message) -> None:
        self.conn.send(msg)
        for data in self.conn.data_to_send():
            await self._send_raw(data)

    async def recv(self) -> list[Message]:
        self.conn.receive_data(await self._recv_raw())
        return [e.message for e in self.conn.events_received() if isinstance(e, MessageReceived)]

    async def close(self, code: int = 1000) -> None:
        await self._close(code)


class FakeRelay:
    """Minimal relay: token check, welcome, record everything received, manual control."""

    def __init__(self, token: str = TOKEN, refuse_role_code: str | None = None,
                 ping_interval_s: float = 0.05) -> None:
        self.token = token
        #: announced in the welcome (the link's silence limit is at least 2.5 times it);
        #: this fake never pings
        self.ping_interval_s = ping_interval_s
        self.refuse_role_code = refuse_role_code
        self.received: asyncio.Queue[tuple[_Peer, Message]] = asyncio.Queue()
        self.peers: list[_Peer] = []
        self.hellos = 0
        self.accepts_s: list[float] = []
        self.reading = asyncio.Event()
        self.reading.set()
        self.welcomed = asyncio.Event()
        self._ws_server: Any = None
        self._tcp_server: asyncio.Server | None = None
        self._tasks: set[asyncio.Task[Any]] = set()

    async def __aenter__(self) -> FakeRelay:
        from websockets.asyncio.server import serve

        self._ws_server = await serve(self._ws_handler, "127.0.0.1", 0, compression=None,
                                      max_size=None)
        self._tcp_server = await asyncio.start_server(self._tcp_handler, "127.0.0.1", 0)
        return self

    async def __aexit__(self, *exc: object) -> None:
        self._ws_server.close()
        await self._ws_server.wait_closed()
        assert self._tcp_server is not None
        self._tcp_server.close()
        for t in list(self._tasks):
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        with contextlib.suppress(asyncio.TimeoutError):
            await asyncio.wait_for(self._tcp_server.wait_closed(), scaled(1.0))

    def url(self, scheme: str) -> str:
        if scheme == "tcp":
            assert self._tcp_server is not None
            port = self._tcp_server.sockets[0].getsockname()[1]
            return f"tcp://127.0.0.1:{port}"
        port = next(iter(self._ws_server.sockets)).getsockname()[1]
        return f"ws://127.0.0.1:{port}/"

    async def _ws_handler(self, ws: Any) -> None:
        async def close(code: int) -> None:
            await ws.close(code)

        await self._serve(_Peer("ws", ws.send, ws.recv, close))

    async def _tcp_handler(self, reader: asyncio.StreamReader,
                          writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)

        async def send(data: bytes) -> None:
            writer.write(data)
            await writer.drain()

        async def recv() -> bytes:
            data = await reader.read(65536)
            if not data:
                raise ConnectionError("eof")
            return data

        async def close(code: int) -> None:
            writer.close()

        try:
            await self._serve(_Peer("tcp", send, recv, close))
        finally:
            writer.close()
            self._tasks.discard(task)

    async def _serve(self, peer: _Peer) -> None:
        self.accepts_s.append(monotonic_s())
        with contextlib.suppress(Exception):
            msgs = await peer.recv()
            hello = msgs[0]
            assert isinstance(hello, Hello)
            self.hellos += 1
            peer.hello = hello
            if hello.token != self.token:
                await peer.send(Error(code="auth", message="wrong token", fatal=True))
                await peer.close(4001)
                return
            if self.refuse_role_code is not None:
                await peer.send(Error(code=self.refuse_role_code, message="no", fatal=True))
                await peer.close(4002)
                return
            await peer.send(Welcome(session=hello.session, role=hello.role,
                                    server_time_us=now_us(), max_message_bytes=1 << 22,
                                    ping_interval_s=self.ping_interval_s))
            self.peers.append(peer)
            self.welcomed.set()
            while True:
                await self.reading.wait()
                for msg in await peer.recv():
                    self.received.put_nowait((peer, msg))

    async def drop_all(self) -> None:
        for peer in self.peers:
            await peer.close(1001)
        self.peers.clear()
        self.welcomed.clear()

    async def next_message(self, msg_type: type[Message], timeout_s: float = 2.0) -> Message:
        async with asyncio.timeout(scaled(timeout_s)):
            while True:
                _, msg = await self.received.get()
                if isinstance(msg, msg_type):
                    return msg


@pytest.fixture
async def relay() -> AsyncIterator[FakeRelay]:
    async with FakeRelay() as r:
        yield r


def _link(url: str, **kw: Any) -> StationLink:
    kw.setdefault("connect_timeout_s", scaled(2.0))
    return StationLink(url, session="lab1", role=kw.pop("role", "local"),
                       token=kw.pop("token", TOKEN), name="test", **kw)


def _state(seq: int) -> PlatformState:
    return PlatformState(seq=seq, ts_us=now_us(), position_mm=(float(seq % 50), 0.0, 1.0))


# --------------------------------------------------------------------------- pure helpers


def test_parse_link_url_schemes_and_errors() -> None:
    assert parse_link_url("ws://relay.example:9000/x") == ("ws", "relay.example", 9000)
    assert parse_link_url("wss://relay.example/") == ("wss", "relay.example", 443)
    assert parse_link_url("tcp://10.0.0.1:8766") == ("tcp", "10.0.0.1", 8766)
    for bad in ("http://h:1", "tcp://h", "ws://:80", "tcp://h:99999"):
        with pytest.raises(ConfigError):
            parse_link_url(bad)


def test_backoff_doubles_to_cap_and_jitter_stays_in_band() -> None:
    rng = random.Random(1)
    exact = [backoff_delay_s(a, min_s=0.1, max_s=5.0, jitter=0.0, rng=rng) for a in range(10)]
    assert exact[:7] == pytest.approx([0.1, 0.2, 0.4, 0.8, 1.6, 3.2, 5.0])
    assert exact[7:] == pytest.approx([5.0] * 3)
    for attempt in range(12):
        base = min(5.0, 0.1 * 2 ** attempt)
        samples = [backoff_delay_s(attempt, min_s=0.1, max_s=5.0, jitter=0.5, rng=rng)
                   for _ in range(200)]
        assert min(samples) >= 0.5 * base - 1e-12 and max(samples) <= base + 1e-12
        assert max(samples) - min(samples) > 0.2 * base  # the jitter is really there


def test_constructor_rejects_bad_settings() -> None:
    with pytest.raises(ConfigError):
        StationLink("tcp://h:1", session="s", role="pilot", token="t")
    with pytest.raises(ConfigError):
        StationLink("tcp://h:1", session="s", role="local", token="t", reconnect_min_s=0)


# --------------------------------------------------------------------------- over sockets


@pytest.mark.parametrize("scheme", ["ws", "tcp"])
async def test_hello_welcome_and_data_both_ways(relay: FakeRelay, scheme: str) -> None:
    async with _link(relay.url(scheme)) as link:
        welcome = await link.wait_connected(scaled(2.0))
        assert welcome.session == "lab1" and welcome.role == "local"
        assert link.is_connected and link.link_down_since is None
        peer = relay.peers[0]
        assert peer.hello == Hello(role="local", session="lab1", token=TOKEN, name="test")

        await link.send(ArmCommand(seq=7, ts_us=now_us(), action="move", target_mm=(1, 2, 3)))
        got = await relay.next_message(ArmCommand)
        assert isinstance(got, ArmCommand) and got.seq == 7 and got.target_mm == (1, 2, 3)

        t_before = now_us()
        await peer.send(_state(42))
        msg = await link.recv(timeout_s=scaled(2.0))
        t_after = now_us()
        assert isinstance(msg, PlatformState) and msg.seq == 42
        hop = msg.hops[-1]
        assert (hop.clock, hop.stage) == ("local", "station_rx")
        assert t_before <= hop.t_us <= t_after

        with pytest.raises(TimeoutError):
            await link.recv(timeout_s=0.05)


@pytest.mark.parametrize("scheme", ["ws", "tcp"])
async def test_clock_ping_gets_a_correct_pong(relay: FakeRelay, scheme: str) -> None:
    async with _link(relay.url(scheme)) as link:
        await link.wait_connected(scaled(2.0))
        peer = relay.peers[0]
        for ping_id in range(3):
            t0 = now_us()
            await peer.send(ClockPing(ping_id=ping_id, t0_us=t0))
            pong = await relay.next_message(ClockPong)
            t3 = now_us()
            assert isinstance(pong, ClockPong)
            assert pong.ping_id == ping_id and pong.t0_us == t0
            # same host, same clock: t0 <= t1 <= t2 <= t3
            assert t0 <= pong.t1_us <= pong.t2_us <= t3
        assert link.counters.pongs_sent == 3


async def test_stats_update_clock_offsets(relay: FakeRelay) -> None:
    async with _link(relay.url("ws"), role="remote") as link:
        await link.wait_connected(scaled(2.0))
        assert link.clock_offsets_us == {} and link.clock_offset_us is None
        metrics = {"clock_offset_us": {"local": -1500, "remote": 250.7}, "sessions": 1}
        await relay.peers[0].send(Stats(scope="relay", time_us=now_us(), metrics=metrics))
        msg = await link.recv(timeout_s=scaled(2.0))
        assert isinstance(msg, Stats) and link.latest_stats is msg
        assert link.clock_offsets_us == {"local": -1500, "remote": 250}
        assert link.clock_offset_us == 250


@pytest.mark.parametrize("scheme", ["ws", "tcp"])
async def test_reconnects_after_the_relay_drops_and_resumes(relay: FakeRelay,
                                                            scheme: str) -> None:
    async with _link(relay.url(scheme), reconnect_min_s=0.05, reconnect_max_s=0.2) as link:
        await link.wait_connected(scaled(2.0))
        await relay.drop_all()
        async with asyncio.timeout(scaled(2.0)):
            while link.is_connected:
                await asyncio.sleep(0.005)
        assert link.link_down_since is not None
        await asyncio.sleep(0.01)
        assert link.link_down_for_s() > 0.0
        # a command sent while down is stale by the time the link is back: dropped at the
        # welcome, never delivered late; what is sent after the welcome goes through
        await link.send(ArmCommand(seq=1, ts_us=now_us(), action="stop"))
        await link.wait_connected(scaled(2.0))
        assert link.link_down_since is None and link.link_down_for_s() == 0.0
        assert link.counters.dropped_on_reconnect == 1
        await link.send(ArmCommand(seq=2, ts_us=now_us(), action="stop"))
        got = await relay.next_message(ArmCommand)
        assert isinstance(got, ArmCommand) and got.seq == 2
        assert link.counters.connects == 2 and link.counters.connection_losses == 1
        assert relay.hellos == 2


async def test_backoff_timing_when_the_relay_is_unreachable(relay: FakeRelay) -> None:
    """A listener that hangs up at once: attempts are spaced by the doubling delays."""
    attempts: list[float] = []

    async def hang_up(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        attempts.append(monotonic_s())
        writer.close()

    server = await asyncio.start_server(hang_up, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        with MachineStalls() as stalls:
            async with _link(
                    f"tcp://127.0.0.1:{port}", reconnect_min_s=0.05, reconnect_max_s=0.2,
                    reconnect_jitter=0.0) as link:
                async with asyncio.timeout(scaled(5.0)):
                    while len(attempts) < 6:
                        await asyncio.sleep(0.01)
                connected, history = link.is_connected, list(link.backoff_history_s)[:5]
        assert not connected
        expected = [0.05, 0.1, 0.2, 0.2, 0.2]
        assert history == pytest.approx(expected)
        gaps = np.diff(attempts[:6])
        for gap, delay in zip(gaps, expected, strict=True):  # a stall lengthens a gap
            assert delay * 0.9 <= gap <= delay + scaled(0.1) + stalls.total_s, (
                gaps, stalls.stalls_s)
    finally:
        server.close()
        await server.wait_closed()


async def test_a_connection_that_opens_as_the_link_closes_is_closed(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The link is closed while it connects, and the connect completes all the same (the
    connection opened in the same instant): the link still closes what it opened. Around
    the connect, Python 3.11's asyncio.wait_for dropped such a connection unclosed; its
    socket stayed open until the garbage collector found it (the suite's leak check saw it
    beside CPU burners)."""
    connecting = asyncio.Event()
    opened: list[Any] = []

    class _Opened:
        framing = "tcp"

        def __init__(self) -> None:
            self.closed = False

        async def write(self, frames: list[bytes]) -> None:
            await asyncio.sleep(0)

        async def recv(self) -> bytes:
            raise TransportClosed("gone")

        async def close(self, code: int = 1000, reason: str = "") -> None:
            self.closed = True

    async def open_as_cancelled(*args: Any, **kwargs: Any) -> _Opened:
        connecting.set()
        # connecting until the link is closed, but the connection opened in that instant
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.Event().wait()
        opened.append(_Opened())
        return opened[-1]

    monkeypatch.setattr("shared.client.open_client_transport", open_as_cancelled)
    link = _link("tcp://127.0.0.1:9", reconnect_min_s=scaled(5.0), reconnect_max_s=scaled(5.0))
    link.start()
    await asyncio.wait_for(connecting.wait(), scaled(2.0))
    await asyncio.wait_for(link.close(), scaled(2.0))
    assert len(opened) == 1 and opened[0].closed


@pytest.mark.parametrize("scheme", ["ws", "tcp"])
async def test_wrong_token_is_final_and_logged_once(relay: FakeRelay, scheme: str,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.ERROR, logger="shared.client")
    async with _link(relay.url(scheme), token="wrong", reconnect_min_s=0.01) as link:
        with pytest.raises(AuthError):
            await link.wait_connected(scaled(2.0))
        await asyncio.sleep(scaled(0.1))  # would be ~4 retries if it retried
        assert relay.hellos == 1
        with pytest.raises(AuthError):
            await link.recv(timeout_s=0.1)
        with pytest.raises(AuthError):
            await link.send(_state(1))
        with pytest.raises(AuthError):
            async for _ in link.messages():
                pass
    refusals = [r for r in caplog.records if "refused" in r.getMessage()]
    assert len(refusals) == 1


async def test_role_taken_is_retried_not_final() -> None:
    """Another station holds the role: it may leave, so the link keeps trying (a station
    never gives up on a transient fault) and counts the refusals."""
    async with (FakeRelay(refuse_role_code="role_taken") as relay,
                _link(relay.url("ws"), reconnect_min_s=0.01, reconnect_max_s=0.02) as link):
        async with asyncio.timeout(scaled(2.0)):
            while relay.hellos < 3:
                await asyncio.sleep(0.005)
        assert link.final_error is None and not link.is_connected
        assert link.counters.role_taken_refusals >= 2


@pytest.mark.parametrize("scheme", ["ws", "tcp"])
async def test_a_send_reaches_the_socket_in_the_callers_task_while_the_socket_keeps_up(
        relay: FakeRelay, scheme: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each message goes to the socket from ``send`` itself (no writer-task wake-up per
    message) and arrives in order; the writer task is left only the hello."""
    cls: Any = WsTransport if scheme == "ws" else TcpTransport
    calls = {"write": 0, "write_nowait": 0}
    write, write_nowait = cls.write, cls.write_nowait

    async def counted_write(self: Any, frames: list[bytes]) -> None:
        calls["write"] += 1
        await write(self, frames)

    def counted_write_nowait(self: Any, frames: list[bytes]) -> None:
        calls["write_nowait"] += len(frames)
        write_nowait(self, frames)

    monkeypatch.setattr(cls, "write", counted_write)
    monkeypatch.setattr(cls, "write_nowait", counted_write_nowait)
    async with _link(relay.url(scheme)) as link:
        await link.wait_connected(scaled(2.0))
        for i in range(20):  # ordered messages: none may be dropped or reordered
            await link.send(ArmCommand(seq=i, ts_us=now_us(), action="stop"))
            assert link.pending_sends == 0  # handed over before send() returned
        seqs: list[int] = []
        while len(seqs) < 20:
            got = await relay.next_message(ArmCommand)
            assert isinstance(got, ArmCommand)
            seqs.append(got.seq)
        assert seqs == list(range(20))
        assert calls == {"write": 1, "write_nowait": 20}  # the hello, then every message


async def test_latest_wins_on_a_stalled_socket(relay: FakeRelay) -> None:
    """The relay stops reading; big frames back up; only the newest state is kept,
    while ordered commands all arrive, in order."""
    async with _link(relay.url("tcp"), write_buffer_bytes=1024) as link:
        await link.wait_connected(scaled(2.0))
        relay.reading.clear()
        layer = np.zeros((160, 160), dtype=np.float64)  # ~200 KiB per frame
        n_frames = 60
        for i in range(n_frames):
            await link.send(TactileFrame(seq=i, ts_us=now_us(), center_mm=(0.0, 0.0),
                                         pitch_mm=0.1, layers={"height_mm": layer},
                                         contact=False, force_n=0.0, indentation_mm=0.0))
            await link.send(ArmCommand(seq=i, ts_us=now_us(), action="stop"))
            await asyncio.sleep(0.002)
            assert link.pending_sends <= 1 + 256
        assert link.counters.stale_dropped_tx > 0
        relay.reading.set()
        frames: list[int] = []
        commands: list[int] = []
        async with asyncio.timeout(scaled(10.0)):
            while not frames or frames[-1] != n_frames - 1 or len(commands) < n_frames:
                _, msg = await relay.received.get()
                if isinstance(msg, TactileFrame):
                    frames.append(msg.seq)
                elif isinstance(msg, ArmCommand):
                    commands.append(msg.seq)
        assert commands == list(range(n_frames))
        assert frames == sorted(frames) and len(frames) < n_frames
        assert len(frames) + link.counters.stale_dropped_tx == n_frames


async def test_inbox_is_latest_wins_for_state_and_ordered_for_commands(
        relay: FakeRelay) -> None:
    async with _link(relay.url("ws"), role="remote") as link:
        await link.wait_connected(scaled(2.0))
        peer = relay.peers[0]
        for i in range(20):
            await peer.send(_state(i))
            await peer.send(ArmCommand(seq=i, ts_us=now_us(), action="stop"))
        async with asyncio.timeout(scaled(2.0)):
            while link.counters.messages_received < 40:
                await asyncio.sleep(0.005)
        got = [await link.recv(timeout_s=scaled(1.0)) for _ in range(21)]
        states = [m.seq for m in got if isinstance(m, PlatformState)]
        cmds = [m.seq for m in got if isinstance(m, ArmCommand)]
        assert states == [19] and cmds == list(range(20))
        assert link.counters.stale_dropped_rx == 19
        assert "platform_state" in LATEST_WINS_TYPES


async def test_the_tap_records_a_state_as_its_queue_carried_it() -> None:
    # never connected: the states wait in the queue, the second replaces the first and
    # takes its motion stamp; a recording must show what would go on the wire
    link = _link(f"tcp://127.0.0.1:{free_tcp_port()}")
    tapped: list[Any] = []
    link.tap = lambda direction, msg, t_us: tapped.append((direction, msg))
    await link.send(motion_state(1, 1_000, 2_000))
    await link.send(motion_state(2, 2_000, 3_000))
    assert [(d, m.seq, motion_of(m)) for d, m in tapped] == [("tx", 1, 1_000), ("tx", 2, 1_000)]
    await link.close()


async def test_the_tap_records_each_welcome_without_its_resume_secret() -> None:
    """A replay must start decoding compact frames anew where the station did (each new link
    session): the welcome is tapped as it arrives, its resume secret blanked."""
    async with _real_relay() as relay:
        link = _link(f"ws://127.0.0.1:{relay.ws_port}/")
        tapped: list[Any] = []
        link.tap = lambda direction, msg, t_us: tapped.append((direction, msg))
        async with link:
            welcome = await link.wait_connected(scaled(3.0))
            assert welcome.resume  # the link itself keeps it
            welcomes = [m for d, m in tapped if d == "rx" and isinstance(m, Welcome)]
            assert len(welcomes) == 1 and welcomes[0].resume == ""
            assert welcomes[0].session == "lab1" and welcomes[0].role == "local"


async def test_invalid_message_is_refused_locally(relay: FakeRelay) -> None:
    async with _link(relay.url("ws")) as link:
        with pytest.raises(LocalProtocolError):
            await link.send(PlatformState(seq=-1, ts_us=0))


async def test_silent_link_is_detected_and_reconnected(relay: FakeRelay) -> None:
    async with _link(relay.url("tcp"), liveness_timeout_s=0.15,
                     reconnect_min_s=0.02) as link:
        await link.wait_connected(scaled(2.0))
        # the fake relay never sends anything: the link must notice and reconnect
        async with asyncio.timeout(scaled(3.0)):
            while link.counters.connects < 2:
                await asyncio.sleep(0.01)
        assert link.counters.connection_losses >= 1
        assert link.silent_for_s() < scaled(1.0)


# --------------------------------------------------------------------------- real relay


@contextlib.asynccontextmanager
async def _real_relay(port: int = 0, tcp_port: int = 0, stats_interval_s: float = 0.1,
                      ping_interval_s: float = 0.1) -> AsyncIterator[Any]:
    from relay_server.config import RelayConfig
    from relay_server.server import RelayServer

    relay = RelayServer(RelayConfig(host="127.0.0.1", port=port, tcp_port=tcp_port,
                                    tokens={"lab1": TOKEN}, stats_interval_s=stats_interval_s,
                                    ping_interval_s=ping_interval_s,
                                    silence_timeout_s=max(10.0, 2 * ping_interval_s),
                                    ping_burst_spacing_s=0.005,
                                    hello_timeout_s=scaled(2.0)))
    await relay.start()
    try:
        yield relay
    finally:
        await relay.close()


async def _recv_type(link: StationLink, msg_type: type[Message], timeout_s: float = 2.0
                     ) -> Message:
    async with asyncio.timeout(scaled(timeout_s)):
        while True:
            msg = await link.recv()
            if isinstance(msg, msg_type):
                return msg


async def test_real_relay_forwards_both_ways_with_hops_and_offsets() -> None:
    async with (_real_relay() as relay,
                _link(f"ws://127.0.0.1:{relay.ws_port}/", role="local") as local,
                _link(f"tcp://127.0.0.1:{relay.tcp_port}", role="remote") as remote):
        await local.wait_connected(scaled(2.0))
        await remote.wait_connected(scaled(2.0))
        sent = _state(5)
        await local.send(sent)
        got = await _recv_type(remote, PlatformState)
        assert isinstance(got, PlatformState) and got.seq == 5
        assert got.position_mm == sent.position_mm
        assert [(h.clock, h.stage) for h in got.hops] == [
            ("relay", "relay_in"), ("relay", "relay_out"), ("remote", "station_rx")]
        stamps = [sent.ts_us] + [h.t_us for h in got.hops]
        assert stamps == sorted(stamps)  # one host, one clock

        await remote.send(ArmCommand(seq=1, ts_us=now_us(), action="stop"))
        await local.send(ArmCommand(seq=2, ts_us=now_us(), action="home"))
        cmd = await _recv_type(remote, ArmCommand)
        assert isinstance(cmd, ArmCommand) and cmd.seq == 2
        # pongs went back: the relay reports both offsets (same host: near zero)
        async with asyncio.timeout(scaled(3.0)):
            while None in (local.clock_offsets_us.get("local"),
                           local.clock_offsets_us.get("remote")):
                await local.recv()
        assert abs(local.clock_offset_us or 0) < 5_000
        assert local.counters.pongs_sent >= 1 and remote.counters.pongs_sent >= 1


async def test_a_station_learns_the_other_stations_offset_as_soon_as_it_is_measured() -> None:
    """The local station is connected; the remote one joins (a relay restart, a reconnect).
    The local station needs the remote's offset to age-check frames, and it gets it from the
    remote's ping burst at once, not at its own next periodic stats (here 60 s away)."""
    async with _real_relay(stats_interval_s=60.0, ping_interval_s=60.0) as relay:
        url = f"ws://127.0.0.1:{relay.ws_port}/"
        async with _link(url, role="local") as local:
            await local.wait_connected(scaled(2.0))
            async with asyncio.timeout(scaled(3.0)):
                while local.clock_offsets_us.get("local") is None:
                    await local.recv()
            assert local.clock_offsets_us.get("remote") is None
            with MachineStalls() as stalls:  # a stall lengthens the first round trips
                async with _link(f"tcp://127.0.0.1:{relay.tcp_port}",
                                 role="remote") as remote:
                    await remote.wait_connected(scaled(2.0))
                    async with asyncio.timeout(scaled(3.0)):
                        while local.clock_offsets_us.get("remote") is None:
                            await local.recv()
                    view = local.clock_view
                    assert view is not None
                    rel = view.relative("local", "remote", now_us())
            # usable by the 30 ms rule
            assert rel is not None and rel[1] < 30_000 + stalls.total_s * 1e6, (
                rel, stalls.stalls_s)


async def test_real_relay_refusals_are_final() -> None:
    async with _real_relay() as relay:
        url = f"ws://127.0.0.1:{relay.ws_port}/"
        async with _link(url, token="nope", reconnect_min_s=0.01) as bad:
            with pytest.raises(AuthError):
                await bad.wait_connected(scaled(2.0))
        async with _link(url, role="local") as first:
            await first.wait_connected(scaled(2.0))
            async with _link(f"tcp://127.0.0.1:{relay.tcp_port}", role="local",
                             reconnect_min_s=0.01, reconnect_max_s=0.05) as second:
                # another station's connection (no resume secret of ours): refused, retried
                async with asyncio.timeout(scaled(2.0)):
                    while second.counters.role_taken_refusals < 2:
                        await asyncio.sleep(0.005)
                assert second.final_error is None and first.is_connected
                await first.close()
                await second.wait_connected(scaled(2.0))  # the role is free: it joins


async def test_real_relay_replaces_a_stations_own_silent_connection() -> None:
    """The station's connection goes silent (blackholed) while the relay still holds it; the
    station's new hello proves the old connection's resume secret and replaces it at once,
    instead of being refused as role_taken until the relay notices the old one is dead."""
    from lab.linkemu import LinkEmulator, LinkProfile

    async with _real_relay() as relay:
        emu = LinkEmulator(listen=("127.0.0.1", 0), target=("127.0.0.1", relay.tcp_port),
                           profile=LinkProfile(name="test", delay_ms=0.0))
        await emu.start()
        try:
            async with _link(f"tcp://127.0.0.1:{emu.port}", role="local",
                             liveness_timeout_s=scaled(0.5), reconnect_min_s=0.02,
                             reconnect_max_s=0.05) as link:
                await link.wait_connected(scaled(2.0))
                first_secret = link.welcome.resume if link.welcome else ""
                assert len(first_secret) == 32
                emu.start_outage(scaled(1.5))  # silent both ways; the relay keeps the peer
                async with asyncio.timeout(scaled(3.0)):
                    while link.is_connected:
                        await asyncio.sleep(0.01)
                await link.wait_connected(scaled(5.0))  # after the outage, at the first try
                assert link.final_error is None and link.counters.role_taken_refusals == 0
                assert link.welcome is not None and link.welcome.resume != first_secret
                assert relay.counters["resumed"] == 1
                assert len(relay.sessions["lab1"].stations) == 1
        finally:
            await emu.close()


async def test_real_relay_restart_is_survived() -> None:
    ws_port, tcp_port = free_tcp_port(), free_tcp_port()
    async with (_link(f"ws://127.0.0.1:{ws_port}/", role="local", reconnect_min_s=0.02,
                      reconnect_max_s=0.1) as local,
                _link(f"tcp://127.0.0.1:{tcp_port}", role="remote", reconnect_min_s=0.02,
                      reconnect_max_s=0.1) as remote):
        async with _real_relay(ws_port, tcp_port):
            await local.wait_connected(scaled(2.0))
            await remote.wait_connected(scaled(2.0))
        async with asyncio.timeout(scaled(2.0)):
            while local.is_connected or remote.is_connected:
                await asyncio.sleep(0.01)
        assert local.link_down_since is not None
        async with _real_relay(ws_port, tcp_port):
            await local.wait_connected(scaled(3.0))
            await remote.wait_connected(scaled(3.0))
            await local.send(_state(9))
            got = await _recv_type(remote, PlatformState)
            assert isinstance(got, PlatformState) and got.seq == 9
        assert local.counters.connects == 2 and remote.counters.connects == 2


async def test_real_relay_through_the_link_emulator() -> None:
    from lab.linkemu import LinkEmulator, LinkProfile

    profile = LinkProfile(name="test", delay_ms=10.0, jitter_ms=0.5)
    async with (_real_relay() as relay,
                LinkEmulator(target=("127.0.0.1", relay.ws_port), profile=profile,
                             seed=4) as emu,
                _link(f"ws://127.0.0.1:{emu.port}/", role="local") as local,
                _link(f"tcp://127.0.0.1:{relay.tcp_port}", role="remote") as remote):
        await local.wait_connected(scaled(3.0))
        await remote.wait_connected(scaled(2.0))
        delays_ms = []
        for seq in range(10):
            sent = _state(seq)
            await local.send(sent)
            got = await _recv_type(remote, PlatformState)
            assert isinstance(got, PlatformState)
            delays_ms.append((got.hops[0].t_us - sent.ts_us) / 1000.0)
            await asyncio.sleep(0.02)
        # local -> relay crosses the emulated 10 ms one-way link
        # the emulator may deliver up to 0.5 ms early; scheduling noise only adds delay
        assert 9.0 <= float(np.median(delays_ms)) <= 10.0 + scaled(2.5)
