"""Per-stream policy without sockets: latest-wins drops, bounded ordered queue, roles."""

from __future__ import annotations

import itertools

import pytest
from hypothesis import given
from hypothesis import strategies as st

from relay_server.session import Peer, Session
from shared.errors import RoleTakenError
from shared.protocol import ArmCommand, ArmState, Hop, PlatformState, TactileCompact
from shared.protocol.peer_session import Outbox
from tests.support import motion_frame, motion_of, motion_state


def make_peer(pid: int, role: str, limit: int = 4) -> Peer:
    return Peer(peer_id=pid, session_id="s", role=role, name="", transport="tcp",
                outbox=Outbox(limit), window=64)


def test_latest_wins_replaces_unsent_and_counts_drops() -> None:
    session = Session("s", 64)
    local, remote, obs = make_peer(1, "local"), make_peer(2, "remote"), make_peer(3, "observer")
    for p in (local, remote, obs):
        session.join(p)
    for seq in range(10):
        msg = PlatformState(seq=seq, ts_us=seq, position_mm=(0.0, 0.0, float(seq)))
        assert session.route(local, msg, 1000 + seq) is None
    pending = remote.outbox.take()
    assert len(pending) == 1 and pending[0].message.seq == 9  # type: ignore[attr-defined]
    assert pending[0].t_in_us == 1009 and pending[0].forwarded
    ledger = session.directions["local_to_remote"].uplink["platform_state"]
    assert ledger.dropped == {"latest_wins": 9}
    assert len(obs.outbox) == 1 and obs.observer_drops == 9


def test_ordered_queue_is_bounded_and_overflow_is_reported() -> None:
    session = Session("s", 64)
    local, remote = make_peer(1, "local"), make_peer(2, "remote", limit=4)
    session.join(local)
    session.join(remote)
    replies = [session.route(local, ArmCommand(seq=s, ts_us=s, action="stop"), 5)
               for s in range(6)]
    assert replies[:4] == [None] * 4
    assert [r.code for r in replies[4:] if r is not None] == ["queue_full", "queue_full"]
    assert "seq 4" in replies[4].message  # type: ignore[union-attr]
    assert [p.message.seq for p in remote.outbox.take()] == [0, 1, 2, 3]  # type: ignore[attr-defined]
    ledger = session.directions["local_to_remote"].uplink["arm_command"]
    assert ledger.dropped == {"queue_full": 2} and ledger.queue_depth_max == 4


def test_no_peer_and_wrong_direction_and_role_taken() -> None:
    session = Session("s", 64)
    local = make_peer(1, "local")
    session.join(local)
    err = session.route(local, ArmCommand(seq=1, ts_us=1, action="stop"), 5)
    assert err is not None and err.code == "no_peer"
    assert session.route(local, PlatformState(seq=2, ts_us=1), 5) is None  # dropped, counted
    assert session.directions["local_to_remote"].uplink["platform_state"].dropped == {
        "no_peer": 1}
    err = session.route(local, ArmState(seq=1, ts_us=1), 5)
    assert err is not None and err.code == "wrong_direction"
    with pytest.raises(RoleTakenError) as info:
        session.join(make_peer(9, "local"))
    assert info.value.close_code == 4002
    session.leave(local)
    assert session.empty


def test_a_station_the_relay_is_closing_is_no_receiver() -> None:
    """A station the relay has decided to close (``silent``: its outbox is closed) stays in
    the session until its socket's close is over (1-3 s); meanwhile an arm command to it
    was put in the dead outbox: no ``no_peer``, no drop counted. It is now as if no
    station were there."""
    session = Session("s", 64)
    local, remote = make_peer(1, "local"), make_peer(2, "remote")
    session.join(local)
    session.join(remote)
    remote.outbox.closed = True
    err = session.route(local, ArmCommand(seq=7, ts_us=1, action="stop"), 5)
    assert err is not None and (err.code, err.stream, err.seq) == ("no_peer", "arm_command", 7)
    assert session.route(local, PlatformState(seq=1, ts_us=1), 5) is None
    uplink = session.directions["local_to_remote"].uplink
    assert uplink["arm_command"].dropped == {"no_peer": 1}
    assert uplink["platform_state"].dropped == {"no_peer": 1}
    assert len(remote.outbox) == 0


def test_ordered_and_latest_leave_in_arrival_order() -> None:
    box = Outbox(8)
    box.put_ordered(ArmCommand(seq=1, ts_us=0))
    box.put_latest("p", PlatformState(seq=2, ts_us=0), 0)
    box.put_ordered(ArmCommand(seq=3, ts_us=0))
    box.put_latest("p", PlatformState(seq=4, ts_us=0), 0)  # replaces seq 2, takes its new place
    assert [p.message.seq for p in box.take()] == [1, 3, 4]  # type: ignore[attr-defined]
    assert len(box) == 0 and box.take() == []


