"""The relay's connections as asyncio protocols (relay_server/wire.py), over real sockets:
input in any chunking (a byte at a time, many messages in one read) is parsed and forwarded
byte-identical but for the stamps; WebSocket protocol violations get their close codes; a
slow reader only fills its own bounded outbox; garbage, resets and plain bytes on the TLS
ports never stop the relay."""

from __future__ import annotations

import asyncio
import contextlib
import random
import socket
import ssl
import struct
from pathlib import Path

import msgpack
import pytest
from websockets.client import ClientProtocol
from websockets.frames import Close, Frame, Opcode
from websockets.http11 import Response
from websockets.protocol import State
from websockets.uri import parse_uri

from relay_server import server as relay_module
from relay_server.auth import derive_token
from relay_server.server import RelayServer
from relay_server.wire import _SLICE_BYTES
from shared.protocol import (
    ArmCommand,
    Hello,
    LengthPrefixDecoder,
    PlatformState,
    encode,
    frame,
)
from shared.protocol.codec import decode_map
from shared.protocol.forward import locate_hops
from tests.relay_server.relay_clients import SECRET, Client, clients, running_relay
from tests.relay_server.test_relay_forwarding import join_pair
from tests.relay_server.test_relay_tls import lab_pki  # noqa: F401  (the fixture)
from tests.support import async_wait_until, scaled

_SKIP = frozenset({"clock_ping", "stats", "welcome"})


def _platform(seq: int, ts_us: int) -> bytes:
    return encode(PlatformState(seq=seq, ts_us=ts_us, position_mm=(1.0, 2.0, float(seq)),
                                velocity_mm_s=(0.0, 0.5, -0.5)))


def _hello(role: str, session: str) -> bytes:
    return encode(Hello(role=role, session=session, token=derive_token(SECRET, session),
                        name=f"raw-{role}"))


