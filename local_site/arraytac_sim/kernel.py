"""The firmware + plant tick loop of :mod:`.plant`, compiled with numba (the ``numba`` engine).

A 10 kHz control loop cannot be vectorised over time (each tick's PID output depends on the
previous tick's measurement), so the numpy engine pays Python overhead on every tick. This
module runs the very same per-tick arithmetic as ``ArrayTacPlant``'s per-step path
(:meth:`ArrayTacPlant._slow_steps` + :mod:`.integrators` + :mod:`.sensor` + Eq. 1-2 of
:mod:`.stiffness`) for all units in one compiled call, operation for operation in the same
order, so both engines give the same trajectories (``tests/local_site/
test_arraytac_sim_kernel.py`` checks it to 1e-9 mm).

Inputs are a few flat arrays to keep the call cheap (the CAN emulator advances the plant every
~2 ms, i.e. 20 ticks per call): :func:`pack_constants` (scalars, built once per plant) and the
plant's own state and command arrays (rows in :mod:`.layout`), read and updated in place. The
per-unit quantities derived from the commands (Eq. 1 cap, PID gains scaled by friction,
vibration amplitude and frequency) are computed here with the plant's formulas, once per call.
``cache=True`` keeps the compiled code in ``__pycache__`` across processes.

Raises ``ImportError`` naming the package when numba is not installed (the plant turns it into
a :class:`~shared.errors.ConfigError`); there is no silent fallback.
"""

from __future__ import annotations

import numpy as np

try:
    from numba import njit
except ImportError as err:  # pragma: no cover - exercised only without numba
    raise ImportError(
        "the ArrayTac simulator's 'numba' engine needs the 'numba' package "
        "(pip install numba, or choose engine='numpy')") from err

import math

from local_site.arraytac_sim.layout import (
    CMD_F,
    CMD_FORCE,
    CMD_HEIGHT,
    CMD_K,
    CMD_OV_A,
    CMD_OV_OMEGA,
    CMD_OV_V,
    CMD_TEST_AMP,
    CMD_TEST_OMEGA,
    N_CMD_ROWS,
    N_STATE_ROWS,
    S_I,
    S_M_PREV,
    S_U,
    S_U_CMD,
    S_Y,
)
from local_site.arraytac_sim.params import PlantParams

__all__ = ["INTEGRATOR_IDS", "N_CONST", "pack_constants", "run_ticks", "warm_up"]

# indices of the constants vector
(C_UB, C_UMAX, C_STROKE, C_EXPO, C_DT, C_GAP, C_RATIO, C_R2, C_LEN, C_HALF_BR, C_VQ,
 C_SENS, C_C3, C_C2, C_C1, C_C0, C_STOP_LO, C_STOP_HI, C_TD, C_TM, C_G, C_INV_B, C_S_UP,
 C_S_DOWN, C_H, C_SUBSTEPS, C_INTEG, C_PH00, C_GA00, C_PH10, C_PH11, C_GA10, C_GA11, C_GA12,
 C_PS10, C_PS11, C_GS10, C_GS11, C_GS12, C_U_SPAN, C_FRIC_AMP, C_TWO_PI, C_FRIC_SPAN_HZ,
 C_BOOST, C_KP, C_KI, C_KD) = range(47)
N_CONST = 47

INTEGRATOR_IDS = {"zoh": 0, "rk4": 1, "euler": 2}


def pack_constants(params: PlantParams, calibration: np.ndarray, integrator_id: int,
                   substeps: int, zoh_matrices: tuple[np.ndarray, ...] | None) -> np.ndarray:
    """All scalar constants of one plant as one float vector (indices ``C_*``).

    Args:
        params: plant constants.
        calibration: cubic Hall calibration, highest power first.
        integrator_id: ``INTEGRATOR_IDS[name]``.
        substeps: integrator sub-steps per tick.
        zoh_matrices: ``(phi, gamma, phi_slew, gamma_slew)`` of the ZOH integrator, or
            ``None`` for the ODE integrators.
    """
    p = params
    c = np.zeros(N_CONST)
    c[C_UB], c[C_UMAX], c[C_STROKE] = p.u_base_v, p.u_max_v, p.stroke_mm
    c[C_EXPO], c[C_DT] = p.penalty_exponent, p.control_period_s
    c[C_GAP], c[C_RATIO] = p.magnet_gap_at_zero_mm, p.magnet_travel_ratio
    c[C_R2], c[C_LEN] = p.magnet_radius_mm ** 2, p.magnet_length_mm
    c[C_HALF_BR], c[C_VQ] = 0.5 * p.magnet_br_t, p.hall_quiescent_v
    c[C_SENS] = p.hall_sensitivity_v_per_mt * 1e3
    c[C_C3], c[C_C2], c[C_C1], c[C_C0] = calibration
    c[C_STOP_LO], c[C_STOP_HI] = p.stop_low_mm, p.stop_high_mm
    c[C_TD], c[C_TM] = p.driver_time_constant_s, p.mech_time_constant_s
    c[C_G], c[C_INV_B] = p.lever_gain_mm_per_v, 1.0 / p.damping_n_s_per_mm
    c[C_S_UP], c[C_S_DOWN] = p.slew_up_v_per_s, p.slew_down_v_per_s
    c[C_H] = p.control_period_s / substeps
    c[C_SUBSTEPS], c[C_INTEG] = substeps, integrator_id
    c[C_U_SPAN], c[C_FRIC_AMP] = p.u_max_v - p.u_base_v, p.friction_amp_mm
    c[C_TWO_PI], c[C_FRIC_SPAN_HZ] = 2.0 * math.pi, p.friction_freq_span_hz
    c[C_BOOST], c[C_KP], c[C_KI], c[C_KD] = (p.friction_gain_boost, p.kp_v_per_mm,
                                             p.ki_v_per_mm_s, p.kd_v_s_per_mm)
    if zoh_matrices is not None:
        ph, ga, ps, gs = zoh_matrices
        c[C_PH00], c[C_GA00] = ph[0, 0], ga[0, 0]
        c[C_PH10], c[C_PH11] = ph[1, 0], ph[1, 1]
        c[C_GA10], c[C_GA11], c[C_GA12] = ga[1, 0], ga[1, 1], ga[1, 2]
        c[C_PS10], c[C_PS11] = ps[1, 0], ps[1, 1]
        c[C_GS10], c[C_GS11], c[C_GS12] = gs[1, 0], gs[1, 1], gs[1, 2]
    return c


