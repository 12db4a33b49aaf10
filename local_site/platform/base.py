"""The XYZ platform device kind: one base class, backends implement a few private methods.

:class:`XYZPlatform` owns everything that does not depend on how samples reach the host:
counts -> mm, zeroing, workspace clamping, the 32-bit counter wrap, board-clock unwrapping,
velocity, the board-clock -> host-clock mapping, a board restart on an open link, waiting with
timeouts, and the link-health checks; the lifecycle (``connect``/``disconnect``, context
manager, errors by phase) is :class:`~shared.devices.base.Device`'s. A backend implements
``_connect()`` / ``_disconnect()`` and, from its own reader thread, hands each raw
:class:`~local_site.platform.protocol.EncoderSample` to :meth:`XYZPlatform._publish` (or a
link failure to :meth:`XYZPlatform._link_failed`).

Typical use (lerobot habit)::

    with open_platform("sim") as platform:        # or "/dev/ttyUSB0", "socket://host:port"
        sample = platform.read_state(timeout_s=0.1)
        sample.position_mm, sample.velocity_mm_s, sample.t_us
"""

from __future__ import annotations

import collections
import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

from local_site.platform.kinematics import PlatformGeometry, WrapUnwrapper
from local_site.platform.protocol import (
    PROTOCOL_VERSION,
    BoardInfo,
    DecoderStats,
    EncoderSample,
)
from shared.devices import Device
from shared.errors import (
    ConfigError,
    DeviceInitError,
    DeviceNotConnectedError,
    DeviceOperationError,
    DeviceTimeoutError,
)
from shared.timebase import monotonic_s, now_us

__all__ = ["PlatformSample", "PlatformStats", "XYZPlatform"]

log = logging.getLogger(__name__)

Vec3 = tuple[float, float, float]
#: the counters are 32-bit two's complement: a difference of two is taken modulo 2^32
_HALF, _MASK = 1 << 31, (1 << 32) - 1
#: the clock offset may rise 1 us per this many us of board time (1 %: see _publish)
_CREEP_PER_US = 100
#: a board "started since its last sample" when its clock reads at most the host time since
#: then, plus 2 % and this (link latency, jitter, a clock started a little before the first
#: sample); see _booted_since_last
_BOOT_SLACK_US = 100_000
#: the fastest sample rate the INFO frame can state (uint16 Hz), for a board that sent none
_MAX_RATE_HZ = 65_536
#: no INFO seen yet in the driver's life: samples wait for it (see ``_info_mismatch``)
_AWAITING_INFO = ConfigError("no INFO frame from the board yet")


@dataclass(frozen=True, slots=True)
class PlatformSample:
    """One platform reading.

    Attributes:
        position_mm: (x, y, z) in platform coordinates, clamped to the workspace.
        velocity_mm_s: finite-difference velocity over the last ``velocity_window_s``.
        t_us: capture time on the host wall clock (board latch time mapped to the host clock,
            so USB/OS jitter does not enter it), integer microseconds.
        seq: board sample number, unwrapped (increases while connected; starts again when
            the board restarts or the link is reopened).
        board_t_us: board clock at the latch instant, unwrapped, microseconds.
        clamped: True when the raw position lay outside the workspace.
    """

    position_mm: Vec3
    velocity_mm_s: Vec3
    t_us: int
    seq: int
    board_t_us: int
    clamped: bool = False


@dataclass(frozen=True, slots=True)
class PlatformStats:
    """Health of the encoder link.

    Every counter is a total since the driver was created, over all its connections.

    Attributes:
        bytes_in: bytes received.
        frames_ok: valid frames decoded.
        crc_errors: candidate frames rejected by their CRC.
        garbage_bytes: bytes skipped while resynchronising.
        unknown_types: well-formed frames of a type this driver does not know.
        samples_missed: gaps in the board's sample sequence (frames lost or dropped).
        samples_clamped: samples that fell outside the workspace.
        reads: samples returned by ``read_state``.
        board_restarts: times the board restarted: on an open link (its ``seq`` or clock
            went back, or it described itself differently), or while its link was down (its
            clock says it started after the previous connection's last sample).
        duplicates: frames equal to the previous one in seq and board time (a link that
            delivered one twice), dropped.
        position_rebases: restarts after which the position was continued from the last
            sample before them (the board's counters began again where the platform was;
            travel while the board was down is not seen).
    """

    bytes_in: int = 0
    frames_ok: int = 0
    crc_errors: int = 0
    garbage_bytes: int = 0
    unknown_types: int = 0
    samples_missed: int = 0
    samples_clamped: int = 0
    reads: int = 0
    board_restarts: int = 0
    duplicates: int = 0
    position_rebases: int = 0


