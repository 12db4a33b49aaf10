"""Maps of what the operator felt, in phantom coordinates, from received tactile frames only.

Input is what reached the local station: every accepted tactile frame (a height patch on a
metric grid centred on ``center_mm`` in platform coordinates, the probe's normal force and
indentation) plus the workspace map that the operator's platform positions go through. No
ground truth and nothing from the remote station's internals is used.

Two maps are built on a regular phantom grid:

* **relief**: how much more the gel is pushed at a point than the pad's average, relative.
  A stiff inclusion under a soft layer carries more of the pad's load, so the gel bulges
  more over it. Each frame's patch is divided by the pad's own pressure profile (estimated
  from the data as the median normalised patch over all contact frames, so no pad model is
  assumed), normalised by the frame's *pad signal* (the ``signal_percentile``-th percentile
  of that ratio over the pad's core; 50 = the median), and accumulated (mean per cell).
  Only the core of the pad (profile >= ``core_fraction`` of its peak) is used, where the
  profile is flat enough to divide by safely. The median over the core rises by ~35 % when
  the pad sits on an inclusion, so a frame's relief depends on where it fell; a low
  percentile follows the healthy part of the patch instead (see ``MapConfig``).
* **secant stiffness**: force / indentation of each contact frame, placed at the frame
  centre (the pad-averaged stiffness the probe felt there), mean per cell.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from local_site.recording import Recording
from shared.errors import ConfigError, InputDataError
from shared.workspace import WorkspaceMap

__all__ = ["MAX_MAP_CELLS_PER_SIDE", "MapConfig", "PalpationMaps", "build_maps",
           "build_maps_at", "map_grid", "pad_profile", "pad_signal"]

#: largest map side (cells): the grid follows the workspace's phantom box, which an
#: analysed recording brings in its metadata, so a huge box (or a tiny ``cell_mm``) is
#: refused before any map is allocated (4096 x 4096 float64 is 128 MiB per map)
MAX_MAP_CELLS_PER_SIDE = 4096


def _is_number(v: object) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)


@dataclass(frozen=True)
class MapConfig:
    """Settings of the map building.

    Attributes:
        cell_mm: grid spacing of the maps (phantom mm).
        min_indentation_mm: frames pressed less than this are not used (secant too noisy).
        min_signal_fraction: frames whose pad signal (see ``signal_percentile``) is below
            this fraction of the session's median pad signal are not used: the
            relief is that signal's relative variation, so its noise grows as 1 / signal
            (an arm lagging its target in z, under load, grazes the phantom and such frames
            drew findings out of noise at the scan's edge).
        core_fraction: pad-profile level defining the pad core used for relief.
        margin_mm: the maps extend this far beyond the phantom bounds of the workspace.
        signal_percentile: each frame's pad signal, which its relief is relative to, is
            this percentile (0-100) of the frame's height over the pad profile across the
            pad core. 50 (the median) rises when the pad sits on an inclusion, so the
            relief (and the typing's malignant score) depends on where the frames fell; a
            low percentile tracks the healthy tissue under the same frame. Changing it
            rescales the relief, so ``DetectionConfig``'s typing references depend on it.
            Measured (benchmarks/results/palpation_typing_percentile.md): 20 halves the
            session-to-session scatter of a finding's malignant score but makes it grow
            with the inclusion's size; with the references re-set it typed the typed pairs
            worse than 50 on fresh seeds (more malignant typed benign) and added false
            positives, so the default stays 50.

        typing_signal_percentile: a number (0-100; default 20):
            :func:`local_site.palpation.analyse_recording` (and
            :func:`local_site.palpation.maps_and_findings`) build a second relief map with
            this ``signal_percentile`` and type each finding - found, located and sized on
            the first maps exactly as with None - from it
            (``find_tumors(..., typing_maps=...)``); both maps come from one pass
            (:func:`build_maps_at`). None: the
            findings are typed from the maps they were found in (the rule before; use it
            with ``DetectionConfig(malignant_size_exponent=0)``, whose defaults are set
            for typing maps at the 20th percentile). Measured
            (benchmarks/results/palpation_typing_hybrid.md): detection, false positives
            and localization unchanged by construction; more types right and fewer wrong
            on fresh seeds 12000-12029 and on four of the five earlier ranges.

    Raises:
        ConfigError: ``signal_percentile`` or ``typing_signal_percentile`` outside
            [0, 100] or not a number; ``cell_mm`` not > 0, ``core_fraction`` outside
            (0, 1], ``margin_mm``, ``min_indentation_mm`` or ``min_signal_fraction``
            negative, or any of them not a finite number (the field is named).
    """

    cell_mm: float = 0.5
    min_indentation_mm: float = 0.5
    min_signal_fraction: float = 0.25
    core_fraction: float = 0.7
    margin_mm: float = 10.0
    signal_percentile: float = 50.0
    typing_signal_percentile: float | None = 20.0

    def __post_init__(self) -> None:
        for name, p in (("signal_percentile", self.signal_percentile),
                        ("typing_signal_percentile", self.typing_signal_percentile)):
            if p is None and name == "typing_signal_percentile":
                continue
            if (isinstance(p, bool) or not isinstance(p, (int, float))
                    or not 0.0 <= p <= 100.0):
                raise ConfigError(f"MapConfig.{name} must be a number in [0, 100], "
                                  f"got {p!r}")
        checks = (("cell_mm", self.cell_mm, lambda v: v > 0.0, "> 0"),
                  ("core_fraction", self.core_fraction, lambda v: 0.0 < v <= 1.0,
                   "in (0, 1] (a level relative to the pad profile's peak)"),
                  ("margin_mm", self.margin_mm, lambda v: v >= 0.0, ">= 0"),
                  ("min_indentation_mm", self.min_indentation_mm, lambda v: v >= 0.0, ">= 0"),
                  ("min_signal_fraction", self.min_signal_fraction, lambda v: v >= 0.0,
                   ">= 0"))
        for name, v, ok, what in checks:
            if not (_is_number(v) and ok(v)):
                raise ConfigError(f"MapConfig.{name} must be a finite number {what}, "
                                  f"got {v!r}")


@dataclass(frozen=True, eq=False)
class PalpationMaps:
    """Relief and stiffness maps on one grid (row = +y, column = +x).

    Attributes:
        x_mm: cell-centre x of each column (phantom).
        y_mm: cell-centre y of each row (phantom).
        relief: mean relative relief (0 = like the pad's average); NaN where never touched.
        relief_count: samples per cell (the coverage map).
        relief_sample_std: standard deviation of the samples within each cell (NaN below 2).
        stiffness_n_per_mm: mean secant stiffness of frames centred in the cell; NaN if none.
        frames_used: contact frames that went into the maps.
        background_stiffness_n_per_mm: median secant stiffness over all used frames.
    """

    x_mm: NDArray[np.float64]
    y_mm: NDArray[np.float64]
    relief: NDArray[np.float64]
    relief_count: NDArray[np.int64]
    relief_sample_std: NDArray[np.float64]
    stiffness_n_per_mm: NDArray[np.float64]
    frames_used: int
    background_stiffness_n_per_mm: float

    @property
    def cell_mm(self) -> float:
        """Grid spacing."""
        return float(self.x_mm[1] - self.x_mm[0]) if self.x_mm.size > 1 else 0.0


def _contact_frames(rec: Recording, cfg: MapConfig) -> NDArray[np.intp]:
    h = rec.frame_height_mm
    ok = (rec.frame_contact & (rec.frame_indentation_mm >= cfg.min_indentation_mm)
          & (rec.frame_force_n > 0))
    if h.size:
        ok &= h.reshape(h.shape[0], -1).max(axis=1) > 0
    return np.nonzero(ok)[0]


def pad_profile(patches: NDArray[np.floating], core_fraction: float = 0.7
                ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Estimate the pad's pressure profile from contact patches.

    Args:
        patches: (N, H, W) height patches of contact frames.
        core_fraction: level (relative to the peak) that defines the core.

    Returns:
        The profile (H, W), peak-normalised, and the core mask.

    Raises:
        InputDataError: no patch, empty patches, or patches with no positive height.
    """
    if patches.shape[0] == 0:
        raise InputDataError("no contact frames to estimate the pad profile from")
    if patches.ndim != 3 or patches.shape[1] == 0 or patches.shape[2] == 0:
        raise InputDataError(f"contact frames must be (N, H, W) patches with H, W >= 1, "
                             f"got shape {patches.shape}")
    flat = patches.reshape(patches.shape[0], -1).astype(np.float64)
    scale = np.percentile(flat, 75, axis=1)
    good = scale > 0
    if not good.any():
        raise InputDataError("contact frames carry no positive height")
    profile = np.median(flat[good] / scale[good, None], axis=0).reshape(patches.shape[1:])
    peak = float(profile.max())
    if not np.isfinite(peak) or peak <= 0:
        raise InputDataError("pad profile is degenerate")
    profile /= peak
    return profile, profile >= core_fraction


def pad_signal(ratios: NDArray[np.floating], percentile: float = 50.0) -> NDArray[np.float64]:
    """Each frame's pad signal: the ``percentile``-th percentile of its core ratios.

    Args:
        ratios: (N, core pixels) frame heights over the pad profile.
        percentile: 0-100 (50: the median, computed as :func:`numpy.median`).

    Returns:
        (N,) the signal per frame.
    """
    if percentile == 50.0:
        return np.median(ratios, axis=1).astype(np.float64, copy=False)
    return np.percentile(ratios, percentile, axis=1).astype(np.float64, copy=False)


def build_maps(rec: Recording, workspace: WorkspaceMap,
               config: MapConfig | None = None) -> PalpationMaps:
    """Build the relief and stiffness maps of a recording.

    Args:
        rec: what the local station received.
        workspace: the platform <-> phantom map the session used.
        config: map settings.

    Returns:
        The maps.

    Raises:
        InputDataError: no usable contact frame, or a grid of more than
            :data:`MAX_MAP_CELLS_PER_SIDE` cells on a side (the workspace's phantom box
            over ``cell_mm``).
    """
    cfg = config or MapConfig()
    return build_maps_at(rec, workspace, cfg, (cfg.signal_percentile,))[0]


#: contact frames placed on the grid per vectorised step (bounds the temporary arrays to a
#: few MB however long the session)
_FRAMES_PER_STEP = 256


def build_maps_at(rec: Recording, workspace: WorkspaceMap, config: MapConfig | None,
                  percentiles: Sequence[float]) -> list[PalpationMaps]:
    """:func:`build_maps` at several ``signal_percentile`` values in one pass.

    The pad profile and where every core pixel of every frame lands on the grid do not
    depend on the percentile, so they are computed once; each percentile only has its own
    pad signal, frame selection and sums. Each returned map equals ``build_maps`` with
    ``dataclasses.replace(config, signal_percentile=p)`` (the same sums in the same order).

    Args:
        rec: what the local station received.
        workspace: the platform <-> phantom map the session used.
        config: map settings (its ``signal_percentile`` is ignored).
        percentiles: the pad-signal percentiles, 0-100.

    Returns:
        One map per percentile, in order.

    Raises:
        InputDataError: no usable contact frame, or a grid of more than
            :data:`MAX_MAP_CELLS_PER_SIDE` cells on a side.
        ConfigError: a percentile outside [0, 100].
    """
    cfg = config or MapConfig()
    for p in percentiles:
        if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0.0 <= p <= 100.0:
            raise ConfigError(f"signal percentile must be a number in [0, 100], got {p!r}")
    x_mm, y_mm = map_grid(workspace, cfg)  # refused before any work if too large
    cell = cfg.cell_mm
    idx = _contact_frames(rec, cfg)
    if idx.size == 0:
        raise InputDataError("the recording has no contact frame pressed deeper than "
                             f"{cfg.min_indentation_mm} mm: nothing was palpated")
    patches = rec.frame_height_mm[idx]
    profile, core = pad_profile(patches, cfg.core_fraction)
    shape = (y_mm.size, x_mm.size)
    _, h_px, w_px = patches.shape
    secant = rec.frame_force_n[idx] / rec.frame_indentation_mm[idx]
    rows, cols = np.nonzero(core)
    inv_profile = 1.0 / profile[rows, cols]
    ratios = patches[:, rows, cols] * inv_profile  # (N, core pixels)
    z_mm = workspace.config.z_surface_mm
    # each frame's centre -> the stiffness cell (-1: off the grid)
    centres = rec.frame_center_mm[idx].astype(np.float64)
    centre_ph = workspace.forward_unclamped(
        np.column_stack([centres, np.full(idx.size, z_mm)]))
    k_flat = _cell_index(centre_ph, x_mm, y_mm, cell)
    col_off = cols - (w_px - 1) / 2.0
    row_off = rows - (h_px - 1) / 2.0
    pitch = rec.frame_pitch_mm[idx].astype(np.float64)

    sums = []
    for p in percentiles:
        signal = pad_signal(ratios, p)
        positive = signal[signal > 0]
        min_signal = (cfg.min_signal_fraction * float(np.median(positive)) if positive.size
                      else 0.0)
        used = (signal > 0) & (signal >= min_signal)
        sums.append((signal, used, np.zeros(shape), np.zeros(shape),
                     np.zeros(shape, np.int64)))
    for start in range(0, idx.size, _FRAMES_PER_STEP):
        step = slice(start, start + _FRAMES_PER_STEP)
        u = col_off * pitch[step, None] + centres[step, 0, None]
        v = row_off * pitch[step, None] + centres[step, 1, None]
        pts = np.stack([u, v, np.full(u.shape, z_mm)], axis=-1)
        flat = _cell_index(workspace.forward_unclamped(pts), x_mm, y_mm, cell)
        for signal, used, acc, acc2, cnt in sums:
            take = used[step, None] & (flat >= 0)
            rel = (ratios[step] / signal[step, None] - 1.0)[take]
            where = flat[take]
            np.add.at(acc.reshape(-1), where, rel)
            np.add.at(acc2.reshape(-1), where, rel ** 2)
            np.add.at(cnt.reshape(-1), where, 1)
    out = []
    for _signal, used, acc, acc2, cnt in sums:
        on_grid = used & (k_flat >= 0)
        k_acc = np.zeros(shape)
        k_cnt = np.zeros(shape, np.int64)
        np.add.at(k_acc.reshape(-1), k_flat[on_grid], secant[on_grid])
        np.add.at(k_cnt.reshape(-1), k_flat[on_grid], 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            relief = np.where(cnt > 0, acc / np.maximum(cnt, 1), np.nan)
            var = (acc2 - cnt * np.nan_to_num(relief) ** 2) / np.maximum(cnt - 1, 1)
            sample_std = np.where(cnt > 1, np.sqrt(np.maximum(var, 0.0)), np.nan)
            stiffness = np.where(k_cnt > 0, k_acc / np.maximum(k_cnt, 1), np.nan)
        out.append(PalpationMaps(x_mm=x_mm, y_mm=y_mm, relief=relief, relief_count=cnt,
                                 relief_sample_std=sample_std,
                                 stiffness_n_per_mm=stiffness, frames_used=int(used.sum()),
                                 background_stiffness_n_per_mm=float(np.median(secant))))
    return out


def map_grid(workspace: WorkspaceMap, config: MapConfig | None = None
             ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The cell centres ``(x_mm, y_mm)`` of the maps: the workspace's phantom box plus
    ``margin_mm`` on every side, every ``cell_mm``.

    Raises:
        InputDataError: more than :data:`MAX_MAP_CELLS_PER_SIDE` cells on a side (checked
            before anything is allocated).
    """
    cfg = config or MapConfig()
    lo, hi = workspace.phantom_bounds_mm
    cell, margin = cfg.cell_mm, cfg.margin_mm
    axes = []
    for axis, name in ((0, "x"), (1, "y")):
        start, stop = lo[axis] - margin, hi[axis] + margin + cell / 2
        # np.arange's length, computed first: it would allocate whatever this says
        n = math.ceil((stop - start) / cell) if math.isfinite((stop - start) / cell) else -1
        if not 1 <= n <= MAX_MAP_CELLS_PER_SIDE:
            raise InputDataError(
                f"the map grid would have {n if n >= 0 else 'infinitely many'} cells along "
                f"{name} (phantom box {lo[axis]:g}..{hi[axis]:g} mm plus {margin:g} mm "
                f"margins, every {cell:g} mm); at most {MAX_MAP_CELLS_PER_SIDE}: check the "
                "recording's workspace or use a larger MapConfig.cell_mm")
        axes.append(np.arange(start, stop, cell))
    return axes[0], axes[1]


def _cell_index(points_mm: NDArray[np.float64], x_mm: NDArray[np.float64],
                y_mm: NDArray[np.float64], cell: float) -> NDArray[np.intp]:
    """Row-major index of the grid cell nearest each point's (x, y); -1 off the grid."""
    ci = np.rint((points_mm[..., 1] - y_mm[0]) / cell).astype(np.intp)
    cj = np.rint((points_mm[..., 0] - x_mm[0]) / cell).astype(np.intp)
    inside = (ci >= 0) & (ci < y_mm.size) & (cj >= 0) & (cj < x_mm.size)
    return np.where(inside, ci * x_mm.size + cj, -1)
