"""The paper's two-stage stiffness law, as pure vectorised functions.

Stage 1 (Eq. 1): the PID output is capped at

    U_limit = (k + 4) / 5 * (U_max - U_base) + U_base.

Stage 2 (Eq. 2): once the PID saturates, the firmware drives

    U_out = (U_limit - U_base) * (1 - (1 - k) * eps / x_piezo_limit)^n + U_base

where ``eps`` is the piezo-side compression and ``x_piezo_limit = beta (U_limit - U_base)``.
Both ``eps`` and ``x_piezo_limit`` scale by the lever gain ``A`` to the pin, so the ratio is the
same in pin millimetres: ``eps / x_piezo_limit = e_mm / y_limit_mm``.

Equilibrium with a finger force ``F`` (Eq. S6 at the pin, ``K_s = K_piezo / A^2``):

    F = K_s * (y_cmd(e) - target + e),   y_cmd(e) = y_lim * (1 - (1 - k) e / y_lim)^n
    K_eff = dF/de = K_s * (1 + dy_cmd/de)                                   (Eq. S8, S11)

For ``n = 2`` ``K_eff > 0`` for ``k > 0.5`` and ``dK_eff/de = 2 K_s (1-k)^2 / y_lim > 0``
(Eq. S20-S21).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "equilibrium_force_n",
    "equivalent_stiffness_n_per_mm",
    "feedforward_voltage_v",
    "u_limit_v",
    "yield_force_n",
]


def u_limit_v(k: np.ndarray | float, u_base_v: float, u_max_v: float) -> np.ndarray:
    """PID output cap ``U_limit`` of Eq. (1) (V)."""
    return (np.asarray(k, float) + 4.0) / 5.0 * (u_max_v - u_base_v) + u_base_v


def feedforward_voltage_v(
    compression_mm: np.ndarray | float,
    k: np.ndarray | float,
    u_limit: np.ndarray | float,
    u_base_v: float,
    y_limit_mm: np.ndarray | float,
    exponent: float = 2.0,
) -> np.ndarray:
    """Feedforward penalty output ``U_out`` of Eq. (2) (V).

    The base of the power is floored at 0 so the law never commands below ``U_base`` and an
    odd/non-integer exponent never produces NaN.

    Args:
        compression_mm: pin compression below target ``e = A * eps`` (mm), >= 0.
        k: normalised stiffness in [0.5, 1].
        u_limit: ``U_limit`` (V).
        u_base_v: ``U_base`` (V).
        y_limit_mm: no-load pin height at ``U_limit``: ``A * x_piezo_limit`` (mm), > 0.
        exponent: ``n`` (2 in the paper).
    """
    base = 1.0 - (1.0 - np.asarray(k, float)) * np.asarray(compression_mm, float) / y_limit_mm
    return (np.asarray(u_limit, float) - u_base_v) * np.maximum(base, 0.0) ** exponent + u_base_v


def yield_force_n(target_mm: np.ndarray | float, y_limit_mm: np.ndarray | float,
                  stiffness_n_per_mm: float) -> np.ndarray:
    """Finger force at which the PID saturates (end of region A): ``K_s (y_lim - target)``."""
    return stiffness_n_per_mm * np.maximum(np.asarray(y_limit_mm, float) - target_mm, 0.0)


def equilibrium_force_n(compression_mm: np.ndarray | float, k: np.ndarray | float,
                        target_mm: np.ndarray | float, y_limit_mm: np.ndarray | float,
                        stiffness_n_per_mm: float, exponent: float = 2.0) -> np.ndarray:
    """Static finger force holding the pin ``e`` mm below target in region B (N)."""
    e = np.asarray(compression_mm, float)
    base = np.maximum(1.0 - (1.0 - np.asarray(k, float)) * e / y_limit_mm, 0.0)
    y_cmd = y_limit_mm * base ** exponent
    return stiffness_n_per_mm * (y_cmd - (np.asarray(target_mm, float) - e))


def equivalent_stiffness_n_per_mm(compression_mm: np.ndarray | float, k: np.ndarray | float,
                                  y_limit_mm: np.ndarray | float, stiffness_n_per_mm: float,
                                  exponent: float = 2.0) -> np.ndarray:
    """Analytic ``K_eff = K_s (1 + dy_cmd/de)`` in region B (Eq. S8 with Eq. S16)."""
    e = np.asarray(compression_mm, float)
    a = 1.0 - np.asarray(k, float)
    base = np.maximum(1.0 - a * e / y_limit_mm, 0.0)
    return stiffness_n_per_mm * (1.0 - exponent * a * base ** (exponent - 1.0))
