"""Tele-Touch message types: frozen dataclasses with wire validation.

Every message is a msgpack map ``{"v": 1, "type": NAME, ...fields}`` (see
``docs/protocol.md``). Data messages (``platform_state``, ``arm_command``, ``arm_state``,
``tactile_frame``) also carry ``seq`` (the sender's sequence number), ``ts`` (capture
timestamp, sender's clock, integer microseconds) and ``hops`` (a list of ``[clock, stage,
t_us]`` stamps that each hop appends; ``clock`` names whose clock the stamp is in, so the
latency ledger can correct it with that clock's offset).

``from_wire`` validates a decoded map and raises :class:`~shared.errors.FieldError`
subclasses; ``to_wire`` gives the map back (without ``v`` and ``type``).
Units: millimetres, newtons, seconds or integer microseconds as the field names say.
"""

from __future__ import annotations

import dataclasses
import math
import re
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, ClassVar, NamedTuple, TypeVar

import numpy as np

from shared.errors import FieldError, NonFiniteError
from shared.protocol.fields import (
    MAX_INT,
    array_to_wire,
    read_array,
    read_bool,
    read_float,
    read_int,
    read_optional,
    read_str,
    read_vector,
)

__all__ = [
    "CLOCKS",
    "LATEST_WINS_TYPES",
    "LAYER_RANGES",
    "MAX_HOPS",
    "MESSAGE_TYPES",
    "MOTION_CARRY_MAX_US",
    "ROLES",
    "SESSION_ID_PATTERN",
    "ArmCommand",
    "ArmState",
    "Bye",
    "ClockPing",
    "ClockPong",
    "CompactLayer",
    "DataMessage",
    "Error",
    "Hello",
    "Hop",
    "Message",
    "PlatformState",
    "Stats",
    "StreamPolicy",
    "TactileCompact",
    "TactileFrame",
    "Welcome",
    "carried_kind",
    "carry_motion",
    "carry_motion_hops",
    "is_latest_wins",
    "without_motion",
]

ROLES = frozenset({"local", "remote", "observer"})
#: names a hop stamp's clock may have: a station role or the relay
CLOCKS = frozenset({"local", "remote", "relay"})
SESSION_ID_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
_STAGE_PATTERN = re.compile(r"[a-z][a-z0-9_]{0,31}")
MAX_HOPS = 32
#: tactile layer name -> allowed value range (all layers: 2-D, same shape, float)
LAYER_RANGES: dict[str, tuple[float, float]] = {
    "height_mm": (-10.0, 10.0),
    "stiffness_k": (0.5, 1.0),
    "friction": (0.0, 1.0),
    "stiffness_n_per_mm": (0.0, 1.0e4),
}
ARM_ACTIONS = frozenset({"move", "stop", "home", "set_force_limit"})
ARM_STATUSES = frozenset({"ok", "moving", "halted", "force_limit", "stale_command", "fault"})
_WORKSPACE_LIMIT_MM = 1.0e4  # sanity bound for any coordinate on the wire


class StreamPolicy(Enum):
    """How a queue treats messages of one type when the receiver or the socket lags.

    ``LATEST_WINS``: state streams; only the newest unsent message matters, a newer one
    replaces it and the replaced one is counted as dropped. ``ORDERED``: commands and
    control; every message is kept, in order, in a bounded queue.
    """

    LATEST_WINS = "latest_wins"
    ORDERED = "ordered"


class Hop(NamedTuple):
    """One latency stamp: ``t_us`` on ``clock``'s clock when ``stage`` happened."""

    clock: str
    stage: str
    t_us: int


def _read_hops(d: Mapping[str, Any], msg_type: str) -> tuple[Hop, ...]:
    raw = d.get("hops", [])
    if not isinstance(raw, list | tuple) or len(raw) > MAX_HOPS:
        raise FieldError(f"{msg_type}.hops must be a list of at most {MAX_HOPS} stamps")
    hops = []
    for i, h in enumerate(raw):
        if (not isinstance(h, list | tuple) or len(h) != 3
                or not isinstance(h[0], str) or h[0] not in CLOCKS  # a list is unhashable
                or not isinstance(h[1], str) or not _STAGE_PATTERN.fullmatch(h[1])
                or isinstance(h[2], bool) or not isinstance(h[2], int)
                or not 0 <= h[2] <= MAX_INT):
            raise FieldError(f"{msg_type}.hops[{i}] must be [clock in {sorted(CLOCKS)}, "
                             f"stage matching {_STAGE_PATTERN.pattern}, t_us >= 0]")
        hops.append(Hop(h[0], h[1], h[2]))
    return tuple(hops)


