"""hypothesis property tests of the fuzz targets' promises (a third engine beside atheris and
the builtin mutator: shrinking gives the smallest failing input), and a stateful test of one
relay connection against the doc's model of it."""

from __future__ import annotations

import random
from collections import Counter

import msgpack
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule

from lab.fuzz.engine import seeds_for
from lab.fuzz.mutate import mutate_message
from lab.fuzz.registry import TARGETS
from lab.fuzz.script import Kind, Op, dump, parse
from lab.fuzz.seeds import FUZZ_SECRET, hello_for, seed_messages
from lab.fuzz.sessions import PEER_SETTINGS, PeerModel, _client_decode, _peer_events
from lab.fuzz.targets import reference_deframe
from relay_server.auth import TokenAuthority
from shared.protocol import LengthPrefixDecoder, encode, frame
from shared.protocol.peer_session import PeerSession

FAST = settings(max_examples=150, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
SEEDS = seed_messages()

#: a message: a real one, or a real one mutated by the structure mutator
messages = st.builds(lambda base, seed, n: _mutated(base, seed, n), st.sampled_from(SEEDS),
                     st.integers(0, 2**32), st.integers(0, 3))


def _mutated(base: bytes, seed: int, n: int) -> bytes:
    rng = random.Random(seed)
    for _ in range(n):
        base = mutate_message(rng, base)
    return base


ops = st.one_of(
    st.builds(lambda p, peer: Op(Kind.MSG, peer, p), messages, st.integers(0, 3)),
    st.builds(lambda p, peer: Op(Kind.RAW, peer, p), st.binary(max_size=64), st.integers(0, 3)),
    st.builds(lambda v: Op(Kind.TIME, value=v), st.sampled_from((1, 20_000, 1_000_000,
                                                                  5_000_000))),
    st.builds(lambda v: Op(Kind.STEP, value=v), st.integers(-2**31, 2**31 - 1)),
    st.builds(lambda peer: Op(Kind.TICK, peer), st.integers(0, 3)),
    st.builds(lambda peer: Op(Kind.FLUSH, peer), st.integers(0, 3)),
    st.builds(lambda peer: Op(Kind.CLOSE, peer), st.integers(0, 3)),
)


def scripts(roles: tuple[str, ...] = ("local",)) -> st.SearchStrategy[bytes]:
    """A hello per peer first (most of the time), then any operations."""
    hellos = [Op(Kind.MSG, i, encode(hello_for(r))) for i, r in enumerate(roles)]
    return st.builds(lambda o, rest, keep: dump(o, (hellos if keep else []) + rest),
                     st.integers(0, 255), st.lists(ops, max_size=40), st.booleans())


@FAST
@given(st.binary(max_size=512))
def test_decoder_any_bytes(data: bytes) -> None:
    TARGETS["decoder"](data)


@FAST
@given(messages)
def test_decoder_mutated_messages(data: bytes) -> None:
    TARGETS["decoder"](data)


@FAST
@given(payloads=st.lists(st.binary(min_size=1, max_size=300), max_size=8),
       cuts=st.lists(st.integers(1, 97), min_size=1, max_size=8))
def test_framing_round_trip_in_any_chunks(payloads: list[bytes], cuts: list[int]) -> None:
    """Framed payloads come back whole and in order, whatever the chunking."""
    stream = b"".join(frame(p) for p in payloads)
    dec, got, pos, i = LengthPrefixDecoder(300), [], 0, 0
    while pos < len(stream):
        size = cuts[i % len(cuts)]
        got += dec.feed(stream[pos:pos + size])
        pos, i = pos + size, i + 1
    assert got == payloads == reference_deframe(stream, 300)[0]
    assert dec.buffered == 0


@FAST
@given(st.binary(max_size=300))
def test_framing_any_bytes(data: bytes) -> None:
    TARGETS["framing"](data)


@FAST
@given(scripts())
def test_station_session_scripts(data: bytes) -> None:
    TARGETS["station"](data)


@FAST
@given(st.sampled_from(("local", "remote", "observer")).flatmap(lambda r: scripts((r,))))
def test_peer_session_scripts(data: bytes) -> None:
    TARGETS["peer"](data)


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(scripts(("local", "remote", "observer", "local")))
def test_relay_scripts(data: bytes) -> None:
    TARGETS["relay"](data)


def test_scripts_survive_a_dump_parse_round_trip() -> None:
    for data in seeds_for("relay") + seeds_for("peer"):
        s = parse(data)
        assert parse(dump(s.options, s.ops)) == s


class OneRelayConnection(RuleBasedStateMachine):
    """A relay-side PeerSession and the doc's model of it, driven step by step."""

    def __init__(self) -> None:
        super().__init__()
        self.now = 1_700_000_000_000_000
        auth = TokenAuthority({}, FUZZ_SECRET)
        self.ps = PeerSession("ws", PEER_SETTINGS, self.now, Counter())
        self.model = PeerModel("ws", PEER_SETTINGS.ordered_queue_len, auth, self.now)

    def _feed(self, data: bytes | str) -> None:
        self.ps.receive_data(data, self.now)
        self.model.feed(data, self.now)
        got = _peer_events(self.ps, self.model)
        assert [g[0] for g in got] == [w[0] for w in self.model.events]
        self.model.events.clear()

    @rule(role=st.sampled_from(("local", "remote", "observer")))
    def hello(self, role: str) -> None:
        self._feed(encode(hello_for(role)))

    @rule()
    def hello_without_token(self) -> None:
        """The issue's first disagreement: a missing token is auth/4001 before the hello."""
        closed_before = self.ps.closing
        joined_before = self.ps.hello is not None
        self._feed(msgpack.packb({"v": 1, "type": "hello", "role": "local", "session": "s1"}))
        if not closed_before and not joined_before:
            assert (self.ps.close_code, self.ps.close_reason) == (4001, "auth")

    @rule(data=messages)
    def message(self, data: bytes) -> None:
        self._feed(data)

    @rule(text=st.text(max_size=20))
    def text(self, text: str) -> None:
        self._feed(text)

    @rule(dt=st.integers(0, 6_000_000))
    def time_passes(self, dt: int) -> None:
        self.now += dt

    @rule()
    def tick(self) -> None:
        self.ps.tick(self.now)
        self.model.tick(self.now)
        got = _peer_events(self.ps, self.model)
        assert [g[0] for g in got] == [w[0] for w in self.model.events]
        self.model.events.clear()

    @rule()
    def flush(self) -> None:
        now = self.now
        self.model.written(_client_decode(self.ps.data_to_send(lambda: now), "ws"))

    @invariant()
    def same_close(self) -> None:
        assert self.ps.close_code == self.model.close_code
        assert len(self.ps.outbox) <= PEER_SETTINGS.ordered_queue_len + 4


TestOneRelayConnection = OneRelayConnection.TestCase
TestOneRelayConnection.settings = settings(max_examples=25, stateful_step_count=30,
                                           deadline=None,
                                           suppress_health_check=[HealthCheck.too_slow])
