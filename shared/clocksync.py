"""Clock offset of a station against the relay: NTP four-timestamp math and a clock filter.

Sans-I/O: the caller sends a ``clock_ping`` (``t0`` on the relay's clock), the station
answers with ``t1`` (receive) and ``t2`` (transmit) on its own clock, and the caller notes
``t3`` (receive of the pong, relay clock). Then (RFC 5905, section 8)::

    offset = ((t1 - t0) + (t2 - t3)) / 2      # station clock minus relay clock
    delay  = (t3 - t0) - (t2 - t1)            # round trip without the station's hold time

The offset error of one sample is at most half the path asymmetry (|d_up - d_down| / 2),
so :class:`ClockFilter` keeps the last few samples and trusts the one with the smallest
round-trip delay (the RFC 5905 clock-filter idea): queueing only ever adds delay, and
the least-queued exchange is the most symmetric one.

All times are integer microseconds. Convert a station timestamp to relay time with
``t_relay = t_station - offset_us``.
"""

from __future__ import annotations

import math
from collections import deque
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
    """

    offset_us: float
    delay_us: float
    t3_us: int

    @property
    def uplink_us(self) -> float:
        """One-way delay station -> reference under this sample's offset (= delay / 2)."""
        return self.delay_us / 2.0


def sample_from_timestamps(t0_us: int, t1_us: int, t2_us: int, t3_us: int) -> ClockSample:
    """Compute offset and delay of one exchange.

    Args:
        t0_us: ping transmit, reference (relay) clock.
        t1_us: ping receive, station clock.
        t2_us: pong transmit, station clock.
        t3_us: pong receive, reference clock.

    Returns:
        The sample.

    Raises:
        InputDataError: the timestamps are inconsistent (t3 before t0, t2 before t1, or a
            negative round trip), so the exchange says nothing about the clocks.
    """
    if t3_us < t0_us or t2_us < t1_us:
        raise InputDataError(f"clock exchange out of order: t0={t0_us} t1={t1_us} "
                             f"t2={t2_us} t3={t3_us}")
    delay = (t3_us - t0_us) - (t2_us - t1_us)
    if delay < 0:
        raise InputDataError(f"clock exchange with negative round trip {delay} us "
                             "(station hold time longer than the round trip)")
    offset = ((t1_us - t0_us) + (t2_us - t3_us)) / 2.0
    return ClockSample(offset_us=offset, delay_us=float(delay), t3_us=int(t3_us))


class ClockFilter:
    """Keep the last ``size`` samples; estimate with the minimum-delay one.

    Args:
        size: samples kept (RFC 5905 uses 8).
    """

    def __init__(self, size: int = 8) -> None:
        if size < 1:
            raise ValueError("size must be >= 1")
        self._samples: deque[ClockSample] = deque(maxlen=size)

    def add(self, sample: ClockSample) -> None:
        """Add one sample (the oldest falls out when full)."""
        if not (math.isfinite(sample.offset_us) and math.isfinite(sample.delay_us)):
            raise InputDataError("clock sample is not finite")
        self._samples.append(sample)

    def add_timestamps(self, t0_us: int, t1_us: int, t2_us: int, t3_us: int) -> ClockSample:
        """Compute a sample from four timestamps and add it (see :func:`sample_from_timestamps`)."""
        sample = sample_from_timestamps(t0_us, t1_us, t2_us, t3_us)
        self.add(sample)
        return sample

    def __len__(self) -> int:
        return len(self._samples)

    @property
    def best(self) -> ClockSample | None:
        """The kept sample with the smallest delay (the newest among equals), or None."""
        best: ClockSample | None = None
        for s in self._samples:
            if best is None or s.delay_us <= best.delay_us:
                best = s
        return best

    @property
    def offset_us(self) -> float | None:
        """Offset estimate (station minus reference, us), or None before any sample."""
        best = self.best
        return None if best is None else best.offset_us

    @property
    def delay_us(self) -> float | None:
        """Round-trip delay of the chosen sample, or None before any sample."""
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
