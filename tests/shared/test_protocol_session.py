"""Session state machines without an event loop: a station and a relay peer exchange bytes."""

from __future__ import annotations

import itertools
from collections import Counter

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.errors import AuthError, LocalProtocolError, MalformedMessageError, RoleTakenError
from shared.protocol import (
    ArmCommand,
    ClockPing,
    ClockPong,
    Error,
    Hello,
    Hop,
    PlatformState,
    Stats,
    StreamPolicy,
    StreamQueue,
    TactileCompact,
    TactileFrame,
    Welcome,
    decode,
    encode,
    frame,
)
from shared.protocol.framing import HEADER
from shared.protocol.messages import LATEST_WINS_TYPES, MAX_HOPS
from shared.protocol.peer_session import (
    ClockSampled,
    Closing,
    DataReceived,
    HelloReceived,
    PeerSession,
    PeerSettings,
    StatsReported,
)
from shared.protocol.station_session import (
    Failed,
    LinkSilent,
    Refused,
    Rejected,
    StationSession,
    Welcomed,
    refusal_for_close_code,
)
from shared.protocol.tactile_codec import CodecSettings, TactileEncoder
from tests.support import motion_frame, motion_of, motion_state

HELLO = Hello(role="local", session="lab1", token="t", name="n")
WELCOME = Welcome(session="lab1", role="local", server_time_us=5, ping_interval_s=1.0,
                  max_message_bytes=1 << 22)
SETTINGS = PeerSettings(hello_timeout_us=1000, ping_burst=2, ping_burst_spacing_us=10,
                        ping_interval_us=100, stats_interval_us=50, bad_message_budget=3,
                        ordered_queue_len=4, settle_max_pings=2)



def joined_pair(framing: str = "tcp") -> tuple[StationSession, PeerSession]:
    """A station and its relay peer, through hello and welcome."""
    station = StationSession(HELLO, send_queue_size=4, receive_queue_size=8)
    peer = PeerSession(framing, SETTINGS, now_us=0)  # type: ignore[arg-type]
    peer.receive_data(station.connect(framing, 0), 1)  # type: ignore[arg-type]
    assert peer.events_received() == [HelloReceived(HELLO)]
    peer.accept(WELCOME, 2)
    for data in peer.data_to_send(lambda: 3):
        station.receive_data(data, 4)
    assert station.events_received() == [Welcomed(WELCOME)]
    return station, peer


def pump(station: StationSession, now_us: int) -> list[bytes]:
    out = []
    while (data := station.next_data(now_us)) is not None:
        out.append(data)
    return out


# --------------------------------------------------------------------------- policy


def test_policy_is_declared_on_the_message_types() -> None:
    assert PlatformState.POLICY is StreamPolicy.LATEST_WINS
    assert TactileFrame.POLICY is StreamPolicy.LATEST_WINS
    assert ArmCommand.POLICY is StreamPolicy.ORDERED and Stats.POLICY is StreamPolicy.ORDERED
    assert {"platform_state", "arm_state", "tactile_frame", "tactile_compact"} == LATEST_WINS_TYPES


def test_stream_queue_arrival_order_latest_and_bound() -> None:
    q: StreamQueue[int] = StreamQueue(2)
    assert q.put_latest("a", 1) is None
    assert q.put_ordered(2) and q.put_ordered(3)
    assert not q.put_ordered(4) and q.ordered_full
    assert q.put_latest("a", 5) == 1  # replaced, and moved to the end
    assert len(q) == 3
    assert [q.pop(), q.pop(), q.pop(), q.pop()] == [2, 3, 5, None]
    assert q.put_ordered(6, force=True) and q.take() == [6] and len(q) == 0
    # held: the unsent item waiting in the slot (the next put_latest replaces it)
    assert q.held("a") is None
    q.put_latest("a", 7)
    q.put_latest("a", 8)
    assert q.held("a") is not None and q.held("b") is None
    assert q.pop() == 8 and q.held("a") is None


# --------------------------------------------------------------------------- handshake


@pytest.mark.parametrize("framing", ["tcp", "ws"])
def test_handshake_bytes_are_the_codec_output(framing: str) -> None:
    station = StationSession(HELLO)
    hello_bytes = station.connect(framing, 0)  # type: ignore[arg-type]
    expected = encode(HELLO)
    assert hello_bytes == (frame(expected) if framing == "tcp" else expected)
    assert station.next_data(0) is None  # nothing leaves before the welcome
    peer = PeerSession(framing, SETTINGS, 0)  # type: ignore[arg-type]
    peer.receive_data(hello_bytes, 1)
    assert peer.events_received() == [HelloReceived(HELLO)]
    peer.accept(WELCOME, 2)
    welcome_bytes = peer.data_to_send(lambda: 3)
    assert welcome_bytes == [frame(encode(WELCOME)) if framing == "tcp" else encode(WELCOME)]
    station.receive_data(welcome_bytes[0], 4)
    assert station.events_received() == [Welcomed(WELCOME)] and station.is_open
    assert station.counters.connects == 1


