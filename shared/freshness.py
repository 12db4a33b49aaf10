"""Is a stamp from another station's clock young enough to act on? With a bounded answer.

Every station stamps on its own clock. The relay measures each station's offset against its
own clock with a bound on the error (:mod:`shared.clocksync`) and reports both in its
``stats`` (``clock_offset_us``, ``clock_uncertainty_us``). A stamp ``t`` taken on station
``B``'s clock is ``t + (off_A - off_B)`` on station ``A``'s clock, give or take
``u_A + u_B`` (plus the drift since the stats were built). :func:`judge_age` turns that into a
verdict that errs on the safe side:

* ``unknown_clock``: an offset is not known yet (no ``stats`` since the connection opened),
  or its error bound is negative or not finite (a bound below zero would widen the window);
* ``uncertain_clock``: the bound is wider than ``max_uncertainty_us``: the age cannot be
  judged finely enough to act on;
* ``stale``: the stamp *may* be older than ``max_age_us`` (``age + uncertainty > max``);
* ``future``: the stamp is later than now by more than the bound allows, so the offsets are
  wrong (a clock stepped since they were measured): refuse until they are re-measured;
* ``fresh``: none of these.

So "0 commands older than 100 ms executed" holds whatever the offset's error, as long as the
error stays within the reported bound.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

__all__ = ["DRIFT_PPM", "AgeVerdict", "ClockView", "Verdict", "clock_view_from_stats",
           "judge_age"]

#: the drift allowance a station adds for the time since it received the offsets (same as
#: the relay's clock filter: NTP's largest slew rate)
DRIFT_PPM = 500.0

Verdict = Literal["fresh", "stale", "future", "unknown_clock", "uncertain_clock"]


@dataclass(frozen=True, slots=True)
class ClockView:
    """The relay's offsets as a station received them.

    Attributes:
        offsets_us: per role, station clock minus relay clock (None: not measured).
        uncertainties_us: per role, the bound on that offset's error when reported.
        received_us: when the station received them (its own clock).
    """

    offsets_us: Mapping[str, int | None]
    uncertainties_us: Mapping[str, int | None]
    received_us: int

    def relative(self, ours: str, theirs: str, now_us: int) -> tuple[float, float] | None:
        """(our clock minus theirs, its error bound) at ``now_us``, or None if unknown (an
        offset or bound not reported, or a negative bound: it would shrink the other's)."""
        off_a, off_b = self.offsets_us.get(ours), self.offsets_us.get(theirs)
        u_a, u_b = self.uncertainties_us.get(ours), self.uncertainties_us.get(theirs)
        if off_a is None or off_b is None or u_a is None or u_b is None or u_a < 0 or u_b < 0:
            return None
        aged = 2.0 * DRIFT_PPM * 1e-6 * max(0, now_us - self.received_us)
        return float(off_a - off_b), float(u_a + u_b) + aged


def _int_map(raw: Any) -> dict[str, int | None]:
    if not isinstance(raw, Mapping):
        return {}
    out: dict[str, int | None] = {}
    for k, v in raw.items():
        ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
        out[str(k)] = int(v) if ok else None
    return out


def clock_view_from_stats(metrics: Mapping[str, Any], received_us: int) -> ClockView:
    """Read ``clock_offset_us`` / ``clock_uncertainty_us`` from relay ``stats`` metrics.

    A relay that reports no uncertainty (an older relay) gives a view in which every age
    is ``unknown_clock``: without a bound the station must not act.
    """
    return ClockView(_int_map(metrics.get("clock_offset_us")),
                     _int_map(metrics.get("clock_uncertainty_us")), received_us)


@dataclass(frozen=True, slots=True)
class AgeVerdict:
    """The judgement of one stamp.

    Attributes:
        verdict: see the module docstring.
        age_us: the estimated age (None when the clock is unknown).
        uncertainty_us: its error bound (None when the clock is unknown).
    """

    verdict: Verdict
    age_us: float | None = None
    uncertainty_us: float | None = None

    @property
    def fresh(self) -> bool:
        """True when the stamp may be acted on."""
        return self.verdict == "fresh"

    @property
    def age_ms(self) -> float | None:
        """The estimated age in milliseconds (None when the clock is unknown)."""
        return None if self.age_us is None else self.age_us / 1000.0


def judge_age(stamp_us: int, now_us: int, relative: tuple[float, float] | None, *,
              max_age_us: float, max_uncertainty_us: float) -> AgeVerdict:
    """Judge a stamp taken on another clock (see the module docstring).

    Args:
        stamp_us: the stamp, on the sender's clock.
        now_us: now, on our clock.
        relative: (our clock minus the sender's, its error bound), e.g. from
            :meth:`ClockView.relative`; None when unknown. A negative or non-finite bound
            counts as unknown (a negative one would widen the age window).
        max_age_us: the largest age that may be acted on.
        max_uncertainty_us: the widest error bound that may be acted on.
    """
    if relative is None:
        return AgeVerdict("unknown_clock")
    offset_us, unc_us = relative
    age_us = now_us - (stamp_us + offset_us)
    if not (math.isfinite(age_us) and math.isfinite(unc_us)) or unc_us < 0:
        return AgeVerdict("unknown_clock")
    if unc_us > max_uncertainty_us:
        return AgeVerdict("uncertain_clock", age_us, unc_us)
    if age_us + unc_us > max_age_us:
        return AgeVerdict("stale", age_us, unc_us)
    if age_us < -unc_us:
        return AgeVerdict("future", age_us, unc_us)
    return AgeVerdict("fresh", age_us, unc_us)
