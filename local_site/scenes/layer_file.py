"""Tactile layer files (``.npz``): the format an image-to-touch pipeline writes.

The format (version 1) is specified in ``docs/layer_files.md``; in short, an ``.npz``
archive (numpy ``savez``, no pickles) with:

=====================  ========  ==========================================================
key                    required  content
=====================  ========  ==========================================================
``format_version``     yes       integer scalar, 1
``extent_mm``          yes       float ``[x_min, x_max, y_min, y_max]``: positions of the
                                 first and last sample centres (x_max > x_min, y_max > y_min)
``height_mm``          yes       float ``(ny, nx)``, row index along +y, column along +x,
                                 finite, ``|h| <= 1000``
``stiffness_k``        no        float ``(ny, nx)`` in [0.5, 1] (display k)
``stiffness_shore00``  no        float ``(ny, nx)`` in [0, 100]; exclusive with stiffness_k
``friction``           no        float ``(ny, nx)`` in [0, 1]
``description``        no        a string of at most 262,144 characters
=====================  ========  ==========================================================

Missing stiffness means k = 1 (rigid); missing friction means 0. Shore 00 is mapped to
k through :class:`~shared.hardness.HardnessTable` when the file is loaded.

A file is hostile input: :func:`load_layer_file` refuses unknown members by name, then
reads every member's ``.npy`` header and checks its dtype, shape and size before it reads
(or decompresses) any array data, so a small file declaring a huge array is refused in
milliseconds; any other read failure (corrupt zip or deflate stream, truncated data) is an
:class:`~shared.errors.InputDataError` naming the file.
"""

from __future__ import annotations

import logging
import lzma
import math
import os
import struct
import zipfile
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from local_site.render.interpolation import DEFAULT_ORDER, MAX_GRID_DIM, GridLayers
from local_site.scenes.base import MAX_SCENE_HEIGHT_MM, OutsidePolicy
from local_site.scenes.grid_scene import GridScene
from shared.errors import ConfigError, InputDataError
from shared.hardness import K_MAX, K_MIN, HardnessTable

__all__ = [
    "LAYER_FILE_KEYS",
    "LAYER_FILE_VERSION",
    "MAX_DESCRIPTION_CHARS",
    "MIN_LAYER_SPACING_MM",
    "LayerFileData",
    "LayerFileScene",
    "load_layer_file",
    "save_layer_file",
    "validate_layers",
]

log = logging.getLogger(__name__)

LAYER_FILE_VERSION = 1
#: layer key -> allowed value range
_LAYER_RANGES: dict[str, tuple[float, float]] = {
    "height_mm": (-MAX_SCENE_HEIGHT_MM, MAX_SCENE_HEIGHT_MM),
    "stiffness_k": (K_MIN, K_MAX),
    "stiffness_shore00": (0.0, 100.0),
    "friction": (0.0, 1.0),
}
LAYER_FILE_KEYS: frozenset[str] = frozenset(
    {"format_version", "extent_mm", "description", *_LAYER_RANGES})
#: smallest sample spacing (mm) a file may imply, ``(x_max - x_min) / (nx - 1)`` and the
#: same along y: far below any physical use (a nanometre), far above where the division
#: underflows to 0 (a file saved with a sub-normal spacing did not load)
MIN_LAYER_SPACING_MM = 1.0e-6
#: largest ``.npy`` member other than a layer (format_version, extent_mm, description)
_MAX_SMALL_MEMBER_BYTES = 1 << 20
#: longest description (numpy stores 4 bytes a character: 262,144 within that 1 MiB)
MAX_DESCRIPTION_CHARS = _MAX_SMALL_MEMBER_BYTES // 4
#: what reading a hostile archive can raise besides our own checks
_READ_ERRORS: tuple[type[BaseException], ...] = (
    OSError, EOFError, ValueError, OverflowError, struct.error, zipfile.BadZipFile,
    zipfile.LargeZipFile, zlib.error, lzma.LZMAError, NotImplementedError, RuntimeError)