def test_messages_behind_the_hello_wait_for_the_welcome() -> None:
    peer = PeerSession("tcp", SETTINGS, 0)
    peer.receive_data(frame(encode(HELLO)) + frame(encode(ClockPing(ping_id=7, t0_us=1))), 10)
    assert peer.events_received() == [HelloReceived(HELLO)]
    assert peer.data_to_send(lambda: 11) == []
    peer.accept(WELCOME, 12)
    out = [decode(d[4:]) for d in peer.data_to_send(lambda: 13)]
    assert out[:2] == [WELCOME, ClockPong(ping_id=7, t0_us=1, t1_us=10, t2_us=13)]


def test_refusal_before_welcome_is_typed() -> None:
    station = StationSession(HELLO)
    station.connect("ws", 0)
    station.receive_data(encode(Error(code="auth", message="wrong token", fatal=True)), 1)
    (event,) = station.events_received()
    assert isinstance(event, Refused) and isinstance(event.error, AuthError)
    assert isinstance(refusal_for_close_code(4002, "x"), RoleTakenError)
    assert refusal_for_close_code(1000, "x") is None


def test_first_message_must_be_hello() -> None:
    peer = PeerSession("ws", SETTINGS, 0)
    peer.receive_data(encode(Stats(scope="local", time_us=1, metrics={})), 1)
    assert peer.events_received() == [Closing(1002, "hello_expected")]
    (sent,) = peer.data_to_send(lambda: 2)
    assert decode(sent) == Error(code="hello_expected", message="the first message must be "
                                 "a hello, got stats", fatal=True)


def test_hello_timeout_closes_with_4003() -> None:
    peer = PeerSession("tcp", SETTINGS, now_us=0)
    assert peer.next_tick_us() == 1000
    assert peer.tick(999) is False and not peer.closing
    peer.tick(1000)
    assert peer.events_received() == [Closing(4003, "hello_timeout")]


# --------------------------------------------------------------------------- clock


def test_clock_ping_pong_gives_the_offset() -> None:
    """Relay pings at t0=100; station (clock +5000 us) receives at 5150, sends at 5160;
    relay receives at 220: offset = ((5150-100) + (5160-220)) / 2 = 4995, delay 110."""
    station, peer = joined_pair()
    peer.tick(100)  # first burst ping is due
    (ping_bytes,) = peer.data_to_send(lambda: 100)
    assert decode(ping_bytes[4:]) == ClockPing(ping_id=0, t0_us=100)
    station.receive_data(ping_bytes, 5150)
    (pong_bytes,) = pump(station, 5160)
    assert pong_bytes == frame(encode(ClockPong(ping_id=0, t0_us=100, t1_us=5150,
                                                t2_us=5160)))
    peer.receive_data(pong_bytes, 220)
    (sampled,) = peer.events_received()
    assert isinstance(sampled, ClockSampled) and sampled.t0_us == 100
    assert peer.clock.offset_us == 4995.0 and peer.clock.delay_us == 110.0
    assert station.counters.pongs_sent == 1


def test_stray_pong_is_counted_not_sampled() -> None:
    counters: Counter[str] = Counter()
    peer = PeerSession("ws", SETTINGS, 0, counters)
    peer.receive_data(encode(HELLO), 1)
    peer.accept(WELCOME, 2)
    peer.receive_data(encode(ClockPong(ping_id=42, t0_us=1, t1_us=2, t2_us=3)), 5)
    assert peer.events_received() == [HelloReceived(HELLO)] and counters["stray_pong"] == 1


def test_a_pong_with_impossible_times_is_not_sampled() -> None:
    """A pong whose station times are 2**63 - 1 made the offset ~9e18 us, and the next
    message's delay overflowed the relay's ledgers. A station clock more than a century from
    the relay's is a client's bug: the pong is counted as stray, not sampled."""
    counters: Counter[str] = Counter()
    peer = PeerSession("tcp", SETTINGS, 0, counters)
    peer.receive_data(frame(encode(HELLO)), 1)
    peer.accept(WELCOME, 2)
    peer.events_received()
    peer.tick(100)
    peer.data_to_send(lambda: 100)  # ping 0, t0 = 100
    wild = 2**63 - 1
    peer.receive_data(frame(encode(ClockPong(ping_id=0, t0_us=100, t1_us=wild,
                                             t2_us=wild))), 220)
    assert peer.events_received() == [] and counters["stray_pong"] == 1
    assert peer.clock.offset_us is None
    peer.tick(112)
    peer.data_to_send(lambda: 300)  # ping 1: an ordinary clock (1,000 s ahead) is sampled
    peer.receive_data(frame(encode(ClockPong(ping_id=1, t0_us=300, t1_us=10**9,
                                             t2_us=10**9))), 400)
    (sampled,) = peer.events_received()
    assert isinstance(sampled, ClockSampled) and peer.clock.offset_us == 10**9 - 350