@dataclass(frozen=True, slots=True)
class Message(ABC):
    """Base of all messages. ``TYPE`` is the wire ``type`` string; ``POLICY`` is how every
    queue (relay outboxes, station send queue and inbox) treats the type."""

    TYPE: ClassVar[str] = ""
    POLICY: ClassVar[StreamPolicy] = StreamPolicy.ORDERED
    #: the first protocol version that defines the type (its messages carry ``v`` = this)
    MIN_VERSION: ClassVar[int] = 1

    @abstractmethod
    def to_wire(self) -> dict[str, Any]:
        """Return the wire fields (without ``v`` and ``type``)."""

    @classmethod
    @abstractmethod
    def from_wire(cls, d: Mapping[str, Any]) -> Message:
        """Validate a decoded wire map and build the message."""


@dataclass(frozen=True, slots=True)
class DataMessage(Message):
    """A message of a data stream: sequence number, capture time and hop stamps."""

    seq: int = 0
    ts_us: int = 0
    hops: tuple[Hop, ...] = ()

    def _head(self) -> dict[str, Any]:
        return {"seq": self.seq, "ts": self.ts_us, "hops": [list(h) for h in self.hops]}

    @staticmethod
    def _read_head(d: Mapping[str, Any], msg_type: str) -> dict[str, Any]:
        return {"seq": read_int(d, msg_type, "seq"), "ts_us": read_int(d, msg_type, "ts"),
                "hops": _read_hops(d, msg_type)}

    def with_hop(self, clock: str, stage: str, t_us: int) -> DataMessage:
        """Return a copy with one more hop stamp appended (at most ``MAX_HOPS`` are kept)."""
        hops = (*self.hops, Hop(clock, stage, t_us))[-MAX_HOPS:]
        return dataclasses.replace(self, hops=hops)


# --------------------------------------------------------------------------- control


@dataclass(frozen=True, slots=True)
class Hello(Message):
    """First message of a client: which session, which role, and the session token."""

    TYPE: ClassVar[str] = "hello"
    role: str = "observer"
    session: str = ""
    token: str = field(default="", repr=False)  # never in a log line through repr()
    name: str = ""
    #: the ``resume`` secret of this station's previous connection (``""``: none)
    resume: str = field(default="", repr=False)

    def to_wire(self) -> dict[str, Any]:
        out = {"role": self.role, "session": self.session, "token": self.token,
               "name": self.name}
        if self.resume:
            out["resume"] = self.resume
        return out

    @classmethod
    def from_wire(cls, d: Mapping[str, Any]) -> Hello:
        t = cls.TYPE
        return cls(role=read_str(d, t, "role", choices=ROLES),
                   session=read_str(d, t, "session", pattern=SESSION_ID_PATTERN),
                   # no token is refused by the relay as `auth` (4001), not as a bad field
                   token=read_str(d, t, "token", max_len=512) if "token" in d else "",
                   name=read_str(d, t, "name", max_len=64) if "name" in d else "",
                   resume=read_str(d, t, "resume", max_len=64) if "resume" in d else "")


@dataclass(frozen=True, slots=True)
class Welcome(Message):
    """The relay's answer to a valid hello."""

    TYPE: ClassVar[str] = "welcome"
    session: str = ""
    role: str = "observer"
    server_time_us: int = 0
    ping_interval_s: float = 1.0
    max_message_bytes: int = 0
    #: per-connection secret: a reconnecting station sends it in its next ``hello`` and the
    #: relay replaces this connection if it is still held (``""``: the relay gives none)
    resume: str = field(default="", repr=False)
    #: period of the relay's ``stats`` push, the only traffic an idle observer gets (0: not
    #: announced, by a relay from before it)
    stats_interval_s: float = 0.0

    def to_wire(self) -> dict[str, Any]:
        out: dict[str, Any] = {"session": self.session, "role": self.role,
                               "server_time_us": self.server_time_us,
                               "ping_interval_s": self.ping_interval_s,
                               "max_message_bytes": self.max_message_bytes}
        if self.resume:
            out["resume"] = self.resume
        if self.stats_interval_s:
            out["stats_interval_s"] = self.stats_interval_s
        return out

    @classmethod
    def from_wire(cls, d: Mapping[str, Any]) -> Welcome:
        t = cls.TYPE
        return cls(session=read_str(d, t, "session", pattern=SESSION_ID_PATTERN),
                   role=read_str(d, t, "role", choices=ROLES),
                   server_time_us=read_int(d, t, "server_time_us"),
                   ping_interval_s=read_float(d, t, "ping_interval_s", lo=0.0, hi=3600.0),
                   max_message_bytes=read_int(d, t, "max_message_bytes"),
                   resume=read_str(d, t, "resume", max_len=64) if "resume" in d else "",
                   stats_interval_s=read_float(d, t, "stats_interval_s", lo=0.0, hi=3600.0)
                   if "stats_interval_s" in d else 0.0)