class XYZPlatform(Device):
    """Base of every XYZ platform backend (serial encoder board, simulator).

    Args:
        geometry: axes' mechanics and workspace; default :class:`PlatformGeometry`.
        velocity_window_s: span of the finite difference for velocity.
        stale_timeout_s: no valid frame for this long means the device is gone (``connect()``
            then closes and reopens it).
        connect_timeout_s: how long ``connect()`` waits for the first valid sample.

    Raises:
        ConfigError: a duration that is not finite and > 0.
    """

    _latest: PlatformSample | None
    _board_info: BoardInfo | None
    _link_error: BaseException | None
    _raw_counts: tuple[int, int, int] | None
    _history: collections.deque[tuple[int, Vec3]]
    _clock_offset_us: int | None
    _offset_board_t_us: int
    _last_read: PlatformSample | None
    _last_rx_s: float

    def __init__(self, *, geometry: PlatformGeometry | None = None,
                 velocity_window_s: float = 0.01, stale_timeout_s: float = 0.5,
                 connect_timeout_s: float = 2.0) -> None:
        for name, value in (("velocity_window_s", velocity_window_s),
                            ("stale_timeout_s", stale_timeout_s),
                            ("connect_timeout_s", connect_timeout_s)):
            if not 0 < value < math.inf:
                raise ConfigError(f"{name} must be finite and > 0, got {value}")
        self.geometry = geometry or PlatformGeometry()
        self._mm_per_count = self.geometry.mm_per_count  # the geometry is immutable
        self._velocity_window_us = int(velocity_window_s * 1e6)
        self._stale_timeout_s = stale_timeout_s
        self._connect_timeout_s = connect_timeout_s
        super().__init__()
        self._cond = threading.Condition()
        #: called with every new sample, in the driver's reader thread, after it is published
        #: (must be quick: e.g. a copy into shared memory,
        #: :mod:`local_site.agent.platform_process`)
        self.sample_listener: Callable[[PlatformSample], None] | None = None
        #: raw 32-bit counter values at the zero pose (raw, so that a reopened link, whose
        #: counts are not unwrapped from the previous connection's, agrees with it)
        self._zero_counts = (0, 0, 0)
        self._zero_at_mm: Vec3 = (0.0, 0.0, 0.0)
        self._missed = self._clamped = self._reads = self._restarts = self._duplicates = 0
        self._rebases = 0
        #: the newest sample of the driver's life, kept across connections (a restarted board
        #: is told by its clock against it): raw board clock, its latch time on the host clock
        #: (t_us), unclamped position; and the board's sample rate from its last INFO
        self._last_board_t_raw = 0
        self._last_latch_us: int | None = None
        self._last_raw_mm: Vec3 = (0.0, 0.0, 0.0)
        self._rate_hz = _MAX_RATE_HZ
        #: the last INFO's disagreement with the geometry, kept across connections until a
        #: matching INFO: no sample is published meanwhile. Until the driver's first INFO it
        #: says so: a running board's samples before its first INFO (up to a second) were
        #: published unchecked, at the wrong scale for a board unlike the geometry
        self._info_mismatch: ConfigError | None = _AWAITING_INFO
        self._reset_track()

    # ------------------------------------------------------------------ backend interface
    # _connect() / _disconnect(): see shared.devices.base.Device

    def _decoder_stats(self) -> DecoderStats:
        """Byte-level counters of the backend (override when there is a byte stream)."""
        return DecoderStats()

    def _silence_hint(self) -> str:
        """What the backend can tell about a silence, appended to the timeout's message
        (override; e.g. whether its reader thread has been running)."""
        return ""

    # ------------------------------------------------------------------ lifecycle steps

    def _before_connect(self) -> None:
        self._reset_track()

    def _after_connect(self) -> None:
        """Wait for the first valid sample (or a link failure) within connect_timeout_s."""
        deadline = monotonic_s() + self._connect_timeout_s
        with self._cond:
            while self._latest is None and self._link_error is None:
                remaining = deadline - monotonic_s()
                if remaining <= 0:
                    break
                self._cond.wait(remaining)
            latest, error = self._latest, self._link_error
        if latest is None or error is not None:  # (an INFO unlike the geometry, with a sample)
            error = error or self._info_mismatch
            if error is _AWAITING_INFO and self._unpublished:
                # not a silence: the board talks, but not as it must (firmware, or its INFO
                # frames corrupted on the line)
                reason = (f"no INFO frame within {self._connect_timeout_s:.2f} s, "
                          f"{self._unpublished} samples (the board sends one at start-up and "
                          "every second; its samples are not used before it: the geometry is "
                          "checked against it)")
                raise DeviceInitError(f"{self.name}: {reason}") from DeviceOperationError(reason)
            error = None if error is _AWAITING_INFO else error
            reason = f"link failed: {error}" if error else \
                f"no valid frame within {self._connect_timeout_s:.2f} s"
            # a silent board is a timeout inside the connect phase (tools tell it from a
            # port that does not open by this cause)
            raise DeviceInitError(f"{self.name}: {reason}") from (
                error or DeviceTimeoutError(reason))
        log.info("%s: board info: %s", self.name, self._board_info)

    def _is_healthy(self) -> bool:
        return self._link_error is None and \
            monotonic_s() - self._last_rx_s < self._stale_timeout_s

    def _after_disconnect(self) -> None:
        with self._cond:
            self._cond.notify_all()

    # ------------------------------------------------------------------ public API

    @property
    def board_info(self) -> BoardInfo | None:
        """The board's last self-description, if it sent one."""
        return self._board_info

    def connect(self) -> None:
        """Open the device and wait for its first valid sample.

        Calling it again on a healthy connection does nothing; after a link failure it
        closes and reopens (this is how a station retries).

        Raises:
            DeviceInitError: the device cannot be opened or sends no valid sample within
                ``connect_timeout_s``.
        """
        super().connect()

    def latest(self) -> PlatformSample | None:
        """The newest sample without waiting (None before the first one)."""
        return self._latest

    def read_state(self, timeout_s: float = 0.1) -> PlatformSample:
        """Wait for a sample newer than the one returned last, and return it.

        Args:
            timeout_s: longest wait (0: only take a sample already there).

        Returns:
            The newest sample (samples in between are skipped: latest wins).

        Raises:
            ConfigError: ``timeout_s`` is negative or not finite.
            DeviceNotConnectedError: called before ``connect()`` or after ``disconnect()``.
            DeviceOperationError: the link failed (device unplugged, port closed).
            DeviceTimeoutError: no new valid sample within ``timeout_s``.
        """
        if not 0 <= timeout_s < math.inf:
            raise ConfigError(f"read_state timeout_s must be finite and >= 0, got {timeout_s}")
        if not self._connected:
            raise DeviceNotConnectedError(f"{self.name}: read_state() before connect()")
        deadline = monotonic_s() + timeout_s
        with self._cond:
            while True:
                error = self._link_error
                if isinstance(error, ConfigError):  # (a board unlike the configuration)
                    raise DeviceOperationError(f"{self.name}: {error}") from error
                if error is not None:
                    raise DeviceOperationError(
                        f"{self.name}: device disappeared ({error}); "
                        f"call connect() to retry") from error
                latest = self._latest
                if latest is not None and latest is not self._last_read:
                    self._last_read = latest
                    self._reads += 1
                    return latest
                if not self._connected:
                    raise DeviceNotConnectedError(f"{self.name}: disconnected while reading")
                remaining = deadline - monotonic_s()
                if remaining <= 0:
                    silent_s = monotonic_s() - self._last_rx_s
                    raise DeviceTimeoutError(
                        f"{self.name}: no new valid sample for {silent_s * 1e3:.0f} ms "
                        f"(waited {timeout_s * 1e3:.0f} ms); device silent or unplugged?"
                        f"{self._silence_hint()}")
                self._cond.wait(remaining)

    def zero(self, at_mm: Vec3 = (0.0, 0.0, 0.0)) -> None:
        """Declare that the platform is now at ``at_mm`` (default: the workspace origin).

        Raises:
            DeviceNotConnectedError: no sample yet to zero against.
            ConfigError: ``at_mm`` outside the workspace.
        """
        at = tuple(float(v) for v in at_mm)
        if len(at) != 3 or any(not 0.0 <= v <= w for v, w in
                               zip(at, self.geometry.workspace_mm, strict=True)):
            raise ConfigError(f"zero position {at_mm} outside the workspace "
                              f"{self.geometry.workspace_mm}")
        with self._cond:
            if self._raw_counts is None:
                raise DeviceNotConnectedError(f"{self.name}: zero() needs a sample first")
            self._zero_counts = self._raw_counts
            self._zero_at_mm = self._last_raw_mm = at
            self._history.clear()
            if self._latest is not None:  # the next read_state waits for a post-zero sample
                self._last_read = self._latest
        log.info("%s zeroed at %s mm (counts %s)", self.name, at, self._zero_counts)

    def stats(self) -> PlatformStats:
        """A snapshot of the link counters."""
        d = self._decoder_stats()
        return PlatformStats(bytes_in=d.bytes_in, frames_ok=d.frames_ok,
                             crc_errors=d.crc_errors, garbage_bytes=d.garbage_bytes,
                             unknown_types=d.unknown_types, samples_missed=self._missed,
                             samples_clamped=self._clamped, reads=self._reads,
                             board_restarts=self._restarts, duplicates=self._duplicates,
                             position_rebases=self._rebases)

    # ------------------------------------------------------------------ for backends

    def _reset_track(self) -> None:
        """Forget the previous connection's samples (the zero and the counters are kept)."""
        self._latest = None
        #: valid samples of this connection not published (no INFO yet, or an unlike one)
        self._unpublished = 0
        self._board_info = None
        self._link_error = None
        self._raw_counts = None
        self._last_read = None
        self._last_rx_s = monotonic_s()
        self._restart_clock()

    def _restart_clock(self) -> None:
        """Start the seq and board-clock tracks, the clock mapping and velocity anew."""
        self._unwrap_seq = WrapUnwrapper(32, signed=False)
        self._unwrap_t = WrapUnwrapper(32, signed=False)
        self._history = collections.deque(maxlen=256)
        self._clock_offset_us = None
        self._offset_board_t_us = 0

    def _board_restarted(self, why: str) -> None:
        """The board restarted on the open link (reader thread): its seq and clock begin
        anew, so the old mapping of its clock to ours would stamp every sample wrong."""
        self._restarts += 1
        log.warning("%s: the board restarted (%s); its clock is mapped anew", self.name, why)
        with self._cond:
            self._restart_clock()

    def _booted_since_last(self, sample: EncoderSample, rx_us: int) -> bool:
        """Whether the board started after the driver's newest sample (that of an earlier
        connection, or the one before a restart on this link).

        A board starts ``seq`` and its clock at 0. It started since then when its clock
        reads no more than the host time from that sample's latch to this sample's arrival
        (plus 2 % and 100 ms; measured from the latch, not the arrival, so frames read in one
        chunk or after a backlog are judged as they were latched), the clock
        does not simply continue from that sample's, and ``seq`` is no more than that clock
        at the board's sample rate allows. A continuing board (reopened link) or one chance
        frame with random fields does not pass (a wrapped clock of a continuing board is
        caught by its ``seq``, up to outages of about an hour).
        """
        last_latch = self._last_latch_us
        if last_latch is None:
            return False
        elapsed = rx_us - last_latch
        if elapsed <= 0:  # (a latch is stamped at or before its arrival: cannot tell)
            return False
        slack = elapsed // 50 + _BOOT_SLACK_US
        board_t = sample.board_t_us
        if board_t > elapsed + slack:  # up since before that sample
            return False
        if abs(((board_t - self._last_board_t_raw) & _MASK) - elapsed) <= slack:
            return False  # its clock went on from that sample's: it kept running
        return sample.seq <= (board_t + _BOOT_SLACK_US) * self._rate_hz * 21 // 20_000_000 + 1

    def _start_track(self, sample: EncoderSample, rx_us: int, restarted: bool) -> None:
        """The first sample of a track (a connection, or after a restart on the link): when
        the board started since the driver's newest sample, its counters began again where
        the platform was, so the position goes on from that sample's instead of jumping to
        the counters' new origin (reader thread, before the sample is mapped)."""
        if not self._booted_since_last(sample, rx_us):
            if restarted:
                log.warning("%s: the board restarted, but its clock (%d us) does not say "
                            "it started since the last sample: its counts are kept",
                            self.name, sample.board_t_us)
            return
        if not restarted:
            self._restarts += 1  # it restarted while the link was down
        with self._cond:
            jump = tuple(round((((c - z + _HALF) & _MASK) - _HALF) * s + a - b, 3)
                         for c, z, s, a, b in zip(sample.counts, self._zero_counts,
                                                  self._mm_per_count, self._zero_at_mm,
                                                  self._last_raw_mm, strict=True))
            self._zero_counts = sample.counts
            self._zero_at_mm = self._last_raw_mm
            self._rebases += 1
        log.warning("%s: the board started again (its clock reads %d us): its counters count "
                    "from where the platform was, so the position goes on from the last sample "
                    "(%s mm; the counters alone would have moved it by %s mm); travel while "
                    "it was down is not seen", self.name, sample.board_t_us,
                    tuple(round(v, 3) for v in self._last_raw_mm), jump)

    def _publish_info(self, info: BoardInfo) -> None:
        """Record the board's self-description (called by the backend); a board that counts
        otherwise than the configured geometry fails the link (its positions would be off by
        the ratio: a 2000-line encoder read 36.8 mm for 18.85), and no sample is published
        again until an INFO of a matching board arrives, also on reopened links (a running
        board's first samples come before its next INFO: they were published at the wrong
        scale for up to a second on every reopen, found by review)."""
        geometry = self.geometry
        if (info.protocol_version, info.axes, info.pulses_per_rev, info.decoding) != \
                (PROTOCOL_VERSION, 3, geometry.pulses_per_rev, geometry.decoding):
            mismatch = ConfigError(
                f"the board describes itself as protocol v{info.protocol_version}, "
                f"{info.axes} axes, {info.pulses_per_rev} pulses per revolution decoded "
                f"x{info.decoding}; this driver reads protocol v{PROTOCOL_VERSION}, 3 axes, "
                f"and the platform geometry is set for {geometry.pulses_per_rev} x"
                f"{geometry.decoding}: set the geometry to the board's")
            self._info_mismatch = mismatch
            if self._link_error is None:  # (once per connection: INFO comes every second)
                self._link_failed(mismatch)
            return
        self._info_mismatch = None
        previous = self._board_info
        if previous is not None and info != previous:
            self._board_restarted(f"it now describes itself as {info}, before {previous}")
        self._board_info = info
        if info.sample_rate_hz > 0:
            self._rate_hz = info.sample_rate_hz

    def _publish(self, sample: EncoderSample, rx_us: int | None = None) -> None:
        """Turn one raw sample into a :class:`PlatformSample` (called by the backend).

        Args:
            sample: the decoded frame.
            rx_us: host wall-clock arrival time; defaults to now.
        """
        if self._link_error is not None or self._info_mismatch is not None:
            # (a board unlike the geometry, or no INFO yet: nothing published)
            self._unpublished += 1
            return
        rx_us = now_us() if rx_us is None else rx_us
        seq = self._unwrap_seq.update(sample.seq)
        board_t = self._unwrap_t.update(sample.board_t_us)
        previous = self._latest
        # the previous sample of this track (none at the start of a connection or a restart)
        before = previous if self._clock_offset_us is not None else None
        if before is not None and seq == before.seq and board_t == before.board_t_us:
            self._duplicates += 1  # the same frame again (a replaying link): not a restart
            return
        restarted = before is None and previous is not None  # (after an INFO's restart)
        if before is not None and (seq <= before.seq or board_t <= before.board_t_us):
            self._board_restarted(f"seq {before.seq} -> {sample.seq}, board clock "
                                  f"{before.board_t_us} -> {sample.board_t_us} us")
            before, restarted = None, True
            seq = self._unwrap_seq.update(sample.seq)
            board_t = self._unwrap_t.update(sample.board_t_us)
        if before is None:
            self._start_track(sample, rx_us, restarted)
        # board clock -> host clock: the smallest (arrival - latch) seen is the link's
        # fixed delay. It follows a larger one by at most 1 us per 100 us of board time (1 %,
        # above any board's drift: a crystal's tens of ppm, a ceramic resonator's 0.5 %,
        # USB full speed's 0.25 %: a 1000 ppm cap left a 2500 ppm board's stamps behind
        # without limit, found by review), so drift cannot pin it, and frames that waited in
        # a queue (a USB stall, a starved reader thread) cannot pull it up and stamp
        # themselves fresh by more than 1 % of their wait.
        candidate = rx_us - board_t
        offset = self._clock_offset_us
        if offset is None or candidate < offset:
            offset, self._offset_board_t_us = candidate, board_t
        else:
            creep = (board_t - self._offset_board_t_us) // _CREEP_PER_US
            if creep > 0:
                offset += min(candidate - offset, creep)
                self._offset_board_t_us += creep * _CREEP_PER_US
        self._clock_offset_us = offset
        with self._cond:
            # counts -> mm as geometry.counts_to_mm, without rebuilding its scale per sample;
            # the counts relative to the zero pose, across a 32-bit wrap
            raw_mm = tuple((((c - z + _HALF) & _MASK) - _HALF) * s + a for c, z, s, a in zip(
                sample.counts, self._zero_counts, self._mm_per_count, self._zero_at_mm,
                strict=True))
            position, clamped = self.geometry.clamp(raw_mm)  # type: ignore[arg-type]
            if before is not None and seq - before.seq > 1:
                self._missed += seq - before.seq - 1
            self._clamped += clamped
            history = self._history
            history.append((board_t, position))
            while len(history) > 2 and board_t - history[1][0] >= self._velocity_window_us:
                history.popleft()
            t_old, p_old = history[0]
            dt_s = (board_t - t_old) * 1e-6
            velocity = tuple((p - q) / dt_s for p, q in zip(position, p_old, strict=True)) \
                if dt_s > 0 else (0.0, 0.0, 0.0)
            self._raw_counts = sample.counts
            # capture times never go backwards, even when a faster arrival lowers the offset
            # estimate (a sample stamped before its predecessor would look older than it is)
            t_us = board_t + offset
            if previous is not None and t_us <= previous.t_us:
                t_us = previous.t_us + 1
            self._last_board_t_raw, self._last_latch_us, self._last_raw_mm = \
                sample.board_t_us, t_us, raw_mm  # type: ignore[assignment]
            published = PlatformSample(position_mm=position, velocity_mm_s=velocity,  # type: ignore[arg-type]
                                       t_us=t_us, seq=seq, board_t_us=board_t,
                                       clamped=clamped)
            self._latest = published
            self._last_rx_s = monotonic_s()
            self._cond.notify_all()
        listener = self.sample_listener
        if listener is not None:
            listener(published)

    def _link_failed(self, err: BaseException) -> None:
        """Record that the link broke (called by the backend's reader thread)."""
        log.warning("%s: link failed: %s", self.name, err)
        with self._cond:
            self._link_error = err
            self._cond.notify_all()