def test_ping_burst_then_interval_and_stats_due() -> None:
    _, peer = joined_pair()  # accepted at t=2: burst of 2 spaced 10, then every 100
    pings = []
    stats_due = []
    for t in range(2, 400):
        if peer.tick(t):
            stats_due.append(t)
        pings += [decode(d[4:]).t0_us for d in peer.data_to_send(itertools.repeat(t).__next__)]  # type: ignore[attr-defined]
    assert pings == [2, 12, 122, 222, 322]
    # the first stats right after the burst (the stations wait for offsets), then every 50
    assert stats_due == [22, 72, 122, 172, 222, 272, 322, 372]


def _burst_pings(peer: PeerSession, station: StationSession | None, rtt_us: int,
                 until_us: int) -> list[int]:
    """Send times of the relay's pings; the station answers each after ``rtt_us``."""
    pings: list[int] = []
    in_flight: list[tuple[int, bytes]] = []
    for t in range(2, until_us):
        peer.tick(t)
        for data in peer.data_to_send(itertools.repeat(t).__next__):
            msg = decode(data[4:])
            if isinstance(msg, ClockPing):
                pings.append(t)
                if station is not None:
                    station.receive_data(data, t + rtt_us // 2)
                    in_flight += [(t + rtt_us, d) for d in pump(station, t + rtt_us // 2)]
        for due, d in [x for x in in_flight if x[0] == t]:
            peer.receive_data(d, due)
        in_flight = [x for x in in_flight if x[0] != t]
    return pings


def test_the_burst_goes_on_while_the_offset_is_uncertain() -> None:
    """Pongs 40 ms round trip (a loaded host): each bounds the offset to +-20 ms, wider
    than the 10 ms wanted, so the burst goes on (to settle_max_pings) instead of leaving
    the stations without a usable offset until the next periodic ping; with 2 ms round
    trips it ends after ping_burst pings, as before."""
    settings = PeerSettings(ping_burst=3, ping_burst_spacing_us=20_000,
                            ping_interval_us=1_000_000, settle_uncertainty_us=10_000,
                            settle_max_pings=8)

    def pair() -> tuple[StationSession, PeerSession]:
        station = StationSession(HELLO, send_queue_size=4, receive_queue_size=8)
        peer = PeerSession("tcp", settings, now_us=0)
        peer.receive_data(station.connect("tcp", 0), 1)
        peer.events_received()
        peer.accept(WELCOME, 2)
        for data in peer.data_to_send(lambda: 3):
            station.receive_data(data, 4)
        station.events_received()
        return station, peer

    station, peer = pair()
    slow = _burst_pings(peer, station, 40_000, 900_000)
    assert len(slow) == 8 and slow[-1] - slow[0] == 7 * 20_000
    events = peer.events_received()
    assert [type(e).__name__ for e in events] == ["ClockSampled"] * 8, events
    assert all(isinstance(e, ClockSampled) and e.settling for e in events)
    station, peer = pair()
    fast = _burst_pings(peer, station, 2_000, 900_000)
    assert len(fast) == 3
    _, peer = pair()  # nobody answers: the cap holds
    assert len(_burst_pings(peer, None, 0, 900_000)) == 8


# --------------------------------------------------------------------------- streams


def test_latest_wins_replaces_unsent_state_and_counts_a_drop() -> None:
    station, peer = joined_pair()
    for seq in range(3):
        assert station.send(PlatformState(seq=seq, ts_us=seq))
    assert station.pending_sends == 1 and station.counters.stale_dropped_tx == 2
    (data,) = pump(station, 10)
    assert station.pending_sends == 0
    assert data == frame(encode(PlatformState(seq=2, ts_us=2)))
    peer.receive_data(data, 20)
    assert peer.events_received() == [DataReceived(PlatformState(seq=2, ts_us=2), 20)]


@given(st.lists(st.booleans(), min_size=1, max_size=60))
def test_through_the_send_queue_every_written_state_starts_at_the_last_written(
        takes: list[bool]) -> None:
    # the uplink stamps each message with its predecessor's sample; whichever the station's
    # own latest-wins slot replaces, what is written names the sample of what was written
    # before it (the first written names the first message's sample, the known part of its
    # wait; none when it is the first message, which had none)
    station, _ = joined_pair()
    written: list[PlatformState] = []
    previous: int | None = None
    for seq, take in enumerate(takes, start=1):
        capture = 1_000 * seq
        assert station.send(motion_state(seq, previous, capture))
        previous = capture
        if take or seq == len(takes):
            written += [m for m in (decode(d[HEADER.size:]) for d in pump(station, capture))
                        if isinstance(m, PlatformState)]
    assert written and written[-1].seq == len(takes)
    assert motion_of(written[0]) == (None if written[0].seq == 1 else 1_000)
    for before, after in itertools.pairwise(written):
        assert motion_of(after) == before.ts_us


def test_the_send_queue_carries_a_replaced_unsent_state_or_frame() -> None:
    station, _ = joined_pair()
    assert station.send(motion_state(1, 1_000, 2_000))
    pump(station, 1)  # written: the next one keeps its own stamp
    assert station.send(motion_state(2, 2_000, 3_000))
    (data,) = pump(station, 2)
    assert motion_of(decode(data[HEADER.size:])) == 2_000  # type: ignore[arg-type]
    # replaced unsent: its successor starts where it started
    assert station.send(motion_state(3, 3_000, 4_000))
    assert station.send(motion_state(4, 4_000, 5_000))
    (data,) = pump(station, 3)
    assert decode(data[HEADER.size:]).hops == motion_state(4, 3_000, 5_000).hops  # type: ignore[attr-defined]
    # a successor whose sender broke the chain keeps none
    assert station.send(motion_state(5, 5_000, 6_000))
    assert station.send(motion_state(6, None, 7_000))
    (data,) = pump(station, 3)
    assert motion_of(decode(data[HEADER.size:])) is None  # type: ignore[arg-type]
    # a tactile frame replaced unsent (the remote's queue) hands its start on too
    for seq in (1, 2):
        assert station.send(motion_frame(seq, seq * 10_000 - 4_000, seq * 10_000))
    (data,) = pump(station, 4)
    sent = decode(data[HEADER.size:])
    assert isinstance(sent, TactileFrame) and sent.seq == 2 and motion_of(sent) == 6_000
    # one written is not carried from
    assert station.send(motion_frame(3, 26_000, 30_000))
    (data,) = pump(station, 4)
    assert motion_of(decode(data[HEADER.size:])) == 26_000  # type: ignore[arg-type]
    # a reconnect drops what was queued: nothing is carried from it
    assert station.send(motion_state(7, 7_000, 8_000))
    assert station.connection_lost()
    peer = PeerSession("tcp", SETTINGS, now_us=0)
    peer.receive_data(station.connect("tcp", 10), 11)
    peer.accept(WELCOME, 12)
    for data in peer.data_to_send(lambda: 13):
        station.receive_data(data, 14)
    assert station.counters.dropped_on_reconnect == 1 and station.pending_sends == 0
    assert station.send(motion_state(8, 8_000, 9_000))
    (data,) = pump(station, 5)
    assert motion_of(decode(data[HEADER.size:])) == 8_000  # type: ignore[arg-type]


def test_send_returns_the_state_as_queued_and_a_refused_one_changes_nothing() -> None:
    station, _ = joined_pair()
    first = station.send(motion_state(1, 1_000, 2_000))
    assert first == motion_state(1, 1_000, 2_000)
    # an invalid state is refused before anything is queued or remembered
    with pytest.raises(LocalProtocolError):
        station.send(PlatformState(seq=-1, ts_us=3_000, hops=motion_state(2, 2_000, 3_000).hops))
    queued = station.send(motion_state(3, 3_000, 4_000))
    assert isinstance(queued, PlatformState) and motion_of(queued) == 1_000  # not the refused one
    (data,) = pump(station, 1)
    assert decode(data[HEADER.size:]) == queued


def test_the_inbox_carries_a_platform_state_replaced_unread() -> None:
    # a state the station's reader never took is shown first by the newer one that replaced it
    station, _ = joined_pair()
    for seq in (1, 2, 3):
        station.receive_data(frame(encode(motion_state(seq, 1_000 * seq, 1_000 * seq + 1_000))),
                             10 + seq)
    got = station.next_message()
    assert isinstance(got, PlatformState) and got.seq == 3 and motion_of(got) == 1_000
    station.receive_data(frame(encode(motion_state(4, 4_000, 5_000))), 20)
    got = station.next_message()
    assert isinstance(got, PlatformState) and motion_of(got) == 4_000  # its predecessor was read


def test_the_inbox_carries_a_tactile_frame_replaced_unread() -> None:
    # the local station's inbox: a compact delta its reader never took is shown first by
    # the newer one; a state arriving between them (another stream) changes nothing
    station, _ = joined_pair()
    encoder = TactileEncoder(CodecSettings())
    key, *deltas = [encoder.encode(motion_frame(seq, 1_000 * seq, 1_000 * seq + 1_000))
                    for seq in (1, 2, 3)]
    assert key.key and not any(d.key for d in deltas)
    station.receive_data(frame(encode(key)), 10)
    got = station.next_message()
    assert isinstance(got, TactileCompact) and got.key and got.seq == 1
    station.receive_data(frame(encode(deltas[0])), 11)
    station.receive_data(frame(encode(motion_state(9, 7_000, 8_000))), 12)
    station.receive_data(frame(encode(deltas[1])), 13)
    got = station.next_message()  # the replacement takes its own place in arrival order
    assert isinstance(got, PlatformState) and motion_of(got) == 7_000
    got = station.next_message()
    assert isinstance(got, TactileCompact) and got.seq == 3 and motion_of(got) == 2_000


def test_a_compact_key_frame_is_never_replaced_by_a_delta() -> None:
    # the deltas need it: a station's inbox and send queue give it a slot of its own (a
    # delta that replaced it could not be decoded until the sender's next key frame)
    encoder = TactileEncoder(CodecSettings())
    key, *deltas = [encoder.encode(motion_frame(seq, 1_000 * seq, 1_000 * seq + 1_000))
                    for seq in (1, 2, 3)]
    station, _ = joined_pair()
    for i, msg in enumerate((key, *deltas)):
        station.receive_data(frame(encode(msg)), 10 + i)
    first, second = station.next_message(), station.next_message()
    assert isinstance(first, TactileCompact) and first.key and first.seq == 1
    assert station.next_message() is None
    assert isinstance(second, TactileCompact) and second.seq == 3
    assert motion_of(second) == 2_000  # from the delta it replaced, not from the key frame
    station, _ = joined_pair()
    for msg in (key, *deltas):
        assert station.send(msg) is not None
    sent = [decode(d[HEADER.size:]) for d in pump(station, 5)]
    assert [m.seq for m in sent] == [1, 3]  # type: ignore[attr-defined]
    assert encode(sent[0]) == encode(key) and motion_of(sent[1]) == 2_000  # type: ignore[arg-type]


def test_a_key_frame_replaces_a_waiting_key_frame_and_the_delta_it_shows_first() -> None:
    # key 1, delta 2, key 3, delta 4, key 5 (a delta after each key frame)
    encoder = TactileEncoder(CodecSettings(key_every=2))
    stream = [encoder.encode(motion_frame(seq, 1_000 * seq, 1_000 * seq + 1_000))
              for seq in range(1, 6)]
    assert [m.key for m in stream] == [True, False, True, False, True]
    station, _ = joined_pair()
    assert all(station.send(ArmCommand(seq=i, ts_us=0)) for i in range(4))
    assert station.outbox.ordered_full
    for msg in stream[:3]:  # key 3 replaces key 1 and delta 2, and never waits for room
        assert station.send(msg) is not None
    assert station.counters.stale_dropped_tx == 2
    sent = [decode(d[HEADER.size:]) for d in pump(station, 5)]
    assert [(m.TYPE, m.seq) for m in sent] == [("arm_command", i) for i in range(4)] + [  # type: ignore[attr-defined]
        ("tactile_compact", 3)]
    assert motion_of(sent[-1]) == 1_000  # type: ignore[arg-type]  # where key 1 started
    # the inbox: delta 4 waits, key 5 comes: key 5 shows it first and takes its start
    station, _ = joined_pair()
    station.receive_data(frame(encode(stream[2])), 10)
    assert station.next_message().seq == 3  # type: ignore[union-attr]
    for i, msg in enumerate(stream[3:]):
        station.receive_data(frame(encode(msg)), 11 + i)
    got = station.next_message()
    assert isinstance(got, TactileCompact) and got.key and got.seq == 5
    assert motion_of(got) == 4_000 and station.next_message() is None
    assert station.counters.stale_dropped_rx == 1


def test_ordered_queue_bound_refuses_and_keeps_order() -> None:
    station, _ = joined_pair()
    assert all(station.send(ArmCommand(seq=i, ts_us=0)) for i in range(4))
    assert station.send(ArmCommand(seq=4, ts_us=0)) is None
    assert [decode(d[4:]).seq for d in pump(station, 1)] == [0, 1, 2, 3]  # type: ignore[attr-defined]


def test_relay_outbox_stamps_relay_hops_at_encoding() -> None:
    _, peer = joined_pair("ws")
    sent: list[int] = []
    msg = PlatformState(seq=5, ts_us=10, hops=(Hop("local", "send", 11),))
    peer.outbox.put_latest("p", msg, 20, on_send=lambda p, t: sent.append(t))
    (data,) = peer.data_to_send(lambda: 30)
    assert data == encode(PlatformState(seq=5, ts_us=10, hops=(
        Hop("local", "send", 11), Hop("relay", "relay_in", 20), Hop("relay", "relay_out", 30))))
    assert sent == [30]
    full = PlatformState(seq=1, ts_us=1, hops=tuple(Hop("local", "s", i) for i in range(MAX_HOPS)))
    peer.outbox.put_ordered(full, forwarded=True, t_in_us=20)
    hops = decode(peer.data_to_send(lambda: 30)[0]).hops  # type: ignore[attr-defined]
    assert len(hops) == MAX_HOPS and hops[-1] == Hop("relay", "relay_out", 30)


def test_station_inbox_latest_wins_and_hop_stamp() -> None:
    station, _ = joined_pair("ws")
    for seq in range(3):
        station.receive_data(encode(PlatformState(seq=seq, ts_us=0)), 100 + seq)
    station.receive_data(encode(ArmCommand(seq=9, ts_us=0)), 200)
    assert station.counters.stale_dropped_rx == 2
    assert station.next_message() == PlatformState(seq=2, ts_us=0,
                                                   hops=(Hop("local", "station_rx", 102),))
    assert station.next_message() == ArmCommand(seq=9, ts_us=0,
                                                hops=(Hop("local", "station_rx", 200),))
    assert station.next_message() is None


# --------------------------------------------------------------------------- errors


def test_malformed_frame_is_rejected_with_its_type_and_code() -> None:
    station, peer = joined_pair()
    peer.receive_data(frame(b"\xc1"), 5)  # 0xc1 is never valid msgpack
    (sent,) = peer.data_to_send(lambda: 6)
    err = decode(sent[4:])
    assert isinstance(err, Error) and err.code == "malformed" and not err.fatal
    assert MalformedMessageError.close_code == 1007
    station.receive_data(frame(b"\xc1"), 7)
    (event,) = station.events_received()
    assert isinstance(event, Rejected) and isinstance(event.error, MalformedMessageError)
    assert station.counters.rejected_rx == 1 and station.is_open


def test_broken_length_prefix_is_fatal() -> None:
    station, peer = joined_pair()
    peer.receive_data(HEADER.pack(0), 5)
    assert peer.events_received() == [Closing(1007, "malformed")]
    station.receive_data(HEADER.pack(0), 5)
    (event,) = station.events_received()
    assert isinstance(event, Failed) and event.error.code == "malformed"


def test_error_budget_exhausted_closes_with_1008() -> None:
    counters: Counter[str] = Counter()
    peer = PeerSession("ws", SETTINGS, 0, counters)
    peer.receive_data(encode(HELLO), 1)
    peer.accept(WELCOME, 2)
    peer.events_received()
    for _ in range(SETTINGS.bad_message_budget + 1):
        peer.receive_data(encode(HELLO), 3)
    assert peer.events_received() == [Closing(1008, "too_many_errors")]
    sent = [decode(d) for d in peer.data_to_send(lambda: 4)]
    codes = [(m.code, m.fatal) for m in sent if isinstance(m, Error)]
    assert codes == [("already_joined", False)] * 3 + [("too_many_errors", True)]
    assert counters["bad_already_joined"] == 4 and counters["fatal_too_many_errors"] == 1
    peer.receive_data(encode(HELLO), 5)  # closed: ignored
    assert peer.events_received() == []


def test_a_data_message_without_room_for_the_relay_stamps_is_refused_on_receipt() -> None:
    """An arm command of exactly max_message_bytes was accepted, then the relay's stamps
    pushed it over the limit and it was dropped unsaid. One that leaves less than
    FORWARD_ROOM_BYTES is refused at once, with an error naming its stream and seq."""
    import dataclasses

    from shared.protocol.peer_session import FORWARD_ROOM_BYTES

    limit = 4096
    small = dataclasses.replace(SETTINGS, max_message_bytes=limit, ping_burst=0)
    counters: Counter[str] = Counter()
    peer = PeerSession("tcp", small, 0, counters)
    peer.receive_data(frame(encode(HELLO)), 1)
    peer.accept(WELCOME, 2)
    peer.events_received()
    peer.data_to_send(lambda: 3)

    def padded(seq: int, size: int) -> bytes:  # an unknown key pads it (forwarded as is)
        body = {"v": 1, "type": "arm_command", "seq": seq, "ts": 1, "hops": [],
                "action": "stop", "note": ""}
        body["note"] = "x" * (size - len(msgpack.packb(body)) - 2)  # str8 -> str16: +2
        data = msgpack.packb(body)
        assert len(data) == size
        return data

    fits, full = padded(1, limit - FORWARD_ROOM_BYTES), padded(2, limit)
    peer.receive_data(frame(fits) + frame(full), 10)
    (received,) = peer.events_received()
    assert isinstance(received, DataReceived) and received.message.seq == 1
    (err,) = [decode(d[4:]) for d in peer.data_to_send(lambda: 11)]
    assert isinstance(err, Error) and not err.fatal
    assert (err.code, err.stream, err.seq) == ("too_large_to_forward", "arm_command", 2)
    assert counters["too_large_to_forward"] == 1 and not peer.closing
    # not counted against the bad-message budget (found by review: a station whose sender
    # allows the whole limit was closed after 21 such messages, and reconnected in a loop)
    assert peer.bad_messages == 0
    for seq in range(3, 3 + 2 * peer.settings.bad_message_budget):
        peer.receive_data(frame(padded(seq, limit)), 12)
    assert not peer.closing
    # the one that fits is forwarded with the relay's stamps (and a clustered relay's two)
    relay = PeerSession("tcp", small, 0)
    relay.outbox.put_ordered(received.message, forwarded=True, t_in_us=2**62,
                             mid_hops=(("relay", "nats_out", 2**62), ("relay", "nats_in", 2**62)),
                             wire=received.wire)
    (out,) = relay.data_to_send(lambda: 2**62)
    assert len(out) - 4 <= limit


def test_observer_is_read_only_but_may_report_stats() -> None:
    peer = PeerSession("ws", SETTINGS, 0)
    peer.receive_data(encode(Hello(role="observer", session="lab1", token="t")), 1)
    peer.accept(Welcome(session="lab1", role="observer"), 2)
    peer.events_received()
    peer.receive_data(encode(PlatformState(seq=1, ts_us=1)), 3)
    peer.receive_data(encode(Stats(scope="local", time_us=1, metrics={"a": 1})), 3)
    assert peer.events_received() == [StatsReported({"a": 1})]
    errors = [decode(d) for d in peer.data_to_send(lambda: 4)]
    assert [e.code for e in errors if isinstance(e, Error)] == ["read_only"]
    assert peer.next_tick_us() == 52  # no pings for observers, only stats


def test_bye_closes_with_1000() -> None:
    station, peer = joined_pair()
    station.send_bye("done")
    for data in pump(station, 5):
        peer.receive_data(data, 6)
    assert peer.events_received() == [Closing(1000, "bye")]


def test_silence_past_the_timeout_gives_the_liveness_event() -> None:
    station = StationSession(HELLO, connect_timeout_us=500, liveness_timeout_us=1000)
    assert station.check_liveness(10**9) is None  # not connected: nothing to time out
    station.connect("ws", 0)
    assert station.check_liveness(499) is None
    assert station.check_liveness(500) == LinkSilent(500, False)
    station.receive_data(encode(WELCOME), 600)
    station.events_received()
    assert station.deadline_us() == 1600
    assert station.check_liveness(1599) is None
    assert station.check_liveness(1600) == LinkSilent(1000, True)
    station.reading_resumed(1700)  # reading was paused (full inbox): silence counts from now
    assert station.deadline_us() == 2700 and station.check_liveness(2000) is None
    assert station.connection_lost() and station.counters.connection_losses == 1


# --------------------------------------------------------------------------- property


@settings(max_examples=50, deadline=None)
@given(cuts=st.lists(st.integers(0, 5000), max_size=20))
def test_any_split_of_the_stream_gives_the_same_events(cuts: list[int]) -> None:
    """However the relay's TCP stream is chunked, the station ends up in the same state."""
    sender = StationSession(Hello(role="remote", session="lab1", token="t"))
    sender.connect("tcp", 0)
    sender.receive_data(frame(encode(Welcome(session="lab1", role="remote"))), 0)
    for seq in range(6):
        sender.send(ArmCommand(seq=seq, ts_us=seq))
        sender.send(PlatformState(seq=seq, ts_us=seq))
    stream = frame(encode(Welcome(session="lab1", role="local"))) + b"".join(pump(sender, 1))
    receiver = StationSession(HELLO)
    receiver.connect("tcp", 0)
    points = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    for a, b in itertools.pairwise(points):
        receiver.receive_data(stream[a:b], 7)
    assert [type(e) for e in receiver.events_received()] == [Welcomed]
    got = []
    while (m := receiver.next_message()) is not None:
        got.append((m.TYPE, m.seq))  # type: ignore[attr-defined]
    assert got == [*(("arm_command", s) for s in range(6)), ("platform_state", 5)]


@settings(max_examples=60, deadline=None)
@given(rate=st.floats(1.0, 1e5), burst=st.integers(1, 10_000),
       steps=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 5000)), max_size=50))
