"""``--motion SPEC``: the scripted operator of the simulated platform, in one string.

Simulator code (beside :mod:`local_site.platform.motion`): the station passes the string to
the platform backend, and only the ``sim`` backend accepts it.

Grammar: ``NAME[:key=value,...]`` or a trajectory file path (``.csv`` / ``.npz``, replayed by
:class:`~local_site.platform.motion.ReplayMotion`). Names and keys (every key of the
underlying class is also accepted under its full name):

``raster`` (:class:`~local_site.platform.motion.RasterSweep`, boustrophedon with presses)
    ``x0``, ``x1``, ``y0``, ``y1`` swept rectangle (mm; defaults from the class:
    x 10..50, y 10..50), ``spacing`` line spacing (mm), ``speed`` (mm/s), ``z`` hover height
    (mm), ``press_depth`` (mm, 0: no presses), ``press_every`` distance between presses
    along a line (mm, 0: none), ``press_speed`` (mm/s), ``dwell`` (s), ``pause`` start
    pause (s), ``loop`` (0/1).
    Example: ``raster:x0=5,x1=55,y0=5,y1=55,spacing=2,speed=20,press_depth=3,press_every=4``
``random`` (:class:`~local_site.platform.motion.RandomWalk`)
    ``seed`` (int), ``speed``, ``z_speed`` (mm/s RMS), ``correlation`` (s), ``x``, ``y``,
    ``z`` start (mm), ``margin`` (mm), ``step`` (s), ``duration`` (s: the walk then holds
    its position, so ``--until-motion-done`` can end a run; default endless).
``hold`` (:class:`~local_site.platform.motion.HoldMotion`)
    ``x``, ``y``, ``z`` (mm; default 30, 30, 100).
``replay``
    ``file`` (path), ``loop`` (0/1). A bare ``path.csv`` / ``path.npz`` is the same.

The motion classes are used as they are; this module only parses the string.
"""

from __future__ import annotations

import math
from pathlib import Path

from local_site.platform.motion import (
    HoldMotion,
    MotionSource,
    RandomWalk,
    RasterSweep,
    RasterSweepParams,
    ReplayMotion,
)
from shared.errors import ConfigError

__all__ = ["MOTION_NAMES", "parse_motion_spec", "split_motion_spec"]

MOTION_NAMES = ("raster", "random", "hold", "replay")

_RASTER_ALIASES = {"spacing": "line_spacing_mm", "speed": "speed_mm_s", "z": "hover_z_mm",
                   "hover_z": "hover_z_mm", "press_depth": "press_depth_mm",
                   "press_every": "press_spacing_mm", "press_speed": "press_speed_mm_s",
                   "dwell": "dwell_s", "pause": "start_pause_s"}
_RANDOM_ALIASES = {"speed": "speed_mm_s", "z_speed": "z_speed_mm_s",
                   "correlation": "correlation_s", "margin": "margin_mm", "step": "step_s",
                   "duration": "duration_s"}
_BOOL_WORDS = {"1": True, "true": True, "yes": True, "0": False, "false": False, "no": False}


def split_motion_spec(spec: str) -> tuple[str, dict[str, str]]:
    """Split ``"name:key=value,..."`` into the lower-case name and raw string values.

    Raises:
        ConfigError: an item that is not ``key=value`` or a key given twice.
    """
    name, _, rest = spec.strip().partition(":")
    params: dict[str, str] = {}
    for item in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise ConfigError(f"motion spec {spec!r}: {item!r} is not key=value")
        if key in params:
            raise ConfigError(f"motion spec {spec!r}: {key!r} given twice")
        params[key] = value.strip()
    return name.strip().lower(), params


def _number(spec: str, key: str, value: str) -> float:
    try:
        number = float(value)
    except ValueError as err:
        raise ConfigError(f"motion spec {spec!r}: {key}={value!r} is not a number") from err
    if not math.isfinite(number):  # (a NaN start slipped through the random walk's checks)
        raise ConfigError(f"motion spec {spec!r}: {key}={value!r} is not a finite number")
    return number


def _integer(spec: str, key: str, value: str) -> int:
    try:
        number = int(value)
    except ValueError as err:
        raise ConfigError(f"motion spec {spec!r}: {key}={value!r} is not an integer") from err
    if number < 0:  # (numpy's seeds: a bare ValueError from deep inside before)
        raise ConfigError(f"motion spec {spec!r}: {key}={value!r} must be >= 0")
    return number


