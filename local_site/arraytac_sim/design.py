r"""Derivation of the plant and controller constants from the paper's measured figures.

Targets (paper, Fig. 2D-F): open-loop bandwidth 15.29 Hz, closed-loop bandwidth 123.39 Hz
(bandwidth = min of the -3 dB and the -90 deg frequency), overdamped step with 10-90 % rise
0.013 s and fall 0.016 s, zero steady-state error.

1. **Plant** (small signal, :mod:`.integrators`): ``y/u = g / ((tau_d s + 1)(tau_m s + 1))``: a
   fast driver lag ``tau_d`` and the dominant lever/soft-load lag ``tau_m``.
2. **PI by pole cancellation** (IMC): ``C = Kp (1 + 1/(tau_m s))`` cancels ``tau_m``; the loop is
   ``L = a / (s (tau_d s + 1))`` with ``a = Kp g / tau_m``, and the closed loop is
   ``wn^2 / (s^2 + 2 zeta wn s + wn^2)`` with ``wn^2 = a / tau_d``, ``2 zeta wn = 1 / tau_d``.
   Its phase is -90 deg at ``wn``; its -3 dB frequency is
   ``w3 = wn sqrt(1 - 2 zeta^2 + sqrt((1 - 2 zeta^2)^2 + 1))``, below ``wn``
   for
   ``zeta > 1/sqrt(2)``, so the bandwidth is ``w3``. Choosing ``zeta`` (> 1: overdamped, no
   overshoot) gives ``wn = 2 pi f_cl / h(zeta)``, ``tau_d = 1 / (2 zeta wn)``,
   ``a = wn / (2 zeta)``.
3. **Open loop**: ``|G(jw)/G(0)|^2 = 1/2`` at ``w_o = 2 pi f_ol``:
   ``(1 + (w_o tau_d)^2)(1 + (w_o tau_m)^2) = 2`` gives ``tau_m`` in closed form. The phase of
   the open loop reaches -90 deg only at ``1/sqrt(tau_d tau_m)`` (well above), so its bandwidth
   is the -3 dB one.
4. **Gains**: ``Kp = a tau_m / g``, ``Ki = Kp / tau_m = a / g``.
5. **Large-signal rise/fall**: a 3 mm step (1 -> 4 mm) saturates the PID (``Kp * 3 mm`` is far
   beyond the 135 V range), so rise and fall are set by the driver's charge and discharge slew
   limits (Fig. S1: current-limited charge, constant-current discharge). They have no closed
   form with the saturating PID; :func:`tune_slew_rates` finds them by bisection on the
   simulated step (rise and fall times are monotone in the slew rates).

The 10 kHz sampling (zero-order hold, half a tick of delay) is ignored by steps 1-4; measured on
the exact discrete transfer function it moves the closed-loop bandwidth from 123.4 to 128.4 Hz
(+4 %). :func:`refine_for_sampling` removes that by a fixed-point iteration on the design
targets (3 iterations reach 1e-6 relative).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from local_site.arraytac_sim.params import PlantParams
from shared.errors import ConfigError

__all__ = [
    "DesignTargets",
    "derive_params",
    "design_linear",
    "refine_for_sampling",
    "second_order_bandwidth_ratio",
    "tune_slew_rates",
]


@dataclass(frozen=True)
class DesignTargets:
    """The paper's figures the simulator is tuned to (Fig. 2D-F)."""

    open_loop_bandwidth_hz: float = 15.29
    closed_loop_bandwidth_hz: float = 123.39
    rise_time_s: float = 0.013
    fall_time_s: float = 0.016
    damping: float = 1.2
    step_low_mm: float = 1.0
    step_high_mm: float = 4.0


def second_order_bandwidth_ratio(zeta: float) -> float:
    """``w_-3dB / wn`` of ``wn^2 / (s^2 + 2 zeta wn s + wn^2)``."""
    c = 1.0 - 2.0 * zeta * zeta
    return math.sqrt(c + math.sqrt(c * c + 1.0))