def test_token_bucket_never_grants_more_than_burst_plus_refill(
        rate: float, burst: int, steps: list[tuple[int, int]]) -> None:
    from shared.protocol.ratelimit import TokenBucket

    bucket = TokenBucket(rate, burst, 0)
    t = granted = 0
    for dt, count in steps:
        t += dt
        got = bucket.take(count, t)
        assert 0 <= got <= count
        granted += got
    assert granted <= burst + rate * t / 1e6 + 1e-6


def _windows_hold(times: list[int], granted: list[int], rate: float, burst: int) -> None:
    """Every window [t_i, t_j] of arrivals got at most burst + rate * (t_j - t_i)."""
    for i in range(len(times)):
        total = 0
        for j in range(i, len(times)):
            total += granted[j]
            assert total <= burst + rate * (times[j] - times[i]) / 1e6 + 1e-6, (
                f"{total} granted in [{times[i]}, {times[j]}] us")


@settings(max_examples=100, deadline=None)
@given(rate=st.floats(1.0, 1e4), burst=st.integers(1, 10_000),
       steps=st.lists(st.tuples(st.integers(0, 10**7), st.integers(0, 20_000)), max_size=40))
def test_token_bucket_grants_at_most_burst_plus_refill_in_any_window(
        rate: float, burst: int, steps: list[tuple[int, int]]) -> None:
    """The refill of an idle time was credited before the cap: after a quiet minute the
    bucket granted twice its burst at one instant."""
    from shared.protocol.ratelimit import TokenBucket

    bucket = TokenBucket(rate, burst, 0)
    t, times, granted = 0, [], []
    for dt, count in steps:
        t += dt
        times.append(t)
        granted.append(bucket.take(count, t))
    _windows_hold(times, granted, rate, burst)


