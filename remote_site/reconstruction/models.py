"""Colour-to-gradient models: features of a pixel -> surface slopes (dh/dx, dh/dy).

Two models, both plain numpy, both serialisable to flat arrays for the calibration file:

* :class:`LutGradientModel` - the classic GelSight lookup table: the colour change is
  quantised into ``bins**3`` cells and each cell holds the mean training slope; cells never
  seen in training take the value of the nearest seen cell. Position-blind. The baseline.
* :class:`PolyGradientModel` - least-squares polynomial of total degree ``degree`` in the
  three colour changes and the normalised pixel position (x, y). The position terms absorb
  the per-pixel illumination differences a LUT cannot represent. Features are scaled to
  unit range first so the normal equations stay well conditioned.

Inputs: ``change`` (N, 3) percent relative colour change, ``x``/``y`` (N,) positions in
[-0.5, 0.5]. Output: (N, 2) float32 slopes, dimensionless (mm per mm), clipped to
``MAX_SLOPE`` so that no feature outside the training range can produce a runaway value.
"""

from __future__ import annotations

import itertools
from abc import ABC, abstractmethod

import numpy as np

from remote_site.reconstruction.grid_predict import (
    MAX_BAKED_BYTES,
    BakedPolyPredictor,
    GridPredictor,
    PlainGridPredictor,
)
from shared.errors import CalibrationError

__all__ = ["MAX_SLOPE", "GradientModel", "LutGradientModel", "PolyGradientModel",
           "model_from_arrays"]

#: slopes are clipped to +-MAX_SLOPE (about 78 degrees): steeper is not observable in a gel
MAX_SLOPE = 5.0