@dataclass(frozen=True, slots=True)
class ClockPing(Message):
    """NTP-style request: ``t0_us`` is the sender's transmit time (its clock)."""

    TYPE: ClassVar[str] = "clock_ping"
    ping_id: int = 0
    t0_us: int = 0

    def to_wire(self) -> dict[str, Any]:
        return {"ping_id": self.ping_id, "t0_us": self.t0_us}

    @classmethod
    def from_wire(cls, d: Mapping[str, Any]) -> ClockPing:
        t = cls.TYPE
        return cls(ping_id=read_int(d, t, "ping_id"), t0_us=read_int(d, t, "t0_us"))


@dataclass(frozen=True, slots=True)
class ClockPong(Message):
    """NTP-style answer: ``t1_us`` receive and ``t2_us`` transmit time, responder's clock."""

    TYPE: ClassVar[str] = "clock_pong"
    ping_id: int = 0
    t0_us: int = 0
    t1_us: int = 0
    t2_us: int = 0

    def to_wire(self) -> dict[str, Any]:
        return {"ping_id": self.ping_id, "t0_us": self.t0_us, "t1_us": self.t1_us,
                "t2_us": self.t2_us}

    @classmethod
    def from_wire(cls, d: Mapping[str, Any]) -> ClockPong:
        t = cls.TYPE
        return cls(ping_id=read_int(d, t, "ping_id"), t0_us=read_int(d, t, "t0_us"),
                   t1_us=read_int(d, t, "t1_us"), t2_us=read_int(d, t, "t2_us"))


def _check_metrics(value: Any, where: str, depth: int = 0) -> None:
    if depth > 4:
        raise FieldError(f"{where} nests deeper than 4 levels")
    if isinstance(value, Mapping):
        if len(value) > 512:
            raise FieldError(f"{where} has more than 512 entries")
        for k, v in value.items():
            if not isinstance(k, str) or len(k) > 64:
                raise FieldError(f"{where} keys must be strings of at most 64 characters")
            _check_metrics(v, f"{where}.{k}", depth + 1)
    elif isinstance(value, float):
        if not math.isfinite(value):
            raise NonFiniteError(f"{where} is {value}")
    elif value is None or isinstance(value, bool | int | str):
        if isinstance(value, str) and len(value) > 256:
            raise FieldError(f"{where} is longer than 256 characters")
    else:
        raise FieldError(f"{where} must be a number, string, bool, null or map")


@dataclass(frozen=True, slots=True, eq=False)
class Stats(Message):
    """Latency and traffic figures (relay -> stations, or a station's own report).

    ``metrics`` is a nested map (depth <= 4) of finite numbers, strings, booleans or
    nulls; its keys are documented in ``docs/protocol.md``.
    """

    TYPE: ClassVar[str] = "stats"
    scope: str = "relay"
    time_us: int = 0
    metrics: Mapping[str, Any] = field(default_factory=dict)

    def to_wire(self) -> dict[str, Any]:
        return {"scope": self.scope, "time_us": self.time_us, "metrics": dict(self.metrics)}

    @classmethod
    def from_wire(cls, d: Mapping[str, Any]) -> Stats:
        t = cls.TYPE
        metrics = d.get("metrics")
        if not isinstance(metrics, Mapping):
            raise FieldError(f"{t}.metrics must be a map")
        _check_metrics(metrics, f"{t}.metrics")
        return cls(scope=read_str(d, t, "scope", choices=CLOCKS),
                   time_us=read_int(d, t, "time_us"), metrics=dict(metrics))


