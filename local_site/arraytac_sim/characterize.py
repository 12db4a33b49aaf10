"""Measure the simulator the way the paper measured the hardware (Fig. 2D-F, Fig. 8D).

Nothing here is copied from the paper: every figure comes from simulated responses.

- **Step** (:func:`measure_step`): k = 1, friction off, settle at ``low``, step to ``high`` and
  back; 10-90 % rise and fall times (linear interpolation of the first crossings of the true pin
  height), overshoot (0.5 ms moving average of the true height against its settled value, as a
  percentage of the step), steady-state error of the measured height (what the controller
  regulates, mean of the last 20 ms) and of the true height (the cubic calibration's residual).
- **Frequency response** (:func:`measure_frequency_response`): the firmware + plant map is
  linear for small signals; its transfer function is evaluated exactly from the probed
  discrete-time matrices (:mod:`.blockpath`) on a dense grid, and the -3 dB and -90 deg
  frequencies are found by root bracketing. A sine sweep (one frequency per unit, lock-in on a
  whole number of cycles) cross-checks it: open loop through the drive override, closed loop
  through the firmware's sine test signal.
- **Force-displacement** (:func:`measure_force_displacement`): pins at 3 mm (paper's stiffness
  study), one unit per k, finger force raised in steps; compression at each settled step.
  Reported per k: yield force (end of region A), region-B slope (least-squares) and secant
  stiffness at the largest force.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np
from scipy.optimize import brentq

from local_site.arraytac_sim.blockpath import modal_decomposition
from local_site.arraytac_sim.params import PlantParams
from local_site.arraytac_sim.plant import ArrayTacPlant
from shared.errors import NumericalError

__all__ = [
    "PAPER_FIGURES",
    "STIFFNESS_LEVELS",
    "CharacterizeResult",
    "ForceDisplacement",
    "FrequencyResponse",
    "StepResult",
    "characterize",
    "measure_force_displacement",
    "measure_frequency_response",
    "measure_step",
    "measure_transfer_bandwidths",
]

#: the paper's measured figures (Fig. 2D-F), only for side-by-side reporting
PAPER_FIGURES: dict[str, float] = {
    "open_loop_bandwidth_hz": 15.29,
    "closed_loop_bandwidth_hz": 123.39,
    "rise_time_s": 0.013,
    "fall_time_s": 0.016,
    "overshoot_pct": 0.0,
    "steady_state_error_mm": 0.0,
}
STIFFNESS_LEVELS = (0.5, 0.625, 0.75, 0.875, 1.0)


@dataclass(frozen=True)
class StepResult:
    """Large-signal step response figures."""

    step_low_mm: float
    step_high_mm: float
    rise_time_s: float
    fall_time_s: float
    overshoot_pct: float
    undershoot_pct: float
    steady_state_error_mm: float
    true_steady_state_error_mm: float


@dataclass(frozen=True)
class FrequencyResponse:
    """Bandwidths (Hz) from the transfer function, with the sine-sweep cross-check."""

    open_loop_minus3db_hz: float
    open_loop_minus90deg_hz: float
    closed_loop_minus3db_hz: float
    closed_loop_minus90deg_hz: float
    open_loop_bandwidth_hz: float
    closed_loop_bandwidth_hz: float
    sweep_open_loop_bandwidth_hz: float
    sweep_closed_loop_bandwidth_hz: float
    sweep_open_freq_hz: list[float] = field(default_factory=list)
    sweep_open_gain_db: list[float] = field(default_factory=list)
    sweep_open_phase_deg: list[float] = field(default_factory=list)
    sweep_closed_freq_hz: list[float] = field(default_factory=list)
    sweep_closed_gain_db: list[float] = field(default_factory=list)
    sweep_closed_phase_deg: list[float] = field(default_factory=list)


@dataclass(frozen=True)
class ForceDisplacement:
    """Force-displacement curve of one stiffness level (pin at ``target_mm``)."""

    k: float
    target_mm: float
    force_n: list[float]
    compression_mm: list[float]
    yield_force_n: float
    region_b_stiffness_n_per_mm: float
    secant_stiffness_n_per_mm: float


@dataclass(frozen=True)
class CharacterizeResult:
    """Everything ``teletouch display characterize`` reports."""

    step: StepResult
    frequency: FrequencyResponse
    force_displacement: list[ForceDisplacement]

    def to_dict(self) -> dict[str, Any]:
        """Flat headline figures plus the detailed sections (JSON-ready)."""
        f, s = self.frequency, self.step
        return {
            "open_loop_bandwidth_hz": f.open_loop_bandwidth_hz,
            "closed_loop_bandwidth_hz": f.closed_loop_bandwidth_hz,
            "rise_time_s": s.rise_time_s,
            "fall_time_s": s.fall_time_s,
            "overshoot_pct": s.overshoot_pct,
            "steady_state_error_mm": s.steady_state_error_mm,
            "step": asdict(s),
            "frequency_response": asdict(f),
            "force_displacement": [asdict(c) for c in self.force_displacement],
            "paper": dict(PAPER_FIGURES),
        }


# ---------------------------------------------------------------------------- step
def _crossing_time(t: np.ndarray, y: np.ndarray, level: float, rising: bool) -> float:
    above = y >= level if rising else y <= level
    idx = np.flatnonzero(above)
    if idx.size == 0 or idx[0] == 0:
        raise NumericalError(f"step response never crosses {level:.3f} mm")
    i = int(idx[0])
    y0, y1 = y[i - 1], y[i]
    frac = (level - y0) / (y1 - y0) if y1 != y0 else 0.0
    return float(t[i - 1] + frac * (t[i] - t[i - 1]))


def _edge(plant: ArrayTacPlant, start: float, end: float, duration_s: float,
          ) -> tuple[float, float, float, float]:
    plant.set_targets(np.full(plant.n_units, end), 1.0, 0.0)
    tr = plant.run(duration_s)
    t = tr.time_s - tr.time_s[0]
    y = tr.true_position_mm.mean(axis=1)
    span = end - start
    rising = span > 0
    t10 = _crossing_time(t, y, start + 0.1 * span, rising)
    t90 = _crossing_time(t, y, start + 0.9 * span, rising)
    tail = max(int(0.02 / plant.params.control_period_s), 1)
    settled = float(y[-tail:].mean())
    width = max(int(0.0005 / plant.params.control_period_s), 1)
    smooth = np.convolve(y, np.ones(width) / width, mode="valid")
    beyond = (smooth.max() - settled) if rising else (settled - smooth.min())
    overshoot = max(float(beyond), 0.0) / abs(span) * 100.0
    measured_error = float(tr.position_mm[-tail:].mean() - end)
    return t90 - t10, overshoot, measured_error, settled - end


def measure_step(params: PlantParams | None = None, low_mm: float = 1.0, high_mm: float = 4.0,
                 integrator: str = "zoh", edge_s: float = 0.12) -> StepResult:
    """Rise/fall time, overshoot and steady-state error of a ``low -> high -> low`` step.

    Raises:
        NumericalError: the response never reaches the 10 %/90 % levels.
    """
    plant = ArrayTacPlant(params, n_units=1, integrator=integrator)
    plant.set_targets(np.full(1, low_mm), 1.0, 0.0)
    plant.advance(0.3)
    rise, over_up, err_up, true_up = _edge(plant, low_mm, high_mm, edge_s)
    fall, over_dn, err_dn, true_dn = _edge(plant, high_mm, low_mm, edge_s)
    err = err_up if abs(err_up) >= abs(err_dn) else err_dn
    true_err = true_up if abs(true_up) >= abs(true_dn) else true_dn
    return StepResult(low_mm, high_mm, rise, fall, over_up, over_dn, err, true_err)


# ---------------------------------------------------------------------------- frequency
def _linear_transfer(plant: ArrayTacPlant) -> tuple[Any, Any]:
    """Exact discrete transfer functions: closed loop r -> y and open loop u -> y."""
    modes = modal_decomposition(plant._linear_map(1.0))
    if modes is None:
        raise NumericalError("closed loop is defective; cannot evaluate its transfer function")
    phi_cl, gam_cl = modes.phi, modes.gamma[:, 0]
    p = plant.params
    zero = np.zeros(3)

    def plant_step(x: np.ndarray) -> np.ndarray:
        u, y = plant._integ.step(x[0], x[1], x[2], zero, slew=False)
        return np.stack([u, y])

    c0 = plant_step(np.zeros((3, 3)))[:, 0]
    probe = plant_step(np.eye(3))
    phi_ol = probe[:, :2] - c0[:, None]
    gam_ol = probe[:, 2] - c0
    dt = p.control_period_s

    def response(phi: np.ndarray, gam: np.ndarray, out: int):
        eye = np.eye(phi.shape[0])

        def h(f_hz: float) -> complex:
            z = np.exp(1j * 2.0 * math.pi * f_hz * dt)
            return complex(np.linalg.solve(z * eye - phi, gam)[out])

        return h

    return response(phi_cl, gam_cl, 1), response(phi_ol, gam_ol, 1)


def _bandwidths(h, f_max_hz: float) -> tuple[float, float]:
    dc = h(1e-3)
    freqs = np.logspace(-1, math.log10(f_max_hz), 400)
    gain = np.array([abs(h(f) / dc) for f in freqs])
    phase = np.unwrap(np.array([np.angle(h(f) / dc) for f in freqs]))

    def first_root(values: np.ndarray, level: float, fn) -> float:
        idx = np.flatnonzero(values < level)
        if idx.size == 0 or idx[0] == 0:
            return math.inf
        i = int(idx[0])
        return float(brentq(fn, freqs[i - 1], freqs[i], xtol=1e-6))

    f3 = first_root(gain, 1 / math.sqrt(2), lambda f: abs(h(f) / dc) - 1 / math.sqrt(2))

    def phase_at(f: float) -> float:
        # continuous phase: unwrap from the grid point below
        i = max(int(np.searchsorted(freqs, f)) - 1, 0)
        raw = np.angle(h(f) / dc)
        return float(raw + 2 * math.pi * round((phase[i] - raw) / (2 * math.pi)))

    f90 = first_root(phase, -math.pi / 2, lambda f: phase_at(f) + math.pi / 2)
    return f3, f90


def _lock_in(tr_t: np.ndarray, sig: np.ndarray, ref: np.ndarray, freqs: np.ndarray,
             settle_s: float) -> np.ndarray:
    """Complex ratio sig/ref at each unit's frequency over a whole number of cycles."""
    out = np.empty(freqs.size, dtype=complex)
    t = tr_t - tr_t[0]
    for i, f in enumerate(freqs):
        usable = t[-1] - settle_s
        cycles = math.floor(usable * f)
        if cycles < 1:
            raise NumericalError(f"sweep too short for {f:.2f} Hz")
        sel = t >= t[-1] - cycles / f
        ph = np.exp(-2j * math.pi * f * t[sel])
        s = sig[sel, i] - sig[sel, i].mean()
        r = ref[sel, i] - ref[sel, i].mean()
        out[i] = np.sum(s * ph) / np.sum(r * ph)
    return out


