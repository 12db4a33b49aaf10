"""Link emulator: an asyncio TCP proxy that makes 127.0.0.1 look like a long-haul link.

The kernel's ``netem`` is not available here, so this proxy listens on a port, forwards
every accepted connection to a target ``host:port`` and delays the bytes of each direction
on the way. It forwards bytes, so it works for WebSocket and raw TCP alike.

Model (per direction, per connection; every read chunk - usually one application write -
is scheduled as a unit):

* **Serialization (bandwidth cap).** A chunk of ``n`` bytes occupies the link for
  ``8 n / bandwidth`` seconds after the previous one left (a token bucket with no burst).
* **Propagation + jitter.** Then it travels ``delay_ms + X`` with ``X ~ Normal(0,
  jitter_ms)``, clipped so the total is never negative.
* **Loss.** TCP cannot lose bytes, so a loss is modelled as what it costs the receiver:
  the chunk's segments (``mss_bytes`` each) are lost with a two-state (Gilbert) process whose
  long-run loss fraction is ``loss`` and mean burst length ``loss_burst_len`` segments; a
  chunk with a lost segment arrives ``loss_penalty_ms`` later (default: one round trip plus
  four jitters, ``2 delay + 4 jitter``, at least 1 ms - roughly fast retransmit / RACK on a
  busy stream; Linux's 200 ms minimum RTO for an idle stream is *not* modelled unless you
  pass ``loss_penalty_ms=200``).
* **In-order delivery.** A TCP stream never reorders bytes, so delivery times are made
  monotone per direction: a chunk is never delivered before the one in front of it. A late
  chunk therefore holds back the ones behind it (head-of-line blocking), as in real TCP.
* **Outages.** Scheduled ``(start_s, duration_s)`` windows after start, random ones
  (exponential gaps with mean ``outage_every_s`` and durations with mean
  ``outage_duration_s``) or :meth:`LinkEmulator.start_outage`. During an outage nothing is
  delivered (held data is delivered when it ends, like retransmissions after the path comes
  back); with ``close_on_outage`` every connection is reset at the outage start and new
  ones are refused until it ends.

The proxy applies backpressure instead of buffering without bound: once ``max_buffer_bytes``
are in flight in one direction it stops reading that side (like a full TCP window).
Delivery times are honoured to about -0.5/+1 ms (the event loop's timer resolution), so the
``lan`` profile effectively measures the proxy hop itself.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import heapq
import logging
import math
import random
import socket
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from shared.errors import ConfigError

__all__ = ["PROFILES", "DirectionStats", "LinkEmulator", "LinkProfile", "get_profile"]

log = logging.getLogger(__name__)

_READ_BYTES = 65536
_EARLY_S = 0.0005  # deliver a chunk this early rather than oversleep the loop's ms tick


@dataclass(frozen=True)
class LinkProfile:
    """Impairments of one direction of a link (both directions unless told otherwise).

    Attributes:
        name: label for reports.
        delay_ms: one-way propagation delay (round trip = 2 x this).
        jitter_ms: standard deviation of the per-chunk extra delay.
        loss: long-run fraction of segments lost, in [0, 1).
        loss_burst_len: mean number of consecutive lost segments (>= 1).
        loss_penalty_ms: extra delay of a chunk with a lost segment; None = ``2 delay +
            4 jitter`` (at least 1 ms).
        bandwidth_mbps: bottleneck rate in megabits per second; None = unlimited.
        outages: scheduled ``(start_s, duration_s)`` windows, seconds after start.
        outage_every_s: mean gap between random outages; None = no random outages.
        outage_duration_s: mean duration of a random outage.
        close_on_outage: reset connections when an outage starts, refuse new ones during it.
    """

    name: str = "custom"
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    loss: float = 0.0
    loss_burst_len: float = 1.0
    loss_penalty_ms: float | None = None
    bandwidth_mbps: float | None = None
    outages: tuple[tuple[float, float], ...] = ()
    outage_every_s: float | None = None
    outage_duration_s: float = 1.0
    close_on_outage: bool = False

    def __post_init__(self) -> None:
        finite = [self.delay_ms, self.jitter_ms, self.loss, self.loss_burst_len,
                  self.outage_duration_s]
        finite += [v for v in (self.loss_penalty_ms, self.bandwidth_mbps,
                               self.outage_every_s) if v is not None]
        finite += [v for window in self.outages for v in window]
        if not all(isinstance(v, int | float) and math.isfinite(v) for v in finite):
            raise ConfigError(f"link profile {self.name}: every number must be finite")
        if self.delay_ms < 0 or self.jitter_ms < 0:
            raise ConfigError(f"link profile {self.name}: delay and jitter must be >= 0")
        if not 0.0 <= self.loss < 1.0:
            raise ConfigError(f"link profile {self.name}: loss must be in [0, 1)")
        if self.loss_burst_len < 1.0:
            raise ConfigError(f"link profile {self.name}: loss_burst_len must be >= 1")
        if self.loss_penalty_ms is not None and self.loss_penalty_ms < 0:
            raise ConfigError(f"link profile {self.name}: loss_penalty_ms must be >= 0")
        if self.bandwidth_mbps is not None and self.bandwidth_mbps <= 0:
            raise ConfigError(f"link profile {self.name}: bandwidth_mbps must be > 0")
        if self.outage_every_s is not None and self.outage_every_s <= 0:
            raise ConfigError(f"link profile {self.name}: outage_every_s must be > 0")
        if self.outage_duration_s <= 0:
            raise ConfigError(f"link profile {self.name}: outage_duration_s must be > 0")
        for start_s, duration_s in self.outages:
            if start_s < 0 or duration_s <= 0:
                raise ConfigError(f"link profile {self.name}: outage windows need start >= 0 "
                                  "and duration > 0")

    @property
    def effective_loss_penalty_ms(self) -> float:
        """The extra delay a lost segment costs (see the module docstring)."""
        if self.loss_penalty_ms is not None:
            return self.loss_penalty_ms
        return max(1.0, 2.0 * self.delay_ms + 4.0 * self.jitter_ms)

    @property
    def round_trip_ms(self) -> float:
        """Nominal round trip through this link (both directions with this profile)."""
        return 2.0 * self.delay_ms

    def replace(self, **overrides: Any) -> LinkProfile:
        """Return a copy with the given fields changed (``None`` values are ignored)."""
        changes = {k: v for k, v in overrides.items() if v is not None}
        return dataclasses.replace(self, **changes)


#: named profiles (one-way figures; round trip is twice the delay)
PROFILES: dict[str, LinkProfile] = {
    # same building: switch + stack, essentially the proxy hop itself
    "lan": LinkProfile(name="lan", delay_ms=0.1, jitter_ms=0.02, bandwidth_mbps=1000.0),
    # 1,000 km of fibre is ~4.9 ms one way; routing and queues make ~10 ms (20 ms RTT)
    "city-1000km": LinkProfile(name="city-1000km", delay_ms=10.0, jitter_ms=1.0, loss=5e-4,
                               bandwidth_mbps=100.0),
    # transoceanic: ~180 ms round trip
    "intercontinental": LinkProfile(name="intercontinental", delay_ms=90.0, jitter_ms=3.0,
                                    loss=1e-3, bandwidth_mbps=50.0),
    # congested Wi-Fi last hop: large jitter and bursts of loss
    "bad-wifi": LinkProfile(name="bad-wifi", delay_ms=8.0, jitter_ms=5.0, loss=0.03,
                            loss_burst_len=5.0, bandwidth_mbps=20.0),
}


def get_profile(name_or_profile: str | LinkProfile) -> LinkProfile:
    """Return a named profile (or the profile given).

    Raises:
        ConfigError: unknown name.
    """
    if isinstance(name_or_profile, LinkProfile):
        return name_or_profile
    try:
        return PROFILES[name_or_profile]
    except KeyError as err:
        raise ConfigError(f"unknown link profile {name_or_profile!r}; known: "
                          f"{sorted(PROFILES)}") from err


# --------------------------------------------------------------------------- statistics


@dataclass
class DirectionStats:
    """Counters of one direction (``up``: client -> target, ``down``: target -> client).

    ``planned_delay_ms`` is the delay the model chose for each chunk; ``actual_delay_ms``
    what it really took from read to write (both bounded windows of recent chunks).
    """

    bytes: int = 0
    chunks: int = 0
    segments: int = 0
    lost_segments: int = 0
    delayed_by_loss: int = 0
    held_by_outage: int = 0
    planned_delay_ms: deque[float] = dataclasses.field(
        default_factory=lambda: deque(maxlen=100_000))
    actual_delay_ms: deque[float] = dataclasses.field(
        default_factory=lambda: deque(maxlen=100_000))

    def summary(self) -> dict[str, Any]:
        """Counters and delay percentiles (ms) as a plain dict."""
        out: dict[str, Any] = {k: getattr(self, k) for k in
                               ("bytes", "chunks", "segments", "lost_segments",
                                "delayed_by_loss", "held_by_outage")}
        for key in ("planned_delay_ms", "actual_delay_ms"):
            values = np.asarray(getattr(self, key), dtype=float)
            if values.size:
                p50, p99 = np.percentile(values, [50, 99])
                out[key] = {"p50": float(p50), "p99": float(p99),
                            "max": float(values.max()), "mean": float(values.mean())}
            else:
                out[key] = {"p50": None, "p99": None, "max": None, "mean": None}
        return out


class _Impairment:
    """The delay model of one direction of one connection (pure: times in, times out)."""

    def __init__(self, profile: LinkProfile, rng: random.Random, mss_bytes: int) -> None:
        self.profile = profile
        self._rng = rng
        self._mss = mss_bytes
        self._link_free_s = -math.inf
        self._last_delivery_s = -math.inf
        self._in_loss_burst = False
        # Gilbert chain: P(lost | previous lost) = 1 - 1/burst; P(lost | previous ok) = p
        # with stationary loss fraction p / (p + 1/burst) = loss
        exit_p = 1.0 / profile.loss_burst_len
        self._p_exit_burst = exit_p
        self._p_enter_burst = (profile.loss * exit_p / (1.0 - profile.loss)
                               if profile.loss > 0 else 0.0)

    def schedule(self, arrival_s: float, n_bytes: int,
                 stats: DirectionStats) -> float:
        """Return the delivery time of a chunk read at ``arrival_s``."""
        p = self.profile
        start_s = max(arrival_s, self._link_free_s)
        if p.bandwidth_mbps is not None:
            start_s += n_bytes * 8.0 / (p.bandwidth_mbps * 1e6)
        self._link_free_s = start_s
        delay_ms = p.delay_ms
        if p.jitter_ms > 0:
            delay_ms = max(0.0, delay_ms + self._rng.gauss(0.0, p.jitter_ms))
        segments = max(1, -(-n_bytes // self._mss))
        stats.segments += segments
        if self._p_enter_burst > 0:
            lost = 0
            for _ in range(segments):
                if self._in_loss_burst:
                    self._in_loss_burst = self._rng.random() >= self._p_exit_burst
                else:
                    self._in_loss_burst = self._rng.random() < self._p_enter_burst
                lost += self._in_loss_burst
            if lost:
                stats.lost_segments += lost
                stats.delayed_by_loss += 1
                delay_ms += p.effective_loss_penalty_ms
        deliver_s = max(start_s + delay_ms / 1000.0, self._last_delivery_s)
        self._last_delivery_s = deliver_s
        return deliver_s


# --------------------------------------------------------------------------- the proxy


class _Pipe:
    """One direction of one proxied connection: read, schedule, deliver in order."""

    def __init__(self, emu: LinkEmulator, reader: asyncio.StreamReader,
                 writer: asyncio.StreamWriter, impairment: _Impairment,
                 stats: DirectionStats) -> None:
        self._emu = emu
        self._reader, self._writer = reader, writer
        self._impairment = impairment
        self._stats = stats
        self._queue: deque[tuple[float, float, bytes]] = deque()
        self._buffered = 0
        self._has_data = asyncio.Event()
        self._room = asyncio.Event()
        self._room.set()
        self._eof = False

    async def read_loop(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            while self._buffered >= self._emu.max_buffer_bytes:
                self._room.clear()
                await self._room.wait()
            data = await self._reader.read(_READ_BYTES)
            now_s = loop.time()
            if not data:
                self._eof = True
                self._has_data.set()
                return
            deliver_s = self._impairment.schedule(now_s, len(data), self._stats)
            self._queue.append((deliver_s, now_s, data))
            self._buffered += len(data)
            self._stats.bytes += len(data)
            self._stats.chunks += 1
            self._stats.planned_delay_ms.append((deliver_s - now_s) * 1000.0)
            self._has_data.set()

    async def deliver_loop(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            if not self._queue:
                if self._eof:
                    with contextlib.suppress(OSError, RuntimeError):
                        if self._writer.can_write_eof():
                            self._writer.write_eof()
                    return
                self._has_data.clear()
                await self._has_data.wait()
                continue
            if not self._emu.link_up.is_set():
                self._stats.held_by_outage += len(self._queue)
                await self._emu.link_up.wait()
                continue
            wait_s = self._queue[0][0] - loop.time()
            if wait_s > _EARLY_S:
                await asyncio.sleep(wait_s)
                continue
            now_s = loop.time()
            parts = []
            while self._queue and self._queue[0][0] <= now_s + _EARLY_S:
                _, arrival_s, data = self._queue.popleft()
                self._stats.actual_delay_ms.append((now_s - arrival_s) * 1000.0)
                parts.append(data)
                self._buffered -= len(data)
            self._room.set()
            self._writer.write(b"".join(parts))
            await self._writer.drain()


class LinkEmulator:
    """A TCP proxy between ``listen`` and ``target`` with link impairments.

    Args:
        listen: ``(host, port)`` to listen on; port 0 picks a free one (see :attr:`port`).
        target: ``(host, port)`` to forward to.
        profile: a :data:`PROFILES` name or a :class:`LinkProfile` (both directions).
        reverse_profile: a different profile for target -> client (asymmetric links).
        seed: seed of the random impairments (None: random).
        max_buffer_bytes: bytes held per direction before the proxy stops reading.
        mss_bytes: segment size for the loss model.

    Example::

        async with LinkEmulator(listen=("127.0.0.1", 0), target=("127.0.0.1", 8765),
                                profile="city-1000km") as emu:
            url = f"ws://127.0.0.1:{emu.port}/"
    """

    def __init__(self, *, listen: tuple[str, int] = ("127.0.0.1", 0),
                 target: tuple[str, int], profile: str | LinkProfile = "lan",
                 reverse_profile: str | LinkProfile | None = None, seed: int | None = None,
                 max_buffer_bytes: int = 4 * 1024 * 1024, mss_bytes: int = 1448) -> None:
        if max_buffer_bytes < _READ_BYTES or mss_bytes < 1:
            raise ConfigError(f"max_buffer_bytes must be >= {_READ_BYTES}, mss_bytes >= 1")
        self.listen = listen
        self.target = target
        self.profile = get_profile(profile)
        self.reverse_profile = get_profile(reverse_profile or self.profile)
        self.max_buffer_bytes = max_buffer_bytes
        self.mss_bytes = mss_bytes
        self._rng = random.Random(seed)
        self.up_stats = DirectionStats()
        self.down_stats = DirectionStats()
        self.connections_total = 0
        self.connections_open = 0
        self.connections_refused = 0
        self.target_failures = 0
        self.outages_started = 0
        #: set while the link is up; cleared during an outage
        self.link_up = asyncio.Event()
        self.link_up.set()
        self._server: asyncio.Server | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self._writers: set[asyncio.StreamWriter] = set()
        self._refuse_new = False
        self._outage_until_s = -math.inf
        self._outage_task: asyncio.Task[None] | None = None
        self._target_failure_logged = False

    @property
    def port(self) -> int:
        """The port the proxy listens on (after :meth:`start`)."""
        if self._server is None or not self._server.sockets:
            raise ConfigError("the link emulator is not started")
        return int(self._server.sockets[0].getsockname()[1])

    @property
    def host(self) -> str:
        """The address the proxy listens on."""
        return self.listen[0]

    async def __aenter__(self) -> LinkEmulator:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def start(self) -> None:
        """Listen and start the outage schedule.

        Raises:
            ConfigError: the listen address cannot be bound.
        """
        try:
            self._server = await asyncio.start_server(self._on_client, self.listen[0],
                                                      self.listen[1])
        except OSError as err:
            raise ConfigError(f"link emulator cannot listen on {self.listen}: {err}") from err
        self._started_s = asyncio.get_running_loop().time()
        if self.profile.outages or self.profile.outage_every_s is not None:
            self._outage_task = asyncio.get_running_loop().create_task(self._outage_schedule())
        log.info("link emulator %s:%d -> %s:%d, profile %s", self.listen[0], self.port,
                 self.target[0], self.target[1], self.profile.name)

    async def close(self) -> None:
        """Stop listening and reset every proxied connection."""
        if self._outage_task is not None:
            self._outage_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._outage_task
        if self._server is not None:
            self._server.close()
        self._reset_connections()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._server is not None:
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._server.wait_closed(), 1.0)

    def start_outage(self, duration_s: float, *, close_connections: bool = False) -> None:
        """Cut the link now for ``duration_s`` (extends a running outage).

        Args:
            duration_s: how long nothing is delivered.
            close_connections: also reset open connections and refuse new ones meanwhile.
        """
        loop = asyncio.get_running_loop()
        until_s = loop.time() + duration_s
        self.outages_started += 1
        self.link_up.clear()
        if close_connections:
            self._refuse_new = True
            self._reset_connections()
        if until_s > self._outage_until_s:
            self._outage_until_s = until_s
            loop.call_at(until_s, self._end_outage_if_due)

    def _end_outage_if_due(self) -> None:
        if asyncio.get_running_loop().time() + 1e-6 >= self._outage_until_s:
            self._refuse_new = False
            self.link_up.set()

    def _outage_windows(self) -> Iterator[tuple[float, float]]:
        scheduled = sorted(self.profile.outages)
        p = self.profile

        def random_windows() -> Iterator[tuple[float, float]]:
            t = 0.0
            while p.outage_every_s is not None:
                t += self._rng.expovariate(1.0 / p.outage_every_s)
                duration_s = self._rng.expovariate(1.0 / p.outage_duration_s)
                yield (t, duration_s)
                t += duration_s

        return heapq.merge(scheduled, random_windows())

    async def _outage_schedule(self) -> None:
        loop = asyncio.get_running_loop()
        for start_s, duration_s in self._outage_windows():
            await asyncio.sleep(max(0.0, self._started_s + start_s - loop.time()))
            log.info("link emulator: outage of %.3f s", duration_s)
            self.start_outage(duration_s, close_connections=self.profile.close_on_outage)

    def _reset_connections(self) -> None:
        for writer in list(self._writers):
            sock = writer.get_extra_info("socket")
            if sock is not None:  # RST rather than FIN: what a dead path looks like
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER,
                                    b"\x01\x00\x00\x00\x00\x00\x00\x00")
            writer.transport.abort()
        self._writers.clear()

    def stats(self) -> dict[str, Any]:
        """Counters and delay percentiles of both directions, as a plain dict."""
        return {"profile": self.profile.name, "reverse_profile": self.reverse_profile.name,
                "connections_total": self.connections_total,
                "connections_open": self.connections_open,
                "connections_refused": self.connections_refused,
                "target_failures": self.target_failures,
                "outages_started": self.outages_started,
                "link_up": self.link_up.is_set(),
                "up": self.up_stats.summary(), "down": self.down_stats.summary()}

    async def _on_client(self, c_reader: asyncio.StreamReader,
                         c_writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        try:
            await self._proxy(c_reader, c_writer)
        except asyncio.CancelledError:
            # close() cancels handler tasks; asyncio's stream server would log a cancelled
            # client_connected_cb as an error, so the handler ends normally instead
            pass
        except ConnectionError as err:
            if log.isEnabledFor(logging.DEBUG):
                log.debug("proxied connection ended: %s", err)
        finally:
            c_writer.close()  # flushes what was delivered; a reset already aborted it
            if task is not None:
                self._tasks.discard(task)

    async def _proxy(self, c_reader: asyncio.StreamReader,
                     c_writer: asyncio.StreamWriter) -> None:
        if self._refuse_new:
            self.connections_refused += 1
            return
        try:
            t_reader, t_writer = await asyncio.open_connection(*self.target)
        except OSError as err:
            self.target_failures += 1
            if not self._target_failure_logged:
                log.warning("link emulator cannot reach target %s:%d: %s", *self.target, err)
                self._target_failure_logged = True
            return
        self.connections_total += 1
        self.connections_open += 1
        self._writers.update((c_writer, t_writer))
        up = _Pipe(self, c_reader, t_writer,
                   _Impairment(self.profile, self._rng, self.mss_bytes), self.up_stats)
        down = _Pipe(self, t_reader, c_writer,
                     _Impairment(self.reverse_profile, self._rng, self.mss_bytes),
                     self.down_stats)
        loop = asyncio.get_running_loop()
        tasks = [loop.create_task(coro) for coro in
                 (up.read_loop(), up.deliver_loop(), down.read_loop(), down.deliver_loop())]
        try:
            # a half-close is forwarded; the connection ends when both deliveries are done
            # or any side fails
            pending = set(tasks)
            while pending:
                done, pending = await asyncio.wait(pending,
                                                   return_when=asyncio.FIRST_COMPLETED)
                if any(t.exception() is not None for t in done if not t.cancelled()):
                    break
                if tasks[1] in done and tasks[3] in done:
                    break
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            self.connections_open -= 1
            self._writers.discard(c_writer)
            self._writers.discard(t_writer)
            t_writer.close()
