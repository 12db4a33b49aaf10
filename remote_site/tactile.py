"""Tactile frame assembly: what the remote station sends the operator for one sensor frame.

Layout of a ``tactile_frame`` built here (see :class:`shared.protocol.TactileFrame`):

* ``height_mm``: the reconstructed height map (mm, positive where the tissue pushes into the
  gel) on the reconstruction's own pooled grid, cropped to ``patch_size_mm`` around the pad
  centre (default: the whole sensor area). Rows run along +y, columns along +x.
* ``stiffness_n_per_mm`` and ``stiffness_k``: the stiffness map sampled at every patch point
  (the probe stiffness the pad would measure centred there), the current estimate where the
  map has none; ``stiffness_k`` comes from the one N/mm -> k mapping
  (:class:`shared.hardness.StiffnessToK`, the probe's stiffness calibration); both layers are
  omitted until a first estimate exists (the local scene then
  uses its default).
* ``friction``: constant (0 for palpation, the paper's setting).
* ``center_mm``: the pad centre mapped back to PLATFORM coordinates
  (:meth:`shared.workspace.WorkspaceMap.inverse`), ``pitch_mm``: the patch pitch in platform
  mm (phantom pitch / ``scale_xy``), so the local renderer samples the patch at the platform
  position directly. When the map turns the plane (a registration's yaw: the phantom lies
  turned on the table), the layers are resampled onto the platform's axes
  (:func:`turn_patch`): the sensor's pixel axes are the arm's, and without the turn a feature
  10 mm off the pad centre would be placed 2.3 mm off at 13 deg.
* ``contact``, ``force_n``, ``indentation_mm`` (pad approach below the surface, phantom mm).
* ``ts_us``: sensor frame capture time; ``source_seq``/``source_ts_us``: the platform_state
  this frame answers; ``hops``: that state's hops + ``remote.arm_command`` +
  ``remote.sensor_frame`` + ``remote.sensor_arrival`` + ``remote.tactile_ready`` (the agents'
  contract).

Why a 0.5 mm patch over the sensor area: the display's pins are 1.7 mm apart, but the
operator slides the platform continuously, so the pins sample the surface at every sub-pitch
offset; a patch 3.4x finer than the pins lets the local renderer interpolate there
(super-resolution) while staying small (about 40 x 30 samples, ~5 kB per layer). Covering the
whole sensor (about 20 x 15 mm, 4x the display's 5.1 mm footprint) keeps the renderer inside
the patch while the platform moves between two frames. The pitch is the nearest integer
multiple of the sensor pixel (0.0634 mm x 8 = 0.507 mm on a GelSight Mini), so the
reconstruction runs directly at that resolution (no resampling, a fraction of the cost).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from remote_site.stiffness.stiffness_map import StiffnessMap
from shared.errors import ConfigError, InputDataError
from shared.hardness import StiffnessToK
from shared.protocol.messages import LAYER_RANGES, Hop, PlatformState, TactileFrame
from shared.timebase import now_us
from shared.workspace import WorkspaceMap

#: wire bounds of the scalar fields (shared.protocol.messages.TactileFrame); never exceeded
_FORCE_LIMIT_N = 1000.0
_INDENTATION_LIMIT_MM = 100.0

__all__ = ["AppliedCommand", "TactileAssembler", "crop_centered", "patch_offsets_mm",
           "sample_stiffness_map", "turn_patch"]

#: below this turn (deg) the layers are sent on the sensor's axes as they are: 0.05 deg moves a
#: patch corner (14 mm out) by 0.012 mm, far under the patch pitch
_TURN_ABOVE_DEG = 0.05


@dataclass(frozen=True)
class AppliedCommand:
    """A platform_state that was turned into an arm command.

    Attributes:
        state: the platform_state as received (its hops end with ``remote.station_rx``).
        arm_command_us: when it was applied to the arm (our clock, microseconds).
        arm_speed_mm_s: the arm's speed when it was applied (None: not known).
        answers: whether a frame taken for it answers it (False: an idle frame, taken with no
            command newer than the last frame's; it shows no movement first and carries
            no platform stamps, so motion-to-touch does not count it).
    """

    state: PlatformState
    arm_command_us: int
    arm_speed_mm_s: float | None = None
    answers: bool = True


def crop_centered(grid: NDArray[np.floating], size_mm: tuple[float, float],
                  pitch_mm: float) -> NDArray[np.floating]:
    """Crop a grid symmetrically about its centre to at most ``size_mm`` (x, y).

    The kept sample counts have the parity of the grid's, so the patch centre stays exactly
    on the grid centre (the pad centre). A size of 0 (or larger than the grid) keeps that axis.

    Raises:
        InputDataError: a non-2-D grid, a non-positive pitch or a negative size.
    """
    if grid.ndim != 2:
        raise InputDataError(f"expected a 2-D grid, got shape {grid.shape}")
    if not (math.isfinite(pitch_mm) and pitch_mm > 0):
        raise InputDataError(f"pitch must be finite and > 0, got {pitch_mm}")
    if not all(math.isfinite(s) and s >= 0 for s in size_mm):
        raise InputDataError(f"patch size must be finite and >= 0, got {size_mm}")
    rows, cols = grid.shape

    def keep(n: int, size: float) -> int:
        if size <= 0:
            return n
        want = min(n, max(2, int(size / pitch_mm) + 1))
        if (n - want) % 2:
            want = want + 1 if want < n else want - 1
        return max(want, 1)

    k_rows, k_cols = keep(rows, size_mm[1]), keep(cols, size_mm[0])
    r0, c0 = (rows - k_rows) // 2, (cols - k_cols) // 2
    return grid[r0:r0 + k_rows, c0:c0 + k_cols]


def patch_offsets_mm(shape: tuple[int, int],
                     pitch_mm: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Offsets of the patch samples from its centre: (x per column, y per row), mm."""
    rows, cols = shape
    xs = (np.arange(cols, dtype=np.float64) - (cols - 1) / 2.0) * pitch_mm
    ys = (np.arange(rows, dtype=np.float64) - (rows - 1) / 2.0) * pitch_mm
    return xs, ys