def _interp_crossing(freqs: np.ndarray, values: np.ndarray, level: float) -> float:
    idx = np.flatnonzero(values < level)
    if idx.size == 0 or idx[0] == 0:
        return math.inf
    i = int(idx[0])
    x0, x1 = math.log(freqs[i - 1]), math.log(freqs[i])
    v0, v1 = values[i - 1], values[i]
    return float(math.exp(x0 + (level - v0) / (v1 - v0) * (x1 - x0)))


def measure_transfer_bandwidths(params: PlantParams | None = None,
                                integrator: str = "zoh") -> tuple[float, float]:
    """Open- and closed-loop bandwidths (Hz) from the exact discrete transfer functions only."""
    probe = ArrayTacPlant(params, n_units=1, integrator=integrator)
    h_cl, h_ol = _linear_transfer(probe)
    nyquist = 0.45 * probe.params.control_rate_hz
    return min(_bandwidths(h_ol, nyquist)), min(_bandwidths(h_cl, nyquist))


def measure_frequency_response(params: PlantParams | None = None, quick: bool = False,
                               integrator: str = "zoh") -> FrequencyResponse:
    """Open- and closed-loop bandwidths (min of -3 dB and -90 deg), TF + sine-sweep check."""
    probe = ArrayTacPlant(params, n_units=1, integrator=integrator)
    h_cl, h_ol = _linear_transfer(probe)
    nyquist = 0.45 * probe.params.control_rate_hz
    ol3, ol90 = _bandwidths(h_ol, nyquist)
    cl3, cl90 = _bandwidths(h_cl, nyquist)

    n_pts = 8 if quick else 16
    # open loop: drive override around mid-stroke, 1 V amplitude (37 um)
    f_ol = np.logspace(math.log10(2.0 if quick else 1.0), math.log10(120.0), n_pts)
    p = probe.params
    plant = ArrayTacPlant(params, n_units=n_pts, integrator=integrator)
    mid_v = 0.5 * (p.u_base_v + p.u_max_v)
    plant.set_drive_override(mid_v)
    plant.advance(0.1)
    plant.set_drive_override(mid_v, 1.0, f_ol)
    settle = 0.1
    tr = plant.run(settle + (2.0 if quick else 3.0) / f_ol[0])
    u_ref = mid_v + np.sin(2 * math.pi * f_ol[None, :] * tr.time_s[:, None])
    g_ol = _lock_in(tr.time_s, tr.position_mm, u_ref, f_ol, settle)
    g_ol = g_ol / abs(g_ol[0])  # normalise by the lowest frequency, as on the bench

    # closed loop: firmware sine test, 20 um around 2.5 mm
    f_cl = np.logspace(math.log10(10.0), math.log10(600.0), n_pts)
    plant = ArrayTacPlant(params, n_units=n_pts, integrator=integrator)
    plant.set_targets(np.full(n_pts, 2.5), 1.0, 0.0)
    plant.advance(0.3)
    plant.set_test_signal(0.02, f_cl)
    tr = plant.run(settle + (3.0 if quick else 6.0) / f_cl[0])
    g_cl = _lock_in(tr.time_s, tr.position_mm, tr.reference_mm, f_cl, settle)

    def gain_phase(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return 20 * np.log10(np.abs(g)), np.degrees(np.unwrap(np.angle(g)))

    ol_db, ol_ph = gain_phase(g_ol)
    cl_db, cl_ph = gain_phase(g_cl)
    level_db = -10 * math.log10(2)
    sweep_ol = min(_interp_crossing(f_ol, ol_db, level_db), _interp_crossing(f_ol, ol_ph, -90))
    sweep_cl = min(_interp_crossing(f_cl, cl_db, level_db), _interp_crossing(f_cl, cl_ph, -90))
    return FrequencyResponse(
        ol3, ol90, cl3, cl90, min(ol3, ol90), min(cl3, cl90), sweep_ol, sweep_cl,
        f_ol.tolist(), ol_db.tolist(), ol_ph.tolist(), f_cl.tolist(), cl_db.tolist(),
        cl_ph.tolist())


# ---------------------------------------------------------------------------- stiffness
def measure_force_displacement(params: PlantParams | None = None,
                               levels: tuple[float, ...] = STIFFNESS_LEVELS,
                               target_mm: float = 3.0, max_force_n: float = 3.0,
                               quick: bool = False, integrator: str = "zoh",
                               ) -> list[ForceDisplacement]:
    """Quasi-static force-displacement curves, one unit per stiffness level."""
    n = len(levels)
    plant = ArrayTacPlant(params, n_units=n, integrator=integrator)
    plant.set_targets(np.full(n, target_mm), np.asarray(levels, float), 0.0)
    plant.advance(0.3)
    forces = np.linspace(0.0, max_force_n, 13 if quick else 31)
    hold_s = 0.12 if quick else 0.2
    tail = max(int(0.02 / plant.params.control_period_s), 1)
    comp = np.empty((forces.size, n))
    for i, f in enumerate(forces):
        plant.set_finger_force(f)
        tr = plant.run(hold_s)
        comp[i] = target_mm - tr.true_position_mm[-tail:].mean(axis=0)
    curves = []
    for j, k in enumerate(levels):
        c = comp[:, j]
        in_a = np.flatnonzero(c < 0.02)
        yield_f = float(forces[in_a[-1]]) if in_a.size else 0.0
        in_b = (c >= 0.05) & (c < target_mm - 0.05)
        if np.count_nonzero(in_b) >= 2:
            slope = float(np.polyfit(c[in_b], forces[in_b], 1)[0])
        else:
            slope = math.nan
        secant = float(forces[-1] / c[-1]) if c[-1] > 1e-6 else math.inf
        curves.append(ForceDisplacement(float(k), target_mm, forces.tolist(), c.tolist(),
                                        yield_f, slope, secant))
    return curves


def characterize(params: PlantParams | None = None, quick: bool = False,
                 integrator: str = "zoh") -> CharacterizeResult:
    """Run all three measurements on the simulator."""
    p = params or PlantParams()
    return CharacterizeResult(
        measure_step(p, integrator=integrator),
        measure_frequency_response(p, quick=quick, integrator=integrator),
        measure_force_displacement(p, quick=quick, integrator=integrator),
    )


def with_targets(params: PlantParams, **changes: Any) -> PlantParams:
    """Convenience for experiments: ``replace`` that keeps validation."""
    return replace(params, **changes)