@dataclass(frozen=True, slots=True)
class Error(Message):
    """A protocol or session error, sent before a close when ``fatal``.

    ``stream`` and ``seq`` (optional) name the data message refused, for the per-message
    refusals of one message (``queue_full``, ``no_peer``); absent otherwise.
    """

    TYPE: ClassVar[str] = "error"
    code: str = "bad_message"
    message: str = ""
    fatal: bool = False
    stream: str | None = None
    seq: int | None = None
    #: a finer cause within ``code`` for a client to act on (``expired`` with ``auth``)
    reason: str | None = None

    def to_wire(self) -> dict[str, Any]:
        out: dict[str, Any] = {"code": self.code, "message": self.message[:1024],
                               "fatal": self.fatal}
        if self.stream is not None:
            out["stream"] = self.stream
        if self.seq is not None:
            out["seq"] = self.seq
        if self.reason is not None:
            out["reason"] = self.reason
        return out

    @classmethod
    def from_wire(cls, d: Mapping[str, Any]) -> Error:
        t = cls.TYPE
        return cls(code=read_str(d, t, "code", max_len=64),
                   message=read_str(d, t, "message", max_len=1024),
                   fatal=read_bool(d, t, "fatal"),
                   stream=read_str(d, t, "stream", max_len=64)
                   if read_optional(d, "stream") else None,
                   seq=read_int(d, t, "seq") if read_optional(d, "seq") else None,
                   reason=read_str(d, t, "reason", max_len=64)
                   if read_optional(d, "reason") else None)


@dataclass(frozen=True, slots=True)
class Bye(Message):
    """A clean goodbye before closing."""

    TYPE: ClassVar[str] = "bye"
    reason: str = ""

    def to_wire(self) -> dict[str, Any]:
        return {"reason": self.reason}

    @classmethod
    def from_wire(cls, d: Mapping[str, Any]) -> Bye:
        return cls(reason=read_str(d, cls.TYPE, "reason", max_len=256) if "reason" in d else "")


# --------------------------------------------------------------------------- data streams


@dataclass(frozen=True, slots=True)
class PlatformState(DataMessage):
    """Local -> remote: the XYZ platform position (platform coordinates, mm)."""

    TYPE: ClassVar[str] = "platform_state"
    POLICY: ClassVar[StreamPolicy] = StreamPolicy.LATEST_WINS
    position_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    velocity_mm_s: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def to_wire(self) -> dict[str, Any]:
        out = self._head()
        out["position_mm"] = list(self.position_mm)
        out["velocity_mm_s"] = list(self.velocity_mm_s)
        return out

    @classmethod
    def from_wire(cls, d: Mapping[str, Any]) -> PlatformState:
        t = cls.TYPE
        lim = _WORKSPACE_LIMIT_MM
        return cls(**cls._read_head(d, t),
                   position_mm=read_vector(d, t, "position_mm", 3, lo=-lim, hi=lim),  # type: ignore[arg-type]
                   velocity_mm_s=read_vector(d, t, "velocity_mm_s", 3, lo=-1e5, hi=1e5))  # type: ignore[arg-type]


_M = TypeVar("_M", bound=Message)
_D = TypeVar("_D", bound=DataMessage)

#: the longest wait :func:`carry_motion_hops` hands on (us); the remote station's frame
#: chain ends after as long (``RemoteStation._frame_source``): longer is an outage
MOTION_CARRY_MAX_US = 1_000_000


def carry_motion(replaced: Message, newer: _M) -> _M:
    """``newer`` as it must travel when it replaces ``replaced`` unsent or unread in a
    latest-wins slot or hand-over, or follows states no frame answered at the remote.

    The slots: on the way out, the local station's send queue, the relay's queue to the
    remote and the remote station's inbox (``platform_state``); on the way back, the remote
    station's send queue, the relay's queue to the local, the local station's inbox and the
    display loop's frame slot while the loop renders (tactile frames).

    Only a message after one of its own kind changes (a ``platform_state`` after a
    ``platform_state``, a tactile frame after a tactile frame, either encoding): the
    movements only ``replaced`` would have shown are first shown by ``newer``, so ``newer``
    starts where ``replaced`` started (:func:`carry_motion_hops`). Any other pair, and a
    ``newer`` whose stamps would not change, is returned as it is.
    """
    kind = carried_kind(newer)
    if kind is None or kind != carried_kind(replaced) or not isinstance(newer, DataMessage) \
            or not isinstance(replaced, DataMessage):
        return newer
    hops = carry_motion_hops(replaced.hops, newer.hops)
    return newer if hops is newer.hops else dataclasses.replace(newer, hops=hops)