@dataclass(frozen=True, eq=False)
class LayerFileData:
    """Validated content of a layer file, stiffness already in k.

    Attributes:
        height_mm, stiffness_k, friction: ``(ny, nx)`` float64 arrays (read-only).
        extent_mm: ``(x_min, x_max, y_min, y_max)`` of the sample centres.
        stiffness_source: ``"k"``, ``"shore00"`` or ``"default"`` (what the file held).
        description: free text from the file.
    """

    height_mm: NDArray[np.float64]
    stiffness_k: NDArray[np.float64]
    friction: NDArray[np.float64]
    extent_mm: tuple[float, float, float, float]
    stiffness_source: str = "default"
    description: str = ""

    def grid(self) -> GridLayers:
        """The layers as a :class:`GridLayers` (height, k, friction)."""
        ny, nx = self.height_mm.shape
        x0, x1, y0, y1 = self.extent_mm
        return GridLayers(np.stack([self.height_mm, self.stiffness_k, self.friction]),
                          x0_mm=x0, y0_mm=y0, dx_mm=(x1 - x0) / (nx - 1),
                          dy_mm=(y1 - y0) / (ny - 1))


def _layer(arrays: Mapping[str, Any], key: str, where: str,
           shape: tuple[int, ...] | None) -> NDArray[np.float64] | None:
    if key not in arrays:
        return None
    arr = np.asarray(arrays[key])
    if arr.dtype.kind != "f":
        raise InputDataError(f"{where}: '{key}' must be a float array, got dtype {arr.dtype}")
    if arr.ndim != 2:
        raise InputDataError(f"{where}: '{key}' must be 2-D (ny, nx), got shape {arr.shape}")
    if shape is not None and arr.shape != shape:
        raise InputDataError(f"{where}: '{key}' has shape {arr.shape}, height_mm has {shape}")
    if not (2 <= arr.shape[0] <= MAX_GRID_DIM and 2 <= arr.shape[1] <= MAX_GRID_DIM):
        raise InputDataError(f"{where}: '{key}' needs 2..{MAX_GRID_DIM} samples per side, "
                             f"got {arr.shape}")
    out = arr.astype(np.float64)
    bad = ~np.isfinite(out)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise InputDataError(f"{where}: '{key}' has {int(bad.sum())} NaN/Inf value(s), "
                             f"first at [row {r}, col {c}]")
    lo, hi = _LAYER_RANGES[key]
    if out.min() < lo or out.max() > hi:
        raise InputDataError(f"{where}: '{key}' must lie in [{lo}, {hi}], got "
                             f"[{out.min():.6g}, {out.max():.6g}]")
    out.setflags(write=False)
    return out


def validate_layers(arrays: Mapping[str, Any], *, where: str = "layer file",
                    hardness: HardnessTable | None = None) -> LayerFileData:
    """Check a mapping of layer-file keys and build :class:`LayerFileData`.

    Args:
        arrays: key -> array, as read from an ``.npz`` (see the module docstring).
        where: name used in error messages (the file path).
        hardness: the Shore 00 -> k table (default table when None).

    Returns:
        The validated data with stiffness in k.

    Raises:
        InputDataError: a missing, unknown or malformed key, NaN/Inf, out-of-range
            values, mismatched shapes, a degenerate extent or a sample spacing below
            :data:`MIN_LAYER_SPACING_MM`.
    """
    unknown = sorted(set(arrays) - LAYER_FILE_KEYS)
    if unknown:
        raise InputDataError(f"{where}: unknown key(s) {unknown}; allowed: "
                             f"{sorted(LAYER_FILE_KEYS)}")
    for key in ("format_version", "extent_mm", "height_mm"):
        if key not in arrays:
            raise InputDataError(f"{where}: required key '{key}' is missing")
    version = np.asarray(arrays["format_version"])
    if version.shape != () or version.dtype.kind not in "iu" or int(version) != LAYER_FILE_VERSION:
        raise InputDataError(f"{where}: format_version must be the integer "
                             f"{LAYER_FILE_VERSION}, got {version!r}")
    extent = np.asarray(arrays["extent_mm"])
    if extent.shape != (4,) or extent.dtype.kind not in "fiu":
        raise InputDataError(f"{where}: extent_mm must be 4 numbers [x_min, x_max, y_min, "
                             f"y_max], got shape {extent.shape} dtype {extent.dtype}")
    ext = extent.astype(np.float64)
    if not np.isfinite(ext).all() or not (ext[1] > ext[0] and ext[3] > ext[2]) \
            or np.abs(ext).max() > 1.0e4:
        raise InputDataError(f"{where}: extent_mm must be finite with x_max > x_min and "
                             f"y_max > y_min (|v| <= 1e4 mm), got {ext.tolist()}")
    height = _layer(arrays, "height_mm", where, None)
    if height is None:  # unreachable: checked above; keeps the type checker informed
        raise InputDataError(f"{where}: required key 'height_mm' is missing")
    shape = height.shape
    # the spacing exactly as LayerFileData.grid() computes it
    dx = (float(ext[1]) - float(ext[0])) / (shape[1] - 1)
    dy = (float(ext[3]) - float(ext[2])) / (shape[0] - 1)
    if not (dx >= MIN_LAYER_SPACING_MM and dy >= MIN_LAYER_SPACING_MM):
        raise InputDataError(f"{where}: extent_mm {ext.tolist()} over {shape[0]} x "
                             f"{shape[1]} samples gives a spacing of dx = {dx:.6g}, "
                             f"dy = {dy:.6g} mm; each must be >= {MIN_LAYER_SPACING_MM:g} mm")
    k_layer = _layer(arrays, "stiffness_k", where, shape)
    shore = _layer(arrays, "stiffness_shore00", where, shape)
    if k_layer is not None and shore is not None:
        raise InputDataError(f"{where}: give stiffness_k or stiffness_shore00, not both")
    if shore is not None:
        k_layer = (hardness or HardnessTable()).shore00_to_k(shore)
        k_layer.setflags(write=False)
        source = "shore00"
    elif k_layer is not None:
        source = "k"
    else:
        k_layer = np.full(shape, K_MAX)
        source = "default"
    friction = _layer(arrays, "friction", where, shape)
    if friction is None:
        friction = np.zeros(shape)
    description = ""
    if "description" in arrays:
        d = np.asarray(arrays["description"])
        if d.shape != () or d.dtype.kind != "U":
            raise InputDataError(f"{where}: description must be a string")
        if d.nbytes > _MAX_SMALL_MEMBER_BYTES:  # what the reader refuses (_check_header)
            raise InputDataError(f"{where}: description is {d.nbytes // 4} characters; at "
                                 f"most {MAX_DESCRIPTION_CHARS} (1 MiB as stored)")
        description = str(d)
    return LayerFileData(height, k_layer, friction,
                         (float(ext[0]), float(ext[1]), float(ext[2]), float(ext[3])),
                         source, description)


