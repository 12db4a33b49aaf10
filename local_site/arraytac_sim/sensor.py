"""Hall A1324 position sensor of one ArrayTac unit and its cubic calibration.

Physics: an axially magnetised NdFeB cylinder (radius ``R``, length ``L``, remanence ``Br``) on
the final lever stage faces the A1324. The on-axis field at gap ``d`` is

    B(d) = Br/2 * [ (d + L) / sqrt((d + L)^2 + R^2) - d / sqrt(d^2 + R^2) ]

and the gap shrinks as the pin rises: ``d = d0 - travel_ratio * y``. The sensor outputs
``V = V_q + S * B`` (A1324: V_q = 2.5 V, S = 5 mV/G) plus white noise.

Calibration (paper, Fig. 2B-C): the firmware maps voltage to displacement with a cubic
polynomial ``y = c(V)`` fitted by least squares to a sweep over the stroke. The fit is not exact
(R^2 ~ 0.99996 here; the paper reports R^2 > 0.997 on hardware), so the pin the controller
holds at ``c(V) = target`` sits a few tens of micrometres off: :meth:`calibration_residual_mm`.
"""

from __future__ import annotations

import numpy as np

from local_site.arraytac_sim.params import PlantParams
from shared.errors import CalibrationError

__all__ = ["HallSensor"]

_CALIBRATION_POINTS = 201


class HallSensor:
    """Vectorised Hall sensor + cubic calibration (shared by all units).

    Args:
        params: plant constants (magnet geometry, sensor gain, noise).

    Raises:
        CalibrationError: if the field is not monotonic over the stroke (no usable fit).
    """

    def __init__(self, params: PlantParams) -> None:
        self._p = params
        y = np.linspace(params.stop_low_mm, params.stop_high_mm, _CALIBRATION_POINTS)
        v = self.voltage_v(y)
        if np.any(np.diff(v) <= 0):
            raise CalibrationError("Hall output is not monotonic over the stroke")
        self._coef = np.polyfit(v, y, 3)  # highest power first
        fit = np.polyval(self._coef, v)
        ss_res = float(np.sum((fit - y) ** 2))
        ss_tot = float(np.sum((y - y.mean()) ** 2))
        self.r_squared: float = 1.0 - ss_res / ss_tot
        self._dcoef = np.polyder(self._coef)

    @property
    def calibration_coefficients(self) -> np.ndarray:
        """Cubic ``y = c3 V^3 + c2 V^2 + c1 V + c0`` coefficients, highest power first."""
        return self._coef.copy()

    def voltage_v(self, position_mm: np.ndarray) -> np.ndarray:
        """Noise-free sensor output (V) for true pin heights (mm)."""
        p = self._p
        d = p.magnet_gap_at_zero_mm - p.magnet_travel_ratio * np.asarray(position_mm, float)
        r2 = p.magnet_radius_mm ** 2
        dl = d + p.magnet_length_mm
        b_t = 0.5 * p.magnet_br_t * (dl / np.sqrt(dl * dl + r2) - d / np.sqrt(d * d + r2))
        return p.hall_quiescent_v + p.hall_sensitivity_v_per_mt * 1e3 * b_t

    def calibrate_mm(self, voltage_v: np.ndarray) -> np.ndarray:
        """Firmware calibration: sensor voltage -> displacement (mm), the cubic fit."""
        c3, c2, c1, c0 = self._coef
        v = voltage_v
        return ((c3 * v + c2) * v + c1) * v + c0

    def measure_mm(self, position_mm: np.ndarray, noise_v: np.ndarray | float = 0.0) -> np.ndarray:
        """What the controller sees: ``c(V(y) + noise)`` (mm)."""
        return self.calibrate_mm(self.voltage_v(position_mm) + noise_v)

    def calibration_residual_mm(self, position_mm: np.ndarray) -> np.ndarray:
        """Noise-free measured minus true position (mm): the cubic fit's error."""
        y = np.asarray(position_mm, float)
        return self.measure_mm(y) - y

    def noise_gain_mm_per_v(self, position_mm: np.ndarray) -> np.ndarray:
        """Slope ``dc/dV`` at the sensor voltage of ``position_mm``: noise volts -> mm."""
        return np.polyval(self._dcoef, self.voltage_v(position_mm))
