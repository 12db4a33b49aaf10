"""Operator motion sources: where the simulated hand puts the platform, as a function of time.

Every source is a deterministic function ``t_s -> (x, y, z)`` in platform millimetres (see
:mod:`local_site.platform.kinematics` for the frame), behind one interface,
:class:`MotionSource`. The simulated encoder board samples it at its own rate; tests and the
demo can sample it directly, vectorised, with :meth:`MotionSource.sample`.

- :class:`RasterSweep`: the demo's scripted operator, a boustrophedon sweep over a rectangle
  with presses (descend, dwell, rise) at regular spacing along each line.
- :class:`RandomWalk`: a seeded, workspace-bounded random walk (Ornstein-Uhlenbeck velocity).
- :class:`ReplayMotion`: replay of a recorded trajectory from CSV or ``.npz`` (t, x, y, z).
- :class:`HoldMotion`: stands still (useful in tests).

:func:`make_motion` picks one by name (``raster``, ``random``, ``hold``) or by file path.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from local_site.platform.kinematics import DEFAULT_WORKSPACE_MM
from shared.errors import ConfigError, InputDataError

__all__ = [
    "HoldMotion",
    "MotionSource",
    "RandomWalk",
    "RasterSweep",
    "RasterSweepParams",
    "ReplayMotion",
    "WaypointMotion",
    "make_motion",
]

Vec3 = tuple[float, float, float]


class MotionSource(ABC):
    """Position of the platform against time (seconds since the source started)."""

    #: length of the motion in seconds; None when endless. Sources hold or loop past it.
    duration_s: float | None = None

    @abstractmethod
    def sample(self, t_s: np.ndarray) -> np.ndarray:
        """Positions at the times ``t_s`` (shape (N,)); returns shape (N, 3), mm."""

    def position_mm(self, t_s: float) -> Vec3:
        """Position at one time ``t_s`` (seconds), mm."""
        x, y, z = self.sample(np.array([float(t_s)]))[0]
        return (float(x), float(y), float(z))


class WaypointMotion(MotionSource):
    """Piecewise-linear motion through timed waypoints.

    Args:
        times_s: strictly increasing waypoint times, shape (N,), N >= 1, starting at >= 0.
        positions_mm: waypoint positions, shape (N, 3).
        loop: repeat after the last waypoint (else hold the last position).

    Raises:
        InputDataError: shapes disagree, times not increasing, or values not finite.
    """

    def __init__(self, times_s: np.ndarray, positions_mm: np.ndarray, *,
                 loop: bool = False) -> None:
        times = np.asarray(times_s, dtype=float)
        pos = np.asarray(positions_mm, dtype=float)
        if times.ndim != 1 or times.size == 0 or pos.shape != (times.size, 3):
            raise InputDataError(f"waypoints need times (N,) and positions (N, 3); got "
                                 f"{times.shape} and {pos.shape}")
        if not (np.all(np.isfinite(times)) and np.all(np.isfinite(pos))):
            raise InputDataError("waypoint times and positions must be finite")
        if times.size > 1 and not np.all(np.diff(times) > 0):
            raise InputDataError("waypoint times must be strictly increasing")
        self._times = times - times[0]
        self._pos = pos
        self._loop = loop and times.size > 1
        self.duration_s = float(self._times[-1])

    @property
    def waypoints(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of (times_s, positions_mm)."""
        return self._times.copy(), self._pos.copy()

    def sample(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        if self._loop and self.duration_s:
            t = np.mod(t, self.duration_s)
        out = np.empty((t.size, 3))
        for axis in range(3):
            out[:, axis] = np.interp(t, self._times, self._pos[:, axis])
        return out


class HoldMotion(WaypointMotion):
    """The platform stays at ``position_mm``."""

    def __init__(self, position_mm: Vec3 = (30.0, 30.0, 100.0)) -> None:
        super().__init__(np.zeros(1), np.asarray([position_mm], dtype=float))


@dataclass(frozen=True, slots=True)
class RasterSweepParams:
    """The scripted operator's sweep.

    Attributes:
        origin_mm: (x, y) corner where the sweep starts.
        size_mm: (width along x, height along y) of the swept rectangle.
        line_spacing_mm: y step between successive lines.
        speed_mm_s: travel speed along and between lines.
        hover_z_mm: z while sliding.
        press_depth_mm: how far z goes down at each press (0: no presses).
        press_spacing_mm: distance along a line between presses (0: no presses).
        press_speed_mm_s: z speed while pressing and releasing.
        dwell_s: time held at the bottom of a press.
        start_pause_s: time held at the start before moving.
        loop: sweep again from the start after returning there.
    """

    origin_mm: tuple[float, float] = (10.0, 10.0)
    size_mm: tuple[float, float] = (40.0, 40.0)
    line_spacing_mm: float = 5.0
    speed_mm_s: float = 20.0
    hover_z_mm: float = 100.0
    press_depth_mm: float = 3.0
    press_spacing_mm: float = 10.0
    press_speed_mm_s: float = 15.0
    dwell_s: float = 0.3
    start_pause_s: float = 0.5
    loop: bool = True

    def validate(self) -> None:
        """Raise ConfigError unless every parameter is finite and in range."""
        values = [*self.origin_mm, *self.size_mm, self.line_spacing_mm, self.speed_mm_s,
                  self.hover_z_mm, self.press_depth_mm, self.press_spacing_mm,
                  self.press_speed_mm_s, self.dwell_s, self.start_pause_s]
        if not all(math.isfinite(v) for v in values):
            raise ConfigError(f"raster sweep parameters must be finite: {self}")
        if min(self.size_mm) < 0 or min(values) < 0:
            raise ConfigError(f"raster sweep parameters must be >= 0: {self}")
        if self.line_spacing_mm <= 0 or self.speed_mm_s <= 0 or self.press_speed_mm_s <= 0:
            raise ConfigError("line_spacing_mm, speed_mm_s and press_speed_mm_s must be > 0")
        if self.press_depth_mm > self.hover_z_mm:
            raise ConfigError("press_depth_mm must not exceed hover_z_mm (z stays >= 0)")


class RasterSweep(WaypointMotion):
    """Boustrophedon sweep with presses: the demo's scripted operator.

    Lines run along x, from ``origin_mm`` to ``origin + size``, stepping y by
    ``line_spacing_mm`` and reversing direction on each line. Along every line a press
    happens each ``press_spacing_mm`` (not at the line start): z goes down by
    ``press_depth_mm`` at ``press_speed_mm_s``, dwells ``dwell_s`` and comes back. After the
    last line the operator slides back to the start (and loops if ``loop``).

    Args:
        params: the sweep; defaults to :class:`RasterSweepParams`.
        **overrides: fields of :class:`RasterSweepParams` to override.
    """

    def __init__(self, params: RasterSweepParams | None = None, **overrides: object) -> None:
        base = params or RasterSweepParams()
        if overrides:
            fields = {f: getattr(base, f) for f in base.__slots__}
            unknown = set(overrides) - set(fields)
            if unknown:
                raise ConfigError(f"unknown raster sweep parameter(s): {sorted(unknown)}")
            fields.update(overrides)
            base = RasterSweepParams(**fields)
        base.validate()
        self.params = base
        times, positions = self._build(base)
        super().__init__(times, positions, loop=base.loop)

    @staticmethod
    def _build(p: RasterSweepParams) -> tuple[np.ndarray, np.ndarray]:
        x0, y0 = p.origin_mm
        width, height = p.size_mm
        z_hover = p.hover_z_mm
        t = 0.0
        points: list[tuple[float, float, float, float]] = [(t, x0, y0, z_hover)]

        def go(x: float, y: float, z: float, speed: float) -> None:
            nonlocal t
            _, px, py, pz = points[-1]
            dist = math.dist((px, py, pz), (x, y, z))
            if dist > 0:
                t += dist / speed
                points.append((t, x, y, z))

        def hold(duration_s: float) -> None:
            nonlocal t
            if duration_s > 0:
                _, px, py, pz = points[-1]
                t += duration_s
                points.append((t, px, py, pz))

        hold(p.start_pause_s)
        n_lines = math.floor(height / p.line_spacing_mm + 1e-9) + 1
        pressing = p.press_depth_mm > 0 and p.press_spacing_mm > 0
        for line in range(n_lines):
            y = y0 + line * p.line_spacing_mm
            forward = line % 2 == 0
            if line:
                go(points[-1][1], y, z_hover, p.speed_mm_s)
            stops = []
            if pressing:
                n_press = math.floor(width / p.press_spacing_mm + 1e-9)
                stops = [k * p.press_spacing_mm for k in range(1, n_press + 1)]
            for d in stops:
                x = x0 + d if forward else x0 + width - d
                go(x, y, z_hover, p.speed_mm_s)
                go(x, y, z_hover - p.press_depth_mm, p.press_speed_mm_s)
                hold(p.dwell_s)
                go(x, y, z_hover, p.press_speed_mm_s)
            go(x0 + width if forward else x0, y, z_hover, p.speed_mm_s)
        go(x0, y0, z_hover, p.speed_mm_s)
        arr = np.asarray(points, dtype=float)
        return arr[:, 0], arr[:, 1:]


class RandomWalk(MotionSource):
    """Seeded random walk: Ornstein-Uhlenbeck velocity, reflected at the workspace bounds.

    Deterministic for a given seed, whatever the order or density of queries: the path is
    generated on a fixed grid (``step_s``) in chunks, as far as queries need.

    Args:
        seed: random seed.
        speed_mm_s: RMS speed per axis in x and y (z uses ``z_speed_mm_s``).
        z_speed_mm_s: RMS speed on z.
        correlation_s: velocity correlation time.
        start_mm: starting position (default: centre of the workspace, z at 100 mm).
        workspace_mm: bounds; the walk stays within [margin, bound - margin] (a step longer
            than that room, from a high speed or a wide margin, is folded back in).
        margin_mm: distance kept from each bound.
        step_s: generation grid.
        duration_s: the walk's length (s): it holds its position from then on, so a run can
            end with it (``--until-motion-done``); None (default): endless.
    """

    _CHUNK = 4096

    def __init__(self, seed: int = 0, *, speed_mm_s: float = 15.0, z_speed_mm_s: float = 3.0,
                 correlation_s: float = 0.5, start_mm: Vec3 | None = None,
                 workspace_mm: Vec3 = DEFAULT_WORKSPACE_MM, margin_mm: float = 2.0,
                 step_s: float = 0.005, duration_s: float | None = None) -> None:
        values = (speed_mm_s, z_speed_mm_s, correlation_s, margin_mm, step_s, *workspace_mm)
        if not all(math.isfinite(v) and v >= 0 for v in values) or step_s <= 0 \
                or correlation_s <= 0:
            raise ConfigError("random walk parameters must be finite, >= 0 (step and "
                              "correlation > 0)")
        if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
            raise ConfigError(f"random walk duration_s must be finite and > 0 (or None: "
                              f"endless), got {duration_s!r}")
        self.duration_s = None if duration_s is None else float(duration_s)
        self._rng = np.random.default_rng(seed)
        self._lo = np.full(3, margin_mm)
        self._hi = np.asarray(workspace_mm, dtype=float) - margin_mm
        if np.any(self._hi <= self._lo):
            raise ConfigError("random walk margin leaves no room in the workspace")
        start = np.asarray(start_mm if start_mm is not None
                           else (workspace_mm[0] / 2, workspace_mm[1] / 2,
                                 min(100.0, workspace_mm[2] / 2)), dtype=float)
        self._step_s = step_s
        self._decay = math.exp(-step_s / correlation_s)
        sigma = np.array([speed_mm_s, speed_mm_s, z_speed_mm_s])
        self._kick = sigma * math.sqrt(1 - self._decay**2)
        self._vel = np.zeros(3)
        self._pos = [np.clip(start, self._lo, self._hi)[None, :]]
        self._n = 1

    def _extend(self, n_needed: int) -> None:
        # one step per grid point, in plain floats per axis (about 20x faster than the same
        # arithmetic on 3-element arrays, with the same IEEE operations in the same order:
        # the same finite values)
        decay, step = self._decay, self._step_s
        lo, hi = self._lo.tolist(), self._hi.tolist()
        while self._n < n_needed:
            noise = self._rng.standard_normal((self._CHUNK, 3))
            chunk = np.empty((self._CHUNK, 3))
            last = self._pos[-1][-1]
            vel = self._vel.tolist()
            for a in range(3):
                p, v, kick, low, high = float(last[a]), vel[a], float(self._kick[a]), lo[a], hi[a]
                column = noise[:, a].tolist()
                out = [0.0] * self._CHUNK
                for i in range(self._CHUNK):
                    v = decay * v + kick * column[i]
                    p = p + v * step
                    if p < low:  # reflected at the bound, the velocity turned
                        p, v = 2 * low - p, -v
                    elif p > high:
                        p, v = 2 * high - p, -v
                    if not low <= p <= high:  # a step longer than the room: fold it in
                        p, v = _fold(p, v, low, high)
                    out[i] = p
                vel[a] = v
                chunk[:, a] = out
            self._vel = np.array(vel)
            self._pos.append(chunk)
            self._n += self._CHUNK
        if len(self._pos) > 1:
            self._pos = [np.concatenate(self._pos)]

    def sample(self, t_s: np.ndarray) -> np.ndarray:
        t = np.clip(np.asarray(t_s, dtype=float), 0.0, None)
        if not np.all(np.isfinite(t)):
            raise InputDataError("random walk queried at a non-finite time")
        if self.duration_s is not None:  # held at its end
            t = np.minimum(t, self.duration_s)
        idx = t / self._step_s
        self._extend(int(np.max(idx, initial=0.0)) + 2)
        path = self._pos[0]
        # linear between grid points (np.interp's arithmetic for finite paths, without its
        # O(n) grid)
        j = np.floor(idx).astype(np.intp)
        frac = (idx - j)[..., None]
        left = path[j]
        return (path[j + 1] - left) * frac + left


def _fold(p: float, v: float, low: float, high: float) -> tuple[float, float]:
    """``p`` reflected at ``low`` and ``high`` as often as it takes to lie between them, and
    ``v`` turned once per reflection (a triangle wave of period twice the room)."""
    room = high - low
    q = (p - low) % (2 * room)
    if q > room:
        return low + (2 * room - q), -v
    return low + q, v


class ReplayMotion(WaypointMotion):
    """Replay of a recorded trajectory: columns t (s), x, y, z (mm).

    CSV: a header line naming ``t,x,y,z`` (any order; extra columns ignored) and one row per
    sample. NPZ: arrays ``t``, ``x``, ``y``, ``z``. Times are shifted to start at 0.

    Args:
        path: the CSV or ``.npz`` file.
        loop: replay again after the end (else hold the last position).

    Raises:
        InputDataError: missing columns, unreadable file, non-finite or unsorted data.
    """

    def __init__(self, path: str | Path, *, loop: bool = False) -> None:
        self.path = Path(path)
        t, xyz = self._load(self.path)
        super().__init__(t, xyz, loop=loop)

    @staticmethod
    def _load(path: Path) -> tuple[np.ndarray, np.ndarray]:
        try:
            if path.suffix == ".npz":
                with np.load(path) as data:
                    cols = {k: np.asarray(data[k], dtype=float) for k in ("t", "x", "y", "z")}
            else:
                table = np.genfromtxt(path, delimiter=",", names=True, dtype=float)
                names = table.dtype.names or ()
                cols = {k: np.atleast_1d(table[k]) for k in ("t", "x", "y", "z") if k in names}
                if len(cols) != 4:
                    raise InputDataError(f"{path}: CSV header must name t,x,y,z; got {names}")
        except (OSError, KeyError, ValueError) as err:
            raise InputDataError(f"cannot read trajectory {path}: {err}") from err
        return cols["t"], np.stack([cols["x"], cols["y"], cols["z"]], axis=1)

    @staticmethod
    def save(path: str | Path, times_s: np.ndarray, positions_mm: np.ndarray) -> None:
        """Write a trajectory in the format :class:`ReplayMotion` reads (by suffix)."""
        path = Path(path)
        t = np.asarray(times_s, dtype=float)
        pos = np.asarray(positions_mm, dtype=float)
        if path.suffix == ".npz":
            np.savez(path, t=t, x=pos[:, 0], y=pos[:, 1], z=pos[:, 2])
        else:
            np.savetxt(path, np.column_stack([t, pos]), delimiter=",", header="t,x,y,z",
                       comments="", fmt="%.6f")


def make_motion(spec: str | MotionSource = "raster", **options: object) -> MotionSource:
    """Build a motion source by name or file path.

    Args:
        spec: ``raster`` (:class:`RasterSweep`), ``random`` (:class:`RandomWalk`), ``hold``
            (:class:`HoldMotion`), a path to a ``.csv``/``.npz`` (:class:`ReplayMotion`), or a
            ready :class:`MotionSource` (returned as is).
        **options: keyword arguments of the chosen class.

    Raises:
        ConfigError: unknown name and no such file.
    """
    if isinstance(spec, MotionSource):
        return spec
    name = spec.strip().lower()
    if name == "raster":
        return RasterSweep(**options)  # type: ignore[arg-type]
    if name == "random":
        return RandomWalk(**options)  # type: ignore[arg-type]
    if name == "hold":
        return HoldMotion(**options)  # type: ignore[arg-type]
    if Path(spec).suffix in (".csv", ".npz"):
        return ReplayMotion(spec, **options)  # type: ignore[arg-type]
    raise ConfigError(f"unknown motion source {spec!r}: use raster, random, hold or a "
                      f".csv/.npz trajectory file")