def sample_stiffness_map(stiffness_map: StiffnessMap, xs_mm: NDArray[np.float64],
                         ys_mm: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                              NDArray[np.bool_]]:
    """The map's cell means at the grid ``ys_mm`` x ``xs_mm`` (phantom mm).

    Returns:
        ``(values, known)``, both (len(ys), len(xs)); ``values`` is 0 where ``known`` is False
        (outside the map or a cell without estimates).
    """
    b = stiffness_map.bounds
    n_rows, n_cols = stiffness_map.count.shape
    cols = np.floor((xs_mm - b.x_min_mm) / b.cell_mm).astype(np.int64)
    rows = np.floor((ys_mm - b.y_min_mm) / b.cell_mm).astype(np.int64)
    col_ok = (xs_mm >= b.x_min_mm) & (xs_mm < b.x_max_mm)
    row_ok = (ys_mm >= b.y_min_mm) & (ys_mm < b.y_max_mm)
    cols = np.clip(cols, 0, n_cols - 1)
    rows = np.clip(rows, 0, n_rows - 1)
    inside = row_ok[:, None] & col_ok[None, :]
    counts = stiffness_map.count[rows[:, None], cols[None, :]]
    means = stiffness_map.mean_at(rows[:, None], cols[None, :])
    known = inside & (counts > 0)
    return np.where(known, means, 0.0), known


