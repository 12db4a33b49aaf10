"""The breast-tissue training phantom and its fast contact model.

Coordinates (phantom frame, mm): origin at the centre of the phantom's top surface, +x to
the right, +y away from the operator, +z up; the undeformed surface is ``z = 0``. A pose
``(x, y, z)`` is the centre of the sensor's gel pad; ``z < 0`` presses into the tissue.

Contact model (first order, linear in depth, vectorised):

1. Column modulus. Each surface point sees a column of silicone (modulus ``E_bg``,
   thickness ``h``) with tumors in it. Using the Boussinesq depth weighting of
   :mod:`~remote_site.phantom.mechanics`, the column's effective modulus is
   ``E_col = E_bg / (1 + sum_t f_t (E_bg / E_t - 1))`` with ``f_t`` the depth-weighted
   share of the column a tumor occupies (:func:`~remote_site.phantom.tumor.tumor_column_fraction`).
   Outside the phantom's footprint ``E_col = 0`` (no material).
2. Pad. The gel pad is a flat disc of radius ``R`` with a rounded edge (linear taper of
   width ``edge_mm``), pad weight ``e(x, y)`` in [0, 1]. Pressed as a rigid flat punch, the
   tissue's contact stiffness is ``K = 8/3 a E_pad c(a/h)`` (flat punch, bonded-layer
   correction) with ``a`` the pad's effective radius and ``E_pad`` the pad-weighted mean of
   ``E_col``. ``K`` over the phantom is precomputed once (FFT convolution of the column
   modulus with the pad) and interpolated, so the arm's 1 kHz force query is O(1).
3. Gel in series. The gel layer is a Winkler layer (``E_gel / t_gel`` per unit area);
   over the pad it is a spring ``k_gel``; the approach ``d = -z`` splits as
   ``F = d / (1/K + 1/k_gel)``.
4. Depth map. The contact pressure follows the column stiffness under the pad,
   ``p ~ e E_col`` (Winkler distribution, normalised so it sums to ``F``), and the gel is
   pushed in by ``p / (E_gel / t_gel)``: a stiff inclusion under the soft layer shows as a
   raised bump. The depth map is the height the object pushes INTO the gel (mm, >= 0) on
   the sensor's pixel grid, row index along +y and column index along +x, centred on the pose.
   Per frame the column modulus is sampled from a table built once per pixel pitch
   (:mod:`~remote_site.phantom.modulus_table`, bilinear at ``modulus_oversample`` samples per
   pixel); ``contact(..., exact=True)`` evaluates it exactly (the reference, ~25x slower).

First-order decoupling: the tissue sees the pad as rigid (uniform displacement) while the gel
deformation follows the pressure; the gel's local deformation does not feed back into the
tissue displacement. The surface is flat (no topography).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.signal import fftconvolve

from remote_site.phantom.mechanics import KPA_TO_N_PER_MM2, punch_stiffness_n_per_mm
from remote_site.phantom.modulus_table import ColumnModulusTable
from remote_site.phantom.tumor import Tumor, tumor_column_fraction
from shared.errors import ConfigError, InputDataError

__all__ = ["Contact", "Phantom", "PixelGrid", "SensorPad", "SiliconeLayer"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SiliconeLayer:
    """The soft silicone body of the phantom.

    Attributes:
        size_mm: (width along x, depth along y) of the footprint.
        thickness_mm: layer thickness h (bonded to a rigid base).
        modulus_kpa: small-strain Young's modulus of the background silicone (tens of kPa).
        nonlinearity: strain stiffening ``beta``: the tissue's contact stiffness at approach
            ``d`` is ``k0 (1 + beta d / h)`` (0 = linear). Soft silicones (Ecoflex, Dragon
            Skin) and breast tissue stiffen with strain; a neo-Hookean / Fung fit of
            indentation data of a finite layer gives beta of order 1-3 at these strains
            (Samani & Plewes 2004 report a 2-4x tangent-modulus rise at 20 % strain).
    """

    size_mm: tuple[float, float] = (100.0, 100.0)
    thickness_mm: float = 20.0
    modulus_kpa: float = 50.0
    nonlinearity: float = 0.0

    def __post_init__(self) -> None:
        vals = (*self.size_mm, self.thickness_mm, self.modulus_kpa)
        if not all(math.isfinite(v) and v > 0 for v in vals):
            raise ConfigError("silicone layer: size, thickness and modulus must be finite and > 0")
        if not (math.isfinite(self.nonlinearity) and self.nonlinearity >= 0):
            raise ConfigError("silicone layer: nonlinearity must be finite and >= 0")


@dataclass(frozen=True)
class SensorPad:
    """The visuotactile sensor's gel pad as a contact body.

    Attributes:
        radius_mm: radius of the flat part of the pad.
        edge_mm: width of the rounded edge (linear taper centred on ``radius_mm``).
        gel_modulus_kpa: Young's modulus of the gel.
        gel_thickness_mm: gel thickness.
    """

    radius_mm: float = 7.0
    edge_mm: float = 1.0
    gel_modulus_kpa: float = 200.0
    gel_thickness_mm: float = 3.0

    def __post_init__(self) -> None:
        vals = (self.radius_mm, self.edge_mm, self.gel_modulus_kpa, self.gel_thickness_mm)
        if not all(math.isfinite(v) and v > 0 for v in vals):
            raise ConfigError("sensor pad: all dimensions and moduli must be finite and > 0")
        if self.edge_mm >= 2.0 * self.radius_mm:
            raise ConfigError("sensor pad: edge_mm must be < 2 * radius_mm")

    @property
    def area_mm2(self) -> float:
        """Weighted contact area, integral of the pad weight (pi (R^2 + edge^2 / 12))."""
        return math.pi * (self.radius_mm ** 2 + self.edge_mm ** 2 / 12.0)

    @property
    def effective_radius_mm(self) -> float:
        """Radius of the disc with the pad's weighted area."""
        return math.sqrt(self.area_mm2 / math.pi)

    @property
    def gel_stiffness_per_area(self) -> float:
        """Winkler stiffness of the gel, N/mm per mm^2."""
        return self.gel_modulus_kpa * KPA_TO_N_PER_MM2 / self.gel_thickness_mm

    @property
    def gel_stiffness_n_per_mm(self) -> float:
        """The gel over the whole pad as one spring (series with the tissue)."""
        return self.gel_stiffness_per_area * self.area_mm2

    def weights(self, r_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """Pad weight in [0, 1] at distance ``r_mm`` from the pad centre."""
        return np.clip((self.radius_mm - r_mm) / self.edge_mm + 0.5, 0.0, 1.0)


@dataclass(frozen=True)
class PixelGrid:
    """The sensor's pixel grid: row index along +y, column index along +x, centred on the pad."""

    width_px: int = 320
    height_px: int = 240
    mm_per_px: float = 0.0634

    def __post_init__(self) -> None:
        if self.width_px < 1 or self.height_px < 1:
            raise ConfigError("pixel grid must be at least 1 x 1")
        if not (math.isfinite(self.mm_per_px) and self.mm_per_px > 0):
            raise ConfigError("mm_per_px must be finite and > 0")

    def offsets_mm(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Pixel-centre offsets from the grid centre: (x per column, y per row)."""
        xs = (np.arange(self.width_px, dtype=np.float64) - (self.width_px - 1) / 2.0) \
            * self.mm_per_px
        ys = (np.arange(self.height_px, dtype=np.float64) - (self.height_px - 1) / 2.0) \
            * self.mm_per_px
        return xs, ys


@dataclass(frozen=True, eq=False)
class Contact:
    """What the pad feels at one pose.

    Attributes:
        depth_map_mm: (height_px, width_px) float32, height pushed into the gel (>= 0).
        force_n: normal force (N), >= 0.
        indentation_mm: approach of the pad below the surface (``max(0, -z)``).
        tissue_indentation_mm: part of the approach taken by the tissue.
        local_modulus_kpa: pad-weighted mean column modulus under the pad.
        tissue_stiffness_n_per_mm: the tissue's contact stiffness K at this (x, y).
    """

    depth_map_mm: NDArray[np.float32]
    force_n: float
    indentation_mm: float
    tissue_indentation_mm: float
    local_modulus_kpa: float
    tissue_stiffness_n_per_mm: float

    @property
    def in_contact(self) -> bool:
        """True when the pad presses the tissue."""
        return self.force_n > 0.0


@dataclass
class _StiffnessTable:
    x0_mm: float
    y0_mm: float
    step_mm: float
    values: NDArray[np.float64]  # (ny, nx) tissue stiffness N/mm


def _check_pose(position_mm: Sequence[float]) -> tuple[float, float, float]:
    try:
        x, y, z = (float(v) for v in position_mm)
    except (TypeError, ValueError) as err:
        raise InputDataError(
            f"pose must be three numbers (x, y, z) mm, got {position_mm!r}") from err
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise InputDataError(f"pose must be finite, got {position_mm!r}")
    return x, y, z


@dataclass
class Phantom:
    """A silicone phantom with embedded tumors and a sensor pad to press it with.

    Args:
        layer: the silicone body.
        tumors: the inclusions (must lie inside the footprint).
        fiducials: registration markers (small rigid beads just under the surface, at
            positions known by design); felt like inclusions, listed apart in the truth.
        pad: the sensor's gel pad.
        name: scene name for the ground truth.
        seed: placement seed for the ground truth.
        table_step_mm: resolution of the precomputed stiffness table.
        modulus_oversample: column-modulus table samples per sensor pixel (contact maps).
    """

    layer: SiliconeLayer = field(default_factory=SiliconeLayer)
    tumors: tuple[Tumor, ...] = ()
    fiducials: tuple[Tumor, ...] = ()
    pad: SensorPad = field(default_factory=SensorPad)
    name: str = "custom"
    seed: int | None = None
    table_step_mm: float = 0.25
    modulus_oversample: int = 2
    _table: _StiffnessTable | None = field(default=None, init=False, repr=False)
    _pad_cache: dict[PixelGrid, tuple[NDArray[np.float32], float]] = field(
        default_factory=dict, init=False, repr=False)
    _modulus_tables: dict[float, ColumnModulusTable] = field(default_factory=dict, init=False,
                                                             repr=False)

    def __post_init__(self) -> None:
        self.tumors = tuple(self.tumors)
        self.fiducials = tuple(self.fiducials)
        half_x, half_y = self.layer.size_mm[0] / 2, self.layer.size_mm[1] / 2
        for t in self.inclusions:
            if abs(t.center_mm[0]) > half_x or abs(t.center_mm[1]) > half_y:
                raise ConfigError(f"tumor {t.tumor_id} lies outside the phantom footprint")
            if t.depth_mm > self.layer.thickness_mm:
                raise ConfigError(f"tumor {t.tumor_id} is deeper than the layer")
        if not (math.isfinite(self.table_step_mm) and self.table_step_mm > 0):
            raise ConfigError("table_step_mm must be finite and > 0")
        if int(self.modulus_oversample) != self.modulus_oversample or self.modulus_oversample < 1:
            raise ConfigError("modulus_oversample must be an integer >= 1")

    @property
    def inclusions(self) -> tuple[Tumor, ...]:
        """Everything stiffer than the layer: tumors, then fiducials."""
        return self.tumors + self.fiducials

    # ------------------------------------------------------------------ modulus field

    @property
    def punch_stiffness_per_kpa(self) -> float:
        """Tissue contact stiffness (N/mm) per kPa of pad-mean modulus."""
        return float(punch_stiffness_n_per_mm(1.0, self.pad.effective_radius_mm,
                                              self.layer.thickness_mm))

    def column_modulus_kpa(self, xs_mm: NDArray[np.float64],
                           ys_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """Effective column modulus on the rectilinear grid ``xs_mm`` x ``ys_mm``.

        Args:
            xs_mm: increasing x of the columns (1-D).
            ys_mm: increasing y of the rows (1-D).

        Returns:
            (len(ys), len(xs)) array in kPa; 0 outside the phantom footprint.
        """
        xs = np.asarray(xs_mm, dtype=float)
        ys = np.asarray(ys_mm, dtype=float)
        e_bg = self.layer.modulus_kpa
        compliance = np.ones((ys.size, xs.size))
        a = self.pad.effective_radius_mm
        h = self.layer.thickness_mm
        for t in self.inclusions:
            cx, cy = t.center_mm
            reach = t.reach_mm
            i0, i1 = np.searchsorted(ys, [cy - reach, cy + reach])
            j0, j1 = np.searchsorted(xs, [cx - reach, cx + reach])
            if i0 >= i1 or j0 >= j1:
                continue
            frac = tumor_column_fraction(t, xs[None, j0:j1] - cx, ys[i0:i1, None] - cy, a, h)
            compliance[i0:i1, j0:j1] += frac * (e_bg / t.modulus_kpa - 1.0)
        modulus = e_bg / compliance
        half_x, half_y = self.layer.size_mm[0] / 2, self.layer.size_mm[1] / 2
        inside = (np.abs(ys)[:, None] <= half_y) & (np.abs(xs)[None, :] <= half_x)
        return np.where(inside, modulus, 0.0)

    # ------------------------------------------------------------------ stiffness table

    def _build_table(self) -> _StiffnessTable:
        step = self.table_step_mm
        reach = self.pad.radius_mm + self.pad.edge_mm
        half_x = self.layer.size_mm[0] / 2 + reach + step
        half_y = self.layer.size_mm[1] / 2 + reach + step
        xs = np.arange(-half_x, half_x + step / 2, step)
        ys = np.arange(-half_y, half_y + step / 2, step)
        modulus = self.column_modulus_kpa(xs, ys)
        n = math.ceil(reach / step)
        k_off = np.arange(-n, n + 1) * step
        kernel = self.pad.weights(np.hypot(k_off[None, :], k_off[:, None]))
        mean_e = fftconvolve(modulus, kernel, mode="same") / kernel.sum()
        values = np.maximum(mean_e, 0.0) * self.punch_stiffness_per_kpa
        log.debug("stiffness table for %s: %d x %d at %.3g mm", self.name, ys.size, xs.size, step)
        return _StiffnessTable(float(xs[0]), float(ys[0]), step, values)

    def _stiffness_lookup(self, x_mm: float, y_mm: float) -> float:
        if self._table is None:
            self._table = self._build_table()
        tab = self._table
        ny, nx = tab.values.shape
        fx = (x_mm - tab.x0_mm) / tab.step_mm
        fy = (y_mm - tab.y0_mm) / tab.step_mm
        if not (0.0 <= fx <= nx - 1 and 0.0 <= fy <= ny - 1):
            return 0.0  # the pad is entirely off the phantom
        j = min(int(fx), nx - 2)
        i = min(int(fy), ny - 2)
        tx, ty = fx - j, fy - i
        v = tab.values
        top = v[i, j] * (1 - tx) + v[i, j + 1] * tx
        bot = v[i + 1, j] * (1 - tx) + v[i + 1, j + 1] * tx
        return float(top * (1 - ty) + bot * ty)

    def tissue_stiffness_n_per_mm(self, x_mm: float, y_mm: float) -> float:
        """Ground-truth tissue contact stiffness K for the pad centred at (x, y).

        Raises:
            InputDataError: a non-finite coordinate.
        """
        x, y, _ = _check_pose((x_mm, y_mm, 0.0))
        return self._stiffness_lookup(x, y)

    def measured_stiffness_n_per_mm(self, x_mm: float, y_mm: float,
                                    approach_mm: float = 0.0) -> float:
        """Secant stiffness the arm sees at (x, y) and approach ``d``: tissue and gel in series.

        With a non-linear layer the tissue's stiffness is ``k0 (1 + beta d / h)`` (first
        order: evaluated at the whole approach, not at the tissue's share of it).
        """
        k_t = self.tissue_stiffness_n_per_mm(x_mm, y_mm)
        if k_t <= 0.0:
            return 0.0
        if self.layer.nonlinearity > 0 and approach_mm > 0:
            k_t *= 1.0 + self.layer.nonlinearity * approach_mm / self.layer.thickness_mm
        return 1.0 / (1.0 / k_t + 1.0 / self.pad.gel_stiffness_n_per_mm)

    def force_n(self, position_mm: Sequence[float]) -> float:
        """Normal force (N) on the pad at a pose; O(1), fit for a 1 kHz loop.

        Raises:
            InputDataError: a pose that is not three finite numbers.
        """
        x, y, z = _check_pose(position_mm)
        if z >= 0.0:
            return 0.0
        return self.measured_stiffness_n_per_mm(x, y, -z) * (-z)

    # ------------------------------------------------------------------ contact

    def _pad_weights(self, grid: PixelGrid) -> tuple[NDArray[np.float32], float]:
        cached = self._pad_cache.get(grid)
        if cached is None:
            xs, ys = grid.offsets_mm()
            w = self.pad.weights(np.hypot(xs[None, :], ys[:, None]))
            cached = (w.astype(np.float32), float(w.sum()))
            self._pad_cache[grid] = cached
        return cached

    def modulus_table(self, mm_per_px: float) -> ColumnModulusTable:
        """The column-modulus table for a pixel pitch (built on first use, then cached)."""
        table = self._modulus_tables.get(mm_per_px)
        if table is None:
            table = ColumnModulusTable(self.layer.size_mm, self.layer.modulus_kpa,
                                       self.layer.thickness_mm, self.pad.effective_radius_mm,
                                       self.inclusions, mm_per_px,
                                       int(self.modulus_oversample))
            self._modulus_tables[mm_per_px] = table
        return table

    def contact(self, position_mm: Sequence[float], grid: PixelGrid | None = None, *,
                exact: bool = False) -> Contact:
        """The gel contact depth map and normal force for the pad at a pose.

        Args:
            position_mm: (x, y, z) of the pad centre in phantom coordinates.
            grid: the sensor pixel grid (default 320 x 240 at 0.0634 mm/px).
            exact: evaluate the column modulus exactly on the pixel grid (reference, ~10 ms)
                instead of sampling the precomputed table (the default, ~0.5 ms).

        Returns:
            A :class:`Contact`; without contact the depth map is all zeros (and the column
            modulus is not evaluated).

        Raises:
            InputDataError: a pose that is not three finite numbers.
        """
        grid = grid or PixelGrid()
        x, y, z = _check_pose(position_mm)
        k_t = self._stiffness_lookup(x, y)
        force = self.force_n((x, y, z))
        approach = max(0.0, -z)
        shape = (grid.height_px, grid.width_px)
        if force <= 0.0:
            return Contact(np.zeros(shape, np.float32), 0.0, approach, 0.0,
                           k_t / self.punch_stiffness_per_kpa, k_t)
        weights, weight_sum = self._pad_weights(grid)
        if exact:
            xs, ys = grid.offsets_mm()
            modulus = self.column_modulus_kpa(xs + x, ys + y).astype(np.float32)
        else:
            modulus = self.modulus_table(grid.mm_per_px).sample(x, y, grid.width_px,
                                                                grid.height_px)
        load = modulus
        load *= weights
        total = float(load.sum(dtype=np.float64))
        px_area = grid.mm_per_px ** 2
        if total <= 0.0:  # only possible if the grid misses the pad: no visible contact
            depth = np.zeros(shape, np.float32)
        else:
            # pressure = load * F / (total * px_area); depth = pressure / gel stiffness
            load *= np.float32(force / (total * px_area * self.pad.gel_stiffness_per_area))
            depth = load
        local = total / weight_sum if weight_sum > 0 else 0.0
        k_eff = k_t * (1.0 + self.layer.nonlinearity * approach / self.layer.thickness_mm)
        return Contact(depth, force, approach, force / k_eff, local, k_t)

    # ------------------------------------------------------------------ ground truth

    def ground_truth(self) -> dict[str, Any]:
        """Plain-JSON ground truth: layer, pad, tumors, and the stiffness over each tumor."""
        tumors = []
        for t in self.tumors:
            d = t.to_dict()
            k = self.tissue_stiffness_n_per_mm(*t.center_mm)
            d["stiffness_n_per_mm"] = k
            d["apparent_modulus_kpa"] = k / self.punch_stiffness_per_kpa
            tumors.append(d)
        k_bg = float(self.punch_stiffness_per_kpa * self.layer.modulus_kpa)
        return {
            "scene": self.name,
            "seed": self.seed,
            "frame": "phantom mm: origin at the top-surface centre, +z up, surface z = 0",
            "layer": asdict(self.layer),
            "pad": {**asdict(self.pad),
                    "gel_stiffness_n_per_mm": self.pad.gel_stiffness_n_per_mm},
            "background_stiffness_n_per_mm": k_bg,
            "tumors": tumors,
            "fiducials": [{"id": f.tumor_id, "center_mm": [float(c) for c in f.center_mm],
                           "depth_mm": f.depth_mm, "radius_mm": f.radius_mm}
                          for f in self.fiducials],
        }

    def write_ground_truth(self, path: str | Path) -> Path:
        """Write :meth:`ground_truth` as JSON to ``path`` and return the path."""
        import json

        out = Path(path)
        out.write_text(json.dumps(self.ground_truth(), indent=2, sort_keys=True))
        return out
