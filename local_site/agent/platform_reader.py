"""The platform read thread: every new sample, a clear error and retry with backoff.

The platform driver streams samples from its own reader thread and keeps the newest one;
:attr:`PlatformReader.latest` is that sample (the display loop renders at the newest
position the driver decoded). The reader thread watches the device with the blocking
``read_state`` every ``poll_s`` (not at every sample: each wake-up of a thread costs the
other threads the GIL, and the display loop runs at 1 kHz beside it). When the device
disappears (link error or no sample for ``read_timeout_s``) it logs one clear error and marks
itself unhealthy (the display loop then puts the pins in their safe state).

:attr:`PlatformReader.healthy` also judges the newest sample by its capture stamp: a sample
latched more than ``read_timeout_s`` ago is not a position to render, however recently it was
decoded (the backlog a driver drains after its thread was starved, or a stall of the reader
thread itself). Health therefore never waits for the reader thread to run.

A link error (port closed, device unplugged) reopens the device after ``retry_min_s``, with
an exponential backoff until it answers again or the agent stops. A link that fails again
within a second of being reopened (a device that opens and then fails, a data callback that
raises on every sample) goes on backing off from where the last episode left it, so such a
link is reopened at most every ``retry_max_s``, not five times a second with a traceback
each. A device that is only *silent* keeps its open port for ``reopen_after_s``:
the samples of a board that was late (or of a driver thread that could not run on a busy
machine) are taken the moment they arrive, with no close/reopen gap; only a silence that
lasts is treated like a lost link. (Closing and reopening at the first 250 ms of silence
turned short stalls of the demo's simulated board into 0.65-0.85 s gaps in the platform
uplink.)
"""

from __future__ import annotations

import logging
import threading

from local_site.platform.base import PlatformSample, PlatformStats, XYZPlatform
from shared.errors import ConfigError, DeviceError, DeviceInitError, DeviceTimeoutError
from shared.timebase import monotonic_s, now_us

__all__ = ["POLL_S", "PlatformReader", "reopen_after", "stale_since_s"]

log = logging.getLogger(__name__)

#: the reader's pause between two health checks (its read timeout must be longer)
POLL_S = 0.005
#: a link that failed sooner than this after being opened is flapping: its reopen backs off
#: on from the last wait; one that lived longer starts again at ``retry_min_s`` (a link that
#: served 2 s and failed is not a flapping one: judged on ``retry_max_s``, 5 s, it was)
_STABLE_S = 1.0


def reopen_after(read_timeout_s: float, reopen_after_s: float | None) -> float:
    """The silence after which a platform is reopened (default: four read timeouts).

    Raises:
        ConfigError: it is shorter than the read timeout, or not finite.
    """
    if reopen_after_s is None:
        reopen_after_s = 4.0 * read_timeout_s
    if not read_timeout_s <= reopen_after_s < float("inf"):
        raise ConfigError(f"reopen_after_s must be finite and >= read_timeout_s "
                          f"({read_timeout_s}), got {reopen_after_s}")
    return reopen_after_s


def stale_since_s(sample: PlatformSample, read_timeout_s: float) -> float | None:
    """When ``sample`` became too old to render, on the monotonic clock: a read timeout
    after its capture stamp; None while it is younger than that."""
    age_s = (now_us() - sample.t_us) / 1e6
    return None if age_s <= read_timeout_s else monotonic_s() - (age_s - read_timeout_s)


