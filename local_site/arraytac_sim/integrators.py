"""Integrators of the ArrayTac plant over one firmware period.

Plant of one unit (pin-side, see :mod:`.params`), driven by the firmware's voltage ``u_cmd``
(held constant over a period: the MCU's DAC is a zero-order hold) and the finger force ``F``:

    dU/dt = clip((u_cmd - U) / tau_d, -S_down, +S_up)       driver + piezo capacitance
    dy/dt = (g (U - U_base) - y) / tau_m - F / b              lever + soft load, Eq. (S6)

with ``y`` clipped to the mechanical stops. Without slew limiting the plant is linear.

Integrators (``substeps`` sub-steps per firmware period):

- ``zoh``: exact discretisation (matrix exponential) of the linear plant and of the slewing
  plant (``U`` a ramp); the mode is chosen per unit at each sub-step. Exact in the linear regime
  for any step size; the only error is where a slew ends inside a sub-step.
- ``rk4``: classic Runge-Kutta on the nonlinear ODE.
- ``euler``: forward Euler on the nonlinear ODE (stable for ``h < 2 tau_d``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np
from scipy.linalg import expm

from local_site.arraytac_sim.params import PlantParams
from shared.errors import ConfigError

__all__ = ["INTEGRATORS", "PlantIntegrator", "make_integrator"]


class PlantIntegrator(ABC):
    """Base: advances ``(U, y)`` of all units by one firmware period.

    Args:
        params: plant constants.
        substeps: sub-steps per firmware period (>= 1).
    """

    name = "base"

    def __init__(self, params: PlantParams, substeps: int = 1) -> None:
        if int(substeps) < 1:
            raise ConfigError(f"substeps must be >= 1, got {substeps}")
        self.p = params
        self.substeps = int(substeps)
        self.h_s = params.control_period_s / self.substeps
        self._g = params.lever_gain_mm_per_v
        self._inv_b = 1.0 / params.damping_n_s_per_mm

    def _derivatives(self, u: np.ndarray, y: np.ndarray, u_cmd: np.ndarray, force_n: np.ndarray,
                     slew: bool) -> tuple[np.ndarray, np.ndarray]:
        p = self.p
        du = (u_cmd - u) / p.driver_time_constant_s
        if slew:
            du = np.clip(du, -p.slew_down_v_per_s, p.slew_up_v_per_s)
        dy = (self._g * (u - p.u_base_v) - y) / p.mech_time_constant_s - force_n * self._inv_b
        return du, dy

    def step(self, u: np.ndarray, y: np.ndarray, u_cmd: np.ndarray, force_n: np.ndarray,
             slew: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Advance one firmware period.

        Args:
            u: piezo voltages (V).
            y: pin heights (mm).
            u_cmd: firmware output (V), held over the period.
            force_n: finger force per unit (N).
            slew: apply the driver slew limits and the end stops (``False`` gives the linear
                map the block integrator uses).

        Returns:
            New ``(u, y)``.
        """
        for _ in range(self.substeps):
            u, y = self._substep(u, y, u_cmd, force_n, slew)
            if slew:
                y = np.clip(y, self.p.stop_low_mm, self.p.stop_high_mm)
        return u, y

    @abstractmethod
    def _substep(self, u: np.ndarray, y: np.ndarray, u_cmd: np.ndarray, force_n: np.ndarray,
                 slew: bool) -> tuple[np.ndarray, np.ndarray]:
        """Advance ``(U, y)`` by one sub-step; each integrator implements it."""


class EulerIntegrator(PlantIntegrator):
    """Forward Euler on the nonlinear ODE."""

    name = "euler"

    def _substep(self, u, y, u_cmd, force_n, slew):
        du, dy = self._derivatives(u, y, u_cmd, force_n, slew)
        return u + self.h_s * du, y + self.h_s * dy