def design_linear(targets: DesignTargets, base: PlantParams | None = None) -> PlantParams:
    """Steps 1-4 of the module docstring: time constants and PI gains in closed form.

    Raises:
        ConfigError: targets that admit no solution (e.g. ``zeta <= 1/sqrt(2)`` or an
            open-loop bandwidth the driver lag alone already undercuts).
    """
    p = base or PlantParams()
    zeta = targets.damping
    if zeta <= 1.0 / math.sqrt(2.0):
        raise ConfigError("damping must exceed 1/sqrt(2) so the -3 dB frequency sets the bandwidth")
    wn = 2.0 * math.pi * targets.closed_loop_bandwidth_hz / second_order_bandwidth_ratio(zeta)
    tau_d = 1.0 / (2.0 * zeta * wn)
    a = wn / (2.0 * zeta)
    w_o = 2.0 * math.pi * targets.open_loop_bandwidth_hz
    rhs = 2.0 / (1.0 + (w_o * tau_d) ** 2) - 1.0
    if rhs <= 0.0:
        raise ConfigError("open-loop bandwidth unreachable with this driver lag")
    tau_m = math.sqrt(rhs) / w_o
    g = p.lever_gain_mm_per_v
    kp = a * tau_m / g
    return replace(p, mech_time_constant_s=tau_m, driver_time_constant_s=tau_d,
                   closed_loop_damping=zeta, kp_v_per_mm=kp, ki_v_per_mm_s=kp / tau_m)


def _bisect(fn, lo: float, hi: float, target: float, iters: int) -> float:
    """Geometric bisection of a decreasing ``fn`` for ``fn(x) = target``."""
    for _ in range(iters):
        mid = math.sqrt(lo * hi)
        if fn(mid) > target:
            lo = mid
        else:
            hi = mid
    return math.sqrt(lo * hi)


def tune_slew_rates(params: PlantParams, targets: DesignTargets, iters: int = 16,
                    passes: int = 3) -> PlantParams:
    """Step 5: bisect the charge/discharge slew limits on the simulated step response."""
    from local_site.arraytac_sim.characterize import measure_step  # local: avoids a cycle

    p = params
    for _ in range(passes):  # the edges interact (fall slew ends a rise), so alternate
        def rise(s: float, base: PlantParams = p) -> float:
            return measure_step(replace(base, slew_up_v_per_s=s), targets.step_low_mm,
                                targets.step_high_mm).rise_time_s

        p = replace(p, slew_up_v_per_s=_bisect(rise, 1e3, 1e6, targets.rise_time_s, iters))

        def fall(s: float, base: PlantParams = p) -> float:
            return measure_step(replace(base, slew_down_v_per_s=s), targets.step_low_mm,
                                targets.step_high_mm).fall_time_s

        p = replace(p, slew_down_v_per_s=_bisect(fall, 1e3, 1e6, targets.fall_time_s, iters))
    return p


def refine_for_sampling(params: PlantParams, targets: DesignTargets,
                        iters: int = 3) -> PlantParams:
    """Correct the closed-form design for the 10 kHz sampling (fixed-point on the targets).

    The analytic steps assume continuous time; the zero-order hold shifts the bandwidths by a
    few per cent. Each iteration measures the exact discrete transfer functions
    (:func:`.characterize.measure_transfer_bandwidths`) and rescales the design targets by
    target/measured.
    """
    from local_site.arraytac_sim.characterize import measure_transfer_bandwidths

    design_t = targets
    p = params
    for _ in range(iters):
        ol_hz, cl_hz = measure_transfer_bandwidths(p)
        design_t = replace(
            design_t,
            open_loop_bandwidth_hz=design_t.open_loop_bandwidth_hz
            * targets.open_loop_bandwidth_hz / ol_hz,
            closed_loop_bandwidth_hz=design_t.closed_loop_bandwidth_hz
            * targets.closed_loop_bandwidth_hz / cl_hz)
        p = design_linear(design_t, p)
    return p


def derive_params(targets: DesignTargets | None = None, base: PlantParams | None = None,
                  ) -> PlantParams:
    """The full derivation: closed form, sampling correction, then slew-rate bisection."""
    t = targets or DesignTargets()
    p = refine_for_sampling(design_linear(t, base), t)
    return tune_slew_rates(p, t)