@settings(max_examples=60, deadline=None)
@given(rate=st.floats(10.0, 1e4), burst=st.integers(1, 200),
       steps=st.lists(st.tuples(st.integers(0, 3 * 10**6), st.integers(1, 250)), max_size=30))
def test_the_relay_rate_limit_grants_at_most_burst_plus_refill_in_any_window(
        rate: float, burst: int, steps: list[tuple[int, int]]) -> None:
    """Through the relay's lazy charging (a counter, the bucket read now and then), at random
    arrival times and chunk sizes: no window gets more than ``burst + rate * T``."""
    import dataclasses

    limited = dataclasses.replace(SETTINGS, rate_limit_per_s=rate, rate_limit_burst=burst,
                                  ping_burst=0, bad_message_budget=10**6)
    peer = PeerSession("tcp", limited, now_us=0)
    peer.receive_data(frame(encode(HELLO)), 0)
    peer.accept(WELCOME, 0)
    peer.events_received()
    seq = itertools.count()
    t, times, granted = 0, [], []
    for dt, count in steps:
        t += dt
        peer.receive_data(b"".join(frame(encode(PlatformState(seq=next(seq), ts_us=1)))
                                   for _ in range(count)), t)
        times.append(t)
        granted.append(sum(isinstance(e, DataReceived) for e in peer.events_received()))
    _windows_hold(times, granted, rate, burst)