class RK4Integrator(PlantIntegrator):
    """Classic fourth-order Runge-Kutta on the nonlinear ODE."""

    name = "rk4"

    def _substep(self, u, y, u_cmd, force_n, slew):
        h = self.h_s
        d = self._derivatives
        k1u, k1y = d(u, y, u_cmd, force_n, slew)
        k2u, k2y = d(u + 0.5 * h * k1u, y + 0.5 * h * k1y, u_cmd, force_n, slew)
        k3u, k3y = d(u + 0.5 * h * k2u, y + 0.5 * h * k2y, u_cmd, force_n, slew)
        k4u, k4y = d(u + h * k3u, y + h * k3y, u_cmd, force_n, slew)
        return (u + h / 6.0 * (k1u + 2 * k2u + 2 * k3u + k4u),
                y + h / 6.0 * (k1y + 2 * k2y + 2 * k3y + k4y))


def _zoh(a: np.ndarray, b: np.ndarray, h_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact ZOH discretisation ``x+ = Phi x + Gamma v`` via one matrix exponential."""
    n, m = b.shape
    aug = np.zeros((n + m, n + m))
    aug[:n, :n] = a
    aug[:n, n:] = b
    e = expm(aug * h_s)
    return e[:n, :n], e[:n, n:]


class ZOHIntegrator(PlantIntegrator):
    """Exact discretisation of the linear and the slewing plant (mode chosen per sub-step)."""

    name = "zoh"

    def __init__(self, params: PlantParams, substeps: int = 1) -> None:
        super().__init__(params, substeps)
        p = params
        g, tm, td = self._g, p.mech_time_constant_s, p.driver_time_constant_s
        # linear mode: inputs [u_cmd, F, 1]
        a = np.array([[-1.0 / td, 0.0], [g / tm, -1.0 / tm]])
        b = np.array([[1.0 / td, 0.0, 0.0], [0.0, -self._inv_b, -g * p.u_base_v / tm]])
        self._phi, self._gam = _zoh(a, b, self.h_s)
        # slewing mode: U is a ramp of slope s; inputs [F, 1, s]
        a_s = np.array([[0.0, 0.0], [g / tm, -1.0 / tm]])
        b_s = np.array([[0.0, 0.0, 1.0], [-self._inv_b, -g * p.u_base_v / tm, 0.0]])
        self._phi_s, self._gam_s = _zoh(a_s, b_s, self.h_s)

    @property
    def matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(Phi, Gamma)`` of the linear mode and ``(Phi_s, Gamma_s)`` of the slewing mode."""
        return self._phi, self._gam, self._phi_s, self._gam_s

    def _substep(self, u, y, u_cmd, force_n, slew):
        ph, ga = self._phi, self._gam
        u_lin = ph[0, 0] * u + ga[0, 0] * u_cmd
        y_lin = ph[1, 0] * u + ph[1, 1] * y + ga[1, 0] * u_cmd + ga[1, 1] * force_n + ga[1, 2]
        if not slew:
            return u_lin, y_lin
        p = self.p
        slope = (u_cmd - u) / p.driver_time_constant_s
        up = slope > p.slew_up_v_per_s
        down = slope < -p.slew_down_v_per_s
        if not (up.any() or down.any()):
            return u_lin, y_lin
        s = np.where(up, p.slew_up_v_per_s, np.where(down, -p.slew_down_v_per_s, 0.0))
        ps, gs = self._phi_s, self._gam_s
        u_ramp = u + s * self.h_s
        u_ramp = np.where(up, np.minimum(u_ramp, u_lin), np.maximum(u_ramp, u_lin))
        y_ramp = ps[1, 0] * u + ps[1, 1] * y + gs[1, 0] * force_n + gs[1, 1] + gs[1, 2] * s
        limited = up | down
        return np.where(limited, u_ramp, u_lin), np.where(limited, y_ramp, y_lin)


INTEGRATORS: dict[str, type[PlantIntegrator]] = {
    "zoh": ZOHIntegrator,
    "rk4": RK4Integrator,
    "euler": EulerIntegrator,
}


def make_integrator(name: str, params: PlantParams, substeps: int = 1) -> PlantIntegrator:
    """Build an integrator by name (``zoh``, ``rk4``, ``euler``).

    Raises:
        ConfigError: unknown name or bad ``substeps``.
    """
    try:
        cls = INTEGRATORS[name]
    except KeyError as err:
        raise ConfigError(
            f"unknown integrator {name!r}; choose from {sorted(INTEGRATORS)}") from err
    return cls(params, substeps)