def load_layer_file(path: str | os.PathLike[str], *,
                    hardness: HardnessTable | None = None) -> LayerFileData:
    """Read and validate a layer file.

    Unknown members are refused by name and every member's ``.npy`` header (dtype, shape,
    size) is checked before any array data is read (see the module docstring).

    Args:
        path: the ``.npz`` file.
        hardness: the Shore 00 -> k table (default table when None).

    Returns:
        The validated data.

    Raises:
        ConfigError: the file does not exist.
        InputDataError: not an ``.npz`` archive, unreadable or corrupt, an unknown member,
            pickled content, an array too large, or invalid layers; the message names the
            file.
    """
    where = os.fspath(path)
    if not os.path.isfile(path):
        raise ConfigError(f"layer file not found: {where}")
    try:
        with open(path, "rb") as fh:
            magic = fh.read(len(np.lib.format.MAGIC_PREFIX))
        if magic == np.lib.format.MAGIC_PREFIX:
            raise InputDataError(f"{where}: not an .npz archive (a single .npy array)")
        with zipfile.ZipFile(path) as zf:
            members = _members(zf, where)
            for key, name in members.items():  # every header before any data
                with zf.open(name) as f:
                    _check_header(f, key, where)
            arrays: dict[str, Any] = {}
            for key, name in members.items():
                with zf.open(name) as f:
                    arrays[key] = np.lib.format.read_array(f, allow_pickle=False)
    except InputDataError:
        raise
    except _READ_ERRORS as err:  # not a zip, corrupt member, truncated data, pickles ...
        raise InputDataError(f"{where}: cannot read as .npz ({type(err).__name__}: "
                             f"{err})") from err
    return validate_layers(arrays, where=where, hardness=hardness)


def _members(zf: zipfile.ZipFile, where: str) -> dict[str, str]:
    """Layer-file key -> archive member name (``key.npy``); unknown or repeated members
    refused by name, before anything is decompressed."""
    members: dict[str, str] = {}
    unknown: list[str] = []
    for name in zf.namelist():
        key = name[:-len(".npy")] if name.endswith(".npy") else None
        if key is None or key not in LAYER_FILE_KEYS:
            unknown.append(name)
        elif key in members:
            raise InputDataError(f"{where}: member {name!r} appears twice")
        else:
            members[key] = name
    if unknown:
        raise InputDataError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: "
                             f"{sorted(LAYER_FILE_KEYS)} (as '<key>.npy' members)")
    return members