def carry_motion_hops(replaced: Sequence[Hop], newer: tuple[Hop, ...]) -> tuple[Hop, ...]:
    """The stamps of a message that replaces one with stamps ``replaced`` (see
    :func:`carry_motion`, which applies this to messages).

    ``newer``'s ``local.motion`` stamp (``shared/motion_to_touch.py``) becomes
    ``replaced``'s ``local.motion``, or, when it had none (the first of a link session, or
    after a break), its ``local.capture``: the known part of its wait. Only an earlier start
    is taken, and none more than :data:`MOTION_CARRY_MAX_US` before ``newer``'s own: a
    longer wait is an outage of the touch path (a stalled queue, a reconnect), not a
    latency. A ``newer`` without ``local.motion`` (its sender saw the chain broken: a new
    link session, a skipped sample, a platform outage; or an idle tactile frame, which shows
    nothing first) and a ``replaced`` with neither stamp (an idle frame) leave ``newer`` as
    it is: the very tuple.
    """
    mine = next((h for h in newer if _is_motion(h)), None)
    if mine is None:
        return newer
    theirs = next((h for h in replaced if _is_motion(h)), None) or next(
        (h for h in replaced if h.stage == "capture" and h.clock == "local"), None)
    if theirs is None or not 0 < mine.t_us - theirs.t_us <= MOTION_CARRY_MAX_US:
        return newer
    return (Hop("local", "motion", theirs.t_us), *(h for h in newer if not _is_motion(h)))


def carried_kind(msg: Message) -> str | None:
    """What :func:`carry_motion` treats as one kind of message (None: never carried):
    ``platform_state``, or ``tactile`` for either encoding of a tactile frame."""
    if isinstance(msg, PlatformState):
        return "platform_state"
    if isinstance(msg, TactileFrame | TactileCompact):
        return "tactile"
    return None


def is_latest_wins(msg: Message) -> bool:
    """Whether ``msg`` goes in its stream's latest-wins slot (a newer one may replace it
    unsent or unread) in the relay's queues. A ``tactile_compact`` key frame never does,
    although its stream is latest-wins: the deltas after it need it, so the relay keeps it
    in order (a station gives it a slot of its own instead:
    ``shared.protocol.station_session.latest_slot``)."""
    return msg.POLICY is StreamPolicy.LATEST_WINS and not (
        isinstance(msg, TactileCompact) and msg.key)


def without_motion(msg: _D) -> _D:
    """``msg`` without its ``local.motion`` stamp (the same message when it has none): its
    frames then count from its ``local.capture``."""
    if not any(_is_motion(h) for h in msg.hops):
        return msg
    return dataclasses.replace(msg, hops=tuple(h for h in msg.hops if not _is_motion(h)))


def _is_motion(hop: Hop) -> bool:
    return hop.stage == "motion" and hop.clock == "local"


@dataclass(frozen=True, slots=True)
class ArmCommand(DataMessage):
    """Local -> remote: an explicit arm command (ordered stream, never dropped).

    ``action`` is ``move`` (with ``target_mm``), ``stop``, ``home`` or
    ``set_force_limit`` (with ``force_limit_n``).
    """

    TYPE: ClassVar[str] = "arm_command"
    action: str = "stop"
    target_mm: tuple[float, float, float] | None = None
    force_limit_n: float | None = None

    def to_wire(self) -> dict[str, Any]:
        out = self._head()
        out["action"] = self.action
        if self.target_mm is not None:
            out["target_mm"] = list(self.target_mm)
        if self.force_limit_n is not None:
            out["force_limit_n"] = self.force_limit_n
        return out

    @classmethod
    def from_wire(cls, d: Mapping[str, Any]) -> ArmCommand:
        t = cls.TYPE
        action = read_str(d, t, "action", choices=ARM_ACTIONS)
        lim = _WORKSPACE_LIMIT_MM
        target = (read_vector(d, t, "target_mm", 3, lo=-lim, hi=lim)
                  if read_optional(d, "target_mm") or action == "move" else None)
        # read for set_force_limit only: on other actions the field means nothing, and a
        # stop is never refused for it (whatever it holds)
        force = (read_float(d, t, "force_limit_n", lo=0.0, hi=1000.0)
                 if action == "set_force_limit" else None)
        if force is not None and force <= 0.0:  # a zero limit is not a limit (SafeArm refuses)
            raise FieldError(f"{t}.force_limit_n must be > 0, got {force}")
        return cls(**cls._read_head(d, t), action=action, target_mm=target,  # type: ignore[arg-type]
                   force_limit_n=force)