@njit(cache=True, error_model="numpy", inline="always")
def _derivatives(c: np.ndarray, u: float, y: float, u_cmd: float,
                 force: float) -> tuple[float, float]:
    du = (u_cmd - u) / c[C_TD]
    if du < -c[C_S_DOWN]:
        du = -c[C_S_DOWN]
    elif du > c[C_S_UP]:
        du = c[C_S_UP]
    dy = (c[C_G] * (u - c[C_UB]) - y) / c[C_TM] - force * c[C_INV_B]
    return du, dy


@njit(cache=True, error_model="numpy", inline="always")
def _substep(c: np.ndarray, kind: int, u: float, y: float, u_cmd: float,
             force: float) -> tuple[float, float]:
    """One integrator sub-step with slew limits (same arithmetic as :mod:`.integrators`)."""
    h = c[C_H]
    if kind == 0:  # zoh
        u_lin = c[C_PH00] * u + c[C_GA00] * u_cmd
        y_lin = (c[C_PH10] * u + c[C_PH11] * y + c[C_GA10] * u_cmd + c[C_GA11] * force
                 + c[C_GA12])
        slope = (u_cmd - u) / c[C_TD]
        if slope > c[C_S_UP]:
            s = c[C_S_UP]
            u_new = min(u + s * h, u_lin)
        elif slope < -c[C_S_DOWN]:
            s = -c[C_S_DOWN]
            u_new = max(u + s * h, u_lin)
        else:
            return u_lin, y_lin
        y_new = c[C_PS10] * u + c[C_PS11] * y + c[C_GS10] * force + c[C_GS11] + c[C_GS12] * s
        return u_new, y_new
    if kind == 1:  # rk4
        k1u, k1y = _derivatives(c, u, y, u_cmd, force)
        k2u, k2y = _derivatives(c, u + 0.5 * h * k1u, y + 0.5 * h * k1y, u_cmd, force)
        k3u, k3y = _derivatives(c, u + 0.5 * h * k2u, y + 0.5 * h * k2y, u_cmd, force)
        k4u, k4y = _derivatives(c, u + h * k3u, y + h * k3y, u_cmd, force)
        return (u + h / 6.0 * (k1u + 2 * k2u + 2 * k3u + k4u),
                y + h / 6.0 * (k1y + 2 * k2y + 2 * k3y + k4y))
    du, dy = _derivatives(c, u, y, u_cmd, force)  # euler
    return u + h * du, y + h * dy