def test_a_steady_stream_under_the_rate_is_never_limited() -> None:
    """The lazy charging is never much stricter than an exact bucket: streams under the rate,
    one message at a time or in chunks of up to half the burst, are never refused."""
    import dataclasses

    limited = dataclasses.replace(SETTINGS, rate_limit_per_s=1000.0, rate_limit_burst=100,
                                  ping_burst=0)
    one = frame(encode(PlatformState(seq=1, ts_us=1)))
    for period_us, chunk, extra in ((1_100, 1, 0), (1_010, 1, 0), (50_000, 45, 0),
                                    (10_000, 9, 0), (1_100, 1, 45)):
        counters: Counter[str] = Counter()
        peer = PeerSession("tcp", limited, 0, counters)
        peer.receive_data(frame(encode(HELLO)), 0)
        peer.accept(WELCOME, 0)
        for i in range(1, 5_000):
            peer.receive_data(one * chunk, i * period_us)
            if extra and i % 1000 == 0:  # now and then a backlog of up to half the burst
                peer.receive_data(one * extra, i * period_us + 100)
        assert counters["rate_limited"] == 0 and not peer.closing, (period_us, chunk, extra)


def test_a_silent_station_is_closed_and_an_observer_is_not() -> None:
    """A station answers every ping; one that sends nothing for silence_timeout_us is a dead
    or blackholed connection and is closed (silent/4005), which frees its role."""
    import dataclasses

    quiet = dataclasses.replace(SETTINGS, silence_timeout_us=500)
    station = StationSession(HELLO, send_queue_size=4, receive_queue_size=8)
    peer = PeerSession("tcp", quiet, now_us=0)
    peer.receive_data(station.connect("tcp", 0), 1)
    peer.accept(WELCOME, 2)
    peer.events_received()
    for t in range(3, 480):
        peer.tick(t)
    assert not peer.closing
    peer.receive_data(frame(encode(ClockPong(ping_id=0, t0_us=2, t1_us=3, t2_us=4))), 480)
    for t in range(480, 981):
        peer.tick(t)
    assert not peer.closing  # 500 us since the last bytes, not more
    peer.tick(1100)
    assert peer.closing and peer.close_code == 4005
    assert [e for e in peer.events_received() if isinstance(e, Closing)] == [
        Closing(4005, "silent")]

    observer = PeerSession("tcp", quiet, now_us=0)
    observer.receive_data(frame(encode(Hello(role="observer", session="lab1", token="t"))), 1)
    observer.accept(Welcome(session="lab1", role="observer"), 2)
    for t in range(3, 5000, 7):
        observer.tick(t)
    assert not observer.closing