def _check_header(f: Any, key: str, where: str) -> None:
    """Read the ``.npy`` header of member ``key`` from ``f`` and refuse, before any data is
    read, a pickled dtype, a non-float or oversized layer, or an oversized other member."""
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        shape, _fortran, dtype = np.lib.format.read_array_header_1_0(f)
    elif version == (2, 0):
        shape, _fortran, dtype = np.lib.format.read_array_header_2_0(f)
    else:
        raise InputDataError(f"{where}: '{key}' has .npy format version {version}; "
                             "expected 1.0 or 2.0")
    if dtype.hasobject:
        raise InputDataError(f"{where}: '{key}' holds pickled (object) data, which is "
                             "never loaded")
    if any(d < 0 for d in shape):
        raise InputDataError(f"{where}: '{key}' declares a negative shape {shape}")
    nbytes = math.prod(shape) * dtype.itemsize
    if key in _LAYER_RANGES:
        if dtype.kind != "f":
            raise InputDataError(f"{where}: '{key}' must be a float array, got dtype {dtype}")
        if len(shape) != 2:
            raise InputDataError(f"{where}: '{key}' must be 2-D (ny, nx), got shape {shape}")
        if max(shape) > MAX_GRID_DIM:
            raise InputDataError(f"{where}: '{key}' needs 2..{MAX_GRID_DIM} samples per "
                                 f"side, got {shape}")
    elif nbytes > _MAX_SMALL_MEMBER_BYTES:
        raise InputDataError(f"{where}: '{key}' declares {nbytes} bytes (shape {shape}, "
                             f"dtype {dtype}); at most {_MAX_SMALL_MEMBER_BYTES}")


def save_layer_file(path: str | os.PathLike[str], *, height_mm: ArrayLike,
                    extent_mm: tuple[float, float, float, float],
                    stiffness_k: ArrayLike | None = None,
                    stiffness_shore00: ArrayLike | None = None,
                    friction: ArrayLike | None = None, description: str = "") -> None:
    """Write a layer file (validated first, so only loadable files are written).

    Args:
        path: destination ``.npz``.
        height_mm: ``(ny, nx)`` heights, row along +y, column along +x.
        extent_mm: ``(x_min, x_max, y_min, y_max)`` of the sample centres.
        stiffness_k: optional k layer; exclusive with ``stiffness_shore00``.
        stiffness_shore00: optional Shore 00 layer.
        friction: optional friction layer.
        description: free text.

    Raises:
        InputDataError: the layers would not load back.
    """
    arrays: dict[str, Any] = {
        "format_version": np.int64(LAYER_FILE_VERSION),
        "extent_mm": np.asarray(extent_mm, dtype=np.float64),
        "height_mm": np.asarray(height_mm),
    }
    for key, value in (("stiffness_k", stiffness_k), ("stiffness_shore00", stiffness_shore00),
                       ("friction", friction)):
        if value is not None:
            arrays[key] = np.asarray(value)
    if description:
        arrays["description"] = np.str_(description)
    validate_layers(arrays, where=os.fspath(path))
    np.savez_compressed(path, **arrays)


class LayerFileScene(GridScene):
    """A static scene from a layer file (``version`` is 1 once loaded, then constant).

    Args:
        data: validated layers (see :func:`load_layer_file`).
        order: interpolation order (0, 1, 3).
        outside: what to return outside the file's extent (default flat at height 0).
    """

    kind: ClassVar[str] = "layer_file"

    def __init__(self, data: LayerFileData, *, order: int = DEFAULT_ORDER,
                 outside: OutsidePolicy | None = None) -> None:
        super().__init__(order=order, outside=outside)
        self.data = data
        self._set_grid(data.grid())

    @classmethod
    def from_file(cls, path: str | os.PathLike[str], *, order: int = DEFAULT_ORDER,
                  outside: OutsidePolicy | None = None,
                  hardness: HardnessTable | None = None) -> LayerFileScene:
        """Load and validate ``path`` and build the scene.

        Raises:
            ConfigError: missing file.
            InputDataError: invalid content.
        """
        data = load_layer_file(path, hardness=hardness)
        try:
            scene = cls(data, order=order, outside=outside)
        except InputDataError as err:  # validated data always makes a grid; name the file
            raise InputDataError(f"{os.fspath(path)}: {err}") from err
        ny, nx = scene.data.height_mm.shape
        log.info("layer file %s: %d x %d samples, extent %s mm, stiffness from %s",
                 os.fspath(path), ny, nx, scene.data.extent_mm, scene.data.stiffness_source)
        return scene
