"""Phantoms described in TOML files (``--phantom FILE.toml``); the named scenes are such files.

A lab mirrors its physical phantom in the simulator by writing one file::

    name = "my-phantom"                # optional (default: the file's stem)

    [layer]                            # the silicone body, bonded to a rigid base
    size_mm = [100.0, 100.0]           # footprint (x, y)
    thickness_mm = 20.0
    modulus_kpa = 50.0                 # small-strain Young's modulus
    nonlinearity = 0.0                 # strain stiffening: k(d) = k0 (1 + nonlinearity d / h)

    [placement]                        # optional: how inclusions without centre_mm are placed
    half_mm = 22.0                     # uniformly in [-half, half]^2 ...
    min_separation_mm = 22.0           # ... at least this far from every other inclusion
    shuffle = false                    # permute which inclusion gets which random centre

    [[inclusion]]                      # any number (0 is a healthy phantom)
    id = "T1"                          # optional (default I1, I2, ...)
    kind = "benign"                    # benign | malignant (ground truth only)
    material = "silicone"              # free text for the ground truth
    center_mm = [10.0, -5.0]           # optional: random per seed (see [placement]) if absent
    depth_mm = 7.0                     # depth of the centre below the surface
    radius_mm = 5.0                    # mean radius
    modulus_kpa = 300.0
    boundary_width_mm = 0.05           # graded boundary width (small = distinct)
    outline = [[3, 0.08, 0.0]]         # radial harmonics [order, rel. amplitude, phase rad]
    # or random per seed: outline = { orders = [3, 5, 7], amplitude = [0.05, 0.1] }
    surface_roughness = 0.0            # relative unevenness of the top surface, [0, 0.5)
    surface_phase_rad = 0.0            # optional: random per seed if absent
    severity_rank = 1                  # optional: 1 = least severe

    [[fiducial]]                       # registration markers: rigid beads at design positions
    center_mm = [42.0, 0.0]            # outside the palpated area
    depth_mm = 1.5                     # optional (1.5), centre depth
    radius_mm = 1.5                    # optional (1.5)
    modulus_kpa = 3.5e6                # optional (rigid: PLA / steel)

Every value is checked; a bad one raises :class:`~shared.errors.ConfigError` naming the file,
the inclusion and the field. The random draws happen in a fixed order (centres, shuffle,
then per inclusion its outline amplitudes and phases), so a file and a seed always give the
same phantom.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from remote_site.phantom.phantom import Phantom, SensorPad, SiliconeLayer
from remote_site.phantom.tumor import FIDUCIAL, TUMOR_KINDS, Tumor
from shared.errors import ConfigError

__all__ = ["load_phantom", "phantom_from_dict", "read_phantom_file", "resolve_phantom",
           "scene_file", "shipped_scene_names"]

_TOP_KEYS = {"name", "layer", "placement", "inclusion", "fiducial"}
_FIDUCIAL_KEYS = {"id", "center_mm", "depth_mm", "radius_mm", "modulus_kpa"}
_LAYER_KEYS = {"size_mm", "thickness_mm", "modulus_kpa", "nonlinearity"}
_PLACEMENT_KEYS = {"half_mm", "min_separation_mm", "shuffle"}
_INCLUSION_KEYS = {"id", "kind", "material", "center_mm", "depth_mm", "radius_mm",
                   "modulus_kpa", "boundary_width_mm", "outline", "surface_roughness",
                   "surface_phase_rad", "severity_rank"}


class _Fields:
    """Typed access to one TOML table with errors that say where."""

    def __init__(self, table: Any, where: str, allowed: set[str]) -> None:
        if not isinstance(table, Mapping):
            raise ConfigError(f"{where} must be a table, got {type(table).__name__}")
        unknown = sorted(set(table) - allowed)
        if unknown:
            raise ConfigError(f"{where}: unknown field(s) {unknown}; allowed: {sorted(allowed)}")
        self.table = table
        self.where = where

    def has(self, key: str) -> bool:
        return key in self.table

    def number(self, key: str, default: float | None = None, *, low: float | None = None,
               low_open: bool = False, high: float | None = None,
               high_open: bool = False) -> float:
        if key not in self.table:
            if default is None:
                raise ConfigError(f"{self.where}: missing required field {key!r}")
            return default
        value = self.table[key]
        if isinstance(value, bool) or not isinstance(value, int | float) \
                or not math.isfinite(value):
            raise ConfigError(f"{self.where}: {key} must be a finite number, got {value!r}")
        v = float(value)
        if low is not None and (v <= low if low_open else v < low):
            raise ConfigError(f"{self.where}: {key} must be {'>' if low_open else '>='} "
                              f"{low:g}, got {v:g}")
        if high is not None and (v >= high if high_open else v > high):
            raise ConfigError(f"{self.where}: {key} must be {'<' if high_open else '<='} "
                              f"{high:g}, got {v:g}")
        return v

    def pair(self, key: str, *, positive: bool) -> tuple[float, float] | None:
        if key not in self.table:
            return None
        value = self.table[key]
        ok = (isinstance(value, list) and len(value) == 2
              and all(isinstance(v, int | float) and not isinstance(v, bool)
                      and math.isfinite(v) and (v > 0 or not positive) for v in value))
        if not ok:
            kind = "positive " if positive else ""
            raise ConfigError(f"{self.where}: {key} must be two finite {kind}numbers [x, y], "
                              f"got {value!r}")
        return float(value[0]), float(value[1])

    def text(self, key: str, default: str | None = None) -> str:
        if key not in self.table:
            if default is None:
                raise ConfigError(f"{self.where}: missing required field {key!r}")
            return default
        value = self.table[key]
        if not isinstance(value, str) or not value.strip():
            raise ConfigError(f"{self.where}: {key} must be a non-empty string, got {value!r}")
        return value

    def flag(self, key: str) -> bool:
        value = self.table.get(key, False)
        if not isinstance(value, bool):
            raise ConfigError(f"{self.where}: {key} must be true or false, got {value!r}")
        return value


def _place(rng: np.random.Generator, count: int, min_separation_mm: float, half_mm: float,
           fixed: list[tuple[float, float]], where: str,
           tries: int = 10_000) -> list[tuple[float, float]]:
    points: list[tuple[float, float]] = []
    if count == 0:
        return points
    for _ in range(tries):
        p = rng.uniform(-half_mm, half_mm, size=2)
        if all(math.dist(p, q) >= min_separation_mm for q in [*fixed, *points]):
            points.append((float(p[0]), float(p[1])))
            if len(points) == count:
                return points
    raise ConfigError(f"{where}: could not place {count} inclusions {min_separation_mm:g} mm apart "
                      f"within +-{half_mm:g} mm")


def _outline(f: _Fields, rng: np.random.Generator, rough: bool
             ) -> tuple[tuple[tuple[int, float, float], ...], float | None]:
    """Outline harmonics and, when drawn with them, the surface phase."""
    spec = f.table.get("outline", [])
    if isinstance(spec, Mapping):
        g = _Fields(spec, f"{f.where}: outline", {"orders", "amplitude"})
        orders = spec.get("orders")
        if not (isinstance(orders, list) and orders
                and all(isinstance(o, int) and not isinstance(o, bool) and o >= 1
                        for o in orders)):
            raise ConfigError(f"{g.where}: orders must be a list of integers >= 1, "
                              f"got {orders!r}")
        amp = g.pair("amplitude", positive=False)
        if amp is None or not 0 <= amp[0] <= amp[1]:
            raise ConfigError(f"{g.where}: amplitude must be [low, high] with "
                              f"0 <= low <= high, got {spec.get('amplitude')!r}")
        amps = rng.uniform(amp[0], amp[1], size=len(orders))
        phases = rng.uniform(0.0, 2 * math.pi, size=len(orders) + int(rough))
        harmonics = tuple((int(o), float(a), float(p))
                          for o, a, p in zip(orders, amps, phases, strict=False))
        return harmonics, float(phases[-1]) if rough else None
    if not isinstance(spec, list):
        raise ConfigError(f"{f.where}: outline must be a list of [order, amplitude, phase] "
                          f"or a table {{orders, amplitude}}, got {spec!r}")
    harmonics_list = []
    for h in spec:
        ok = (isinstance(h, list) and len(h) == 3 and isinstance(h[0], int)
              and not isinstance(h[0], bool) and h[0] >= 1
              and all(isinstance(v, int | float) and not isinstance(v, bool)
                      and math.isfinite(v) for v in h[1:]))
        if not ok:
            raise ConfigError(f"{f.where}: each outline harmonic must be [order >= 1, "
                              f"amplitude, phase_rad], got {h!r}")
        harmonics_list.append((int(h[0]), float(h[1]), float(h[2])))
    return tuple(harmonics_list), None


def phantom_from_dict(data: Mapping[str, Any], seed: int = 0, *, source: str = "phantom",
                      pad: SensorPad | None = None, default_name: str = "custom") -> Phantom:
    """Build a phantom from the parsed TOML (see the module docstring).

    Args:
        data: the parsed file.
        seed: seed of the random parts (placement, shuffle, outlines).
        source: named in error messages (the file path).
        pad: the sensor pad (default :class:`SensorPad`).
        default_name: the name when the file gives none.

    Raises:
        ConfigError: a missing, unknown or invalid field (the message says which).
    """
    top = _Fields(data, f"phantom file {source}", _TOP_KEYS)
    lf = _Fields(data.get("layer"), f"{top.where}: [layer]", _LAYER_KEYS) \
        if "layer" in data else None
    if lf is None:
        raise ConfigError(f"{top.where}: missing the [layer] table")
    size = lf.pair("size_mm", positive=True)
    if size is None:
        raise ConfigError(f"{lf.where}: missing required field 'size_mm'")
    layer = SiliconeLayer(size_mm=size, thickness_mm=lf.number("thickness_mm", low=0,
                                                               low_open=True),
                          modulus_kpa=lf.number("modulus_kpa", low=0, low_open=True),
                          nonlinearity=lf.number("nonlinearity", 0.0, low=0, high=20))
    pf = _Fields(data.get("placement", {}), f"{top.where}: [placement]", _PLACEMENT_KEYS)
    half = pf.number("half_mm", min(size) / 2 - 5.0 if min(size) > 10 else min(size) / 2,
                     low=0, low_open=True)
    if half > min(size) / 2:
        raise ConfigError(f"{pf.where}: half_mm {half:g} reaches beyond the layer "
                          f"(half size {min(size) / 2:g} mm)")
    separation = pf.number("min_separation_mm", 0.0, low=0)
    shuffle = pf.flag("shuffle")
    raw = data.get("inclusion", [])
    if not isinstance(raw, list):
        raise ConfigError(f"{top.where}: inclusion must be an array of tables ([[inclusion]])")
    fields = [_Fields(t, f"{top.where}: inclusion {i + 1}", _INCLUSION_KEYS)
              for i, t in enumerate(raw)]
    rng = np.random.default_rng(seed)
    centres: list[tuple[float, float] | None] = [f.pair("center_mm", positive=False)
                                                 for f in fields]
    fixed = [c for c in centres if c is not None]
    free = iter(_place(rng, sum(c is None for c in centres), separation, half, fixed,
                       pf.where))
    slots = [c if c is not None else next(free) for c in centres]
    order = rng.permutation(len(fields)) if shuffle else np.arange(len(fields))
    tumors = []
    ids: set[str] = set()
    for slot, k in enumerate(order):
        f = fields[int(k)]
        tid = f.text("id", f"I{int(k) + 1}")
        if tid in ids:
            raise ConfigError(f"{f.where}: duplicate id {tid!r}")
        ids.add(tid)
        kind = f.text("kind")
        if kind not in TUMOR_KINDS:
            raise ConfigError(f"{f.where}: kind must be one of {sorted(TUMOR_KINDS)}, "
                              f"got {kind!r}")
        rough = f.number("surface_roughness", 0.0, low=0, high=0.5, high_open=True)
        harmonics, drawn_phase = _outline(f, rng, rough > 0)
        if sum(abs(a) for _, a, _ in harmonics) >= 0.5:
            raise ConfigError(f"{f.where}: outline amplitudes must sum to < 0.5")
        if f.has("surface_phase_rad"):
            phase = f.number("surface_phase_rad")
        elif drawn_phase is not None:
            phase = drawn_phase
        else:
            phase = float(rng.uniform(0.0, 2 * math.pi)) if rough > 0 else 0.0
        rank = f.table.get("severity_rank")
        if rank is not None and (isinstance(rank, bool) or not isinstance(rank, int)
                                 or rank < 1):
            raise ConfigError(f"{f.where}: severity_rank must be an integer >= 1, "
                              f"got {rank!r}")
        centre = slots[slot] if shuffle else slots[int(k)]
        if abs(centre[0]) > size[0] / 2 or abs(centre[1]) > size[1] / 2:
            raise ConfigError(f"{f.where}: center_mm {list(centre)} lies outside the layer "
                              f"footprint {list(size)}")
        depth = f.number("depth_mm", low=0)
        if depth > layer.thickness_mm:
            raise ConfigError(f"{f.where}: depth_mm {depth:g} is deeper than the layer "
                              f"({layer.thickness_mm:g} mm)")
        tumors.append(Tumor(
            tid, kind, centre, depth_mm=depth,
            radius_mm=f.number("radius_mm", low=0, low_open=True),
            modulus_kpa=f.number("modulus_kpa", low=0, low_open=True),
            material=f.text("material", "silicone"),
            boundary_width_mm=f.number("boundary_width_mm", 0.05, low=0, low_open=True),
            harmonics=harmonics, surface_roughness=rough, surface_phase_rad=phase,
            severity_rank=rank))
    name = top.text("name", default_name)
    return Phantom(layer=layer, tumors=tuple(tumors), fiducials=_fiducials(data, top.where, layer),
                   pad=pad or SensorPad(), name=name, seed=seed)


def _fiducials(data: Mapping[str, Any], where: str, layer: SiliconeLayer) -> tuple[Tumor, ...]:
    raw = data.get("fiducial", [])
    if not isinstance(raw, list):
        raise ConfigError(f"{where}: fiducial must be an array of tables ([[fiducial]])")
    out = []
    for i, table in enumerate(raw):
        f = _Fields(table, f"{where}: fiducial {i + 1}", _FIDUCIAL_KEYS)
        centre = f.pair("center_mm", positive=False)
        if centre is None:
            raise ConfigError(f"{f.where}: missing required field 'center_mm'")
        if abs(centre[0]) > layer.size_mm[0] / 2 or abs(centre[1]) > layer.size_mm[1] / 2:
            raise ConfigError(f"{f.where}: center_mm {list(centre)} lies outside the layer")
        depth = f.number("depth_mm", 1.5, low=0, high=layer.thickness_mm)
        out.append(Tumor(f.text("id", f"F{i + 1}"), FIDUCIAL, centre, depth_mm=depth,
                         radius_mm=f.number("radius_mm", 1.5, low=0, low_open=True),
                         modulus_kpa=f.number("modulus_kpa", 3.5e6, low=0, low_open=True),
                         material="fiducial"))
    return tuple(out)


def read_phantom_file(path: str | Path) -> dict[str, Any]:
    """Parse a phantom TOML file.

    Raises:
        ConfigError: the file cannot be read or is not TOML.
    """
    p = Path(path)
    try:
        return tomllib.loads(p.read_text())
    except OSError as err:
        raise ConfigError(f"cannot read phantom file {p}: {err}") from err
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise ConfigError(f"phantom file {p} is not valid TOML: {err}") from err


def load_phantom(path: str | Path, seed: int = 0, *, pad: SensorPad | None = None) -> Phantom:
    """Read and validate a phantom file.

    Raises:
        ConfigError: unreadable file or an invalid field.
    """
    p = Path(path)
    return phantom_from_dict(read_phantom_file(p), seed, source=str(p), pad=pad,
                             default_name=p.stem)


def _scenes_dir() -> Path:
    return Path(str(resources.files("remote_site.phantom") / "data" / "scenes"))


def shipped_scene_names() -> list[str]:
    """Names of the phantom files shipped with the package (the named scenes)."""
    return sorted(p.stem for p in _scenes_dir().glob("*.toml"))


def scene_file(name: str) -> Path:
    """The shipped file of a named scene.

    Raises:
        ConfigError: no such scene.
    """
    path = _scenes_dir() / f"{name}.toml"
    if not path.is_file():
        raise ConfigError(f"unknown phantom scene {name!r}; known: {shipped_scene_names()} "
                          "(or give a FILE.toml)")
    return path


def resolve_phantom(spec: str, seed: int = 0) -> Phantom:
    """A phantom from ``--phantom``: a shipped scene name or a path to a ``.toml`` file.

    Raises:
        ConfigError: unknown scene, unreadable file or an invalid field.
    """
    if spec.endswith(".toml") or "/" in spec or Path(spec).is_file():
        return load_phantom(spec, seed)
    return load_phantom(scene_file(spec), seed)
