"""Relay workers joined by NATS: a station may connect to any worker of any host.

Each relay process (a *worker*) serves its own connections exactly as the single-process
relay does (:mod:`relay_server.server`, :mod:`relay_server.session`); this module adds what
makes several of them one relay:

* **Directory.** Every worker publishes a heartbeat on ``<prefix>.hb`` every
  ``HEARTBEAT_S`` and at once when a peer joins or leaves: its id, pid, host, ports, and which
  roles and how many observers of which sessions it holds, its counters, its clock fields
  (send time, boot id, wall anchor, echoes of the others' heartbeats) and the clock offset
  and bound of each station it holds. A worker not heard from for ``3 x HEARTBEAT_S`` is gone
  (a killed worker says nothing; its entry is dropped after ``_FORGET_S``); a worker that
  closes says so. A heartbeat of another shape (another release, a bug, a stray publisher)
  is ignored (``nats_bad_heartbeat``).
* **Pairing.** A station may join any worker; a role held by another live worker is refused
  (``role_taken``, as on one relay; a station whose worker died retries within its grace
  window until the dead worker expires).
* **Forwarding.** A station's message goes to the receiving station directly when it is on
  the same worker (no NATS hop). Otherwise the worker publishes it once to each worker that
  holds the receiver or observers of the session (``<prefix>.w.<worker id>``): an envelope
  with the message as received (station hops only), its ``relay_in`` time, its send time on
  the relay clock, and the ``nats_out`` time. The receiving worker queues it with the stream's
  policy (latest-wins slot or ordered queue: NATS keeps one publisher's order) and its writer
  stamps ``relay_in``, ``nats_out``, ``nats_in``, ``relay_out``. Books: the uplink ledger is
  the sender's worker's; relay residence (``relay_in -> relay_out``), end-to-end and the NATS
  leg (``nats_out -> nats_in``) are the receiver's worker's. The sender puts its stamps of an
  envelope on the receiver's clock, with the receiver's offset measured on their heartbeats
  (:mod:`relay_server.worker_clocks`; exact for workers on one kernel), so the hosts' clocks
  need not agree; station offsets are each estimated against the worker the station is
  connected to, as before, and a worker's ``stats`` report a station held by another worker
  with that worker's heartbeat's figure moved onto its own clock
  (:meth:`ClusterLink.station_clock`), so that the stations of a pair split across workers
  can age-check each other's stamps.
* **Limits.** Envelopes wait in a bounded queue for the publisher (``nats_queue_full``); one
  more than 0.5 s old since it reached the relay is dropped (``nats_stale``) before it is
  published and again when it arrives (the NATS client takes envelopes in while a stalled
  server does not read them), and nothing is buffered while NATS reconnects
  (``nats_publish_failed``): no frame is delivered late after a NATS stall or outage. An
  envelope of another shape, or with a stream its sender's role does not send, is dropped
  (``nats_bad_envelope``). A message over the NATS server's max payload (1 MB by default)
  is not forwarded across workers (``nats_too_large``). An ordered
  message refused by the receiving worker (``queue_full``, ``no_peer``) is counted there
  (``nats_undelivered_<code>``); the sender gets no ``error`` for it.

:mod:`relay_server.workers` runs N workers on one host, one process each, all bound to the
same ports with SO_REUSEPORT, and restarts a worker that dies or hangs.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import re
import socket
import ssl
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack

from relay_server.config import RelayConfig
from relay_server.session import STREAMS_OF, Session
from relay_server.worker_clocks import WorkerClocks
from shared.errors import ConfigError, RemoteProtocolError, RoleTakenError
from shared.protocol import DataMessage, decode, encode
from shared.timebase import wall_anchor_ns

__all__ = ["HEARTBEAT_S", "ClusterLink", "redact_url"]

log = logging.getLogger(__name__)

HEARTBEAT_S = 0.5
_EXPIRE_S = 3 * HEARTBEAT_S
_OUT_QUEUE = 20_000  # envelopes waiting for the NATS connection
_MAX_QUEUED_US = 500_000  # an envelope older than this (since relay_in): not sent, not delivered
_FORGET_S = 60.0  # a worker not heard from for this long is dropped from the directory
#: a station's clock against its worker's may drift this fast (the clock filter's allowance)
_STATION_DRIFT_PPM = 500.0
#: a worker id is one token of a NATS subject (no space, dot or wildcard)
_WORKER_ID = re.compile(r"[^\s.*>]{1,256}")
_STATION_ROLES = frozenset(STREAMS_OF)
#: the NATS header of an envelope whose times are on its receiver's clock
_SYNCED = {"tt-clock": "receiver"}


def redact_url(url: str) -> str:
    """``url`` without its user information (``nats://user:password@host`` ->
    ``nats://***@host``: a token alone is a user name), to show it in logs and ``/status``;
    each URL of a comma-separated list."""
    parts = []
    for part in url.split(","):
        scheme, sep, rest = part.partition("://")
        if not sep:
            scheme, rest = "", part
        if "@" in rest:  # up to the LAST '@': a password may hold '/' (found by review)
            rest = "***@" + rest.rpartition("@")[2]
        parts.append(f"{scheme}{sep}{rest}")
    return ",".join(parts)


class ClusterLink:
    """One worker's membership in a cluster (see the module docstring).

    Args:
        config: the relay settings (``nats_url``, ``nats_subject_prefix``).
        sessions: the worker's sessions (the relay's dictionary, read live).
        counters: the worker's counters (``nats_*`` are added).
        ports: returns the worker's bound ``{"ws": port, "tcp": port}``.
        anchor_ns: the worker's clock: wall time minus the monotonic clock. It must be
            the clock of the times given to :meth:`forward` (the relay's ``now_us``, whose
            anchor is the default: :func:`shared.timebase.wall_anchor_ns`); tests give two
            links in one process different clocks with it.
        worker_id: the worker's name in the cluster (default ``<host>-<pid>``).
    """

    def __init__(self, config: RelayConfig, sessions: dict[str, Session],
                 counters: Counter[str], ports: Callable[[], dict[str, int]],
                 anchor_ns: int | None = None, worker_id: str | None = None) -> None:
        if config.nats_url is None:
            raise ConfigError("a cluster needs relay.nats_url")
        self.url = config.nats_url
        self.ca_file = config.nats_ca_file
        self.connect_timeout_s = config.nats_connect_timeout_s
        self.prefix = config.nats_subject_prefix
        self.sessions = sessions
        self.counters = counters
        self.ports = ports
        self._anchor_ns = wall_anchor_ns() if anchor_ns is None else int(anchor_ns)
        self.worker_id = worker_id or f"{socket.gethostname()}-{os.getpid()}".replace(".", "_")
        self.workers: dict[str, tuple[float, dict[str, Any]]] = {}  # id -> (seen, heartbeat)
        #: the other workers' clocks against this one's (envelopes go out on theirs)
        self.clocks = WorkerClocks(self.worker_id, _boot_id(), self._anchor_ns)
        self._nc: Any = None
        self._out: asyncio.Queue[tuple[str, tuple[Any, ...]]] = asyncio.Queue(_OUT_QUEUE)
        self._changed = asyncio.Event()
        self._tasks: list[asyncio.Task[None]] = []

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Connect to NATS, subscribe, start the heartbeat and the publisher.

        Raises:
            ConfigError: the NATS server cannot be reached.
        """
        import nats
        from nats.errors import NoServersError

        last_error: list[Exception] = []  # the last one, for the start error

        async def on_error(err: Exception) -> None:
            self.counters["nats_errors"] += 1
            last_error[:] = [err]
            log.warning("NATS: %s", err)

        tls = None
        if self.url.startswith("tls://") or self.ca_file is not None:
            tls = ssl.create_default_context(cafile=str(self.ca_file) if self.ca_file else None)
        # TLS first, before the server's INFO: otherwise nats-py goes TLS only when the
        # server's INFO asks for it, and a plain server (or a machine in the middle that
        # leaves tls_required out) received the password and every frame in clear. The NATS
        # server needs `handshake_first` in its tls block (deploy/config/nats.conf).
        try:
            # nats-py retries an unreachable server for ever when reconnects are unlimited:
            # the first connection gets a deadline, later ones are retried
            async with asyncio.timeout(self.connect_timeout_s):
                self._nc = await nats.connect(
                    servers=[self.url], name=f"teletouch-relay-{self.worker_id}",
                    connect_timeout=5, allow_reconnect=True, max_reconnect_attempts=-1,
                    reconnect_time_wait=0.5, error_cb=on_error, tls=tls,
                    tls_handshake_first=tls is not None,
                    pending_size=0)  # nothing buffered while reconnecting: no stale frames
        except (NoServersError, OSError, TimeoutError, ssl.SSLError) as err:
            # the deadline's TimeoutError says less than the connection's own last error
            cause = last_error[0] if last_error and isinstance(err, TimeoutError) else err
            raise ConfigError(f"cannot reach the NATS server {redact_url(self.url)} within "
                              f"{self.connect_timeout_s:g} s (nats_connect_timeout_s): "
                              f"{str(cause) or type(cause).__name__}") from err
        await self._nc.subscribe(f"{self.prefix}.hb", cb=self._on_heartbeat)
        await self._nc.subscribe(f"{self.prefix}.w.{self.worker_id}", cb=self._on_data)
        self._tasks = [asyncio.create_task(self._heartbeat_loop(), name="cluster-heartbeat"),
                       asyncio.create_task(self._publish_loop(), name="cluster-publisher")]
        log.info("relay worker %s joined the cluster on %s (subjects %s.*)", self.worker_id,
                 redact_url(self.url), self.prefix)

    async def close(self) -> None:
        """Say goodbye to the other workers and disconnect."""
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._nc is not None and not self._nc.is_closed:
            with contextlib.suppress(Exception):
                await self._nc.publish(f"{self.prefix}.hb", msgpack.packb(
                    {"w": self.worker_id, "gone": True}))
                await self._nc.flush(timeout=2)
            with contextlib.suppress(Exception):
                await self._nc.close()

    # ------------------------------------------------------------------ directory

    def _live(self) -> dict[str, dict[str, Any]]:
        now = time.monotonic()
        return {w: hb for w, (seen, hb) in self.workers.items() if now - seen < _EXPIRE_S}

    def check_role(self, session_id: str, role: str) -> None:
        """Refuse a station role that another live worker holds.

        Raises:
            RoleTakenError: it does.
        """
        if role == "observer":
            return
        for worker, hb in self._live().items():
            held = hb["sessions"].get(session_id)
            if held is not None and role in held[0]:
                raise RoleTakenError(f"role {role!r} is already taken in session "
                                     f"{session_id!r} (on relay worker {worker})")

    def station_clock(self, session_id: str, role: str) -> tuple[int, int] | None:
        """The clock offset of station ``role`` of a session when another live worker holds
        it, moved onto this worker's clock: (station clock minus this worker's, a bound on
        its error now: the station's bound when that worker's heartbeat was sent, plus the
        bound on that worker's offset, plus the station's drift since); None when no live
        worker reports it, or that worker's clock is not known yet."""
        now = self._now()
        for worker, hb in self._live().items():
            entry = hb["clocks"].get(session_id, {}).get(role)
            if entry is None:
                continue
            theirs = self.clocks.estimate(worker, now)  # its clock minus ours
            if theirs is None:
                return None
            offset, bound = entry  # station minus its clock, at its send time hb["t"]
            age_us = max(0, now - (hb["t"] - theirs[0]))
            return offset + theirs[0], math.ceil(
                bound + theirs[1] + _STATION_DRIFT_PPM * 1e-6 * age_us)
        return None

    def changed(self) -> None:
        """A peer joined or left: publish a heartbeat now."""
        self._changed.set()

    def _now(self) -> int:
        """This worker's clock (``now_us`` unless another anchor was given)."""
        return (time.monotonic_ns() + self._anchor_ns) // 1000

    def _heartbeat(self) -> dict[str, Any]:
        return {"w": self.worker_id, "pid": os.getpid(), "host": socket.gethostname(),
                "ports": self.ports(),
                "sessions": {sid: [sorted(s.stations), len(s.observers)]
                             for sid, s in self.sessions.items()},
                "counters": dict(self.counters), "drops": self._drops()}

    def _station_clocks(self, t_us: int) -> dict[str, dict[str, list[int]]]:
        """Per session and role, the offset of each station this worker holds (station clock
        minus this worker's) and a bound on its error at ``t_us``, where known."""
        out: dict[str, dict[str, list[int]]] = {}
        for sid, session in self.sessions.items():
            for role, peer in session.stations.items():
                offset, bound = peer.clock.offset_us, peer.clock.uncertainty_us(t_us)
                if offset is not None and bound is not None:
                    out.setdefault(sid, {})[role] = [round(offset), math.ceil(bound + 0.5)]
        return out

    def _drops(self) -> dict[str, int]:
        """Messages this worker's sessions dropped, by reason (latest_wins, queue_full, ...)."""
        out: Counter[str] = Counter()
        for session in self.sessions.values():
            for direction in session.directions.values():
                for ledger in direction.uplink.values():
                    out.update(ledger.dropped)
        return dict(out)

    async def _heartbeat_loop(self) -> None:
        while True:
            self._changed.clear()
            self._forget_silent()
            hb = self._heartbeat()
            t_us = self._now()
            self.clocks.stamp(hb, t_us)  # last: building the rest takes time
            hb["clocks"] = self._station_clocks(t_us)
            try:
                await self._nc.publish(f"{self.prefix}.hb", msgpack.packb(hb))
            except Exception as err:  # NATS down: keep serving local sessions, retry
                self.counters["nats_heartbeat_failed"] += 1
                log.debug("heartbeat not published: %s", err)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(HEARTBEAT_S):
                    await self._changed.wait()

    async def _on_heartbeat(self, msg: Any) -> None:
        received_us = self._now()
        try:
            hb = _checked_heartbeat(msgpack.unpackb(msg.data, raw=False))
        except (ValueError, TypeError, msgpack.UnpackException):
            # another release's shape, a bug, a stray publisher: ignored, as if not heard
            self.counters["nats_bad_heartbeat"] += 1
            return
        worker = hb["w"]
        if worker == self.worker_id:
            return
        if hb.get("gone"):
            self.workers.pop(worker, None)  # its clock goes at the next _forget_silent
        else:
            self.workers[worker] = (time.monotonic(), hb)
            self.clocks.heard(worker, hb, received_us)

    def _forget_silent(self) -> None:
        """Drop the workers not heard from for ``_FORGET_S`` (killed ones say nothing)."""
        now = time.monotonic()
        for worker in [w for w, (seen, _) in self.workers.items() if now - seen > _FORGET_S]:
            del self.workers[worker]
        for worker in self.clocks.known() - set(self.workers):
            self.clocks.forget(worker)

    # ------------------------------------------------------------------ forwarding

    def forward(self, session_id: str, sender_role: str, msg: DataMessage, t_in_us: int,
                sent_ref_us: int | None, need_station: bool) -> bool:
        """Publish ``msg`` to the workers holding the session's observers and (when
        ``need_station``) its receiving station; True when one holds that station."""
        receiver = "remote" if sender_role == "local" else "local"
        station_elsewhere = False
        data: bytes | None = None
        for worker, hb in self._live().items():
            held = hb["sessions"].get(session_id)
            if held is None:
                continue
            to_station = need_station and receiver in held[0]
            if not to_station and not held[1]:
                continue
            station_elsewhere = station_elsewhere or to_station
            if data is None:
                data = encode(msg, validate=False)
            try:
                self._out.put_nowait((worker, (session_id, sender_role, t_in_us, sent_ref_us,
                                               data, to_station)))
            except asyncio.QueueFull:
                self.counters["nats_queue_full"] += 1
        return station_elsewhere

    async def _publish_loop(self) -> None:
        from nats.errors import MaxPayloadError

        while True:
            worker, body = await self._out.get()
            t_out = self._now()
            if t_out - body[2] > _MAX_QUEUED_US:  # waited too long for NATS: stale, dropped
                self.counters["nats_stale"] += 1
                continue
            # the stamps on the receiver's clock (relay_in, the sender's send time, nats_out)
            sid, role, t_in_us, sent_ref_us, data, to_station = body
            theirs = self.clocks.to_theirs
            ref = None if sent_ref_us is None else theirs(worker, sent_ref_us)
            if ref is not None and not _is_time(ref):
                ref = None  # a station's nonsense stamp: forwarded, as on one relay
            envelope = msgpack.packb([sid, role, theirs(worker, t_in_us), ref, data,
                                      to_station, theirs(worker, t_out)])  # ..., nats_out
            # the times are on the receiver's clock only once its offset is known: then it
            # may judge the envelope's age (a header, which a receiver of an older release
            # ignores)
            synced = _SYNCED if self.clocks.offset_us(worker) is not None else None
            try:
                await self._nc.publish(f"{self.prefix}.w.{worker}", envelope, headers=synced)
                self.counters["nats_sent"] += 1
            except MaxPayloadError:
                self.counters["nats_too_large"] += 1
            except Exception as err:  # NATS down: the message is lost, like a dropped link
                self.counters["nats_publish_failed"] += 1
                log.debug("NATS publish failed: %s", err)

    async def _on_data(self, msg: Any) -> None:
        t_nats_in = self._now()
        try:
            sid, sender_role, t_in_us, sent_ref_us, data, to_station, t_out = \
                msgpack.unpackb(msg.data, raw=False)
            message = decode(data)
            if not (_is_time(t_in_us) and _is_time(t_out)
                    and (sent_ref_us is None or _is_time(sent_ref_us))):
                raise TypeError("an envelope's times must be integer microseconds")
            if not (isinstance(sid, str) and isinstance(to_station, bool)
                    and sender_role in _STATION_ROLES
                    and isinstance(message, DataMessage)
                    and message.TYPE in STREAMS_OF[sender_role]):
                raise TypeError("not a stream the sender's role sends")
        except (ValueError, TypeError, msgpack.UnpackException, RemoteProtocolError):
            self.counters["nats_bad_envelope"] += 1
            return
        # held up on the way (a NATS stall); judged only on times the sender put on this
        # worker's clock (before the workers' clocks are known, the sender's check alone:
        # a clock difference is no stall, found by review)
        if getattr(msg, "headers", None) == _SYNCED and t_nats_in - t_in_us > _MAX_QUEUED_US:
            self.counters["nats_stale"] += 1
            return
        session = self.sessions.get(sid)
        if session is None:
            self.counters["nats_no_session"] += 1
            return
        self.counters["nats_received"] += 1
        direction = session.directions["local_to_remote" if sender_role == "local"
                                       else "remote_to_local"]
        direction.nats.record(None, t_out, t_nats_in)
        err = session.deliver(sender_role, message, t_in_us, sent_ref_us,
                              (("relay", "nats_out", t_out), ("relay", "nats_in", t_nats_in)),
                              to_station)
        if err is not None:
            self.counters[f"nats_undelivered_{err.code}"] += 1

    # ------------------------------------------------------------------ status

    def status(self) -> dict[str, Any]:
        """The cluster as this worker sees it (every live worker, this one included)."""
        now = time.monotonic()
        workers: dict[str, Any] = {}
        for worker, (seen, hb) in sorted(self.workers.items()):
            if now - seen < _EXPIRE_S:
                workers[worker] = {**_worker_doc(hb, now - seen),
                                   **self.clocks.status(worker, self._now())}
        workers[self.worker_id] = {**_worker_doc(self._heartbeat(), 0.0), "clock_offset_us": 0,
                                   "clock_uncertainty_us": 0, "nats_rtt_min_us": None,
                                   "same_kernel": True}
        return {"worker": self.worker_id, "nats_url": redact_url(self.url),
                "nats_connected": bool(self._nc is not None and self._nc.is_connected),
                "sessions": len({sid for doc in workers.values() for sid in doc["sessions"]}),
                "workers": workers}