def test_forwarded_encoding_appends_two_hops_and_keeps_the_hop_limit() -> None:
    from shared.protocol import decode, encode, frame
    from shared.protocol.messages import MAX_HOPS

    relay_hops = (Hop("relay", "relay_in", 20), Hop("relay", "relay_out", 30))
    msg = PlatformState(seq=5, ts_us=10, hops=(Hop("local", "send", 11),))
    data = encode(msg, validate=False, extra_hops=relay_hops)
    assert decode(data) == PlatformState(seq=5, ts_us=10, hops=(Hop("local", "send", 11),
                                                                *relay_hops))
    assert frame(data)[4:] == data
    full = PlatformState(seq=1, ts_us=1, hops=tuple(Hop("local", "s", i) for i in range(MAX_HOPS)))
    hops = decode(encode(full, validate=False, extra_hops=relay_hops)).hops  # type: ignore[attr-defined]
    assert len(hops) == MAX_HOPS and hops[-1] == Hop("relay", "relay_out", 30)


def _compact_stream(n: int) -> list[TactileCompact]:
    """``n`` tactile frames through the real compact encoder (key frame first, then deltas)."""
    import numpy as np

    from shared.protocol import TactileFrame
    from shared.protocol.tactile_codec import TactileEncoder

    enc = TactileEncoder()
    out = []
    base = np.linspace(0.0, 2.0, 36, dtype=np.float32).reshape(6, 6)
    for seq in range(1, n + 1):
        h = base.copy()
        h[seq % 6, 0] += 0.5  # one pin changes: a sparse delta
        out.append(enc.encode(TactileFrame(seq=seq, ts_us=seq * 1000, layers={"height_mm": h})))
    assert [m.key for m in out] == [True] + [False] * (n - 1)
    return out


def test_a_late_joiner_gets_the_key_frame_before_the_first_delta() -> None:
    """The remote sent its key frame while no local station was there (a relay restart:
    the remote came back first). The local joins: before the first delta it is given the
    cached key frame, so it decodes at once instead of waiting for the next key frame."""
    from shared.protocol import TactileFrame
    from shared.protocol.tactile_codec import TactileDecoder

    session = Session("s", 64)
    remote = make_peer(2, "remote", limit=8)
    session.join(remote)
    key, d1, d2 = _compact_stream(3)
    assert isinstance(key, TactileCompact) and key.key and isinstance(d1, TactileCompact)
    assert session.route(remote, key, 10) is None  # nobody to deliver to: cached
    local = make_peer(1, "local", limit=8)
    session.join(local)
    session.route(remote, d1, 20)
    got = [p.message for p in local.outbox.take()]
    assert [(m.seq, m.key) for m in got] == [(1, True), (2, False)]  # type: ignore[attr-defined]
    decoder = TactileDecoder()
    frames = [decoder.decode(m) for m in got if isinstance(m, TactileCompact)]
    assert isinstance(frames[-1], TactileFrame) and frames[-1].seq == 2
    assert session.compact_keys_resent == 1
    session.route(remote, d2, 30)  # the key is not sent twice
    assert [p.message.seq for p in local.outbox.take()] == [3]  # type: ignore[attr-defined]


def test_a_key_frame_is_not_superseded_by_its_deltas_in_the_queue() -> None:
    """Latest-wins would let a delta replace the unsent key frame it needs: key frames go in
    the ordered queue, deltas replace each other only."""
    session = Session("s", 64)
    local, remote = make_peer(1, "local", limit=8), make_peer(2, "remote")
    session.join(local)
    session.join(remote)
    for seq, msg in enumerate(_compact_stream(4)):
        assert session.route(remote, msg, 10 + seq) is None
    assert [p.message.seq for p in local.outbox.take()] == [1, 4]  # type: ignore[attr-defined]
    assert session.compact_keys_resent == 0




@given(st.lists(st.booleans(), min_size=1, max_size=60))
def test_through_a_latest_wins_slot_every_delivered_state_starts_at_the_last_delivered(
        takes: list[bool]) -> None:
    # the station stamps each message with its predecessor's sample; whichever the relay's
    # slot replaces, what the remote gets names the sample of what it got before (the first
    # delivered names the first message's sample, the known part of its wait, or none when
    # it is the first message, which had none)
    session = Session("s", 64)
    local, remote = make_peer(1, "local"), make_peer(2, "remote")
    session.join(local)
    session.join(remote)
    delivered: list[PlatformState] = []
    previous: int | None = None
    for seq, take in enumerate(takes, start=1):
        capture = 1_000 * seq
        assert session.route(local, motion_state(seq, previous, capture), capture + 10) is None
        previous = capture
        if take or seq == len(takes):
            delivered += [p.message for p in remote.outbox.take()
                          if isinstance(p.message, PlatformState)]
    assert delivered and delivered[-1].seq == len(takes)
    assert motion_of(delivered[0]) == (None if delivered[0].seq == 1 else 1_000)
    for before, after in itertools.pairwise(delivered):
        assert motion_of(after) == before.ts_us


