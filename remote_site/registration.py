"""Arm <-> phantom registration from fiducials felt with the tactile sensor.

A phantom carries small rigid beads (fiducials) just under its surface at positions known by
design, in phantom coordinates, outside the palpated area. Placed on the table by hand, the
phantom sits a few millimetres and degrees away from where the workspace map assumes. The
procedure (:func:`calibrate_with_fiducials`) presses the pad gently where each fiducial
should be (its design position, then where the fiducials already found put it, searching
around that for a phantom shifted and turned by hand), finds the bead in the reconstructed
height map (it pushes the gel in more than the soft tissue around it, :func:`locate_bump`),
and so measures where each fiducial really is in the arm's frame. A least-squares rigid fit
of the plane (:func:`fit_registration`, 2-D Kabsch) gives the registration
``q = R(yaw) a + d`` from arm positions ``a`` to phantom positions ``q``, with its
uncertainty from the fit's residuals:
``cov = s^2 (J^T J)^-1`` with ``s^2`` the residual variance (2n - 3 degrees of freedom) and
``J`` the fit's Jacobian, floored by the per-fiducial localization noise ``sigma_floor_mm``.

The result goes into the workspace map (:meth:`shared.workspace.WorkspaceMap.registered`),
so the arm then goes where the operator means on the real phantom and every tactile frame is
reported where it was really taken.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from remote_site.arm.base import Arm, ArmLimits, ArmReading
from remote_site.arm.safety import SafeArm, SafetyConfig
from remote_site.reconstruction.reconstructor import Reconstructor
from remote_site.sensor.base import TactileSensor
from shared.errors import CalibrationError, DeviceError, InputDataError
from shared.workspace import WorkspaceMap

__all__ = ["MAX_YAW_DEG", "GuardedMotion", "RegistrationEstimate", "SafeMotion",
           "calibrate_with_fiducials", "fit_registration", "guarded", "locate_bump",
           "robust_fit"]


#: the largest turn of a hand-placed phantom the fiducial search covers (the simulated world
#: draws 3 deg sigma; a phantom set down 20 deg askew is searched for, not assumed away)
MAX_YAW_DEG = 20.0


@dataclass(frozen=True)
class RegistrationEstimate:
    """``q_phantom = R(yaw) a_arm + (dx, dy)`` with its uncertainty.

    Attributes:
        dx_mm, dy_mm, yaw_deg: the rigid motion.
        std_dx_mm, std_dy_mm, std_yaw_deg: one-sigma uncertainties.
        residual_rms_mm: rms distance between fitted and measured fiducials.
        fiducials: how many fiducials were used.
        measured_arm_mm: where each fiducial was found (arm frame).
    """

    dx_mm: float
    dy_mm: float
    yaw_deg: float
    std_dx_mm: float
    std_dy_mm: float
    std_yaw_deg: float
    residual_rms_mm: float
    fiducials: int
    measured_arm_mm: tuple[tuple[float, float], ...] = ()

    def arm_to_phantom(self, xy_mm: ArrayLike) -> NDArray[np.float64]:
        """Arm-frame (x, y) point(s) to phantom (x, y)."""
        p = np.asarray(xy_mm, float)
        th = math.radians(self.yaw_deg)
        rot = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        return np.asarray(p @ rot.T + np.array([self.dx_mm, self.dy_mm]), float)

    def phantom_to_arm(self, xy_mm: Sequence[float]) -> tuple[float, float]:
        """Phantom (x, y) to the arm frame: ``a = R(-yaw) (q - d)``."""
        th = math.radians(-self.yaw_deg)
        px, py = float(xy_mm[0]) - self.dx_mm, float(xy_mm[1]) - self.dy_mm
        return (math.cos(th) * px - math.sin(th) * py, math.sin(th) * px + math.cos(th) * py)

    def position_std_mm(self, radius_mm: float) -> float:
        """One-sigma position uncertainty of a point ``radius_mm`` from the origin."""
        return math.sqrt(self.std_dx_mm ** 2 + self.std_dy_mm ** 2
                         + (math.radians(self.std_yaw_deg) * radius_mm) ** 2)

    def workspace_to_arm(self, workspace: WorkspaceMap) -> WorkspaceMap:
        """The platform -> ARM map that makes the arm reach ``workspace``'s phantom points.

        ``a = R(-yaw) (q - d)``: the inverse rigid motion after the designed map.
        """
        shift = self.phantom_to_arm((0.0, 0.0))  # where the phantom origin lies for the arm
        return workspace.registered(shift[0], shift[1], -self.yaw_deg)

    def to_dict(self) -> dict[str, object]:
        """Plain JSON."""
        return {k: (list(map(list, v)) if k == "measured_arm_mm" else v)
                for k, v in self.__dict__.items()}


def fit_registration(arm_xy_mm: ArrayLike, phantom_xy_mm: ArrayLike, *,
                     sigma_floor_mm: float = 0.1) -> RegistrationEstimate:
    """Least-squares rigid motion (rotation + translation) taking arm points to phantom points.

    Args:
        arm_xy_mm: (n, 2) measured positions in the arm frame.
        phantom_xy_mm: (n, 2) the same points' design positions on the phantom.
        sigma_floor_mm: smallest per-point noise assumed for the uncertainty (with 2
            points there are no residual degrees of freedom at all).

    Raises:
        InputDataError: fewer than 2 points, shapes that differ, non-finite values, or all
            points at one place.
    """
    a = np.asarray(arm_xy_mm, float)
    q = np.asarray(phantom_xy_mm, float)
    if a.ndim != 2 or a.shape[1] != 2 or a.shape != q.shape:
        raise InputDataError(f"need two (n, 2) point sets of equal shape, got {a.shape}, "
                             f"{q.shape}")
    n = a.shape[0]
    if n < 2:
        raise InputDataError("a registration needs at least 2 fiducials")
    if not (np.isfinite(a).all() and np.isfinite(q).all()):
        raise InputDataError("fiducial positions must be finite")
    ca, cq = a.mean(axis=0), q.mean(axis=0)
    a0, q0 = a - ca, q - cq
    if float((a0 ** 2).sum()) < 1e-12:
        raise InputDataError("the fiducials must not all be at one place")
    # 2-D Kabsch: the angle maximising sum q0 . R a0
    h = a0.T @ q0
    yaw = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    d = cq - rot @ ca
    resid = q - (a @ rot.T + d)
    dof = 2 * n - 3
    s2 = float((resid ** 2).sum()) / dof if dof > 0 else 0.0
    s2 = max(s2, sigma_floor_mm ** 2)
    # Jacobian of the residuals w.r.t. (dx, dy, yaw) at the solution
    jac = np.zeros((2 * n, 3))
    jac[0::2, 0] = 1.0
    jac[1::2, 1] = 1.0
    drot = np.array([[-math.sin(yaw), -math.cos(yaw)], [math.cos(yaw), -math.sin(yaw)]])
    jac[:, 2] = (a @ drot.T).reshape(-1)
    cov = s2 * np.linalg.pinv(jac.T @ jac)
    return RegistrationEstimate(
        dx_mm=float(d[0]), dy_mm=float(d[1]), yaw_deg=math.degrees(yaw),
        std_dx_mm=math.sqrt(max(cov[0, 0], 0.0)), std_dy_mm=math.sqrt(max(cov[1, 1], 0.0)),
        std_yaw_deg=math.degrees(math.sqrt(max(cov[2, 2], 0.0))),
        residual_rms_mm=float(np.sqrt((resid ** 2).sum(axis=1).mean())), fiducials=n,
        measured_arm_mm=tuple((float(x), float(y)) for x, y in a))


def locate_bump(height_mm: ArrayLike, pitch_mm: float, *, min_prominence_mm: float = 0.035,
                smooth_px: float = 1.0, window_mm: float = 6.0,
                search_radius_mm: float = 5.5) -> tuple[float, float]:
    """Offset (x, y) mm of the most prominent bump from the height map's centre.

    The pad's own pressure plateau is removed by a white top-hat (the map minus its
    morphological opening with a ``window_mm`` disc, wider than a bead, narrower than the
    pad); the bump is searched within ``search_radius_mm`` of the centre (the pad's rim
    leaves top-hat residue further out); it is the connected region above half the highest
    remaining point there, and its prominence-weighted centroid is returned (sub-pixel).
    Rows run along +y, columns along +x.

    Raises:
        InputDataError: a non-2-D or non-finite map, a bad pitch, or no bump above
            ``min_prominence_mm``.
    """
    h = np.asarray(height_mm, float)
    if h.ndim != 2 or min(h.shape) < 3 or not np.isfinite(h).all():
        raise InputDataError(f"need a finite 2-D height map, got shape {h.shape}")
    if not (math.isfinite(pitch_mm) and pitch_mm > 0):
        raise InputDataError(f"pitch must be > 0, got {pitch_mm}")
    smooth = ndimage.gaussian_filter(h, smooth_px) if smooth_px > 0 else h
    r_px = max(1, round(window_mm / 2.0 / pitch_mm))
    yy, xx = np.mgrid[-r_px:r_px + 1, -r_px:r_px + 1]
    excess = smooth - ndimage.grey_opening(smooth, footprint=xx ** 2 + yy ** 2 <= r_px ** 2)
    rows, cols = h.shape
    ry, rx = np.mgrid[0:rows, 0:cols]
    near = np.hypot((rx - (cols - 1) / 2.0) * pitch_mm,
                    (ry - (rows - 1) / 2.0) * pitch_mm) <= search_radius_mm
    excess = np.where(near, excess, 0.0)
    peak = float(excess.max())
    if not peak >= min_prominence_mm:
        raise InputDataError(f"no bump: highest point {peak:.4f} mm above the median "
                             f"(< {min_prominence_mm} mm)")
    labels, _ = ndimage.label(excess >= peak / 2.0)
    i, j = np.unravel_index(int(np.argmax(excess)), excess.shape)
    region = labels == labels[i, j]
    weights = np.where(region, excess - peak / 2.0, 0.0)
    cy, cx = ndimage.center_of_mass(weights)
    return (float((cx - (cols - 1) / 2.0) * pitch_mm), float((cy - (rows - 1) / 2.0) * pitch_mm))


class GuardedMotion(Protocol):
    """What the registration needs of an arm: its box, a move and a reading. The station
    passes :class:`SafeMotion` (the safety layer's force limit and box), never the raw arm."""

    @property
    def limits(self) -> ArmLimits: ...

    def move_to(self, target_mm: Sequence[float]) -> object: ...

    def state(self) -> ArmReading: ...


class SafeMotion:
    """An arm seen through :class:`~remote_site.arm.safety.SafeArm` for scripted moves:
    every target is clamped, force-limited and, in the press zone, stepped down at the safety
    layer's press rate, like a stream of operator commands: each reading re-issues the
    current target, so a deep target is reached in safe steps. Build the ``SafeArm`` with a
    command timeout longer than one scripted move (:func:`guarded`)."""

    def __init__(self, safe: SafeArm) -> None:
        self.safe = safe
        self._target: tuple[float, float, float] | None = None

    @property
    def limits(self) -> ArmLimits:
        return self.safe.arm.limits

    def move_to(self, target_mm: Sequence[float]) -> object:
        target = (float(target_mm[0]), float(target_mm[1]), float(target_mm[2]))
        result = self.safe.move(target)  # no stamp: a local script, not a remote command
        if not result.accepted:
            raise CalibrationError(f"the safety layer refused the move to {target}: "
                                   f"{result.status}")
        self._target = target
        return result.applied_mm

    def state(self) -> ArmReading:
        reading = self.safe.poll()
        if self._target is not None:
            self.safe.move(self._target)  # the next safe step towards the target
        return reading


def guarded(arm: Arm, safety: SafetyConfig | None = None) -> SafeMotion:
    """``arm`` behind a :class:`SafeArm` made for scripted moves (the given safety settings,
    with a command timeout of a minute: the moves are not a command stream)."""
    cfg = dataclasses.replace(safety or SafetyConfig(), command_timeout_ms=60_000.0)
    return SafeMotion(SafeArm(arm, cfg))


def _move_and_wait(arm: GuardedMotion, target: tuple[float, float, float],
                   wait: Callable[[float], object], tolerance_mm: float,
                   timeout_s: float) -> None:
    target = arm.limits.clamp(target)
    arm.move_to(target)
    waited = 0.0
    while waited < timeout_s:
        wait(0.02)
        waited += 0.02
        reading = arm.state()
        dist = float(np.linalg.norm(np.asarray(reading.position_mm, float) - np.asarray(target)))
        speed = float(np.linalg.norm(reading.velocity_mm_s))
        # a noisy position reading may never come within the tolerance: at rest within 1 mm
        # counts as arrived
        if dist <= tolerance_mm or (speed < 0.5 and dist < 1.0):
            return
    raise CalibrationError(f"the arm did not reach {target} within {timeout_s:.1f} s")


def calibrate_with_fiducials(arm: GuardedMotion, sensor: TactileSensor,
                             reconstructor: Reconstructor,
                             fiducials_mm: Sequence[Sequence[float]], *,
                             press_mm: float = 1.5, hover_mm: float = 5.0,
                             settle_s: float = 0.2, pitch_mm: float = 0.5,
                             wait: Callable[[float], object] = time.sleep,
                             timeout_s: float = 10.0, outlier_mm: float = 0.5,
                             centred_mm: float = 3.0, ring_mm: float = 5.0,
                             rigid_mm: float = 1.0, max_yaw_deg: float = MAX_YAW_DEG,
                             max_presses: int = 25) -> RegistrationEstimate:
    """Press each fiducial, find the bead, fit the registration.

    For each fiducial the arm presses where the fiducials found so far predict it, lowering
    the pad ``press_mm`` into the surface, waiting ``settle_s`` and taking one sensor frame.
    Where to press:

    * none found yet: the design position, then a ring of ``ring_mm`` around it (and, in a
      last pass when nothing at all was found, a ring of twice that);
    * one found: along the arc of the design distance around it, yaw 0 first, then
      alternately further either way up to ``max_yaw_deg`` (one fiducial fixes the shift,
      not the turn: a 13 deg turn puts a fiducial 59 mm away 13 mm off the shift's
      prediction);
    * two or more: the rigid fit's prediction, then the ring around it.

    A bead felt more than ``centred_mm`` off the pad centre is pressed again, centred. A bead
    is accepted only if its distance to every fiducial found so far matches the design
    distance within ``rigid_mm`` (a rigid motion keeps distances): a bump that is not the
    fiducial (the phantom's edge, a tumor) is named in the error and the search goes on.
    Fiducials not found are tried again, from better predictions, while a pass finds more.
    The arm is commanded in its own frame (the designed map's phantom coordinates).

    Args:
        arm: the connected arm behind its safety layer (:class:`SafeMotion`).
        sensor: the connected sensor.
        reconstructor: with the sensor's calibration and a current background.
        fiducials_mm: (x, y) design positions on the phantom.
        press_mm: press depth below the designed surface.
        hover_mm: height of the moves between fiducials.
        settle_s: wait after reaching the press depth.
        pitch_mm: height-map pitch used to find the bead.
        wait: sleeps (realtime arm) or advances the simulated arm by the given seconds.
        timeout_s: longest wait for one move.
        outlier_mm: residual rms above which the worst fiducial is dropped (see
            :func:`robust_fit`).
        centred_mm: a bead felt further off the pad centre is pressed again on it.
        ring_mm: radius of the search ring when a bead is not felt; also the largest gap
            between neighbouring presses along an arc.
        rigid_mm: largest mismatch between a bead's distance to a found fiducial and their
            design distance.
        max_yaw_deg: largest turn of the phantom searched for.
        max_presses: presses per designed fiducial after which the search gives up (a real
            arm takes seconds a press; a fiducial found at once takes 1, one searched on
            both rings and never felt 19).

    Raises:
        CalibrationError: a move times out, fewer than 3 mutually consistent fiducials are
            found (2 when only 2 are designed), the press budget is spent, or the sensor
            fails.
    """
    design = [(float(f[0]), float(f[1])) for f in fiducials_mm]
    hits: list[tuple[int, tuple[float, float]]] = []  # (design index, arm x, y): every bead
    found: dict[int, tuple[float, float]] = {}  # the largest rigidly consistent set of hits
    pressed: dict[int, list[tuple[float, float]]] = {i: [] for i in range(len(design))}
    misses: list[str] = []
    presses_left = max_presses * len(design)

    def press(xy: tuple[float, float]) -> tuple[float, float, float] | None:
        """Press at arm (x, y); the bead's arm position and its distance from the pad
        centre, or None when no bead is felt."""
        nonlocal presses_left
        if presses_left <= 0:
            raise CalibrationError(
                f"registration: gave up after {max_presses * len(design)} presses with "
                f"{len(found)} of {len(design)} fiducials found ({'; '.join(misses[-8:])})")
        presses_left -= 1
        _move_and_wait(arm, (xy[0], xy[1], hover_mm), wait, 0.5, timeout_s)
        _move_and_wait(arm, (xy[0], xy[1], -press_mm), wait, 0.05, timeout_s)
        wait(settle_s)
        try:
            frame = sensor.read_latest(max_age_ms=1e9)
            pose = arm.state().position_mm
            hm = reconstructor.height_map(frame.rgb, out_pitch_mm=pitch_mm)
            ox, oy = locate_bump(hm.height_mm, hm.mm_per_px)
        except InputDataError as err:
            misses.append(f"({xy[0]:.1f}, {xy[1]:.1f}): {err}")
            return None
        except DeviceError as err:
            raise CalibrationError(f"sensor failed during the registration: {err}") from err
        finally:
            _move_and_wait(arm, (xy[0], xy[1], hover_mm), wait, 0.5, timeout_s)
        return pose[0] + ox, pose[1] + oy, math.hypot(ox, oy)

    def candidates(i: int, wide: bool) -> list[tuple[float, float]]:
        q = design[i]
        if len(found) >= 2:
            keys = sorted(found)
            guess = fit_registration([found[k] for k in keys], [design[k] for k in keys])
            centre = guess.phantom_to_arm(q)
            return [centre, *_ring(centre, ring_mm, 6)]
        # no pair yet: around every bead felt so far (one of them may not be a fiducial)
        arcs = [xy for k, a in hits if k != i
                for xy in _arc(a, design[k], q, max_yaw_deg, ring_mm)]
        return [*arcs, q, *_ring(q, ring_mm, 6), *(_ring(q, 2 * ring_mm, 12) if wide else [])]

    def search(i: int, wide: bool) -> bool:
        """Look for fiducial ``i``; True once the consistent set has changed."""
        for xy in candidates(i, wide):
            if any(math.dist(xy, done) < 1.0 for done in pressed[i]):
                continue  # pressed there before for this fiducial, nothing to be found
            pressed[i].append(xy)
            hit = press(xy)
            if hit is not None and hit[2] > centred_mm:  # felt off-centre: press on it
                hit = press((hit[0], hit[1]))
            if hit is None or hit[2] > centred_mm:
                continue
            hits.append((i, (hit[0], hit[1])))
            best = _consistent(hits, design, rigid_mm)
            if best != found:
                found.clear()
                found.update(best)
                return True
            misses.append(f"bump at ({hit[0]:.1f}, {hit[1]:.1f}) does not fit the rigid "
                          f"layout as fiducial {design[i]}")
        return False

    wide = False
    while len(found) < len(design):
        progress = False
        for i in range(len(design)):
            if i not in found and search(i, wide):
                progress = True
        if not progress:
            if hits or wide:
                break
            wide = True  # nothing felt anywhere: one more pass on wider rings
    # two beads fit many layouts (the shipped square has four equal sides): with three or
    # more designed, a registration rests on at least three
    needed = 3 if len(design) >= 3 else 2
    if len(found) < needed:
        raise CalibrationError(f"registration: only {len(found)} of {len(design)} "
                               f"fiducials found, {needed} needed ({'; '.join(misses)})")
    keys = sorted(found)
    return robust_fit([found[k] for k in keys], [design[k] for k in keys],
                      outlier_mm=outlier_mm)


def _consistent(hits: Sequence[tuple[int, tuple[float, float]]],
                design: Sequence[tuple[float, float]],
                rigid_mm: float) -> dict[int, tuple[float, float]]:
    """The largest set of hits, one per fiducial, whose pairwise distances all match the
    design's within ``rigid_mm`` (a rigid motion keeps distances); of equal sizes, the one
    whose distances match best, then the earliest."""
    for size in range(min(len(design), len(hits)), 0, -1):
        best: tuple[float, tuple[int, ...]] | None = None
        for combo in itertools.combinations(range(len(hits)), size):
            ids = [hits[c][0] for c in combo]
            if len(set(ids)) < size:
                continue
            worst = 0.0
            for b, c in itertools.combinations(combo, 2):
                (i, a), (k, e) = hits[b], hits[c]
                worst = max(worst, abs(math.dist(a, e) - math.dist(design[i], design[k])))
            if worst <= rigid_mm and (best is None or worst < best[0]):
                best = (worst, combo)
        if best is not None:
            return {hits[c][0]: hits[c][1] for c in best[1]}
    return {}


def _ring(centre: tuple[float, float], radius: float, n: int) -> list[tuple[float, float]]:
    return [(centre[0] + radius * math.cos(2 * math.pi * k / n),
             centre[1] + radius * math.sin(2 * math.pi * k / n)) for k in range(n)]


def _arc(found_arm: tuple[float, float], found_design: tuple[float, float],
         design: tuple[float, float], max_yaw_deg: float,
         spacing_mm: float) -> list[tuple[float, float]]:
    """Where ``design`` lies in the arm frame if the phantom is turned by yaw about the one
    fiducial found, for yaw 0, then alternately either way, in steps that leave at most
    ``spacing_mm`` between neighbours, up to ``max_yaw_deg``."""
    vx, vy = design[0] - found_design[0], design[1] - found_design[1]
    radius = math.hypot(vx, vy)
    step = min(math.radians(max_yaw_deg), spacing_mm / max(radius, 1e-9))
    n = math.ceil(math.radians(max_yaw_deg) / step)
    out = []
    for k in [0, *(s * j for j in range(1, n + 1) for s in (1, -1))]:
        th = -k * step  # the arm sees the phantom turned back: a = a1 + R(-yaw)(q - q1)
        out.append((found_arm[0] + math.cos(th) * vx - math.sin(th) * vy,
                    found_arm[1] + math.sin(th) * vx + math.cos(th) * vy))
    return out


def robust_fit(arm_xy_mm: Sequence[Sequence[float]], phantom_xy_mm: Sequence[Sequence[float]],
               *, outlier_mm: float = 0.5) -> RegistrationEstimate:
    """:func:`fit_registration`, dropping the worst-fitting fiducial while the residual rms
    exceeds ``outlier_mm`` and more than 3 remain (a bead mislocated, e.g. by a tumor or
    the phantom's edge in the sensor's view)."""
    a = [tuple(p) for p in arm_xy_mm]
    q = [tuple(p) for p in phantom_xy_mm]
    est = fit_registration(a, q)
    while est.residual_rms_mm > outlier_mm and len(a) > 3:
        resid = np.linalg.norm(est.arm_to_phantom(a) - np.asarray(q, float), axis=1)
        worst = int(np.argmax(resid))
        del a[worst], q[worst]
        est = fit_registration(a, q)
    return est
