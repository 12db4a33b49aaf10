"""The platform read thread: every new sample, a clear error and retry with backoff.

The platform driver streams samples from its own reader thread and keeps the newest one;
:attr:`PlatformReader.latest` is that sample (the display loop renders at the newest
position the driver decoded). The reader thread watches the device with the blocking
``read_state`` every ``poll_s`` (not at every sample: each wake-up of a thread costs the
other threads the GIL, and the display loop runs at 1 kHz beside it). When the device
disappears (link error or no sample for ``read_timeout_s``) it logs one clear error, marks
itself unhealthy (the display loop then puts the pins in their safe state) and reopens the
device with an exponential backoff until it answers again or the agent stops.
"""

from __future__ import annotations

import logging
import threading

from local_site.platform.base import PlatformSample, XYZPlatform
from shared.errors import ConfigError, DeviceError, DeviceInitError
from shared.timebase import monotonic_s

__all__ = ["PlatformReader"]

log = logging.getLogger(__name__)


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
    """

    def __init__(self, platform: XYZPlatform, *, read_timeout_s: float = 0.1,
                 retry_min_s: float = 0.2, retry_max_s: float = 5.0,
                 motion_duration_s: float | None = None, poll_s: float = 0.005) -> None:
        if not 0 <= poll_s < read_timeout_s:
            raise ConfigError(f"poll_s must be in [0, read_timeout_s), got {poll_s}")
        self.platform = platform
        self._poll_s = poll_s
        self._read_timeout_s = read_timeout_s
        self._retry_min_s = retry_min_s
        self._retry_max_s = retry_max_s
        self._motion_duration_s = motion_duration_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_sample: PlatformSample | None = None
        self.healthy = False
        self.lost_since_s: float | None = monotonic_s()
        self.motion_done = threading.Event()
        #: samples the driver delivered while the reader watched (board sequence advances)
        self.reads = 0
        self.errors = 0
        self.reconnects = 0
        self.last_error: str | None = None
        self._first_board_t_us: int | None = None

    @property
    def latest(self) -> PlatformSample | None:
        """The newest sample (None before the first); replaced as a whole, safe to read
        anywhere. While the device is reopened, the last sample of the previous connection."""
        sample = self.platform.latest()
        return sample if sample is not None else self._last_sample

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

    def _connect_with_backoff(self) -> bool:
        delay = self._retry_min_s
        first = True
        if self.lost_since_s is not None and self.errors and self._stop.wait(self._retry_min_s):
            return False
        while not self._stop.is_set():
            try:
                self.platform.connect()
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

    def _run(self) -> None:
        ever_connected = False
        while not self._stop.is_set():
            if not self.healthy:
                if not self._connect_with_backoff():
                    return
                if ever_connected:
                    self.reconnects += 1
                    log.info("platform %s is back", self.platform.name)
                ever_connected = True
                self.healthy, self.lost_since_s = True, None
            try:
                sample = self.platform.read_state(timeout_s=self._read_timeout_s)
            except DeviceError as err:
                self.errors += 1
                self.last_error = str(err)
                self.healthy, self.lost_since_s = False, monotonic_s()
                log.error("platform lost: %s; display to its safe state, reopening with "
                          "backoff", err)
                try:
                    self.platform.disconnect()  # a silent device is reopened, not re-read
                except DeviceError as close_err:
                    log.debug("platform disconnect after loss failed: %s", close_err)
                continue
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