@dataclass(frozen=True, slots=True)
class ArmState(DataMessage):
    """Remote -> local: arm tool position (phantom coordinates, mm) and measured force."""

    TYPE: ClassVar[str] = "arm_state"
    POLICY: ClassVar[StreamPolicy] = StreamPolicy.LATEST_WINS
    position_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    force_n: float = 0.0
    status: str = "ok"
    source_seq: int | None = None

    def to_wire(self) -> dict[str, Any]:
        out = self._head()
        out.update(position_mm=list(self.position_mm), force_n=self.force_n, status=self.status)
        if self.source_seq is not None:
            out["source_seq"] = self.source_seq
        return out

    @classmethod
    def from_wire(cls, d: Mapping[str, Any]) -> ArmState:
        t = cls.TYPE
        lim = _WORKSPACE_LIMIT_MM
        return cls(**cls._read_head(d, t),
                   position_mm=read_vector(d, t, "position_mm", 3, lo=-lim, hi=lim),  # type: ignore[arg-type]
                   force_n=read_float(d, t, "force_n", lo=-1000.0, hi=1000.0),
                   status=read_str(d, t, "status", choices=ARM_STATUSES),
                   source_seq=read_int(d, t, "source_seq") if read_optional(d, "source_seq")
                   else None)


def _tactile_scalars_to_wire(m: TactileFrame | TactileCompact, out: dict[str, Any]) -> None:
    """Write the fields both tactile messages share (read by :func:`_read_tactile_scalars`)."""
    out.update(center_mm=list(m.center_mm), pitch_mm=m.pitch_mm, contact=m.contact,
               force_n=m.force_n, indentation_mm=m.indentation_mm)
    if m.source_seq is not None:
        out["source_seq"] = m.source_seq
    if m.source_ts_us is not None:
        out["source_ts"] = m.source_ts_us


def _read_tactile_scalars(d: Mapping[str, Any], t: str) -> dict[str, Any]:
    """Validate the fields both tactile messages share (placement, contact, provenance)."""
    lim = _WORKSPACE_LIMIT_MM
    return {"center_mm": read_vector(d, t, "center_mm", 2, lo=-lim, hi=lim),
            "pitch_mm": read_float(d, t, "pitch_mm", lo=1e-4, hi=100.0),
            "contact": read_bool(d, t, "contact"),
            "force_n": read_float(d, t, "force_n", lo=-1000.0, hi=1000.0),
            "indentation_mm": read_float(d, t, "indentation_mm", lo=-100.0, hi=100.0),
            "source_seq": read_int(d, t, "source_seq") if read_optional(d, "source_seq")
            else None,
            "source_ts_us": read_int(d, t, "source_ts") if read_optional(d, "source_ts")
            else None}


def _read_layer_map(d: Mapping[str, Any], t: str, what: str,
                    need_height: str | None) -> Mapping[str, Any]:
    """The ``layers`` map with known names only; ``need_height``: where height_mm is required."""
    raw_layers = d.get("layers")
    if not isinstance(raw_layers, Mapping):
        raise FieldError(f"{t}.layers must be a map of layer name -> {what}")
    unknown = sorted(str(k) for k in raw_layers if k not in LAYER_RANGES)
    if unknown:
        raise FieldError(f"{t}.layers has unknown layer(s) {unknown}; known: "
                         f"{sorted(LAYER_RANGES)}")
    if need_height is not None and "height_mm" not in raw_layers:
        raise FieldError(f"{t}.layers.height_mm is missing{need_height}")
    return raw_layers