class GradientModel(ABC):
    """A calibrated map from pixel features to surface slopes."""

    kind: str = ""

    @abstractmethod
    def predict(self, change: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Return (N, 2) slopes (dh/dx, dh/dy) for N pixels."""

    def grid_predictor(self, x: np.ndarray, y: np.ndarray) -> GridPredictor:
        """A predictor for a fixed grid with pixel positions ``x``, ``y`` ((rows, cols)).

        The default gathers the active pixels and calls :meth:`predict`; models with
        position terms override it to precompute what depends on the position only.
        """
        return PlainGridPredictor(self, x, y)

    @abstractmethod
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Serialise to named arrays (stored in the calibration .npz with a ``model_`` prefix)."""

    @classmethod
    @abstractmethod
    def fit(cls, change: np.ndarray, x: np.ndarray, y: np.ndarray,
            slopes: np.ndarray, **options: int) -> GradientModel:
        """Fit to N training pixels with known slopes (N, 2)."""


# --------------------------------------------------------------------------- polynomial


def _exponents(n_vars: int, degree: int) -> np.ndarray:
    rows = [np.zeros(n_vars, np.int64)]
    for d in range(1, degree + 1):
        for combo in itertools.combinations_with_replacement(range(n_vars), d):
            e = np.zeros(n_vars, np.int64)
            for j in combo:
                e[j] += 1
            rows.append(e)
    return np.array(rows)


class PolyGradientModel(GradientModel):
    """Polynomial regression of slopes on (colour change, position).

    Args:
        coef: (n_terms, 2) coefficients.
        scale: (n_vars,) divisor applied to each variable before the polynomial.
        degree: total degree.
        use_position: whether x, y are variables (5 variables) or not (3).
    """

    kind = "poly"

    def __init__(self, coef: np.ndarray, scale: np.ndarray, degree: int,
                 use_position: bool) -> None:
        self.degree = int(degree)
        self.use_position = bool(use_position)
        self.exponents = _exponents(5 if use_position else 3, self.degree)
        if coef.shape != (len(self.exponents), 2) or scale.shape != (self.exponents.shape[1],):
            raise CalibrationError(f"polynomial model arrays do not match degree {degree}: "
                                   f"coef {coef.shape}, scale {scale.shape}")
        if not (np.isfinite(coef).all() and np.isfinite(scale).all() and (scale > 0).all()):
            raise CalibrationError("polynomial model contains non-finite or zero-scale values")
        self.coef = coef.astype(np.float32)
        self._coef_t = np.ascontiguousarray(self.coef.T)
        self.scale = scale.astype(np.float32)

    @staticmethod
    def _variables(change: np.ndarray, x: np.ndarray, y: np.ndarray,
                   use_position: bool) -> np.ndarray:
        cols = [change[:, 0], change[:, 1], change[:, 2]]
        if use_position:
            cols += [np.asarray(x, np.float32).ravel(), np.asarray(y, np.float32).ravel()]
        return np.stack(cols, axis=1).astype(np.float32, copy=False)

    @staticmethod
    def _design_t(v: np.ndarray, exponents: np.ndarray) -> np.ndarray:
        """Transposed design matrix (n_terms, N): rows are contiguous monomials (fast)."""
        n_vars = v.shape[1]
        max_deg = int(exponents.max())
        columns = np.ascontiguousarray(v.T)
        powers = [[np.ones(len(v), v.dtype)] for _ in range(n_vars)]
        for j in range(n_vars):
            for _ in range(max_deg):
                powers[j].append(powers[j][-1] * columns[j])
        out = np.empty((len(exponents), len(v)), v.dtype)
        for t, e in enumerate(exponents):
            np.copyto(out[t], powers[0][e[0]])
            for j in range(1, n_vars):
                if e[j]:
                    out[t] *= powers[j][e[j]]
        return out

    def predict(self, change: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Return (N, 2) clipped slopes."""
        v = self._variables(change, x, y, self.use_position) / self.scale
        out = (self._coef_t @ self._design_t(v, self.exponents)).T
        return np.clip(out, -MAX_SLOPE, MAX_SLOPE)

    def grid_predictor(self, x: np.ndarray, y: np.ndarray) -> GridPredictor:
        """Bake the position part per pixel (exact regrouping; see ``grid_predict``).

        Falls back to the plain predictor without position terms or when the per-pixel
        table would exceed :data:`~remote_site.reconstruction.grid_predict.MAX_BAKED_BYTES`.
        """
        size = BakedPolyPredictor.table_bytes(int(np.size(x)), self.exponents)
        if not self.use_position or size > MAX_BAKED_BYTES:
            return PlainGridPredictor(self, x, y)
        return BakedPolyPredictor(self.coef, self.scale, self.exponents, x, y, MAX_SLOPE)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Serialise coefficients and settings."""
        return {"coef": self.coef, "scale": self.scale,
                "degree": np.array(self.degree), "use_position": np.array(self.use_position)}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> PolyGradientModel:
        """Inverse of :meth:`to_arrays`."""
        return cls(arrays["coef"], arrays["scale"], int(arrays["degree"]),
                   bool(arrays["use_position"]))

    @classmethod
    def fit(cls, change: np.ndarray, x: np.ndarray, y: np.ndarray, slopes: np.ndarray,
            **options: int) -> PolyGradientModel:
        """Least-squares fit (small ridge term for conditioning).

        Options: ``degree`` (default 5), ``use_position`` (default 1).

        Raises:
            CalibrationError: fewer training pixels than terms, or a singular fit.
        """
        degree = int(options.get("degree", 5))
        use_position = bool(options.get("use_position", 1))
        v = cls._variables(change, x, y, use_position).astype(np.float64)
        scale = np.maximum(np.percentile(np.abs(v), 99, axis=0), 1e-6)
        exponents = _exponents(v.shape[1], degree)
        if len(v) < 4 * len(exponents):
            raise CalibrationError(f"only {len(v)} training pixels for {len(exponents)} "
                                   "polynomial terms: label more presses")
        design = cls._design_t(v / scale, exponents).T
        gram = design.T @ design
        gram[np.diag_indices_from(gram)] += 1e-6 * np.trace(gram) / len(gram)
        try:
            coef = np.linalg.solve(gram, design.T @ slopes.astype(np.float64))
        except np.linalg.LinAlgError as err:
            raise CalibrationError("polynomial calibration fit is singular") from err
        return cls(coef, scale, degree, use_position)


# --------------------------------------------------------------------------- lookup table


class LutGradientModel(GradientModel):
    """Quantised colour change -> mean slope (the classic GelSight LUT; position-blind).

    Args:
        table: (bins, bins, bins, 2) slopes.
        lo: lower edge of the colour-change range (percent), per channel.
        hi: upper edge, per channel.
    """

    kind = "lut"

    def __init__(self, table: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
        if table.ndim != 4 or table.shape[-1] != 2 or len(set(table.shape[:3])) != 1:
            raise CalibrationError(f"LUT must be (b, b, b, 2), got {table.shape}")
        if not (np.isfinite(table).all() and (np.asarray(hi) > np.asarray(lo)).all()):
            raise CalibrationError("LUT contains non-finite values or an empty range")
        self.table = table.astype(np.float32)
        self.bins = table.shape[0]
        self.lo = np.asarray(lo, np.float32)
        self.hi = np.asarray(hi, np.float32)
        self._step = (self.hi - self.lo) / self.bins

    def _index(self, change: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        idx = ((change - self.lo) / self._step).astype(np.int32)
        np.clip(idx, 0, self.bins - 1, out=idx)
        return idx[:, 0], idx[:, 1], idx[:, 2]

    def predict(self, change: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Return (N, 2) slopes looked up from the nearest cell."""
        return self.table[self._index(change)]

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Serialise table and range."""
        return {"table": self.table, "lo": self.lo, "hi": self.hi}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> LutGradientModel:
        """Inverse of :meth:`to_arrays`."""
        return cls(arrays["table"], arrays["lo"], arrays["hi"])

    @classmethod
    def fit(cls, change: np.ndarray, x: np.ndarray, y: np.ndarray, slopes: np.ndarray,
            **options: int) -> LutGradientModel:
        """Average training slopes per cell; fill empty cells from the nearest filled one.

        Options: ``bins`` per channel (default 32).

        Raises:
            CalibrationError: no training pixels.
        """
        from scipy import ndimage

        bins = int(options.get("bins", 32))
        if len(change) == 0:
            raise CalibrationError("no training pixels for the lookup table")
        lo = np.percentile(change, 0.5, axis=0).astype(np.float32)
        hi = np.percentile(change, 99.5, axis=0).astype(np.float32)
        hi = np.maximum(hi, lo + 1e-3)
        model = cls(np.zeros((bins, bins, bins, 2), np.float32), lo, hi)
        ir, ig, ib = model._index(change.astype(np.float32))
        flat = (ir * bins + ig) * bins + ib
        count = np.bincount(flat, minlength=bins**3).astype(np.float64)
        table = np.zeros((bins**3, 2))
        for k in range(2):
            table[:, k] = np.bincount(flat, weights=slopes[:, k], minlength=bins**3)
        seen = count > 0
        table[seen] /= count[seen, None]
        cube = table.reshape(bins, bins, bins, 2)
        seen_cube = seen.reshape(bins, bins, bins)
        _, nearest = ndimage.distance_transform_edt(~seen_cube, return_indices=True)
        filled = cube[nearest[0], nearest[1], nearest[2]]
        return cls(filled.astype(np.float32), lo, hi)


_MODELS: dict[str, type[GradientModel]] = {
    PolyGradientModel.kind: PolyGradientModel,
    LutGradientModel.kind: LutGradientModel,
}


def model_from_arrays(kind: str, arrays: dict[str, np.ndarray]) -> GradientModel:
    """Rebuild a model from its serialised arrays.

    Raises:
        CalibrationError: unknown kind or missing arrays.
    """
    cls = _MODELS.get(kind)
    if cls is None:
        raise CalibrationError(f"unknown gradient model kind {kind!r}; known: {sorted(_MODELS)}")
    try:
        return cls.from_arrays(arrays)  # type: ignore[attr-defined]
    except KeyError as err:
        raise CalibrationError(f"calibration model {kind!r} is missing array {err}") from err