class PlatformReader:
    """Reads a platform in a thread, retrying with backoff when it is lost.

    Args:
        platform: the platform (connected or not: the thread connects it).
        read_timeout_s: no new sample for this long means the device is lost.
        retry_min_s: first delay before reopening.
        retry_max_s: largest delay (doubling from ``retry_min_s``).
        motion_duration_s: length of the scripted motion, when known; the reader then sets
            :attr:`motion_done` once that much board time has passed since the first sample.
        poll_s: pause between two health checks (a link failure is noticed at most this
            much later than by a reader blocked in ``read_state``).
        reopen_after_s: a device silent this long (>= ``read_timeout_s``) is closed and
            reopened like a lost link (default: four read timeouts).
    """

    def __init__(self, platform: XYZPlatform, *, read_timeout_s: float = 0.1,
                 retry_min_s: float = 0.2, retry_max_s: float = 5.0,
                 motion_duration_s: float | None = None, poll_s: float = POLL_S,
                 reopen_after_s: float | None = None) -> None:
        if not 0 <= poll_s < read_timeout_s:
            raise ConfigError(f"poll_s must be in [0, read_timeout_s), got {poll_s}")
        reopen_after_s = reopen_after(read_timeout_s, reopen_after_s)
        self.platform = platform
        self._poll_s = poll_s
        self._read_timeout_s = read_timeout_s
        self._reopen_after_s = reopen_after_s
        self._retry_min_s = retry_min_s
        self._retry_max_s = retry_max_s
        self._motion_duration_s = motion_duration_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_sample: PlatformSample | None = None
        # the reader thread's view: the device answers (set and cleared by the thread only)
        self._device_ok = False
        self._lost_at_s: float | None = monotonic_s()
        self.motion_done = threading.Event()
        #: samples the driver delivered while the reader watched (board sequence advances)
        self.reads = 0
        self.errors = 0
        self.reconnects = 0
        #: silences that ended on the open port (no reopen needed)
        self.recoveries = 0
        self.last_error: str | None = None
        self._first_board_t_us: int | None = None
        #: when the device was last opened, and the wait before the next reopen if it fails
        #: again before retry_max_s has passed (doubling per such failure)
        self._opened_at_s: float | None = None
        self._flap_delay_s = retry_min_s

    @property
    def latest(self) -> PlatformSample | None:
        """The newest sample (None before the first); replaced as a whole, safe to read
        anywhere. While the device is reopened, the newest sample the driver had decoded
        before (never an older one: stamps must not go backwards)."""
        sample = self.platform.latest()
        return sample if sample is not None else self._last_sample

    @property
    def healthy(self) -> bool:
        """The device answers and its newest sample was captured at most ``read_timeout_s``
        ago (by its capture stamp, whenever the reader thread last ran)."""
        if not self._device_ok:
            return False
        sample = self.latest
        return sample is not None and stale_since_s(sample, self._read_timeout_s) is None

    @property
    def lost_since_s(self) -> float | None:
        """When the platform was lost, on the monotonic clock; None: healthy."""
        if not self._device_ok:
            lost_at = self._lost_at_s  # (None only in the instant the thread sets the pair)
            return lost_at if lost_at is not None else monotonic_s()
        sample = self.latest
        return monotonic_s() if sample is None else stale_since_s(sample, self._read_timeout_s)

    def start(self) -> None:
        """Start the thread (idempotent)."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="platform-reader",
                                            daemon=True)
            self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop the thread (the platform stays open; disconnect it yourself)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    def platform_stats(self) -> PlatformStats:
        """The device link's counters."""
        return self.platform.stats()

    def disconnect(self) -> None:
        """Close the device (after :meth:`stop`)."""
        self.platform.disconnect()

    def _connect_with_backoff(self, link_failed: bool = False) -> bool:
        delay = self._retry_min_s
        opened_at = self._opened_at_s
        if link_failed and opened_at is not None and monotonic_s() - opened_at < _STABLE_S:
            delay = self._flap_delay_s  # it failed soon after the last reopen: back off on
        first = True
        if self._lost_at_s is not None and self.errors:
            if self._stop.wait(delay):
                return False
            delay = min(self._retry_max_s, delay * 2.0)
        while not self._stop.is_set():
            try:
                self.platform.connect()
                self._opened_at_s, self._flap_delay_s = monotonic_s(), delay
                return True
            except DeviceInitError as err:
                self.last_error = str(err)
                if first:
                    log.error("platform %s cannot be opened: %s; retrying with backoff",
                              self.platform.name, err)
                    first = False
                elif log.isEnabledFor(logging.DEBUG):
                    log.debug("platform reopen failed: %s (next try in %.2f s)", err, delay)
            if self._stop.wait(delay):
                return False
            delay = min(self._retry_max_s, delay * 2.0)
        return False

    def _lost(self, err: DeviceError, reopen: bool) -> None:
        """Unhealthy from now (the first error of an episode is counted and logged)."""
        self.last_error = str(err)
        if self._device_ok:
            self.errors += 1
            self._device_ok, self._lost_at_s = False, monotonic_s()
            action = "reopening with backoff" if reopen else \
                f"waiting for it (reopened after {self._reopen_after_s:.2g} s of silence)"
            log.error("platform lost: %s; display to its safe state, %s", err, action)
        elif reopen:
            log.error("platform %s: %s; reopening with backoff", self.platform.name, err)
        if reopen:
            try:
                self.platform.disconnect()  # a silent device is reopened, not re-read
            except DeviceError as close_err:
                log.debug("platform disconnect after loss failed: %s", close_err)
            # connect() forgets the driver's newest sample: keep it (the one this thread read
            # last may be older, and latest must never step back to it)
            self._last_sample = self.platform.latest() or self._last_sample

    def _run(self) -> None:
        ever_connected = False
        needs_open = link_failed = True
        while not self._stop.is_set():
            if needs_open:
                if not self._connect_with_backoff(link_failed):
                    return
                if ever_connected:
                    self.reconnects += 1
                    log.info("platform %s is back", self.platform.name)
                ever_connected, needs_open = True, False
                self._device_ok, self._lost_at_s = True, None
            try:
                sample = self.platform.read_state(timeout_s=self._read_timeout_s)
            except DeviceTimeoutError as err:  # silent, the port still open
                silent_since = self._lost_at_s if not self._device_ok else None
                # silent since one read timeout before the episode was noticed
                needs_open = silent_since is not None and monotonic_s() - silent_since \
                    + self._read_timeout_s >= self._reopen_after_s
                link_failed = False
                self._lost(err, reopen=needs_open)
                if not needs_open and self._poll_s > 0 and self._stop.wait(self._poll_s):
                    return  # (a read_state that times out at once must not spin)
                continue
            except DeviceError as err:  # the link failed: reopen
                needs_open = link_failed = True
                self._lost(err, reopen=True)
                continue
            if not self._device_ok:  # the silence ended on the open port
                self.recoveries += 1
                silent_s = monotonic_s() - (self._lost_at_s or monotonic_s()) \
                    + self._read_timeout_s
                log.info("platform %s is back on the open port (silent for about %.0f ms)",
                         self.platform.name, silent_s * 1e3)
                self._device_ok, self._lost_at_s = True, None
            previous, self._last_sample = self._last_sample, sample
            advance = sample.seq - previous.seq if previous is not None else 1
            self.reads += advance if advance > 0 else 1  # a reopened board starts anew
            if self._motion_duration_s is not None:
                # a reopened link to a running board continues its clock (the scripted
                # motion went on meanwhile); a board that restarted begins again
                if self._first_board_t_us is None or sample.board_t_us < self._first_board_t_us:
                    self._first_board_t_us = sample.board_t_us
                elif (sample.board_t_us - self._first_board_t_us) * 1e-6 \
                        >= self._motion_duration_s:
                    self.motion_done.set()
            if self._poll_s > 0 and self._stop.wait(self._poll_s):
                return