@njit(cache=True, error_model="numpy")
def run_ticks(c: np.ndarray, cmd: np.ndarray, state: np.ndarray, sat: np.ndarray,
              noise_v: np.ndarray, k0: int, override: bool, record: bool,
              rec: np.ndarray) -> bool:
    """Run ``noise_v.shape[0]`` firmware ticks for every unit, in place.

    Args:
        c: constants from :func:`pack_constants`.
        cmd: the plant's commands ``(N_CMD_ROWS, n)`` (rows ``layout.CMD_*``, clamped).
        state: ``(N_STATE_ROWS, n)`` (rows ``layout.S_*``); updated in place.
        sat: ``(n,)`` bool, stiffness stage 2 active at the last tick; updated in place.
        noise_v: Hall noise ``(ticks, n)`` in volts.
        k0: index of the first tick (the firmware clock).
        override: open-loop drive test mode (rows ``CMD_OV_*``) instead of the PID.
        record: write ``rec``.
        rec: ``(4, ticks, n)`` measured height, true height, voltage, reference at the start
            of each tick (untouched unless ``record``).

    Returns:
        Whether any unit synthesised the friction vibration (some ``f > 0``).
    """
    n_ticks, n = noise_v.shape
    ub, dt = c[C_UB], c[C_DT]
    kind = int(c[C_INTEG])
    substeps = int(c[C_SUBSTEPS])
    # per-unit quantities, same formulas and order as ArrayTacPlant._derive_commands
    ulim = (cmd[CMD_K] + 4.0) / 5.0 * c[C_U_SPAN] + ub
    ylim = c[C_G] * (ulim - ub)
    soft = 1.0 - cmd[CMD_K]
    f = cmd[CMD_F]
    amp = f * c[C_FRIC_AMP]
    omega = c[C_TWO_PI] * f * c[C_FRIC_SPAN_HZ]
    gain = 1.0 + c[C_BOOST] * f
    kp = c[C_KP] * gain
    ki_dt = c[C_KI] * gain * dt
    kd_dt = c[C_KD] * gain / dt
    height, force = cmd[CMD_HEIGHT], cmd[CMD_FORCE]
    test_amp, test_omega = cmd[CMD_TEST_AMP], cmd[CMD_TEST_OMEGA]
    any_vib = False
    any_test = False
    for i in range(n):
        any_vib = any_vib or f[i] > 0.0
        any_test = any_test or test_amp[i] > 0.0
    any_sine = any_vib or any_test
    su, sy, si, sm, sc = state[S_U], state[S_Y], state[S_I], state[S_M_PREV], state[S_U_CMD]
    # tick-major: the units' independent dependency chains overlap in the CPU
    for j in range(n_ticks):
        t = (k0 + j) * dt
        for i in range(n):
            u, y = su[i], sy[i]
            # Hall sensor + cubic calibration (sensor.measure_mm)
            d = c[C_GAP] - c[C_RATIO] * y
            dl = d + c[C_LEN]
            b_t = c[C_HALF_BR] * (dl / np.sqrt(dl * dl + c[C_R2]) - d / np.sqrt(d * d + c[C_R2]))
            v = c[C_VQ] + c[C_SENS] * b_t + noise_v[j, i]
            m = ((c[C_C3] * v + c[C_C2]) * v + c[C_C1]) * v + c[C_C0]
            # reference: height + friction vibration + firmware sine test, clipped
            r = height[i]
            if any_sine:
                if f[i] > 0.0:
                    r += amp[i] * np.sin(omega[i] * t)
                if test_amp[i] > 0.0:
                    r += test_amp[i] * np.sin(test_omega[i] * t)
                r = min(max(r, 0.0), c[C_STROKE])
            if record:
                rec[0, j, i], rec[1, j, i], rec[2, j, i], rec[3, j, i] = m, y, u, r
            if not override:
                # PID with clamping anti-windup, Eq. (1) cap, Eq. (2) stage 2
                e = r - m
                integ = si[i]
                u_raw = ub + kp[i] * e + integ + kd_dt[i] * (sm[i] - m)
                s_i = u_raw > ulim[i] and e > 0.0
                hold = s_i or (u_raw < ub and e < 0.0)
                if not hold:
                    si[i] = integ + ki_dt[i] * e
                u_cmd = min(max(u_raw, ub), ulim[i])
                if s_i:
                    base = max(1.0 - soft[i] * max(e, 0.0) / ylim[i], 0.0)
                    u_cmd = (ulim[i] - ub) * base ** c[C_EXPO] + ub
            else:
                u_cmd = min(max(cmd[CMD_OV_V, i] + cmd[CMD_OV_A, i]
                                * np.sin(cmd[CMD_OV_OMEGA, i] * t), ub), c[C_UMAX])
                s_i = False
            for _ in range(substeps):
                u, y = _substep(c, kind, u, y, u_cmd, force[i])
                y = min(max(y, c[C_STOP_LO]), c[C_STOP_HI])
            su[i], sy[i], sm[i], sc[i] = u, y, m, u_cmd
            sat[i] = s_i
    return any_vib


def warm_up() -> None:
    """Compile (or load from the cache) :func:`run_ticks` for the types the plant passes."""
    c = np.zeros(N_CONST)
    c[C_SUBSTEPS], c[C_TD], c[C_TM], c[C_H], c[C_DT] = 1.0, 1.0, 1.0, 1.0, 1.0
    c[C_STOP_HI], c[C_STROKE], c[C_R2], c[C_INV_B] = 1.0, 1.0, 1.0, 1.0
    cmd = np.zeros((N_CMD_ROWS, 1))
    cmd[CMD_K] = 1.0
    run_ticks(c, cmd, np.zeros((N_STATE_ROWS, 1)), np.zeros(1, dtype=np.bool_),
              np.zeros((1, 1)), 0, False, False, np.zeros((4, 0, 1)))
