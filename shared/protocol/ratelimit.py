"""Token bucket for the relay's per-connection message-rate limit (sans-I/O, integer us).

The bucket holds up to ``burst`` tokens and refills at ``rate_per_s``; each received message
takes one. :meth:`TokenBucket.take` is an exact bucket for messages that arrive at the time
given: its tokens after the refill since the last call are capped at ``burst`` before the
charge (an idle connection saves up one burst, never more), so over any time ``T`` it grants
at most ``burst + rate_per_s * T`` messages.

The relay charges it lazily (:mod:`~shared.protocol.peer_session`): it counts messages and
reads the bucket only when the count passes half the tokens of the last reading, then charges
the earlier of them as if they had all come with the last chunk before this one (no earlier
than they did: the bucket is never more lenient than an exact one) and this chunk's at its
arrival.
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
        """Take up to ``count`` tokens for messages arriving at ``now_us``; return how many
        were granted (0..count)."""
        elapsed = now_us - self._last_us
        if elapsed > 0:
            self._last_us = now_us
            self._tokens_us = min(self._cap_us, self._tokens_us + int(elapsed * self._rate))
        granted = min(count, self._tokens_us // 1_000_000)
        self._tokens_us -= granted * 1_000_000
        return granted
