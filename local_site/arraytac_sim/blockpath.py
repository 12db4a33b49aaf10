"""Exact block integration of the linear closed loop (the simulator's fast path).

While no nonlinearity is active (PID output inside ``[U_base, U_limit]``, driver below its slew
limits, pin between the end stops) firmware + plant form one affine discrete-time system per
unit,

    z[k+1] = Phi z[k] + Gamma w[k],   z = [U, y, I, y_meas_prev],   w = [r, F, delta, nu, 1]

(``r`` reference incl. friction vibration, ``F`` finger force, ``delta`` calibration residual,
``nu`` sensor noise in mm). ``Phi`` and ``Gamma`` are obtained by *probing* the same per-step
code the slow path runs (so both paths are the same map), then diagonalised: each mode is a
scalar recursion ``q[k+1] = lambda q[k] + beta[k]`` that ``scipy.signal.lfilter`` runs in C for
a whole block at once. The block is then verified step by step (vectorised) against every
nonlinearity; the caller replays from the first violating step with the per-step path.

Only the Hall chain is linearised (``c(V(y) + n) ~ y + delta(y0) + c'(V(y0)) n`` around the
block's start height); the benchmark measures what that costs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

__all__ = ["LinearModes", "modal_decomposition", "propagate"]

N_STATE = 4
N_INPUT = 5


@dataclass(frozen=True)
class LinearModes:
    """Eigen-decomposition of one closed loop (one PID gain scale)."""

    eigenvalues: np.ndarray        # (4,) real when all modes are real, else complex
    vectors: np.ndarray            # (4, 4) columns are eigenvectors
    input_to_modes: np.ndarray     # (4, 5) V^-1 Gamma
    inverse_vectors: np.ndarray    # (4, 4) V^-1
    phi: np.ndarray                # (4, 4) real
    gamma: np.ndarray              # (4, 5) real


def modal_decomposition(step: Callable[[np.ndarray, np.ndarray], np.ndarray],
                        max_condition: float = 1e8) -> LinearModes | None:
    """Probe an affine per-step map and diagonalise it.

    Args:
        step: ``step(z, w) -> z_next`` for arrays ``z (4, P)``, ``w (4, P)`` (the constant
            input is implicit), vectorised over ``P`` probes.
        max_condition: refuse (return ``None``) when the eigenvector matrix is worse conditioned.

    Returns:
        The modes, or ``None`` when the map is (nearly) defective.
    """
    n_free = N_INPUT - 1
    probes = 1 + N_STATE + n_free
    z = np.zeros((N_STATE, probes))
    w = np.zeros((n_free, probes))
    z[:, 1:1 + N_STATE] = np.eye(N_STATE)
    w[:, 1 + N_STATE:] = np.eye(n_free)
    out = step(z, w)
    c = out[:, 0]
    phi = out[:, 1:1 + N_STATE] - c[:, None]
    gamma = np.concatenate([out[:, 1 + N_STATE:] - c[:, None], c[:, None]], axis=1)
    lam, vec = np.linalg.eig(phi)
    if not np.all(np.isfinite(lam)) or np.linalg.cond(vec) > max_condition:
        return None
    if np.all(np.abs(lam.imag) <= 1e-12 * np.maximum(np.abs(lam), 1.0)):
        lam, vec = lam.real, vec.real   # real modes (overdamped loop): real arithmetic
    vinv = np.linalg.inv(vec)
    return LinearModes(lam, vec, vinv @ gamma, vinv, phi, gamma)


def propagate(modes: LinearModes, z0: np.ndarray, r: np.ndarray, force_n: np.ndarray,
              delta_mm: np.ndarray, nu_mm: np.ndarray) -> np.ndarray:
    """Run the linear closed loop over a block.

    Args:
        modes: from :func:`modal_decomposition`.
        z0: initial states ``(4, U)``.
        r: references ``(N, U)`` (mm).
        force_n: finger forces ``(U,)``.
        delta_mm: calibration residuals ``(U,)``.
        nu_mm: sensor noise ``(N, U)`` (mm).

    Returns:
        States ``z[1..N]`` as ``(N, 4, U)``.
    """
    g = modes.input_to_modes
    q0 = modes.inverse_vectors @ z0
    q = np.empty((r.shape[0], N_STATE, r.shape[1]), dtype=g.dtype)
    for i in range(N_STATE):
        const = g[i, 1] * force_n + g[i, 2] * delta_mm + g[i, 4]
        beta = g[i, 0] * r + g[i, 3] * nu_mm + const
        lam = modes.eigenvalues[i]
        if lam == 0:
            q[:, i, :] = beta
        else:
            q[:, i, :], _ = lfilter([1.0], [1.0, -lam], beta, axis=0,
                                    zi=(lam * q0[i])[None, :])
    z = np.matmul(modes.vectors, q)
    return z.real if np.iscomplexobj(z) else z