@dataclass(frozen=True, slots=True, eq=False)
class TactileFrame(DataMessage):
    """Remote -> local: what the probe feels, as layers on a metric grid.

    Layers are 2-D float arrays of one shape, row index along +y and column index along
    +x, spaced ``pitch_mm`` apart and centred on ``center_mm`` (platform coordinates,
    so the renderer samples them at the platform position). ``height_mm`` is required;
    ``stiffness_k`` (display k in [0.5, 1]), ``friction`` ([0, 1]) and
    ``stiffness_n_per_mm`` (measured, >= 0) are optional. ``source_seq``/``source_ts_us``
    name the platform_state this frame answers (for motion-to-touch latency).
    """

    TYPE: ClassVar[str] = "tactile_frame"
    POLICY: ClassVar[StreamPolicy] = StreamPolicy.LATEST_WINS
    center_mm: tuple[float, float] = (0.0, 0.0)
    pitch_mm: float = 1.7
    layers: Mapping[str, np.ndarray] = field(default_factory=dict)
    contact: bool = False
    force_n: float = 0.0
    indentation_mm: float = 0.0
    source_seq: int | None = None
    source_ts_us: int | None = None

    def to_wire(self) -> dict[str, Any]:
        out = self._head()
        out["layers"] = {k: array_to_wire(v) for k, v in self.layers.items()}
        _tactile_scalars_to_wire(self, out)
        return out

    @classmethod
    def from_wire(cls, d: Mapping[str, Any]) -> TactileFrame:
        t = cls.TYPE
        raw_layers = _read_layer_map(d, t, "array", need_height="")
        layers: dict[str, np.ndarray] = {}
        shape = None
        for name, raw in raw_layers.items():
            lo, hi = LAYER_RANGES[name]
            arr = read_array(raw, f"{t}.layers.{name}", lo=lo, hi=hi, ndim=2)
            if arr.dtype.kind != "f":
                raise FieldError(f"{t}.layers.{name} must be float32 or float64")
            if shape is not None and arr.shape != shape:
                raise FieldError(f"{t}.layers.{name} has shape {arr.shape}, height_mm has {shape}")
            shape = arr.shape
            layers[name] = arr
        return cls(**cls._read_head(d, t), layers=layers, **_read_tactile_scalars(d, t))


class CompactLayer(NamedTuple):
    """One layer of a ``tactile_compact`` frame: quantized values ``q`` (int16; value =
    ``offset + scale * q``). In a key frame ``q`` is 2-D and ``scale``/``offset`` are set; in
    a delta ``q`` is either 2-D (every sample) or 1-D with ``idx`` (flat row-major indices,
    strictly increasing) and the key frame's ``scale``/``offset`` apply."""

    q: np.ndarray
    scale: float | None = None
    offset: float | None = None
    idx: np.ndarray | None = None


_MAX_SCALE = 1.0e3
_MAX_OFFSET = 1.0e5


def _read_compact_layer(raw: Any, where: str, key: bool,
                        shape: tuple[int, int]) -> CompactLayer:
    if not isinstance(raw, Mapping):
        raise FieldError(f"{where} must be a map with q (and scale/offset or idx)")
    q = read_array(raw.get("q"), f"{where}.q")
    if q.dtype != np.dtype("<i2"):
        raise FieldError(f"{where}.q must be <i2 (int16), got {q.dtype.str}")
    if key:
        scale = read_float(raw, where, "scale", lo=0.0, hi=_MAX_SCALE)
        if scale <= 0.0:
            raise FieldError(f"{where}.scale must be > 0")
        offset = read_float(raw, where, "offset", lo=-_MAX_OFFSET, hi=_MAX_OFFSET)
        if q.shape != shape:
            raise FieldError(f"{where}.q has shape {list(q.shape)}, the frame's is {list(shape)}")
        return CompactLayer(q, scale, offset)
    if "scale" in raw or "offset" in raw:
        raise FieldError(f"{where}: a delta layer uses the key frame's scale and offset")
    if read_optional(raw, "idx"):
        idx = read_array(raw["idx"], f"{where}.idx", ndim=1)
        if idx.dtype != np.dtype("<i4"):
            raise FieldError(f"{where}.idx must be <i4, got {idx.dtype.str}")
        if q.ndim != 1 or q.shape != idx.shape:
            raise FieldError(f"{where}.q must be 1-D with one value per idx entry")
        if idx.size and (int(idx[0]) < 0 or int(idx[-1]) >= shape[0] * shape[1]
                         or (idx.size > 1 and not bool((idx[1:] > idx[:-1]).all()))):
            raise FieldError(f"{where}.idx must be strictly increasing flat indices in "
                             f"[0, {shape[0] * shape[1]})")
        return CompactLayer(q, idx=idx)
    if q.shape != shape:
        raise FieldError(f"{where}.q has shape {list(q.shape)}, the frame's is {list(shape)}")
    return CompactLayer(q)


