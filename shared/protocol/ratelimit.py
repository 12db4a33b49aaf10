"""Token bucket for the relay's per-connection message-rate limit (sans-I/O, integer us).

The bucket holds up to ``burst`` tokens and refills at ``rate_per_s``; each received message
takes one. The relay charges it lazily (:mod:`~shared.protocol.peer_session`): it counts
messages and reads the bucket only when the count passes the tokens of the last reading,
charging all of them at once; the refill of the interval is credited before the cap, as the
messages arrived spread over it. So the bucket is never stricter than an exact one, and over
any time ``T`` grants at most ``burst + rate_per_s * T`` messages.
"""

from __future__ import annotations

__all__ = ["TokenBucket"]


class TokenBucket:
    """Messages allowed at ``rate_per_s`` with bursts of up to ``burst``.

    Args:
        rate_per_s: sustained messages per second (> 0).
        burst: bucket size in messages (>= 1); the bucket starts full.
        now_us: the current time in microseconds.

    Raises:
        ValueError: a non-positive rate or burst.
    """

    def __init__(self, rate_per_s: float, burst: int, now_us: int) -> None:
        if not rate_per_s > 0 or burst < 1:
            raise ValueError("rate_per_s must be > 0 and burst >= 1")
        self.rate_per_s = rate_per_s
        self.burst = burst
        # tokens scaled by 1e6 so the refill stays integer: tokens_us = tokens * 1e6
        self._tokens_us = burst * 1_000_000
        self._cap_us = burst * 1_000_000
        self._rate = rate_per_s
        self._last_us = now_us

    @property
    def tokens(self) -> int:
        """Whole tokens left at the last :meth:`take`."""
        return self._tokens_us // 1_000_000

    def take(self, count: int, now_us: int) -> int:
        """Take up to ``count`` tokens; return how many were granted (0..count)."""
        available = self._tokens_us
        elapsed = now_us - self._last_us
        if elapsed > 0:
            self._last_us = now_us
            available += int(elapsed * self._rate)
        granted = min(count, available // 1_000_000)
        # the cap applies after the charge: the ``count`` messages arrived spread over the
        # elapsed time, during which the real bucket refilled as they drained it
        self._tokens_us = min(self._cap_us, available - granted * 1_000_000)
        return granted