def turn_patch(layer: NDArray[np.floating], rotation_deg: float) -> NDArray[np.float32]:
    """``layer`` (sensor axes) resampled on axes turned by ``-rotation_deg``: the value at
    grid offset ``u`` from the centre is the input's at ``R(rotation_deg) u`` (bicubic: a
    sharp bump keeps at least 92 % of its peak where bilinear kept 83 %; corners beyond the
    input repeat its edge; the caller clips the overshoot to the layer's range). With the
    workspace map's ``rotation_deg`` this puts a patch taken on the arm's axes onto the
    platform's."""
    src = np.ascontiguousarray(layer, np.float32)
    rows, cols = src.shape
    th = math.radians(rotation_deg)
    c, s = math.cos(th), math.sin(th)
    cx, cy = (cols - 1) / 2.0, (rows - 1) / 2.0
    # destination -> source: src = R (dst - centre) + centre (rows run along +y)
    m = np.array([[c, -s, cx - c * cx + s * cy], [s, c, cy - s * cx - c * cy]])
    return np.asarray(cv2.warpAffine(src, m, (cols, rows),
                                     flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_REPLICATE), np.float32)


class TactileAssembler:
    """Builds tactile frames from a height map, the probe pose and the stiffness state.

    Args:
        workspace: the platform <-> phantom map (for ``center_mm`` and ``pitch_mm``).
        patch_size_mm: (x, y) extent of the height patch in phantom mm; 0 = whole sensor.
        friction: value of the friction layer (0 for palpation).
        stiffness_to_k: N/mm -> display k (the probe's stiffness calibration).

    Raises:
        ConfigError: a friction outside [0, 1] or a bad patch size.
    """

    def __init__(self, workspace: WorkspaceMap, *, stiffness_to_k: StiffnessToK,
                 patch_size_mm: Sequence[float] = (0.0, 0.0), friction: float = 0.0) -> None:
        size = tuple(float(v) for v in patch_size_mm)
        if len(size) != 2 or not all(math.isfinite(v) and v >= 0 for v in size):
            raise ConfigError(f"patch_size_mm must be two finite numbers >= 0, got {patch_size_mm}")
        if not (math.isfinite(friction) and 0.0 <= friction <= 1.0):
            raise ConfigError(f"friction must lie in [0, 1], got {friction}")
        self.workspace = workspace
        self.patch_size_mm: tuple[float, float] = (size[0], size[1])
        self.friction = float(friction)
        self.stiffness_to_k = stiffness_to_k

    @property
    def scale_xy(self) -> float:
        """Phantom mm per platform mm in the plane."""
        return float(self.workspace.config.scale_xy)

    def phantom_pitch_mm(self, platform_pitch_mm: float) -> float:
        """The phantom-side pitch that gives ``platform_pitch_mm`` on the display side."""
        return platform_pitch_mm * self.scale_xy

    def stiffness_patch(self, stiffness_map: StiffnessMap | None, probe_xy_mm: Sequence[float],
                        shape: tuple[int, int], pitch_mm: float,
                        current_n_per_mm: float | None) -> NDArray[np.float64] | None:
        """Stiffness (N/mm) at every patch point, or None when nothing is known yet.

        Cells of the map with estimates give their mean; the rest get the current estimate,
        or, without one, the mean of the known cells in the patch.
        """
        xs, ys = patch_offsets_mm(shape, pitch_mm)
        if stiffness_map is not None:
            values, known = sample_stiffness_map(stiffness_map, xs + float(probe_xy_mm[0]),
                                                 ys + float(probe_xy_mm[1]))
        else:
            values, known = np.zeros(shape), np.zeros(shape, bool)
        fill = current_n_per_mm
        if fill is None or not math.isfinite(fill) or fill < 0:
            fill = float(values[known].mean()) if known.any() else None
        if fill is None:
            return None
        return np.where(known, values, fill)

    def assemble(self, *, seq: int, frame_ts_us: int, height_mm: NDArray[np.floating],
                 pitch_mm: float, probe_mm: Sequence[float], force_n: float, contact: bool,
                 stiffness_map: StiffnessMap | None, current_n_per_mm: float | None,
                 source: AppliedCommand | None, tactile_ready_us: int | None = None,
                 sensor_arrival_us: int | None = None) -> TactileFrame:
        """Build one tactile frame (see the module docstring for the layout).

        Args:
            seq: our tactile frame sequence number.
            frame_ts_us: sensor frame capture time (our clock).
            height_mm: the reconstructed heights on a grid of ``pitch_mm`` (phantom mm),
                centred on the pad; cropped here to the patch size.
            pitch_mm: grid pitch in phantom mm.
            probe_mm: the pad centre (phantom x, y, z) when the frame was taken.
            force_n: measured normal force.
            contact: whether the pad touches the tissue.
            stiffness_map: the scan's stiffness map (phantom mm), or None.
            current_n_per_mm: the current stiffness estimate, or None.
            source: the platform_state this frame answers (None before the first command).
            tactile_ready_us: the ``remote.tactile_ready`` stamp (None: now, taken as the
                last step of the assembly).
            sensor_arrival_us: the ``remote.sensor_arrival`` stamp, when the image reached
                the station (None: ``frame_ts_us``, a source that stamps as it delivers).

        Raises:
            InputDataError: non-finite heights, pose or force.
        """
        patch = crop_centered(np.asarray(height_mm), self.patch_size_mm, pitch_mm)
        if not np.isfinite(patch).all():
            raise InputDataError("height patch contains NaN/Inf")
        x, y, z = (float(v) for v in probe_mm)
        if not all(math.isfinite(v) for v in (x, y, z, force_n)):
            raise InputDataError("probe pose and force must be finite")
        lo, hi = LAYER_RANGES["height_mm"]
        layers: dict[str, np.ndarray] = {
            "height_mm": np.clip(patch, lo, hi).astype(np.float32),
            "friction": np.full(patch.shape, self.friction, np.float32),
        }
        stiffness_n_per_mm = self.stiffness_patch(stiffness_map, (x, y), patch.shape, pitch_mm,
                                                  current_n_per_mm)
        if stiffness_n_per_mm is not None:
            k_lo, k_hi = LAYER_RANGES["stiffness_n_per_mm"]
            n_per_mm = np.clip(np.nan_to_num(stiffness_n_per_mm, nan=0.0), k_lo, k_hi)
            layers["stiffness_n_per_mm"] = n_per_mm.astype(np.float32)
            layers["stiffness_k"] = self.stiffness_to_k.k(n_per_mm).astype(np.float32)
        rotation = float(self.workspace.config.rotation_deg)
        if abs(rotation) > _TURN_ABOVE_DEG:
            layers = {name: layer if name == "friction" else
                      np.clip(turn_patch(layer, rotation), *LAYER_RANGES[name]).astype(np.float32)
                      for name, layer in layers.items()}
        center = self.workspace.inverse([x, y, z])
        hops: tuple[Hop, ...] = ()
        source_seq = source_ts = None
        if source is not None:
            if source.answers:
                hops = (*source.state.hops, Hop("remote", "arm_command", source.arm_command_us))
            source_seq, source_ts = source.state.seq, source.state.ts_us
        ready_us = now_us() if tactile_ready_us is None else int(tactile_ready_us)
        arrival_us = frame_ts_us if sensor_arrival_us is None else sensor_arrival_us
        hops = (*hops, Hop("remote", "sensor_frame", int(frame_ts_us)),
                Hop("remote", "sensor_arrival", int(arrival_us)),
                Hop("remote", "tactile_ready", ready_us))
        return TactileFrame(seq=seq, ts_us=int(frame_ts_us), hops=hops,
                            center_mm=(float(center[0]), float(center[1])),
                            pitch_mm=float(pitch_mm) / self.scale_xy, layers=layers,
                            contact=bool(contact),
                            force_n=min(max(float(force_n), -_FORCE_LIMIT_N), _FORCE_LIMIT_N),
                            indentation_mm=min(max(0.0, -z), _INDENTATION_LIMIT_MM),
                            source_seq=source_seq,
                            source_ts_us=source_ts)
