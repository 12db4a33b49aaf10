"""ArrayTac simulator: 16 units of drive-board firmware + piezo/lever plant.

Per unit and per 10 kHz firmware tick:

1. Hall sensor: ``y_meas = c(V(y) + noise)`` (:mod:`.sensor`, cubic calibration, seeded noise).
2. Reference: ``r = height + a(f) sin(2 pi f_v(f) t)`` clipped to the stroke, with amplitude
   ``a = f * friction_amp_mm`` and frequency ``f_v = f * friction_freq_span_hz`` (paper: 0-200 Hz
   over f, at most 512 Hz). When every ``f == 0`` no sinusoid is evaluated at all.
3. PID (gains scaled by ``1 + friction_gain_boost * f``): ``u_raw = U_base + Kp e + I +
   Kd (y_meas_prev - y_meas)/T``, output clamped to ``[U_base, U_limit(k)]`` (Eq. 1) with
   clamping anti-windup (the integrator holds while the output is clamped in the direction of
   the error).
4. Stiffness stage 2: while the PID is saturated high with the pin below target, the output is
   the feedforward penalty of Eq. (2), ``U = (U_limit - U_base)(1 - (1-k) e / y_lim)^2 +
   U_base`` (``e`` the compression in mm, ``y_lim = g (U_limit - U_base)``).
5. Plant: driver lag + slew limits and lever/soft-load lag (:mod:`.integrators`), finger force.

Engines (``engine=``): ``"numba"`` (default) runs steps 1-5 for all units in one compiled call
per :meth:`ArrayTacPlant.advance` (:mod:`.kernel`); ``"numpy"`` is the reference
implementation, vectorised over units with one Python iteration per tick. Both run the same
arithmetic in the same order and consume the same noise stream, so their trajectories agree to
rounding (``tests/local_site/test_arraytac_sim_kernel.py``).

Fast path (numpy engine only): while nothing saturates, whole blocks of ticks are integrated
exactly with the modal decomposition of :mod:`.blockpath`; any tick that would hit a
nonlinearity is replayed by the per-step path, so results are those of the per-step firmware up
to the Hall-chain linearisation (measured in ``benchmarks/bench_arraytac_sim.py``).

Asymmetric rise/fall (paper: 0.013 s vs 0.016 s): the driver charges the piezo through a
current-limited voltage follower and discharges it through a constant-current sink (paper,
Fig. S1); a current limit into the piezo capacitance is a voltage slew limit, so large steps
rise at ``slew_up_v_per_s`` and fall at the lower ``slew_down_v_per_s``.
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict
from dataclasses import dataclass, replace

import numpy as np

from local_site.arraytac_sim import layout
from local_site.arraytac_sim.blockpath import LinearModes, modal_decomposition, propagate
from local_site.arraytac_sim.integrators import ZOHIntegrator, make_integrator
from local_site.arraytac_sim.params import PlantParams
from local_site.arraytac_sim.sensor import HallSensor
from local_site.arraytac_sim.stiffness import u_limit_v
from shared.errors import ConfigError, InputDataError

__all__ = ["ENGINES", "ArrayTacPlant", "PlantParams", "PlantTrace"]

#: tick-loop implementations: the compiled kernel and the numpy reference
ENGINES = ("numba", "numpy")

log = logging.getLogger(__name__)

_MIN_BLOCK_STEPS = 16      # below this the per-step path is cheaper
_MAX_BLOCK_STEPS = 4000    # longer blocks waste work when a late tick saturates
_REPLAY_STEPS = 4          # per-step ticks after a violation before retrying the fast path
_MAX_BACKOFF_STEPS = 400   # longest per-step stretch before the fast path is tried again
_MAX_FAST_GROUPS = 4       # distinct friction gains handled by the fast path
_MODE_CACHE = 64
_LINEARISATION_SPAN_MM = 0.02  # Hall chain linearised within +-20 um of the block start
_NOISE_BLOCK_TICKS = 2048  # sensor noise is drawn in blocks (same stream, fewer calls)


@dataclass(frozen=True)
class PlantTrace:
    """Per-tick record of a :meth:`ArrayTacPlant.run` (arrays are ``(ticks, n_units)``).

    Values are sampled at the *start* of each tick, as the firmware sees them.
    """

    time_s: np.ndarray
    position_mm: np.ndarray
    true_position_mm: np.ndarray
    drive_voltage_v: np.ndarray
    reference_mm: np.ndarray


def _as_unit_array(name: str, value: float | np.ndarray, n_units: int) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(n_units, float(arr))
    if arr.shape != (n_units,):
        raise InputDataError(f"{name} must be a scalar or shape ({n_units},), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise InputDataError(f"{name} contains NaN or Inf: {arr}")
    return arr


def _store_clamped(out: np.ndarray, name: str, value: float | np.ndarray, low: float,
                   high: float) -> None:
    """Validate ``value`` like :func:`_as_unit_array` and store ``clip(value, low, high)``.

    Commands arrive at 1 kHz from the emulated CAN link, so this avoids ``np.clip`` (slow on
    16 elements) and handles plain scalars without building an array.
    """
    if isinstance(value, float | int):
        x = float(value)
        if not math.isfinite(x):
            raise InputDataError(f"{name} contains NaN or Inf: {x}")
        out.fill(min(max(x, low), high))
        return
    arr = _as_unit_array(name, value, out.shape[0])
    np.minimum(np.maximum(arr, low, out=out), high, out=out)


class ArrayTacPlant:
    """The simulated ArrayTac array: firmware + plant for ``n_units`` pins.

    Args:
        params: plant constants (defaults: :class:`PlantParams`, tuned to the paper).
        n_units: number of pins (16 for the 4 x 4 array).
        control_rate_hz: firmware rate, overrides ``params.control_rate_hz``.
        integrator: plant integrator, ``"zoh"`` (exact, default), ``"rk4"`` or ``"euler"``.
        substeps: integrator sub-steps per firmware tick.
        fast_path: numpy engine: integrate saturation-free blocks exactly in one go (see
            module docstring); the numba engine always runs the exact per-step firmware.
        engine: ``"numba"`` (compiled tick loop, default) or ``"numpy"`` (the reference).

    Raises:
        ConfigError: bad ``n_units``, rate, integrator or engine, or the ``numba`` engine
            without the ``numba`` package installed.
    """

    def __init__(self, params: PlantParams | None = None, n_units: int = 16,
                 control_rate_hz: float = 10_000.0, integrator: str = "zoh",
                 substeps: int = 1, fast_path: bool = True, engine: str = "numba") -> None:
        if int(n_units) < 1:
            raise ConfigError(f"n_units must be >= 1, got {n_units}")
        if engine not in ENGINES:
            raise ConfigError(f"unknown engine {engine!r}; choose from {list(ENGINES)}")
        if not (math.isfinite(control_rate_hz) and control_rate_hz > 0):
            raise ConfigError(f"control_rate_hz must be > 0, got {control_rate_hz}")
        base = params or PlantParams()
        self.params = replace(base, control_rate_hz=float(control_rate_hz))
        self.n_units = int(n_units)
        self.integrator_name = integrator
        self._integ = make_integrator(integrator, self.params, substeps)
        self.sensor = HallSensor(self.params)
        self.fast_path = bool(fast_path)
        self._dt = self.params.control_period_s
        self._modes: OrderedDict[float, LinearModes | None] = OrderedDict()
        self._empty_record = {name: np.empty((0, self.n_units)) for name in "myur"}
        self.engine = engine
        self._run_ticks = {"numba": self._compiled_steps, "numpy": self._numpy_steps}[engine]
        if engine == "numba":
            self._init_kernel(integrator)
        #: counters of ticks run by each path (the benchmark reads them); ``slow_ticks`` counts
        #: per-step ticks of either engine
        self.fast_ticks = 0
        self.slow_ticks = 0
        self.vibration_ticks = 0
        self._block_len = 4 * _MIN_BLOCK_STEPS
        self._backoff = 0
        self._backoff_len = _REPLAY_STEPS
        self.reset()

    def _init_kernel(self, integrator: str) -> None:
        try:
            from local_site.arraytac_sim import kernel
        except ImportError as err:
            raise ConfigError(f"ArrayTac engine 'numba' unavailable: {err}") from err
        kernel.warm_up()  # compile or load from the cache now, not in the first advance()
        zoh = self._integ.matrices if isinstance(self._integ, ZOHIntegrator) else None
        self._kernel = kernel.run_ticks
        self._consts = kernel.pack_constants(self.params, self.sensor.calibration_coefficients,
                                             kernel.INTEGRATOR_IDS[integrator],
                                             self._integ.substeps, zoh)
        self._no_rec = np.empty((4, 0, self.n_units))

    # ------------------------------------------------------------------ commands
    def reset(self) -> None:
        """Return to t = 0, pins retracted and at rest, zero commands, noise re-seeded."""
        n, p = self.n_units, self.params
        # state and commands: rows of two arrays (layout), updated in place by both engines
        self._z = np.empty((layout.N_STATE_ROWS, n))
        self._u, self._y, self._i, self._m_prev, self._u_cmd = self._z
        self._cmd = np.zeros((layout.N_CMD_ROWS, n))
        self._height, self._k, self._f, self._force = self._cmd[:layout.CMD_TEST_AMP]
        self._test = self._cmd[layout.CMD_TEST_AMP:layout.CMD_TEST_OMEGA + 1]
        self._k_new, self._f_new = np.empty(n), np.empty(n)   # validated before stored
        self._u[:] = p.u_base_v
        self._y[:] = 0.0
        self._i[:] = 0.0
        self._m_prev[:] = self.sensor.measure_mm(self._y)
        self._u_cmd[:] = p.u_base_v
        self._sat = np.zeros(n, dtype=bool)
        self._step = 0
        self._t_req_s = 0.0
        self._override: np.ndarray | None = None
        self._test_units = np.flatnonzero(self._test[0] > 0.0)
        self._rng = np.random.default_rng(p.noise_seed)
        self._noise_buf = np.empty((0, n))
        self._noise_pos = 0
        self.set_targets(np.zeros(n), np.ones(n) * p.k_max, np.zeros(n))

    def set_targets(self, height_mm: float | np.ndarray, stiffness_k: float | np.ndarray,
                    friction: float | np.ndarray) -> None:
        """Set per-pin commands; out-of-range values are clamped.

        Args:
            height_mm: pin heights, clamped to ``[0, stroke_mm]``.
            stiffness_k: normalised stiffness, clamped to ``[k_min, k_max]`` (0.5..1).
            friction: normalised friction, clamped to ``[0, 1]``.

        Raises:
            InputDataError: NaN/Inf or wrong shape.
        """
        p = self.params
        # validate all three before storing any (a bad command changes nothing)
        h = _as_unit_array("height_mm", height_mm, self.n_units)
        _store_clamped(self._k_new, "stiffness_k", stiffness_k, p.k_min, p.k_max)
        _store_clamped(self._f_new, "friction", friction, 0.0, 1.0)
        np.minimum(np.maximum(h, 0.0, out=self._height), p.stroke_mm, out=self._height)
        self._k[:] = self._k_new
        self._f[:] = self._f_new
        self._derived = False

    def _derive_commands(self) -> None:
        """Per-unit quantities of the numpy engine (the kernel derives the same ones itself)."""
        p, k, f = self.params, self._k, self._f
        self._u_limit = u_limit_v(k, p.u_base_v, p.u_max_v)
        self._y_lim = p.lever_gain_mm_per_v * (self._u_limit - p.u_base_v)
        self._amp = f * p.friction_amp_mm
        self._omega = 2.0 * math.pi * f * p.friction_freq_span_hz
        self._gain = 1.0 + p.friction_gain_boost * f
        self._vib = np.flatnonzero(f > 0.0)
        self._derived = True

    def set_finger_force(self, force_n: float | np.ndarray) -> None:
        """Fingertip load pressing on each pin (N); negative values clamp to 0 (no pulling).

        Raises:
            InputDataError: NaN/Inf or wrong shape.
        """
        _store_clamped(self._force, "force_n", force_n, 0.0, math.inf)

    def set_drive_override(self, voltage_v: float | np.ndarray | None,
                           amplitude_v: float | np.ndarray = 0.0,
                           frequency_hz: float | np.ndarray = 0.0) -> None:
        """Open-loop test mode: drive ``voltage + amplitude sin(2 pi f t)``, bypassing the PID.

        Used to measure the open-loop response. ``None`` returns to closed loop (the integrator
        restarts bumplessly from the current voltage). Drive voltages clamp to
        ``[U_base, U_max]``.

        Raises:
            InputDataError: NaN/Inf, wrong shape or a negative frequency.
        """
        p = self.params
        if voltage_v is None:
            if self._override is not None:
                self._i[:] = self._u_cmd - p.u_base_v
            self._override = None
            return
        n = self.n_units
        freq = _as_unit_array("frequency_hz", frequency_hz, n)
        if np.any(freq < 0):
            raise InputDataError("frequency_hz must be >= 0")
        volt = _as_unit_array("voltage_v", voltage_v, n)
        amp = _as_unit_array("amplitude_v", amplitude_v, n)
        self._override = self._cmd[layout.CMD_OV_V:layout.CMD_OV_OMEGA + 1]
        self._override[:] = volt, amp, 2.0 * math.pi * freq

    def set_test_signal(self, amplitude_mm: float | np.ndarray,
                        frequency_hz: float | np.ndarray) -> None:
        """Firmware sine test: superpose ``a sin(2 pi f t)`` on the height targets.

        Unlike friction, the PID gains stay nominal; used for closed-loop frequency sweeps.
        Zero amplitude switches it off.

        Raises:
            InputDataError: NaN/Inf, wrong shape or negative values.
        """
        n = self.n_units
        amp = _as_unit_array("amplitude_mm", amplitude_mm, n)
        freq = _as_unit_array("frequency_hz", frequency_hz, n)
        if np.any(amp < 0) or np.any(freq < 0):
            raise InputDataError("test-signal amplitude and frequency must be >= 0")
        self._test[:] = amp, 2.0 * math.pi * freq
        self._test_units = np.flatnonzero(amp > 0.0)

    # ------------------------------------------------------------------ state
    @property
    def time_s(self) -> float:
        """Simulated time (s), a whole number of firmware ticks."""
        return self._step * self._dt

    @property
    def position_mm(self) -> np.ndarray:
        """Pin heights as the firmware measures them (Hall sensor + cubic calibration)."""
        return self._m_prev.copy()

    @property
    def true_position_mm(self) -> np.ndarray:
        """Actual pin heights (mm)."""
        return self._y.copy()

    @property
    def saturated(self) -> np.ndarray:
        """True where the feedforward stiffness stage (Eq. 2) drove the last tick."""
        return self._sat.copy()

    @property
    def drive_voltage_v(self) -> np.ndarray:
        """Piezo voltages (V)."""
        return self._u.copy()

    @property
    def commands(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The applied (clamped) ``(height_mm, stiffness_k, friction)``."""
        return self._height.copy(), self._k.copy(), self._f.copy()

    # ------------------------------------------------------------------ running
    def advance(self, duration_s: float) -> None:
        """Run firmware + plant for ``duration_s`` (rounded to whole ticks, without drift).

        Raises:
            InputDataError: negative or non-finite duration.
        """
        self._run(self._ticks_for(duration_s), record=False)

    def run(self, duration_s: float) -> PlantTrace:
        """Like :meth:`advance`, returning the per-tick trace."""
        n_ticks = self._ticks_for(duration_s)
        return self._trace(self._run(n_ticks, record=True), n_ticks)

    def _ticks_for(self, duration_s: float) -> int:
        if not (math.isfinite(duration_s) and duration_s >= 0.0):
            raise InputDataError(f"duration_s must be finite and >= 0, got {duration_s}")
        self._t_req_s += duration_s
        return max(round(self._t_req_s * self.params.control_rate_hz) - self._step, 0)

    def _reference(self, k0: int, n_ticks: int) -> np.ndarray:
        ref = np.broadcast_to(self._height, (n_ticks, self.n_units)).copy()
        if self._vib.size or self._test_units.size:
            t = (k0 + np.arange(n_ticks))[:, None] * self._dt
            if self._vib.size:  # friction on: synthesise the vibration only where f > 0
                v = self._vib
                ref[:, v] += self._amp[v] * np.sin(self._omega[v] * t)
                self.vibration_ticks += n_ticks
            if self._test_units.size:
                v = self._test_units
                ref[:, v] += self._test[0, v] * np.sin(self._test[1, v] * t)
            np.clip(ref, 0.0, self.params.stroke_mm, out=ref)
        return ref

    def _run(self, n_ticks: int, record: bool) -> dict[str, np.ndarray]:
        """Run ``n_ticks``; return the per-tick record (no rows when not recording)."""
        if n_ticks == 0:
            return self._empty_record
        rec = self._run_ticks(n_ticks, self._noise_v(n_ticks), record)
        return self._empty_record if rec is None else rec

    def _noise_v(self, n_ticks: int) -> np.ndarray:
        """The next ``n_ticks`` rows of Hall noise (V), drawn from the seeded stream in blocks.

        Drawing ``(a, n)`` then ``(b, n)`` normals gives the same numbers as one ``(a + b, n)``
        draw, so the block size does not change the trajectory.
        """
        buf, pos = self._noise_buf, self._noise_pos
        if pos + n_ticks > buf.shape[0]:
            fresh = self._rng.standard_normal((max(n_ticks, _NOISE_BLOCK_TICKS), self.n_units))
            buf = np.concatenate([buf[pos:], fresh * self.params.hall_noise_v_rms])
            self._noise_buf, pos = buf, 0
        self._noise_pos = pos + n_ticks
        return buf[pos:pos + n_ticks]

    def _compiled_steps(self, n_ticks: int, noise_v: np.ndarray,
                        record: bool) -> dict[str, np.ndarray] | None:
        """The numba engine: all ticks of all units in one compiled call (:mod:`.kernel`)."""
        rec = np.empty((4, n_ticks, self.n_units)) if record else self._no_rec
        vibrated = self._kernel(self._consts, self._cmd, self._z, self._sat, noise_v,
                                self._step, self._override is not None, record, rec)
        if vibrated:
            self.vibration_ticks += n_ticks
        self._step += n_ticks
        self.slow_ticks += n_ticks
        return dict(zip("myur", rec, strict=True)) if record else None

    def _numpy_steps(self, n_ticks: int, noise_v: np.ndarray,
                     record: bool) -> dict[str, np.ndarray] | None:
        """The numpy engine: block fast path + per-step path, one Python iteration per tick."""
        n = self.n_units
        if not self._derived:
            self._derive_commands()
        rec = {name: np.empty((n_ticks, n)) for name in "myur"} if record else None
        ref = self._reference(self._step, n_ticks)
        k = 0
        while k < n_ticks:
            remaining = n_ticks - k
            done = 0
            if (self.fast_path and self._override is None and remaining >= _MIN_BLOCK_STEPS
                    and self._backoff == 0 and not self._sat.any()):
                # adaptive block: grows while blocks pass, shrinks to where the last one failed
                size = min(remaining, self._block_len)
                done = self._fast_block(ref[k:k + size], noise_v[k:k + size], rec, k)
                self._block_len = (min(2 * size, _MAX_BLOCK_STEPS) if done == size
                                   else max(4 * _MIN_BLOCK_STEPS, done))
            if done == 0:
                if self._backoff == 0 and self.fast_path:
                    # a block failed at its first tick: back off exponentially (saturated
                    # loads, vibration near the slew limit) instead of retrying every tick
                    self._backoff_len = min(2 * self._backoff_len, _MAX_BACKOFF_STEPS)
                    self._backoff = self._backoff_len
                chunk = min(remaining, max(self._backoff, _REPLAY_STEPS)) if self.fast_path \
                    else remaining
                self._slow_steps(ref[k:k + chunk], noise_v[k:k + chunk], rec, k)
                self._backoff = max(self._backoff - chunk, 0)
                done = chunk
            else:
                self._backoff_len = _REPLAY_STEPS
            k += done
        return rec

    def _trace(self, rec: dict[str, np.ndarray], n_ticks: int) -> PlantTrace:
        t = (self._step - n_ticks + np.arange(n_ticks)) * self._dt
        return PlantTrace(t, rec["m"], rec["y"], rec["u"], rec["r"])

    # ------------------------------------------------------------------ per-step path
    def _slow_steps(self, ref: np.ndarray, noise_v: np.ndarray,
                    rec: dict[str, np.ndarray] | None, offset: int) -> None:
        p = self.params
        dt = self._dt
        kp = p.kp_v_per_mm * self._gain
        ki_dt = p.ki_v_per_mm_s * self._gain * dt
        kd_dt = p.kd_v_s_per_mm * self._gain / dt
        ub, ulim, ylim = p.u_base_v, self._u_limit, self._y_lim
        a = 1.0 - self._k
        expo = p.penalty_exponent
        u, y, integ, m_prev, force = self._u, self._y, self._i, self._m_prev, self._force
        u_cmd, sat = self._u_cmd, self._sat
        override = self._override
        for j in range(ref.shape[0]):
            m = self.sensor.measure_mm(y, noise_v[j])
            r = ref[j]
            if rec is not None:
                rec["m"][offset + j], rec["y"][offset + j] = m, y
                rec["u"][offset + j], rec["r"][offset + j] = u, r
            if override is None:
                e = r - m
                u_raw = ub + kp * e + integ + kd_dt * (m_prev - m)
                high = u_raw > ulim
                low = u_raw < ub
                sat = high & (e > 0.0)
                hold = sat | (low & (e < 0.0))
                integ = np.where(hold, integ, integ + ki_dt * e)
                u_cmd = np.clip(u_raw, ub, ulim)
                if sat.any():
                    base = np.maximum(1.0 - a * np.maximum(e, 0.0) / ylim, 0.0)
                    u_cmd = np.where(sat, (ulim - ub) * base ** expo + ub, u_cmd)
            else:
                t = (self._step + j) * dt
                u_cmd = np.clip(override[0] + override[1] * np.sin(override[2] * t),
                                ub, p.u_max_v)
                sat = np.zeros(self.n_units, dtype=bool)
            u, y = self._integ.step(u, y, u_cmd, force)
            m_prev = m
        self._u[:], self._y[:], self._i[:], self._m_prev[:] = u, y, integ, m_prev
        self._u_cmd[:], self._sat[:] = u_cmd, sat
        self._step += ref.shape[0]
        self.slow_ticks += ref.shape[0]

    # ------------------------------------------------------------------ fast path
    def _linear_map(self, gain: float):
        p = self.params
        dt = self._dt

        def step(z: np.ndarray, w: np.ndarray) -> np.ndarray:
            u, y, integ, m_prev = z
            r, force, delta, nu = w
            m = y + delta + nu
            e = r - m
            u_raw = (p.u_base_v + p.kp_v_per_mm * gain * e + integ
                     + p.kd_v_s_per_mm * gain / dt * (m_prev - m))
            u_new, y_new = self._integ.step(u, y, u_raw, force, slew=False)
            return np.stack([u_new, y_new, integ + p.ki_v_per_mm_s * gain * dt * e, m])

        return step

    def _modes_for(self, gain: float) -> LinearModes | None:
        if gain in self._modes:
            self._modes.move_to_end(gain)
            return self._modes[gain]
        modes = modal_decomposition(self._linear_map(gain))
        self._modes[gain] = modes
        if len(self._modes) > _MODE_CACHE:
            self._modes.popitem(last=False)
        return modes

    def _fast_block(self, ref: np.ndarray, noise_v: np.ndarray,
                    rec: dict[str, np.ndarray] | None, offset: int) -> int:
        """Integrate as many ticks as possible exactly; return how many were accepted."""
        gains, group_of = np.unique(self._gain, return_inverse=True)
        if gains.size > _MAX_FAST_GROUPS:
            return 0
        p = self.params
        n_ticks, n = ref.shape
        delta = self.sensor.calibration_residual_mm(self._y)
        nu = noise_v * self.sensor.noise_gain_mm_per_v(self._y)
        z0 = np.stack([self._u, self._y, self._i, self._m_prev])
        z_next = np.empty((n_ticks, 4, n))
        for gi, gain in enumerate(gains):
            modes = self._modes_for(float(gain))
            if modes is None:
                return 0
            idx = np.flatnonzero(group_of == gi)
            z_next[:, :, idx] = propagate(modes, z0[:, idx], ref[:, idx], self._force[idx],
                                          delta[idx], nu[:, idx])
        def seq(i: int) -> np.ndarray:  # state i at the start of each tick
            out = np.empty((n_ticks, n))
            out[0] = z0[i]
            out[1:] = z_next[:-1, i]
            return out

        u, y, integ, m_prev = seq(0), seq(1), seq(2), seq(3)
        m = y + delta + nu
        e = ref - m
        gain_u = self._gain
        u_raw = (p.u_base_v + p.kp_v_per_mm * gain_u * e + integ
                 + p.kd_v_s_per_mm * gain_u / self._dt * (m_prev - m))
        slope = (u_raw - u) / p.driver_time_constant_s
        y_new = z_next[:, 1]
        ok = ((u_raw >= p.u_base_v) & (u_raw <= self._u_limit)
              & (slope <= p.slew_up_v_per_s) & (slope >= -p.slew_down_v_per_s)
              & (y_new >= p.stop_low_mm) & (y_new <= p.stop_high_mm)
              & (np.abs(y_new - self._y) <= _LINEARISATION_SPAN_MM)).all(axis=1)
        bad = np.flatnonzero(~ok)
        accepted = int(bad[0]) if bad.size else n_ticks
        if accepted == 0:
            return 0
        last = z_next[accepted - 1]
        self._u[:], self._y[:], self._i[:], self._m_prev[:] = last
        self._u_cmd[:] = u_raw[accepted - 1]
        self._sat[:] = False
        if rec is not None:
            sl = slice(offset, offset + accepted)
            rec["m"][sl], rec["y"][sl] = m[:accepted], y[:accepted]
            rec["u"][sl], rec["r"][sl] = u[:accepted], ref[:accepted]
        self._step += accepted
        self.fast_ticks += accepted
        return accepted