@dataclass(frozen=True, slots=True, eq=False)
class TactileCompact(DataMessage):
    """Remote -> local (protocol version 2): a tactile frame with quantized layers, as a
    key frame or as a delta against the key frame ``key_seq``.

    Same header and scalar fields as :class:`TactileFrame`. A key frame (``key``) carries
    every layer in full; a delta carries only the layers with samples outside the sender's
    deadband, each dense or as (flat index, value) pairs; a receiver builds the frame from
    the key frame ``key_seq`` and this delta only (never from earlier deltas), and renders
    nothing from a delta whose key frame it does not hold. :mod:`shared.protocol.tactile_codec`
    encodes and decodes; ``docs/protocol.md`` specifies the bytes.
    """

    TYPE: ClassVar[str] = "tactile_compact"
    POLICY: ClassVar[StreamPolicy] = StreamPolicy.LATEST_WINS
    MIN_VERSION: ClassVar[int] = 2
    center_mm: tuple[float, float] = (0.0, 0.0)
    pitch_mm: float = 1.7
    key: bool = True
    key_seq: int = 0
    shape: tuple[int, int] = (0, 0)
    layers: Mapping[str, CompactLayer] = field(default_factory=dict)
    contact: bool = False
    force_n: float = 0.0
    indentation_mm: float = 0.0
    source_seq: int | None = None
    source_ts_us: int | None = None

    def to_wire(self) -> dict[str, Any]:
        out = self._head()
        layers: dict[str, Any] = {}
        for name, layer in self.layers.items():
            m: dict[str, Any] = {"q": array_to_wire(layer.q)}
            if layer.scale is not None:
                m["scale"] = layer.scale
                m["offset"] = layer.offset
            if layer.idx is not None:
                m["idx"] = array_to_wire(layer.idx)
            layers[name] = m
        out.update(key=self.key, key_seq=self.key_seq, shape=list(self.shape), layers=layers)
        _tactile_scalars_to_wire(self, out)
        return out

    @classmethod
    def from_wire(cls, d: Mapping[str, Any]) -> TactileCompact:
        t = cls.TYPE
        head = cls._read_head(d, t)
        key = read_bool(d, t, "key")
        key_seq = read_int(d, t, "key_seq")
        if key and key_seq != head["seq"]:
            raise FieldError(f"{t}.key_seq must equal seq in a key frame")
        if not key and key_seq >= head["seq"]:
            raise FieldError(f"{t}.key_seq must be < seq in a delta")
        rows, cols = (int(v) for v in read_vector(d, t, "shape", 2, lo=1, hi=4096))
        shape_raw = d["shape"]
        if any(isinstance(v, bool) or not isinstance(v, int) for v in shape_raw):
            raise FieldError(f"{t}.shape must be two integers")
        raw_layers = _read_layer_map(d, t, "layer map",
                                     need_height=" from a key frame" if key else None)
        layers = {name: _read_compact_layer(raw, f"{t}.layers.{name}", key, (rows, cols))
                  for name, raw in raw_layers.items()}
        for name, layer in layers.items():
            if key and layer.scale is not None and layer.offset is not None:
                lo, hi = LAYER_RANGES[name]
                vmin = layer.offset + layer.scale * float(layer.q.min())
                vmax = layer.offset + layer.scale * float(layer.q.max())
                if vmin < lo - layer.scale or vmax > hi + layer.scale:
                    raise FieldError(f"{t}.layers.{name} decodes to [{vmin:.6g}, {vmax:.6g}], "
                                     f"allowed [{lo}, {hi}]")
        return cls(**head, key=key, key_seq=key_seq, shape=(rows, cols), layers=layers,
                   **_read_tactile_scalars(d, t))


#: wire ``type`` -> message class
MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (Hello, Welcome, ClockPing, ClockPong, Stats, Error, Bye, PlatformState,
                ArmCommand, ArmState, TactileFrame, TactileCompact)
}
#: wire ``type`` of every latest-wins stream (derived from ``POLICY``)
LATEST_WINS_TYPES = frozenset(t for t, cls in MESSAGE_TYPES.items()
                              if cls.POLICY is StreamPolicy.LATEST_WINS)