class RawStation:
    """A station on a bare socket that decides how its bytes are cut into writes (TCP, or
    WebSocket through websockets' Sans-I/O client protocol)."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self.ws: ClientProtocol | None = None
        self.decoder = LengthPrefixDecoder(2**24)
        self.received: list[bytes] = []
        self.close_code: int | None = None
        self.pongs = 0

    async def connect(self, relay: RelayServer) -> RawStation:
        port = relay.ws_port if self.kind == "ws" else relay.tcp_port
        self.reader, self.writer = await asyncio.open_connection("127.0.0.1", port)
        if self.kind == "ws":
            self.ws = ClientProtocol(parse_uri(f"ws://127.0.0.1:{port}/"), max_size=None)
            self.ws.send_request(self.ws.connect())
            await self._flush()
            async with asyncio.timeout(scaled(3.0)):
                while self.ws.state is State.CONNECTING:
                    await self._read()
        return self

    def encoded(self, payload: bytes) -> bytes:
        """The bytes of one message as this station puts them on the wire."""
        if self.ws is None:
            return frame(payload)
        self.ws.send_binary(payload)
        return b"".join(self.ws.data_to_send())

    async def write(self, data: bytes, chunk: int | None = None) -> None:
        step = chunk or len(data)
        for i in range(0, len(data), step):
            self.writer.write(data[i:i + step])
            await self.writer.drain()

    async def _flush(self) -> None:
        assert self.ws is not None
        for data in self.ws.data_to_send():
            if data:
                self.writer.write(data)
        await self.writer.drain()

    async def _read(self) -> bool:
        data = await self.reader.read(2**20)
        if self.ws is None:
            if not data:
                return False
            self.received.extend(self.decoder.feed(data))
            return True
        if data:
            self.ws.receive_data(data)
        else:
            self.ws.receive_eof()
        for event in self.ws.events_received():
            if isinstance(event, Frame) and event.opcode is Opcode.BINARY:
                self.received.append(bytes(event.data))
            elif isinstance(event, Frame) and event.opcode is Opcode.PONG:
                self.pongs += 1
            elif isinstance(event, Frame) and event.opcode is Opcode.CLOSE:
                self.close_code = Close.parse(event.data).code
            elif isinstance(event, Response) and event.status_code != 101:
                raise AssertionError(f"handshake refused: {event.status_code}")
        await self._flush()
        return bool(data)

    async def next_message(self, timeout_s: float = 3.0) -> bytes:
        """The next message other than clock pings, stats and the welcome."""
        async with asyncio.timeout(scaled(timeout_s)):
            while True:
                while self.received:
                    raw = self.received.pop(0)
                    if msgpack.unpackb(raw).get("type") not in _SKIP:
                        return raw
                if not await self._read():
                    raise ConnectionError("closed")

    async def closed(self, timeout_s: float = 3.0) -> None:
        async with asyncio.timeout(scaled(timeout_s)):
            while await self._read():
                pass

    def close(self) -> None:
        self.writer.close()


def _without_hops(data: bytes) -> tuple[bytes, bytes]:
    wire = locate_hops(data, decode_map(data))
    assert wire is not None
    return data[:wire.hops_start], data[wire.hops_end:]


@pytest.mark.parametrize("kind", ["ws", "tcp"])
@pytest.mark.parametrize("chunk", [1, None], ids=["byte-by-byte", "one-write"])
async def test_any_chunking_forwards_every_message_byte_identical(kind: str,
                                                                  chunk: int | None) -> None:
    """A byte at a time, and hundreds of messages in one write (more than one slice of the
    relay's input handling), arrive in order, the sender's bytes but for ``hops``."""
    n = 8 if chunk == 1 else 2 * _SLICE_BYTES // 60
    async with running_relay(rate_limit_per_s=10**6, rate_limit_burst=10**6) as relay:
        local, remote = RawStation(kind), RawStation(kind)
        await local.connect(relay)
        await remote.connect(relay)
        try:
            await local.write(local.encoded(_hello("local", f"chunks-{kind}")), chunk)
            await remote.write(remote.encoded(_hello("remote", f"chunks-{kind}")), chunk)
            sid = f"chunks-{kind}"
            await async_wait_until(lambda: sid in relay.sessions and len(
                relay.sessions[sid].stations) == 2, 3.0, "both stations joined")
            payloads = [_platform(seq, 1000 + seq) for seq in range(1, n + 1)]
            # ordered arm commands ride along, so none of them may be dropped
            commands = [encode(ArmCommand(seq=seq, ts_us=1, action="stop"))
                        for seq in range(1, n + 1)]
            data = b"".join(local.encoded(p) + local.encoded(c)
                            for p, c in zip(payloads, commands, strict=True))
            if chunk is None:
                assert len(data) > _SLICE_BYTES
            await local.write(data, chunk)
            got_commands: list[bytes] = []
            got_states: list[bytes] = []
            while len(got_commands) < n:
                raw = await remote.next_message()
                (got_commands if msgpack.unpackb(raw)["type"] == "arm_command"
                 else got_states).append(raw)
            for sent, got in zip(commands, got_commands, strict=True):
                assert _without_hops(got) == _without_hops(sent)
            # latest-wins states may be replaced by newer ones, never reordered or altered
            seqs = [msgpack.unpackb(s)["seq"] for s in got_states]
            assert seqs == sorted(seqs) and seqs, seqs
            for raw in got_states:
                assert _without_hops(raw) == _without_hops(payloads[msgpack.unpackb(raw)["seq"]
                                                                    - 1])
            assert relay.counters["bad_messages"] == 0
        finally:
            local.close()
            remote.close()


# a client frame with the mask bit clear; a frame with a reserved opcode (masked);
# a fragmented control frame
_WS_VIOLATIONS = [
    ("unmasked", bytes([0x82, 0x03]) + b"abc"),
    ("reserved_opcode", bytes([0x83, 0x80]) + b"\0\0\0\0"),
    ("fragmented_ping", bytes([0x09, 0x80]) + b"\0\0\0\0"),
]


@pytest.mark.parametrize(("name", "data"), _WS_VIOLATIONS, ids=[v[0] for v in _WS_VIOLATIONS])
async def test_websocket_protocol_violations_close_1002_and_others_go_on(
        name: str, data: bytes) -> None:
    async with running_relay() as relay, clients(("ws", 0), ("tcp", 0)) as (local, remote):
        await join_pair(relay, f"v-{name}", local, remote)
        bad = await RawStation("ws").connect(relay)
        try:
            await bad.write(data)
            await bad.closed()
            assert bad.close_code == 1002
        finally:
            bad.close()
        await local.send(ArmCommand(seq=1, ts_us=local.now(), action="stop"))
        assert (await remote.expect("arm_command")).seq == 1
        await async_wait_until(lambda: len(relay._wires) == 2, 3.0, "the bad socket gone")


async def test_websocket_message_over_twice_the_limit_is_refused_with_1009() -> None:
    async with running_relay(max_message_bytes=2048) as relay:
        station = await RawStation("ws").connect(relay)
        try:  # before the hello the limit is the hello's (2 x max_hello_bytes)
            await station.write(station.encoded(b"\x81" + b"x" * 10_000))
            await station.closed()
            assert station.close_code == 1009
        finally:
            station.close()
        assert relay._wires == set() or all(w.ended.is_set() for w in relay._wires)


@pytest.mark.parametrize("kind", ["ws", "tcp"])
async def test_garbage_and_resets_never_stop_the_relay(kind: str) -> None:
    rng = random.Random(13)
    async with running_relay() as relay, clients(("ws", 0), ("tcp", 0)) as (local, remote):
        await join_pair(relay, f"garbage-{kind}", local, remote)
        port = relay.ws_port if kind == "ws" else relay.tcp_port
        for i in range(30):
            _reader, writer = await asyncio.open_connection("127.0.0.1", port)
            blob = bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 3000)))
            if i % 3 == 0 and kind == "ws":
                blob = b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\n" + blob
            if i % 3 == 1 and kind == "tcp":
                blob = struct.pack(">I", 200) + blob[:50]  # a frame cut short
            writer.write(blob)
            if i % 2:  # reset: SO_LINGER 0, the kernel drops the connection
                sock = writer.get_extra_info("socket")
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()
        for seq in range(3):
            await local.send(ArmCommand(seq=seq, ts_us=local.now(), action="stop"))
            assert (await remote.expect("arm_command")).seq == seq
        await async_wait_until(lambda: len(relay._wires) == 2, 10.0,
                               "every garbage connection closed")
        assert relay.status()["sessions"][f"garbage-{kind}"]


async def test_a_slow_reader_only_fills_its_own_bounded_outbox() -> None:
    """The remote station stops reading: its socket and the relay's write buffer fill up,
    newer states replace unsent ones (latest-wins drops), the relay's memory for it stays
    bounded, and the other session is unaffected; when it reads again it gets fresh ones."""
    async with running_relay(rate_limit_per_s=10**6, rate_limit_burst=10**6) as relay:
        local, remote = RawStation("tcp"), RawStation("tcp")
        l2, r2 = RawStation("ws"), RawStation("ws")
        try:
            for station, role, session in ((local, "local", "slow"), (remote, "remote", "slow"),
                                           (l2, "local", "other"), (r2, "remote", "other")):
                await station.connect(relay)
                await station.write(station.encoded(_hello(role, session)))
            await async_wait_until(lambda: all(s in relay.sessions and len(
                relay.sessions[s].stations) == 2 for s in ("slow", "other")), 3.0,
                "both sessions joined")
            wire = next(w for w in relay._wires if w.transport is not None and
                        w.transport.get_extra_info("peername") ==
                        remote.writer.get_extra_info("sockname"))
            big = b"\0" * 60_000
            seq = 0
            high = 0
            for _ in range(40):  # ~ 5 MB offered, the reader reads nothing
                batch = []
                for _ in range(20):
                    seq += 1
                    body = PlatformState(seq=seq, ts_us=seq, position_mm=(0.0, 0.0, 0.0),
                                         velocity_mm_s=(0.0, 0.0, 0.0)).to_wire()
                    # an unknown key pads it (the relay forwards unknown keys as they are)
                    payload = msgpack.packb({"v": 1, "type": "platform_state", **body,
                                             "pad": big[:6000]}, use_bin_type=True)
                    batch.append(frame(payload))
                await local.write(b"".join(batch))
                assert wire.transport is not None
                high = max(high, wire.transport.get_write_buffer_size())
            peer = relay.sessions["slow"].stations["remote"]
            await async_wait_until(lambda: peer.outbox.closed or len(peer.outbox) <= 4,
                                   3.0, "outbox bounded")
            # the write buffer holds at most what was written before it passed its mark
            assert high < 64 * 1024 + 20 * 6200, high
            drops = relay.status()["sessions"]["slow"]["drops"]["local_to_remote"]
            assert drops["latest_wins"] > 0, drops
            await l2.write(l2.encoded(encode(ArmCommand(seq=1, ts_us=1, action="stop"))))
            got = msgpack.unpackb(await r2.next_message())  # the other session is fine
            assert (got["type"], got["seq"]) == ("arm_command", 1)
            # reading again: the newest state arrives (the stale ones were replaced)
            newest = 0
            async with asyncio.timeout(scaled(5.0)):
                while newest < seq:
                    raw = await remote.next_message()
                    newest = max(newest, msgpack.unpackb(raw)["seq"])
        finally:
            for station in (local, remote, l2, r2):
                station.close()


async def test_tls_ports_survive_plain_bytes_and_broken_handshakes(
        lab_pki: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: F811
    open_timeout_s = scaled(0.5)
    monkeypatch.setattr(relay_module, "_OPEN_TIMEOUT_S", open_timeout_s)
    async with running_relay(tls_cert=lab_pki["relay.crt"], tls_key=lab_pki["relay.key"]
                             ) as relay:
        for port in (relay.ws_port, relay.tcp_port):
            # plain bytes, a TLS record cut short (the handshake never finishes: cut after
            # the open timeout, not asyncio's 60 s), a station's message without TLS
            for blob in (b"GET /status HTTP/1.1\r\n\r\n", b"\x16\x03\x01\x00\xff garbage",
                         frame(_hello("local", "x"))):
                reader, writer = await asyncio.open_connection("127.0.0.1", port)
                writer.write(blob)
                t0 = asyncio.get_running_loop().time()
                async with asyncio.timeout(open_timeout_s + scaled(5.0)):
                    with contextlib.suppress(ConnectionError):
                        while await reader.read(4096):  # until the relay ends it
                            pass
                assert asyncio.get_running_loop().time() - t0 <= open_timeout_s + scaled(2.0)
                writer.close()
        ctx = ssl.create_default_context(cafile=str(lab_pki["ca.crt"]))
        # a TLS handshake, then a station's messages on the TLS TCP port
        reader, writer = await asyncio.open_connection("127.0.0.1", relay.tcp_port, ssl=ctx,
                                                       server_hostname="127.0.0.1")
        writer.write(frame(_hello("local", "tls-raw")))
        decoder = LengthPrefixDecoder(2**20)
        async with asyncio.timeout(scaled(5.0)):
            got: list[bytes] = []
            while not any(msgpack.unpackb(m)["type"] == "welcome" for m in got):
                got.extend(decoder.feed(await reader.read(65536)))
        writer.close()
        # and the WebSocket port over TLS answers /status
        reader, writer = await asyncio.open_connection("127.0.0.1", relay.ws_port, ssl=ctx,
                                                       server_hostname="127.0.0.1")
        writer.write(b"GET /status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        async with asyncio.timeout(scaled(5.0)):
            head = await reader.readuntil(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 200"), head[:40]
        writer.close()
        await async_wait_until(lambda: not relay._wires, 10.0, "every connection closed")


async def test_status_404_and_a_client_that_never_upgrades() -> None:
    async with running_relay() as relay:
        reader, writer = await asyncio.open_connection("127.0.0.1", relay.ws_port)
        writer.write(b"GET /nothing HTTP/1.1\r\nHost: x\r\n\r\n")
        async with asyncio.timeout(scaled(3.0)):
            head = await reader.readuntil(b"\r\n\r\n")
            assert head.startswith(b"HTTP/1.1 404")
            await reader.read()  # the relay closes after the response
        writer.close()
        ok = Client("ws")
        await ok.connect(relay)
        await ok.hello("local", "after-404")
        await ok.close()


def _client_frame(opcode: Opcode, data: bytes, fin: bool = True) -> bytes:
    return Frame(opcode, data, fin=fin).serialize(mask=True)


async def test_websocket_fragments_pings_text_and_a_hello_in_the_upgrade_write() -> None:
    """Frames the relay's fast path leaves to websockets' protocol: the hello (and half of
    the next frame) in the same write as the upgrade request, a message in fragments with a
    ping between them, a text message; the binary messages around them still go fast."""
    async with running_relay() as relay, clients(("tcp", 0)) as (remote,):
        await remote.connect(relay)
        await remote.hello("remote", "frag")
        reader, writer = await asyncio.open_connection("127.0.0.1", relay.ws_port)
        station = RawStation("ws")
        station.reader, station.writer = reader, writer
        station.ws = ClientProtocol(parse_uri(f"ws://127.0.0.1:{relay.ws_port}/"),
                                    max_size=None)
        station.ws.send_request(station.ws.connect())
        request = b"".join(station.ws.data_to_send())
        first = _client_frame(Opcode.BINARY, _platform(1, 11))
        try:
            writer.write(request + _client_frame(Opcode.BINARY, _hello("local", "frag"))
                         + first[:5])
            await writer.drain()
            async with asyncio.timeout(scaled(3.0)):
                while station.ws.state is State.CONNECTING:
                    await station._read()
            fragmented = _platform(2, 12)
            writer.write(first[5:]
                         + _client_frame(Opcode.BINARY, fragmented[:7], fin=False)
                         + _client_frame(Opcode.PING, b"are you there")
                         + _client_frame(Opcode.CONT, fragmented[7:20], fin=False)
                         + _client_frame(Opcode.CONT, fragmented[20:])
                         + _client_frame(Opcode.TEXT, b"hello as text")
                         + _client_frame(Opcode.BINARY, _platform(3, 13)))
            await writer.drain()
            for seq in (1, 2, 3):
                got = await remote.expect("platform_state")
                assert (got.seq, got.ts_us) == (seq, 10 + seq)
            err = msgpack.unpackb(await station.next_message())
            assert (err["type"], err["code"], err["fatal"]) == ("error", "malformed", False)
            async with asyncio.timeout(scaled(3.0)):
                while not station.pongs:  # the protocol answered the ping
                    await station._read()
        finally:
            writer.close()