def test_a_carried_replacement_is_encoded_anew_not_sent_as_received() -> None:
    # the relay forwards a message's received bytes with its own stamps spliced in; one whose
    # local.motion it changed must not go out with the old stamp in those bytes
    import msgpack

    from shared.protocol.codec import decode, encode
    from shared.protocol.forward import locate_hops

    session = Session("s", 64)
    local, remote = make_peer(1, "local"), make_peer(2, "remote")
    session.join(local)
    session.join(remote)
    first, second = motion_state(1, 1_000, 2_000), motion_state(2, 2_000, 3_000)
    wires = []
    for msg in (first, second):
        data = encode(msg)
        wires.append(locate_hops(data, msgpack.unpackb(data)))
    assert all(w is not None for w in wires)
    session.route(local, first, 2_010, wire=wires[0])
    session.route(local, second, 3_010, wire=wires[1])
    (pending,) = remote.outbox.take()
    assert pending.wire is None and motion_of(pending.message) == 1_000  # type: ignore[arg-type]
    # and a replacement that keeps its stamps (its sender broke the chain) keeps its bytes
    fourth = motion_state(4, None, 5_000)
    data = encode(fourth)
    session.route(local, motion_state(3, 3_000, 4_000), 4_010)
    session.route(local, fourth, 5_010, wire=locate_hops(data, msgpack.unpackb(data)))
    (pending,) = remote.outbox.take()
    assert pending.wire is not None and decode(pending.wire.data) == fourth


def test_a_tactile_frame_that_replaces_one_starts_where_that_one_started() -> None:
    # on the way back too: the local is first shown the replaced frame's movements by the
    # frame that replaced it, encoded anew; compact deltas replace each other the same way
    import msgpack

    from shared.protocol.codec import decode, encode
    from shared.protocol.forward import locate_hops
    from shared.protocol.tactile_codec import CodecSettings, TactileEncoder

    session = Session("s", 64)
    local, remote = make_peer(1, "local"), make_peer(2, "remote")
    session.join(local)
    session.join(remote)
    frames = [motion_frame(seq, seq * 10_000 - 4_000, seq * 10_000) for seq in (1, 2)]
    for frame in frames:
        data = encode(frame)
        session.route(remote, frame, frame.ts_us + 500,
                      wire=locate_hops(data, msgpack.unpackb(data)))
    (pending,) = local.outbox.take()
    assert pending.wire is None and pending.message.seq == 2  # type: ignore[attr-defined]
    assert motion_of(pending.message) == 6_000  # type: ignore[arg-type]
    assert pending.message.hops[1:] == frames[1].hops[1:]  # type: ignore[attr-defined]
    encoder = TactileEncoder(CodecSettings())
    stream = [encoder.encode(motion_frame(seq, seq * 10_000 - 4_000, seq * 10_000))
              for seq in (3, 4, 5)]
    assert stream[0].key and not stream[1].key and not stream[2].key
    for msg in stream:
        data = encode(msg)
        session.route(remote, msg, msg.ts_us + 500,
                      wire=locate_hops(data, msgpack.unpackb(data)))
    key, delta = local.outbox.take()
    assert key.wire is not None and decode(key.wire.data) == stream[0]  # ordered, untouched
    assert delta.message.seq == 5 and motion_of(delta.message) == 36_000  # type: ignore[attr-defined,arg-type]


def test_a_restarted_station_is_a_new_sequence_run_for_the_ledger() -> None:
    """Found by review: a station restarted from seq 1 had its new run counted out_of_order
    and its losses hidden; the session tells the ledger when a new connection sends."""
    session = Session("s", 64)
    first, remote = make_peer(1, "local"), make_peer(2, "remote")
    for p in (first, remote):
        session.join(p)
    first.clock.add_timestamps(0, 0, 0, 0)
    for seq in (s for s in range(1, 41) if s != 20):  # one lost
        session.route(first, PlatformState(seq=seq, ts_us=seq, position_mm=(0.0, 0.0, 1.0)), 50)
    session.leave(first)
    again = make_peer(3, "local")  # the restarted process: a new connection, seqs from 1
    session.join(again)
    again.clock.add_timestamps(0, 0, 0, 0)
    for seq in (s for s in range(1, 31) if s != 10):  # one more lost
        session.route(again, PlatformState(seq=seq, ts_us=seq, position_mm=(0.0, 0.0, 1.0)), 60)
    ledger = session.directions["local_to_remote"].uplink["platform_state"]
    assert (ledger.lost, ledger.out_of_order, ledger.seq_resets) == (2, 0, 1)
