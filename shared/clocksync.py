"""Clock offset of a station against the relay: NTP four-timestamp math and a clock filter.

Sans-I/O: the caller sends a ``clock_ping`` (``t0`` on the relay's clock), the station
answers with ``t1`` (receive) and ``t2`` (transmit) on its own clock, and the caller notes
``t3`` (receive of the pong, relay clock). Then (RFC 5905, section 8)::

    offset = ((t1 - t0) + (t2 - t3)) / 2      # station clock minus relay clock
    delay  = (t3 - t0) - (t2 - t1)            # round trip without the station's hold time

The offset error of one sample is at most half the path asymmetry (|d_up - d_down| / 2),
and the true offset lies in ``[offset - delay/2, offset + delay/2]`` whatever the
asymmetry (every one-way delay and processing time is >= 0). :class:`ClockFilter` keeps the
last few samples and intersects their intervals, each widened by the clocks' largest relative
drift times the sample's age (Marzullo's idea with one source): the truth lies in the
intersection. The estimate is the least-queued sample's offset (the RFC 5905 minimum-delay
idea: queueing only adds delay, the least-queued exchange is the most symmetric one),
clamped into the intersection, and its distance to the far end of the intersection is a
*bound* on its error: the uncertainty that the safety checks use. An empty intersection
means a clock stepped (or drifted beyond the bound): the filter keeps only the samples
consistent with the newest one and counts a step, so it follows a step with the next
exchange instead of after the window.

All times are integer microseconds. Convert a station timestamp to relay time with
``t_relay = t_station - offset_us``.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

from shared.errors import InputDataError

__all__ = ["ClockFilter", "ClockSample", "sample_from_timestamps"]


@dataclass(frozen=True, slots=True)
class ClockSample:
    """One four-timestamp exchange.

    Attributes:
        offset_us: station clock minus reference clock.
        delay_us: round-trip delay with the station's hold time removed (>= 0).
        t3_us: when the exchange completed (reference clock), for ageing.
        dispersion_us: how far the clocks may have drifted apart during the exchange
            (RFC 5905's dispersion), added to the sample's half-width: 0 for a clock
            ping, whose hold is microseconds; a held exchange (the relay workers' echoed
            heartbeats) sets it.
    """

    offset_us: float
    delay_us: float
    t3_us: int
    dispersion_us: float = 0.0

    @property
    def uplink_us(self) -> float:
        """One-way delay station -> reference under this sample's offset (= delay / 2)."""
        return self.delay_us / 2.0


def sample_from_timestamps(t0_us: int, t1_us: int, t2_us: int, t3_us: int,
                           drift_ppm: float = 0.0) -> ClockSample:
    """Compute offset and delay of one exchange.

    Args:
        t0_us: ping transmit, reference (relay) clock.
        t1_us: ping receive, station clock.
        t2_us: pong transmit, station clock.
        t3_us: pong receive, reference clock.
        drift_ppm: how fast the two clocks may drift apart while the other side holds the
            exchange (0 for a clock ping, held microseconds; the relay workers' echoed
            heartbeats are held up to a heartbeat period). Its drift over the exchange is
            the sample's ``dispersion_us``, and a round trip that this drift (and the
            stamps' microsecond) could make negative counts as 0.

    Returns:
        The sample.

    Raises:
        InputDataError: the timestamps are inconsistent (t3 before t0, t2 before t1, or a
            negative round trip beyond that drift), so the exchange says nothing about the
            clocks.
    """
    if t3_us < t0_us or t2_us < t1_us:
        raise InputDataError(f"clock exchange out of order: t0={t0_us} t1={t1_us} "
                             f"t2={t2_us} t3={t3_us}")
    dispersion = drift_ppm * 1e-6 * (t3_us - t0_us)
    delay = (t3_us - t0_us) - (t2_us - t1_us)
    if delay < (-dispersion - 1 if drift_ppm > 0 else 0):
        raise InputDataError(f"clock exchange with negative round trip {delay} us "
                             "(station hold time longer than the round trip)")
    offset = ((t1_us - t0_us) + (t2_us - t3_us)) / 2.0
    return ClockSample(offset_us=offset, delay_us=float(max(0, delay)), t3_us=int(t3_us),
                       dispersion_us=dispersion)


class ClockFilter:
    """Keep the last ``size`` samples; estimate by intersecting their intervals.

    Args:
        size: samples kept (RFC 5905 uses 8).
        drift_ppm: largest relative frequency error of the two clocks; each sample's
            interval widens by this much per second of its age (500 ppm is NTP's largest
            slew rate, so a clock being slewed by NTP stays within the bound).
    """

    def __init__(self, size: int = 8, drift_ppm: float = 500.0) -> None:
        if size < 1:
            raise ValueError("size must be >= 1")
        if not (math.isfinite(drift_ppm) and drift_ppm >= 0):
            raise ValueError("drift_ppm must be finite and >= 0")
        self._samples: deque[ClockSample] = deque(maxlen=size)
        self._drift = drift_ppm * 1e-6
        #: (best, offset_us) of the current samples: both depend on the samples only, and
        #: the relay reads them for every forwarded message (None: not computed yet)
        self._estimate: tuple[ClockSample | None, float | None] | None = None
        #: clock steps detected (samples inconsistent with all earlier ones)
        self.steps = 0
        #: ``t3_us`` of the sample that revealed the last step (None: no step yet)
        self.last_step_t3_us: int | None = None

    def add(self, sample: ClockSample) -> bool:
        """Add one sample (the oldest falls out when full).

        Returns:
            True when the sample revealed a clock step: the earlier samples inconsistent
            with it were dropped.
        """
        if not (math.isfinite(sample.offset_us) and math.isfinite(sample.delay_us)
                and math.isfinite(sample.dispersion_us) and sample.dispersion_us >= 0):
            raise InputDataError("clock sample is not finite (or a negative dispersion)")
        self._estimate = None
        self._samples.append(sample)
        if self._interval(self._samples, sample.t3_us) is not None:
            return False
        # keep the longest run of newest samples that still agree
        kept: list[ClockSample] = [sample]
        for older in reversed(list(self._samples)[:-1]):
            if self._interval([older, *kept], sample.t3_us) is None:
                break
            kept.insert(0, older)
        self._samples.clear()
        self._samples.extend(kept)
        self.steps += 1
        self.last_step_t3_us = sample.t3_us
        return True

    def add_timestamps(self, t0_us: int, t1_us: int, t2_us: int, t3_us: int) -> ClockSample:
        """Compute a sample from four timestamps and add it (see :func:`sample_from_timestamps`)."""
        sample = sample_from_timestamps(t0_us, t1_us, t2_us, t3_us)
        self.add(sample)
        return sample

    def _interval(self, samples: Iterable[ClockSample], now_us: int
                  ) -> tuple[float, float] | None:
        lo, hi = -math.inf, math.inf
        for s in samples:
            half = s.delay_us / 2.0 + s.dispersion_us + self._drift * max(0, now_us - s.t3_us)
            lo = max(lo, s.offset_us - half)
            hi = min(hi, s.offset_us + half)
        return (lo, hi) if lo <= hi else None

    def interval(self, now_us: int | None = None) -> tuple[float, float] | None:
        """Where the true offset lies (lo, hi), at reference time ``now_us`` (default: the
        newest sample's time); None before any sample."""
        if not self._samples:
            return None
        t = self._samples[-1].t3_us if now_us is None else max(now_us, self._samples[-1].t3_us)
        return self._interval(self._samples, t)

    def __len__(self) -> int:
        return len(self._samples)

    def _estimated(self) -> tuple[ClockSample | None, float | None]:
        """(best, offset_us), computed once per change of the samples."""
        if self._estimate is None:
            best: ClockSample | None = None
            for s in self._samples:
                if best is None or s.delay_us <= best.delay_us:
                    best = s
            iv = self.interval()
            offset = None if iv is None or best is None else \
                min(max(best.offset_us, iv[0]), iv[1])
            self._estimate = (best, offset)
        return self._estimate

    @property
    def best(self) -> ClockSample | None:
        """The kept sample with the smallest delay (the newest among equals), or None."""
        return self._estimated()[0]

    @property
    def offset_us(self) -> float | None:
        """Offset estimate (station minus reference, us): the least-queued sample's offset,
        clamped into the intersection; None before any sample."""
        return self._estimated()[1]

    def uncertainty_us(self, now_us: int | None = None) -> float | None:
        """Bound on the error of :attr:`offset_us` at reference time ``now_us`` (default:
        the newest sample's time): the distance from the estimate to the far end of the
        intersection, plus the drift since the newest sample. None before any sample."""
        iv, est = self.interval(), self.offset_us
        if iv is None or est is None:
            return None
        latest = self._samples[-1].t3_us
        aged = 0.0 if now_us is None else self._drift * max(0, now_us - latest)
        return max(est - iv[0], iv[1] - est) + aged

    @property
    def delay_us(self) -> float | None:
        """Round-trip delay of the least-queued kept sample, or None before any sample."""
        best = self.best
        return None if best is None else best.delay_us

    @property
    def latest(self) -> ClockSample | None:
        """The newest sample, or None."""
        return self._samples[-1] if self._samples else None

    def to_reference_us(self, station_t_us: int) -> int | None:
        """Convert a station timestamp to the reference clock, or None before any sample."""
        offset = self.offset_us
        return None if offset is None else round(station_t_us - offset)