def _boolean(spec: str, key: str, value: str) -> bool:
    try:
        return _BOOL_WORDS[value.lower()]
    except KeyError as err:
        raise ConfigError(f"motion spec {spec!r}: {key}={value!r} is not 0/1") from err


def _raster(spec: str, params: dict[str, str]) -> RasterSweep:
    base = RasterSweepParams()
    (ox, oy), (sx, sy) = base.origin_mm, base.size_mm
    x0 = _number(spec, "x0", params.pop("x0")) if "x0" in params else ox
    y0 = _number(spec, "y0", params.pop("y0")) if "y0" in params else oy
    x1 = _number(spec, "x1", params.pop("x1")) if "x1" in params else x0 + sx
    y1 = _number(spec, "y1", params.pop("y1")) if "y1" in params else y0 + sy
    if x1 < x0 or y1 < y0:
        raise ConfigError(f"motion spec {spec!r}: need x0 <= x1 and y0 <= y1")
    overrides: dict[str, object] = {"origin_mm": (x0, y0), "size_mm": (x1 - x0, y1 - y0)}
    for key, value in params.items():
        field = _RASTER_ALIASES.get(key, key)
        overrides[field] = _boolean(spec, key, value) if field == "loop" \
            else _number(spec, key, value)
    return RasterSweep(**overrides)  # type: ignore[arg-type]


def _random(spec: str, params: dict[str, str]) -> RandomWalk:
    kwargs: dict[str, float] = {}
    seed = 0
    start = [params.pop(k, None) for k in ("x", "y", "z")]
    for key, value in params.items():
        if key == "seed":
            seed = _integer(spec, key, value)
            continue
        kwargs[_RANDOM_ALIASES.get(key, key)] = _number(spec, key, value)
    if any(v is not None for v in start):
        if any(v is None for v in start):
            raise ConfigError(f"motion spec {spec!r}: give all of x, y, z for the start")
        kwargs["start_mm"] = tuple(_number(spec, k, v)  # type: ignore[assignment]
                                   for k, v in zip("xyz", start, strict=True) if v is not None)
    try:
        return RandomWalk(seed, **kwargs)  # type: ignore[arg-type]
    except TypeError as err:
        raise ConfigError(f"motion spec {spec!r}: {err}") from err


def parse_motion_spec(spec: str) -> MotionSource:
    """Build the motion source a ``--motion`` spec names (see the module docstring).

    Args:
        spec: e.g. ``"raster:x0=5,x1=55,spacing=2"``, ``"random:seed=3"``,
            ``"hold:x=30,y=30,z=100"`` or ``"path/to/trajectory.csv"``.

    Returns:
        The motion source, to pass as ``open_platform("sim", motion=...)``.

    Raises:
        ConfigError: unknown name or key, or an invalid value.
        InputDataError: an unreadable trajectory file.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise ConfigError("a motion spec must be a non-empty string")
    if Path(spec.strip()).suffix.lower() in (".csv", ".npz"):
        return ReplayMotion(spec.strip())
    name, params = split_motion_spec(spec)
    try:
        if name == "raster":
            return _raster(spec, params)
        if name == "random":
            return _random(spec, params)
        if name == "hold":
            unknown = sorted(set(params) - {"x", "y", "z"})
            if unknown:
                raise ConfigError(f"motion spec {spec!r}: unknown key(s) {unknown}")
            default = (30.0, 30.0, 100.0)
            pos = tuple(_number(spec, k, params[k]) if k in params else d
                        for k, d in zip("xyz", default, strict=True))
            return HoldMotion(pos)  # type: ignore[arg-type]
        if name == "replay":
            unknown = sorted(set(params) - {"file", "loop"})
            if unknown or "file" not in params:
                raise ConfigError(f"motion spec {spec!r}: replay needs file=PATH [,loop=0/1]")
            loop = _boolean(spec, "loop", params["loop"]) if "loop" in params else False
            return ReplayMotion(params["file"], loop=loop)
    except TypeError as err:
        raise ConfigError(f"motion spec {spec!r}: {err}") from err
    raise ConfigError(f"unknown motion {name!r} in {spec!r}: use one of {', '.join(MOTION_NAMES)} "
                      f"or a .csv/.npz trajectory")
