"""All physical and controller constants of the ArrayTac simulator, with units and sources.

Sources: "paper" is ``../shared/reference/arraytac-paper.md`` (ArrayTac, main text and
supplement); "design" means derived from the paper's measured figures by
:mod:`local_site.arraytac_sim.design` (the derivation is written out there); "assumed" means a
plausible hardware value the paper does not give. The "design" defaults are the output of
``design.derive_params()`` (rounded to 5 digits); ``tests/local_site/test_arraytac_sim_design.py``
re-derives them.

Coordinates: pin heights ``y`` are in mm at the end-effector (0 = retracted, 5 = full stroke);
voltages in V across the piezo stack; forces in N at the pin tip. The no-load lever gain
``g = stroke_mm / (u_max_v - u_base_v)`` (mm/V) is ``A * beta`` of Eq. (S9).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from shared.errors import ConfigError

__all__ = ["PlantParams"]


@dataclass(frozen=True)
class PlantParams:
    """Constants of one ArrayTac unit (all 16 units share them).

    Attributes:
        stroke_mm: end-effector stroke, paper: 40 um piezo x 125 lever = 5 mm.
        piezo_stroke_um: piezo stack free stroke, paper (DCS3-050536): 40 um.
        lever_gain: three-stage micro-lever amplification ``A``, paper: 125.
        u_base_v: ``U_base``, voltage that brings the unit to its zero position, assumed.
        u_max_v: ``U_max``, full-stroke voltage, paper: the 150 V boost rail.
        passive_stiffness_n_per_mm: ``K_piezo / A**2`` (Eq. S8), the passive stiffness at the
            pin, assumed 1 N/mm (K_piezo = 15.6 N/um, blocking force 625 N: a 5x5x36 mm stack);
            it puts the yield force of a 3 mm pin at 1.5-2 N, the force range of Fig. 8F.
        mech_time_constant_s: ``tau_m = b / K_s``, the dominant lag of lever + soft (silicone /
            fingertip) load, design: sets the open-loop bandwidth to 15.29 Hz.
        driver_time_constant_s: ``tau_d``, the small-signal lag of the half-bridge driver
            charging the piezo capacitance, design: with the PI gain sets the closed-loop
            bandwidth to 123.39 Hz at damping ``closed_loop_damping``.
        closed_loop_damping: design damping ratio of the small-signal closed loop (> 1:
            overdamped, as the paper's Fig. 2D).
        slew_up_v_per_s: charge slew limit of the driver (op-amp + MOSFET current limit), design:
            sets the 10-90 % rise time of the characterisation step to 0.013 s.
        slew_down_v_per_s: discharge slew limit (the constant-current sink of Fig. S1: a fixed
            current into the piezo capacitance is a fixed dU/dt), design: fall time 0.016 s.
        control_rate_hz: firmware PID rate, paper: 10 kHz.
        kp_v_per_mm: PID proportional gain, design (IMC: the PI zero cancels ``tau_m``).
        ki_v_per_mm_s: PID integral gain, design (``kp / tau_m``).
        kd_v_s_per_mm: PID derivative gain on the measurement; the pole-cancelling design needs
            none (0), the path stays in the firmware for hardware tuning.
        penalty_exponent: ``n`` of Eq. (2), paper: 2.
        k_min, k_max: normalised stiffness range, paper: [0.5, 1].
        friction_freq_span_hz: vibration frequency at ``f = 1``, paper: 200 Hz in the study.
        friction_freq_max_hz: hardware limit for the span, paper: 512 Hz.
        friction_amp_mm: vibration amplitude at ``f = 1`` (linear in f), assumed 0.2 mm.
        friction_gain_boost: PID gain scale is ``1 + boost * f`` (linear in f), assumed 1: at
            f = 1 the loop is fast enough to pass the 200 Hz vibration.
        hall_quiescent_v: A1324 zero-field output, datasheet: 2.5 V.
        hall_sensitivity_v_per_mt: A1324 sensitivity, datasheet: 5 mV/G = 0.05 V/mT.
        hall_noise_v_rms: output noise of the Hall channel after the ADC's oversampling,
            assumed 0.1 mV rms (0.5-1.5 um at the pin).
        magnet_br_t: remanence of the N35 NdFeB magnet, 1.2 T.
        magnet_radius_mm, magnet_length_mm: magnet cylinder, assumed 1 x 2 mm.
        magnet_gap_at_zero_mm: sensor-magnet gap with the pin at 0 mm, assumed.
        magnet_travel_ratio: magnet travel per mm of pin travel (lever position), assumed.
        stop_low_mm, stop_high_mm: mechanical end stops of the pin.
        noise_seed: seed of the sensor-noise generator (reproducible runs).
    """

    stroke_mm: float = 5.0
    piezo_stroke_um: float = 40.0
    lever_gain: float = 125.0
    u_base_v: float = 15.0
    u_max_v: float = 150.0
    passive_stiffness_n_per_mm: float = 1.0
    mech_time_constant_s: float = 0.0104015
    driver_time_constant_s: float = 2.7880e-4
    closed_loop_damping: float = 1.2
    slew_up_v_per_s: float = 33_234.0
    slew_down_v_per_s: float = 8_764.0
    control_rate_hz: float = 10_000.0
    kp_v_per_mm: float = 174.88
    ki_v_per_mm_s: float = 16_813.0
    kd_v_s_per_mm: float = 0.0
    penalty_exponent: float = 2.0
    k_min: float = 0.5
    k_max: float = 1.0
    friction_freq_span_hz: float = 200.0
    friction_freq_max_hz: float = 512.0
    friction_amp_mm: float = 0.2
    friction_gain_boost: float = 1.0
    hall_quiescent_v: float = 2.5
    hall_sensitivity_v_per_mt: float = 0.05
    hall_noise_v_rms: float = 1.0e-4
    magnet_br_t: float = 1.2
    magnet_radius_mm: float = 1.0
    magnet_length_mm: float = 2.0
    magnet_gap_at_zero_mm: float = 4.5
    magnet_travel_ratio: float = 0.3
    stop_low_mm: float = 0.0
    stop_high_mm: float = 5.25
    noise_seed: int = 0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise ConfigError(f"PlantParams.{f.name} must be a finite number, got {value!r}")
        positive = ("stroke_mm", "piezo_stroke_um", "lever_gain", "passive_stiffness_n_per_mm",
                    "mech_time_constant_s", "driver_time_constant_s", "slew_up_v_per_s",
                    "slew_down_v_per_s", "control_rate_hz", "kp_v_per_mm", "penalty_exponent",
                    "hall_sensitivity_v_per_mt", "magnet_br_t", "magnet_radius_mm",
                    "magnet_length_mm", "magnet_gap_at_zero_mm", "magnet_travel_ratio")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ConfigError(f"PlantParams.{name} must be > 0, got {getattr(self, name)}")
        if self.u_max_v <= self.u_base_v:
            raise ConfigError("PlantParams.u_max_v must exceed u_base_v")
        if not 0 < self.k_min < self.k_max <= 1:
            raise ConfigError("PlantParams needs 0 < k_min < k_max <= 1")
        if not 0 < self.friction_freq_span_hz <= self.friction_freq_max_hz:
            raise ConfigError("friction_freq_span_hz must be in (0, friction_freq_max_hz]")
        if self.magnet_gap_at_zero_mm - self.magnet_travel_ratio * self.stop_high_mm <= 0:
            raise ConfigError("magnet would hit the Hall sensor inside the stroke")
        if min(self.ki_v_per_mm_s, self.kd_v_s_per_mm, self.hall_noise_v_rms,
               self.friction_amp_mm, self.friction_gain_boost) < 0:
            raise ConfigError("gains, noise and friction coefficients must be >= 0")

    # ----------------------------------------------------------------- derived quantities
    @property
    def lever_gain_mm_per_v(self) -> float:
        """No-load pin travel per volt above ``U_base``: ``g = A * beta`` (mm/V)."""
        return self.stroke_mm / (self.u_max_v - self.u_base_v)

    @property
    def beta_um_per_v(self) -> float:
        """Piezo voltage-to-displacement coefficient ``beta`` of Eq. (S9) (um/V)."""
        return self.piezo_stroke_um / (self.u_max_v - self.u_base_v)

    @property
    def damping_n_s_per_mm(self) -> float:
        """Viscous damping ``b`` of lever + soft load (N s/mm), ``K_s * tau_m``."""
        return self.passive_stiffness_n_per_mm * self.mech_time_constant_s

    @property
    def control_period_s(self) -> float:
        """Firmware period (s)."""
        return 1.0 / self.control_rate_hz
