"""Fuzz targets of the sans-I/O session cores and of the relay's session pairing.

Each input is a :mod:`~lab.fuzz.script` (messages, raw bytes, text, time passing, clock steps,
ticks, flushes, disconnects). The harness plays the asyncio glue's part and checks:

* ``peer``: one relay-side :class:`~shared.protocol.peer_session.PeerSession` against
  :class:`PeerModel`, a model of one connection written from ``docs/protocol.md`` §3 and §6
  (handshake, per-message and fatal errors, the error budget, observers, clock pings): every
  answer the relay writes, in order, and its close code, must be the model's;
* ``station``: a :class:`~shared.protocol.station_session.StationSession` (welcome, refusals,
  rejected messages, pongs with the right stamps, ``station_rx`` hops, liveness exactly at its
  deadline, bounded queues), with the relay's clock stepping both ways;
* ``relay``: up to four peers of a :class:`relay_server.server.RelayServer` (not started: its
  token check and session pairing, ``_join``/``_drop_peer``) with their ``PeerSession`` and
  the relay's :class:`~relay_server.session.Session` routing, dispatched as
  ``relay_server.server._Connection._handle`` does: roles, ``role_taken``, forwarding (every
  delivered message is one its sender sent, to the right peers of the same session only, with
  ``relay_in``/``relay_out`` appended), ``no_peer``/``queue_full`` naming the refused seq,
  ``stats`` that encode, and a ``lost`` count that a sequence jump cannot blow up.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any, Literal

from lab.fuzz.docspec import Fatality, error_table
from lab.fuzz.script import Kind, Op, parse
from lab.fuzz.seeds import FUZZ_SECRET, hello_for
from lab.fuzz.targets import check, check_error, reference_deframe, same_message
from relay_server.auth import TokenAuthority
from relay_server.config import RelayConfig
from relay_server.metrics import session_metrics
from relay_server.server import RelayServer
from relay_server.session import STREAMS_OF
from shared.errors import (
    ProtocolError,
    RemoteProtocolError,
    ReplacedError,
    SessionError,
)
from shared.ledger import DEFAULT_MAX_SEQ_JUMP
from shared.protocol import (
    ArmCommand,
    Bye,
    ClockPing,
    ClockPong,
    DataMessage,
    Error,
    Hello,
    Message,
    Stats,
    Welcome,
    decode,
    frame,
)
from shared.protocol.messages import MAX_HOPS
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
    Refused,
    Rejected,
    StationSession,
    Welcomed,
)

__all__ = ["PEER_SETTINGS", "PeerModel", "peer", "relay", "station"]

_T0_US = 1_700_000_000_000_000  # the harness clock starts at a realistic wall-clock time
_HELLO_LIMIT = 1024
_MESSAGE_LIMIT = 16 * 1024
#: §1: a data message must leave this many bytes under the limit for the relay's stamps
_FORWARD_ROOM = 128
#: §3: a pong whose station times lie further than a century from the relay's is ignored
_SANE_CLOCK_US = 100 * 365 * 86_400 * 1_000_000
#: the relay settings of the ``peer`` target: small size limits (so ``oversize`` is reachable
#: by a short input), the doc's budget and periods, a rate limit no input reaches
PEER_SETTINGS = PeerSettings(max_message_bytes=_MESSAGE_LIMIT, max_hello_bytes=_HELLO_LIMIT,
                             rate_limit_per_s=1e9, rate_limit_burst=1_000_000)
_OBSERVER_MAY_SEND = ("clock_ping", "clock_pong", "stats", "bye")
_PERIODIC = ("clock_ping", "stats")  # the relay's own latest-wins control messages
_MAX_OUTSTANDING_PINGS = 16


def _step(now: int, op: Op) -> int:
    """The harness clock after a TIME or STEP operation (never below 1 us)."""
    return max(1, now + op.value)


def _clock(t_us: int) -> Callable[[], int]:
    """A relay clock frozen at ``t_us`` (the harness's time)."""
    return lambda: t_us


def _client_decode(frames: list[bytes], framing: str) -> list[Message]:
    """What a client reads from the relay's output: every frame must be a valid message."""
    if framing == "tcp":
        payloads, err, left = reference_deframe(b"".join(frames), 2**31)
        check(err is None and left == 0, f"the relay wrote broken TCP framing ({err}, {left})")
    else:
        payloads = frames
    out = []
    for p in payloads:
        try:
            out.append(decode(p, max_message_bytes=2**31))
        except RemoteProtocolError as err:
            raise AssertionError(f"the relay wrote an invalid message: {err}") from err
    return out


# --------------------------------------------------------------------------- peer (model)


@dataclass
class PeerModel:
    """One relay connection as ``docs/protocol.md`` describes it (§1, §3, §6).

    It is fed the same bytes as the session and predicts, in order, the answers the relay
    writes (``welcome``, ``error``, ``clock_pong``; the periodic ``clock_ping`` and ``stats``
    aside), the events for the relay, and the close code.
    """

    framing: str
    ordered_limit: int
    auth: TokenAuthority
    start_us: int
    budget: int = 20
    hello: Hello | None = None
    joined: bool = False
    close_code: int | None = None
    replies: list[tuple[Any, ...]] = field(default_factory=list)
    events: list[tuple[Any, ...]] = field(default_factory=list)
    ordered_queued: int = 0
    bad: int = 0
    pings: dict[int, int] = field(default_factory=dict)  # ping_id -> t0 of pings written
    _stream: bytearray = field(default_factory=bytearray)
    _framing_dead: bool = False
    last_rx_us: int | None = None  # §6 `silent`: when the peer last sent anything

    @property
    def observer(self) -> bool:
        return self.hello is not None and self.hello.role == "observer"

    def limit(self) -> int:
        return _MESSAGE_LIMIT if self.joined else _HELLO_LIMIT

    def _reply(self, entry: tuple[Any, ...], *, force: bool = False) -> None:
        if force or self.ordered_queued < self.ordered_limit:
            self.ordered_queued += 1
            self.replies.append(entry)

    def _fatal(self, code: str) -> None:
        rule = error_table()[code]
        check(rule.fatality is not Fatality.PER_MESSAGE or code == "too_many_errors",
              f"model: {code} is never fatal")
        self._reply(("error", code, True, None, None), force=True)
        self.close_code = rule.close_code
        self.events.append(("closing", self.close_code))

    def _per_message(self, code: str, stream: str | None = None, seq: int | None = None) -> None:
        """A refused message after the hello: an error, or the budget's end."""
        rule = error_table()[code]
        if not self.joined or rule.fatality is Fatality.ALWAYS:
            self._fatal(code)
            return
        if rule.counted:
            self.bad += 1
            if self.bad > self.budget:
                self._fatal("too_many_errors")
                return
        self._reply(("error", code, False, stream, seq))

    def feed(self, data: bytes | str, t_us: int) -> None:
        """One receive: a TCP chunk, a WebSocket binary message, or a text message."""
        if self.close_code is not None:
            return
        self.last_rx_us = t_us
        if isinstance(data, str):
            items: list[bytes | str] = [data]
        elif self.framing == "ws":
            items = [data]
        else:
            if self._framing_dead:
                return
            self._stream += data
            payloads, err, left = reference_deframe(bytes(self._stream), self.limit())
            del self._stream[:len(self._stream) - left]
            items = list(payloads)
            if err is not None:
                self._framing_dead = True
                items.append(("framing", err))  # type: ignore[arg-type]
        limit = self.limit()  # one chunk is read with the limit in force when it arrived
        for item in items:
            if self.close_code is not None:
                return
            if isinstance(item, tuple):  # a broken length prefix: fatal
                self._fatal(item[1])
                return
            self._message(item, t_us, limit)

    def _message(self, item: bytes | str, t_us: int, limit: int) -> None:
        if isinstance(item, str):
            self._per_message("malformed")
            return
        try:
            msg = decode(item, max_message_bytes=limit)
        except RemoteProtocolError as err:
            self._per_message(err.code)
            return
        if self.hello is None:
            if not isinstance(msg, Hello):
                self._fatal("hello_expected")
                return
            self.hello = msg
            try:
                self.auth.check(msg.session, msg.token, msg.role)
            except SessionError as err:  # which refusal is the token check's; its close
                self._fatal(err.code)      # code is the doc's
                return
            self.joined = True
            self._reply(("welcome", msg.session, msg.role), force=True)
            return
        if isinstance(msg, DataMessage):
            if self.observer:
                self._per_message("read_only")
            elif len(item) > _MESSAGE_LIMIT - _FORWARD_ROOM:  # no room for the relay's stamps
                self._per_message("too_large_to_forward", msg.TYPE, msg.seq)
            else:
                self.events.append(("data", msg, t_us))
        elif isinstance(msg, ClockPong):
            t0 = self.pings.pop(msg.ping_id, None)
            if (t0 is not None and t0 == msg.t0_us and t_us >= t0 and msg.t2_us >= msg.t1_us
                    and (t_us - t0) - (msg.t2_us - msg.t1_us) >= 0
                    and abs(msg.t1_us - t0) <= _SANE_CLOCK_US
                    and abs(msg.t2_us - t_us) <= _SANE_CLOCK_US):
                self.events.append(("clock", t0, msg.t1_us))
        elif isinstance(msg, ClockPing):
            self._reply(("clock_pong", msg.ping_id, msg.t0_us, t_us))
        elif isinstance(msg, Bye):
            self.close_code = 1000
            self.events.append(("closing", 1000))
        elif self.observer and msg.TYPE not in _OBSERVER_MAY_SEND:
            self._per_message("read_only")
        elif isinstance(msg, Stats):
            self.events.append(("stats",))
        elif isinstance(msg, Error):
            pass  # a station's own error report: counted, never answered
        elif isinstance(msg, Hello):
            self._per_message("already_joined")
        else:
            self._per_message("unexpected_type")

    def tick(self, now_us: int) -> None:
        if (self.close_code is None and self.hello is None
                and now_us >= self.start_us + PEER_SETTINGS.hello_timeout_us):
            self._fatal("hello_timeout")
        last = self.start_us if self.last_rx_us is None else self.last_rx_us
        if (self.close_code is None and self.joined and not self.observer
                and now_us - last > PEER_SETTINGS.silence_timeout_us):
            self._fatal("silent")  # §6: a station that sends nothing for the limit

    def written(self, messages: list[Message]) -> None:
        """The relay flushed: check what it wrote against the predicted answers."""
        got: list[tuple[Any, ...]] = []
        for m in messages:
            if isinstance(m, ClockPing):
                self.pings[m.ping_id] = m.t0_us
                while len(self.pings) > _MAX_OUTSTANDING_PINGS:
                    del self.pings[next(iter(self.pings))]
            elif isinstance(m, Error):
                got.append(("error", m.code, m.fatal, m.stream, m.seq))
            elif isinstance(m, Welcome):
                got.append(("welcome", m.session, m.role))
            elif isinstance(m, ClockPong):
                got.append(("clock_pong", m.ping_id, m.t0_us, m.t1_us))
            elif not isinstance(m, Stats):
                got.append((m.TYPE,))
        check(got == self.replies, f"the relay answered {got}, the doc says {self.replies}")
        self.replies.clear()
        self.ordered_queued = 0


def _peer_events(ps: PeerSession, model: PeerModel) -> list[tuple[Any, ...]]:
    out: list[tuple[Any, ...]] = []
    for ev in ps.events_received():
        if isinstance(ev, HelloReceived):
            try:
                model.auth.check(ev.hello.session, ev.hello.token, ev.hello.role)
            except SessionError as err:
                ps.fail(err)
                out.extend(_peer_events(ps, model))  # the Closing it queued
                continue
            ps.accept(Welcome(session=ev.hello.session, role=ev.hello.role,
                              server_time_us=_T0_US, ping_interval_s=1.0,
                              max_message_bytes=_MESSAGE_LIMIT, stats_interval_s=1.0), _T0_US)
            out.extend(_peer_events(ps, model))  # what was held behind the hello
        elif isinstance(ev, DataReceived):
            out.append(("data", ev.message, ev.t_in_us))
        elif isinstance(ev, ClockSampled):
            out.append(("clock", ev.t0_us, ev.t1_us))
        elif isinstance(ev, StatsReported):
            out.append(("stats",))
        elif isinstance(ev, Closing):
            out.append(("closing", ev.close_code))
    return out


def _same_events(got: list[tuple[Any, ...]], want: list[tuple[Any, ...]]) -> bool:
    if len(got) != len(want):
        return False
    for g, w in zip(got, want, strict=True):
        if g[0] != w[0]:
            return False
        if g[0] == "data":
            if not same_message(g[1], w[1]) or g[2] != w[2]:
                return False
        elif g != w:
            return False
    return True


def peer(data: bytes) -> None:
    """Target: one relay-side ``PeerSession`` against :class:`PeerModel` (module doc).

    Option bits: 0 framing (tcp/ws), 1 a 4-entry ordered queue (else 256).
    """
    script = parse(data)
    framing: Literal["tcp", "ws"] = "ws" if script.options & 1 else "tcp"
    settings = PEER_SETTINGS
    if script.options & 2:
        settings = PeerSettings(**{**PEER_SETTINGS.__dict__, "ordered_queue_len": 4})
    now = _T0_US
    auth = TokenAuthority({}, FUZZ_SECRET)
    ps = PeerSession(framing, settings, now, Counter())
    model = PeerModel(framing, settings.ordered_queue_len, auth, now)
    for op in script.ops:
        kind = op.kind
        if kind in (Kind.MSG, Kind.RAW, Kind.TEXT):
            if kind is Kind.TEXT and framing == "ws":
                chunk: bytes | str = op.payload.decode("latin-1")
            elif kind is Kind.MSG and framing == "tcp":
                chunk = frame(op.payload)
            else:
                chunk = op.payload
            ps.receive_data(chunk, now)
            model.feed(chunk, now)
            got = _peer_events(ps, model)
            check(_same_events(got, model.events),
                  f"relay events {got} differ from the doc's {model.events}")
            model.events.clear()
        elif kind in (Kind.TIME, Kind.STEP):
            now = _step(now, op)
        elif kind is Kind.TICK:
            if ps.tick(now) and ps.hello is not None:
                ps.send_stats(Stats(scope="relay", time_us=now, metrics={"session": "x"}))
            model.tick(now)
            got = _peer_events(ps, model)
            check(_same_events(got, model.events), f"tick: {got} != {model.events}")
            model.events.clear()
        elif kind is Kind.FLUSH:
            model.written(_client_decode(ps.data_to_send(_clock(now)), framing))
        check(ps.close_code == model.close_code,
              f"close code {ps.close_code}, the doc says {model.close_code}")
        check(len(ps.outbox) <= settings.ordered_queue_len + 4,
              f"outbox of {len(ps.outbox)} entries")
    model.written(_client_decode(ps.data_to_send(_clock(now)), framing))


# --------------------------------------------------------------------------- station


def station(data: bytes) -> None:
    """Target: a station's ``StationSession`` (module doc).

    Option bits: 0 framing (tcp/ws), 1 small queues (4 entries), 2-3 role
    (local, remote, observer, local).
    """
    script = parse(data)
    framing: Literal["tcp", "ws"] = "ws" if script.options & 1 else "tcp"
    small = bool(script.options & 2)
    role = ("local", "remote", "observer", "local")[(script.options >> 2) & 3]
    hello = hello_for(role)
    rx_size = 4 if small else 1024
    ss = StationSession(hello, max_message_bytes=_MESSAGE_LIMIT,
                        send_queue_size=4 if small else 256, receive_queue_size=rx_size,
                        connect_timeout_us=5_000_000, liveness_timeout_us=5_000_000)
    now = _T0_US

    def connect() -> None:
        (first,) = _client_decode([ss.connect(framing, now)], framing)
        check(same_message(first, hello), "the first message written is not the hello")

    connect()
    alive, welcomed, last_rx = True, False, now
    pending_pongs: deque[tuple[int, int, int]] = deque(maxlen=16)
    stream = bytearray()
    for op in script.ops:
        kind = op.kind
        if kind in (Kind.MSG, Kind.RAW, Kind.TEXT):
            if not alive:  # the glue reconnects after a failure
                connect()
                alive, welcomed, last_rx, stream = True, False, now, bytearray()
                pending_pongs.clear()
            chunk = frame(op.payload) if kind is Kind.MSG and framing == "tcp" else op.payload
            while ss.inbox.ordered_full:  # the glue's back-pressure: the station consumes
                ss.next_message()
            ss.receive_data(chunk, now)
            last_rx = now
            # the model: which messages this chunk completes
            if framing == "tcp":
                stream += chunk
                payloads, err, left = reference_deframe(bytes(stream), _MESSAGE_LIMIT)
                del stream[:len(stream) - left]
            else:
                payloads, err = [chunk], None
            events = ss.events_received()
            expected: list[str] = []
            for p in payloads:
                try:
                    msg: Message | None = decode(p, max_message_bytes=_MESSAGE_LIMIT)
                except RemoteProtocolError:
                    msg = None
                if msg is None:
                    if welcomed:
                        expected.append("rejected")
                        continue
                    expected.append("failed")
                    break
                if not welcomed and isinstance(msg, Welcome):
                    welcomed = True
                    expected.append("welcomed")
                elif not welcomed and isinstance(msg, Error):
                    expected.append("refused:" + msg.code)
                    break
                elif isinstance(msg, ClockPing):
                    pending_pongs.append((msg.ping_id, msg.t0_us, now))
            else:
                if err is not None:
                    expected.append("failed")
            got = []
            for ev in events:
                if isinstance(ev, Welcomed):
                    got.append("welcomed")
                elif isinstance(ev, Refused):
                    got.append("refused:" + ev.error.code)
                elif isinstance(ev, Failed):
                    check(isinstance(ev.error, RemoteProtocolError), f"failed with {ev.error!r}")
                    got.append("failed")
                elif isinstance(ev, Rejected):
                    check_error(ev.error)  # the doc's codes (its fatality is the relay's)
                    got.append("rejected")
            check(got == expected, f"station events {got}, expected {expected}")
            if expected and expected[-1] != "welcomed" and expected[-1] != "rejected":
                check(ss.connection_lost() is welcomed and not ss.is_open,
                      "a failed or refused connection stays open")
                alive = False
            check(ss.is_open == (welcomed and alive), "is_open disagrees with the welcome")
        elif kind in (Kind.TIME, Kind.STEP):
            now = _step(now, op)
        elif kind is Kind.TICK:
            silent = ss.check_liveness(now)
            limit = 5_000_000
            want = alive and now - last_rx >= limit
            check((silent is not None) == want,
                  f"liveness {silent} after {now - last_rx} us silent (alive={alive})")
            if silent is not None:
                check(silent.welcomed == welcomed, "LinkSilent.welcomed is wrong")
                ss.connection_lost()
                alive = False
        elif kind is Kind.FLUSH:
            frames = []
            while (chunk_out := ss.next_data(now)) is not None:
                frames.append(chunk_out)
                check(len(frames) <= 2048, "next_data never runs dry")
            if not (alive and welcomed):
                check(not frames, "data written before the welcome")
                continue
            for m in _client_decode(frames, framing):
                if isinstance(m, ClockPong):
                    check(pending_pongs, "a pong without a ping")
                    ping_id, t0, t1 = pending_pongs.popleft()
                    check((m.ping_id, m.t0_us, m.t1_us, m.t2_us) == (ping_id, t0, t1, now),
                          f"pong {m} does not answer ping {ping_id} received at {t1}")
            check(not pending_pongs, "pings left unanswered after a flush")
        elif kind is Kind.CLOSE:
            was = ss.connection_lost()
            check(was == (alive and welcomed), "connection_lost's answer is wrong")
            alive = False
        # what the station consumes, and the bounds of its queues
        check(len(ss.inbox) <= rx_size + 256 + 8, f"inbox of {len(ss.inbox)}")
        while (m_in := ss.next_message()) is not None:
            if isinstance(m_in, DataMessage) and role != "observer":
                check(m_in.hops and tuple(m_in.hops[-1])[:2] == (role, "station_rx"),
                      f"{m_in.TYPE} without its station_rx stamp")
                check(len(m_in.hops) <= MAX_HOPS, "more than 32 hops kept")


# --------------------------------------------------------------------------- relay


@dataclass
class _Sent:
    """A data message a station sent, as the relay accepted it."""

    message: DataMessage
    session: str
    role: str
    t_in_us: int


class _RelayPeer:
    def __init__(self, relay: RelayServer, framing: Literal["tcp", "ws"], now: int) -> None:
        self.framing = framing
        self.ps = PeerSession(framing, relay.peer_settings, now, relay.counters)
        self.conn = SimpleNamespace(transport=SimpleNamespace(framing=framing), protocol=self.ps,
                                    evict=self._evicted, request_stats=lambda: None)
        self.session: Any = None
        self.peer: Any = None
        self.hello: Hello | None = None
        self.arm_sent: dict[int, int] = {}  # seq -> times sent while this peer was local

    def _evicted(self) -> None:
        """The relay replaced this connection (a reconnect proved its resume secret)."""
        self.session = self.peer = None
        self.ps.fail(ReplacedError("a newer connection of this station resumed the session"))


def relay(data: bytes) -> None:
    """Target: four connections to one relay's pairing and routing (module doc).

    Option bits: 0-3 framing of peers 0-3 (tcp/ws), 4 ordered queues of 2 (else 256), 5 at
    most one session (``relay_full`` reachable).
    """
    script = parse(data)
    opts = script.options
    cfg = RelayConfig(secret=FUZZ_SECRET, max_message_bytes=_MESSAGE_LIMIT,
                      max_hello_bytes=_HELLO_LIMIT, rate_limit_per_s=1e9,
                      rate_limit_burst=1_000_000, ordered_queue_len=2 if opts & 16 else 256,
                      max_sessions=1 if opts & 32 else 1000, ledger_window=64)
    server = RelayServer(cfg)
    now = _T0_US
    peers = [_RelayPeer(server, "ws" if opts >> i & 1 else "tcp", now) for i in range(4)]
    sent: list[_Sent] = []
    rules = error_table()

    def dispatch(p: _RelayPeer) -> None:
        """``relay_server.server._Connection._handle`` for one peer's events."""
        for ev in p.ps.events_received():
            if isinstance(ev, HelloReceived):
                p.hello = ev.hello
                roles_before = ({r for r, s in server.sessions[ev.hello.session].stations.items()}
                                if ev.hello.session in server.sessions else set())
                try:
                    p.session, p.peer = server._join(ev.hello, p.conn)  # type: ignore[arg-type]
                except (ProtocolError, SessionError) as err:
                    if err.code == "role_taken":  # the token is checked first
                        check(ev.hello.role in roles_before, "role_taken for a free role")
                    if err.code == "relay_full":
                        check(len(server.sessions) >= cfg.max_sessions
                              and ev.hello.session not in server.sessions,
                              "relay_full below max_sessions or for an existing session")
                    p.ps.fail(err)
                    continue
                check(ev.hello.role == "observer" or ev.hello.role not in roles_before,
                      f"two {ev.hello.role} stations joined one session")
                p.ps.accept(Welcome(session=ev.hello.session, role=ev.hello.role,
                                    server_time_us=now, ping_interval_s=cfg.ping_interval_s,
                                    max_message_bytes=cfg.max_message_bytes,
                                    stats_interval_s=cfg.stats_interval_s), now)
                dispatch(p)
                return
            if isinstance(ev, DataReceived) and p.peer is not None:
                msg = ev.message
                if isinstance(msg, ArmCommand) and p.peer.role == "local":
                    p.arm_sent[msg.seq] = p.arm_sent.get(msg.seq, 0) + 1
                reply = p.session.route(p.peer, msg, ev.t_in_us)
                if msg.TYPE in STREAMS_OF.get(p.peer.role, ()):
                    sent.append(_Sent(msg, p.session.session_id, p.peer.role, ev.t_in_us))
                if reply is None:
                    continue
                if reply.code == "wrong_direction":
                    check(msg.TYPE not in STREAMS_OF.get(p.peer.role, ()), "wrong_direction "
                          "for an allowed stream")
                    p.ps.reject(SessionError(reply.message, code=reply.code))
                else:
                    check(reply.code in ("no_peer", "queue_full") and reply.seq == msg.seq
                          and reply.stream == msg.TYPE, f"route reply {reply}")
                    p.ps.reply(reply)
            elif isinstance(ev, ClockSampled) and p.peer is not None:
                p.peer.record_clock_exchange(ev.t0_us, ev.t1_us, ev.sample.delay_us)
            elif isinstance(ev, StatsReported) and p.peer is not None:
                p.peer.reported = ev.metrics

    def leave(p: _RelayPeer) -> None:
        if p.peer is not None and p.session is not None:
            server._drop_peer(p.session, p.peer)
        p.peer = p.session = None

    def flush(p: _RelayPeer) -> None:
        out = _client_decode(p.ps.data_to_send(_clock(now)), p.framing)
        role = p.hello.role if p.hello is not None else None
        for m in out:
            if isinstance(m, Error):
                rule = rules.get(m.code)
                check(rule is not None, f"error {m.code} is not in docs/protocol.md §6")
                if rule is not None:
                    if not m.fatal:
                        check(rule.fatality is not Fatality.ALWAYS, f"{m.code} sent non-fatal")
                    else:
                        check(p.ps.close_code == rule.close_code, f"fatal {m.code} closed "
                              f"with {p.ps.close_code}, the doc says {rule.close_code}")
                    if m.code in ("no_peer", "queue_full"):
                        check(m.stream == "arm_command" and m.seq is not None
                              and p.arm_sent.get(m.seq), f"{m.code} names seq {m.seq} that "
                              "this station did not send")
            elif isinstance(m, DataMessage):
                check((role is not None and p.session is not None) or p.ps.closing,
                      "data reached a peer that has not joined")
                check(role is None or m.TYPE not in STREAMS_OF.get(role, ()),
                      f"{role} received its own stream {m.TYPE}")
                check(len(m.hops) >= 2 and tuple(m.hops[-2])[:2] == ("relay", "relay_in")
                      and tuple(m.hops[-1]) == ("relay", "relay_out", now),
                      f"forwarded {m.TYPE} without relay_in/relay_out: {m.hops}")
                src = [s for s in sent if s.message.seq == m.seq and s.message.TYPE == m.TYPE
                       and s.t_in_us == m.hops[-2][2]
                       and same_message(s.message.with_hop("relay", "relay_in", s.t_in_us)
                                        .with_hop("relay", "relay_out", now), m)]
                check(src, f"{m.TYPE} seq {m.seq} delivered but never sent so")
                check(p.hello is not None and any(s.session == p.hello.session for s in src),
                      f"{m.TYPE} crossed from another session")
        if p.ps.closing:
            leave(p)

    for op in script.ops:
        p = peers[op.peer % 4]
        kind = op.kind
        if kind in (Kind.MSG, Kind.RAW, Kind.TEXT):
            if kind is Kind.TEXT and p.framing == "ws":
                chunk: bytes | str = op.payload.decode("latin-1")
            elif kind is Kind.MSG and p.framing == "tcp":
                chunk = frame(op.payload)
            else:
                chunk = op.payload
            p.ps.receive_data(chunk, now)
            dispatch(p)
        elif kind in (Kind.TIME, Kind.STEP):
            now = _step(now, op)
        elif kind is Kind.TICK:
            for q in peers:
                if q.ps.tick(now) and q.session is not None and q.peer is not None:
                    metrics = session_metrics(q.session, q.peer.role)
                    q.ps.send_stats(Stats(scope="relay", time_us=now, metrics=metrics))
                    for d in q.session.directions.values():
                        snap = d.uplink_snapshot()
                        check(0 <= snap.lost <= snap.received * DEFAULT_MAX_SEQ_JUMP,
                              f"lost={snap.lost} after {snap.received} messages")
                dispatch(q)
        elif kind is Kind.FLUSH:
            flush(p)
        elif kind is Kind.CLOSE:
            leave(p)
            peers[op.peer % 4] = _RelayPeer(server, p.framing, now)
        for q in peers:
            check(len(q.ps.outbox) <= cfg.ordered_queue_len + 10,
                  f"outbox of {len(q.ps.outbox)}")
            if q.ps.closing and q.peer is not None:
                flush(q)
    for q in peers:
        flush(q)
    for s in server.sessions.values():
        check(not s.empty, "an empty session is kept")