def _is_time(value: object) -> bool:
    """An integer microsecond time msgpack can carry (a peer's bug is not one)."""
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value < 2**63


_is_count = _is_time  # a count is a non-negative integer msgpack can carry too


def _counts(raw: object) -> dict[str, int]:
    if not (isinstance(raw, dict) and all(isinstance(k, str) and _is_count(v)
                                          for k, v in raw.items())):
        raise TypeError("not a map of counts")
    return raw


def _checked_heartbeat(raw: object) -> dict[str, Any]:
    """A peer's heartbeat in the shape this worker reads, or an error (ValueError,
    TypeError) for anything else: the directory fields are checked here, the clock fields
    (``t`` only when station clocks come with it) by :class:`WorkerClocks`."""
    if not isinstance(raw, dict):
        raise TypeError("a heartbeat is a map")
    worker = raw.get("w")
    if not (isinstance(worker, str) and _WORKER_ID.fullmatch(worker)):
        raise ValueError("a heartbeat's worker id must be one subject token")
    if raw.get("gone") is True:
        return {"w": worker, "gone": True}
    sessions = raw.get("sessions")
    if not isinstance(sessions, dict):
        raise TypeError("a heartbeat's sessions are a map")
    for sid, held in sessions.items():
        if not (isinstance(sid, str) and isinstance(held, list) and len(held) == 2
                and isinstance(held[0], list) and set(held[0]) <= _STATION_ROLES
                and _is_count(held[1])):
            raise TypeError(f"session {sid!r}: not [roles, observers]")
    clocks = raw.get("clocks", {})
    if not isinstance(clocks, dict):
        raise TypeError("a heartbeat's station clocks are a map")
    for sid, roles in clocks.items():
        if not (isinstance(sid, str) and isinstance(roles, dict)
                and set(roles) <= _STATION_ROLES
                and all(isinstance(e, list) and len(e) == 2 and _is_int(e[0])
                        and abs(e[0]) < 2**62 and _is_count(e[1]) for e in roles.values())):
            raise TypeError(f"session {sid!r}: not station clocks")
    if clocks and not (_is_int(raw.get("t")) and abs(raw["t"]) < 2**62):
        raise TypeError("station clocks need the heartbeat's send time")
    pid, host, ports = raw.get("pid"), raw.get("host"), raw.get("ports")
    if not ((pid is None or _is_count(pid)) and (host is None or isinstance(host, str))):
        raise TypeError("a heartbeat's pid or host")
    return {**raw, "sessions": sessions, "clocks": clocks,
            "ports": None if ports is None else _counts(ports),
            "counters": _counts(raw.get("counters", {})), "drops": _counts(raw.get("drops", {}))}


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _boot_id() -> str | None:
    """The running kernel's boot id (Linux), None elsewhere: workers with the same one
    read one monotonic clock."""
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip() or None
    except OSError:
        return None


def _worker_doc(hb: dict[str, Any], age_s: float) -> dict[str, Any]:
    return {"pid": hb.get("pid"), "host": hb.get("host"), "ports": hb.get("ports"),
            "heartbeat_age_s": round(age_s, 3), "counters": hb["counters"],
            "drops": hb["drops"],
            "sessions": {sid: {"stations": held[0], "observers": held[1]}
                         for sid, held in hb["sessions"].items()}}
