"""Device factory: the arm, the sensor and the calibration, and the simulated world they share.

A *world* is what simulated backends act on: with ``--phantom SCENE --seed N`` the sim arm
feels that phantom (force at every 1 kHz step) and the sim sensor renders that phantom's gel
contact depth map at the arm's current pose. The pipeline never asks whether a device is
simulated: this module decides, in one place, which backend receives the world, by whether
its constructor accepts it (an arm's ``phantom``, a sensor's ``depth_provider``). A real
backend asked to act on a phantom is refused with a clear :class:`ConfigError`.

Calibrations: ``--calibration PATH`` always wins; without it a backend may have a default
in :data:`DEFAULT_CALIBRATIONS` (the shipped sim calibration for ``sim``), otherwise start-up
fails with :class:`CalibrationError`. A calibration made for another frame size or pixel
pitch than the sensor delivers is refused the same way.
"""

from __future__ import annotations

import importlib
import inspect
import json
import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from remote_site.arm.base import Arm
from remote_site.arm.registry import arm_class
from remote_site.phantom.phantom import Phantom, PixelGrid
from remote_site.phantom.scenes import make_scene
from remote_site.reconstruction.calibration import Calibration
from remote_site.sensor.base import TactileSensor
from remote_site.sensor.registry import SENSORS, open_sensor, sensor_class
from remote_site.stiffness.shore import ShoreConversion
from shared.errors import CalibrationError, ConfigError
from shared.workspace import WorkspaceMap

__all__ = ["DEFAULT_CALIBRATIONS", "SimWorld", "build_world", "load_calibration",
           "open_world_arm", "open_world_sensor", "write_ground_truth"]

log = logging.getLogger(__name__)

#: sensor backend name -> "module:function" returning its default Calibration
DEFAULT_CALIBRATIONS: dict[str, str] = {
    "sim": "remote_site.sensor.sim_calibration:simulated_calibration",
}


@dataclass
class SimWorld:
    """The simulated scene simulated backends act on.

    Attributes:
        phantom: the phantom pressed by the sim arm and seen by the sim sensor.
    """

    phantom: Phantom

    def depth_provider(self, arm: Arm, grid: Callable[[], PixelGrid]) -> Callable[[], np.ndarray]:
        """A sensor depth provider: the phantom's contact depth map at the arm's pose."""

        def provide() -> np.ndarray:
            return self.phantom.contact(arm.state().position_mm, grid()).depth_map_mm

        return provide


def build_world(phantom: str | None, seed: int = 0) -> SimWorld | None:
    """The simulated world for ``--phantom SCENE --seed N`` (None without a phantom).

    Raises:
        ConfigError: an unknown scene name.
    """
    if phantom is None:
        return None
    return SimWorld(make_scene(phantom, seed))


def _accepts(cls: type, name: str) -> bool:
    try:
        return name in inspect.signature(cls).parameters
    except (TypeError, ValueError):
        return False


def open_world_arm(name: str, world: SimWorld | None, **options: Any) -> Arm:
    """Build (not connect) the arm backend ``name``, wired to the world if given.

    Raises:
        ConfigError: unknown backend, or a world given to a backend that cannot act on it.
        DeviceInitError: the backend's module cannot be imported.
    """
    cls = arm_class(name)
    if world is not None:
        if not _accepts(cls, "phantom"):
            raise ConfigError(f"arm backend {name!r} is real hardware and cannot act on a "
                              "simulated phantom; drop --phantom or use --arm sim")
        options = {**options, "phantom": world.phantom}
    try:
        return cls(**options)
    except TypeError as err:
        raise ConfigError(f"bad options for arm {name!r}: {err}") from err


def open_world_sensor(name: str, world: SimWorld | None, arm: Arm, **options: Any
                      ) -> TactileSensor:
    """Build (not connect) the sensor ``name`` (or a camera), wired to the world if given.

    With a world, the sensor's depth provider renders the phantom at ``arm``'s pose.

    Raises:
        ConfigError: unknown sensor, or a world given to a sensor that cannot render it.
    """
    holder: list[TactileSensor] = []
    if world is not None:
        cls = sensor_class(name) if name in SENSORS else None
        if cls is None or not _accepts(cls, "depth_provider"):
            raise ConfigError(f"sensor {name!r} is a real camera and cannot render a simulated "
                              "phantom; drop --phantom or use --sensor sim")

        def grid() -> PixelGrid:
            sensor = holder[0]
            return PixelGrid(width_px=sensor.shape_hw[1], height_px=sensor.shape_hw[0],
                             mm_per_px=sensor.mm_per_px)

        options = {**options, "depth_provider": world.depth_provider(arm, grid)}
    sensor = open_sensor(name, **options)
    holder.append(sensor)
    if world is not None:  # build the contact table now, not on the first pressed frame
        world.phantom.modulus_table(sensor.mm_per_px)
    return sensor


def load_calibration(sensor_name: str, path: str | Path | None,
                     sensor: TactileSensor) -> Calibration:
    """The calibration for this sensor, checked against its frame size and pitch.

    Args:
        sensor_name: the backend name given on the command line.
        path: ``--calibration`` (wins), or None for the backend's default.
        sensor: the (built) sensor, for its ``shape_hw`` and ``mm_per_px``.

    Raises:
        CalibrationError: no calibration for this sensor, a missing/unreadable file, or a
            calibration made for another frame size or pixel pitch.
    """
    if path is not None:
        calib = Calibration.load(path)
        where = str(path)
    else:
        target = DEFAULT_CALIBRATIONS.get(sensor_name)
        if target is None:
            raise CalibrationError(f"sensor {sensor_name!r} has no default calibration: pass "
                                   "--calibration calib.npz (made by `teletouch sensor "
                                   "calibrate`)")
        module_name, _, func_name = target.partition(":")
        calib = getattr(importlib.import_module(module_name), func_name)()
        where = f"the default calibration of {sensor_name!r}"
    if tuple(calib.shape_hw) != tuple(sensor.shape_hw):
        raise CalibrationError(f"{where} is for {calib.shape_hw[1]}x{calib.shape_hw[0]} frames "
                               f"but the sensor delivers {sensor.shape_hw[1]}x"
                               f"{sensor.shape_hw[0]}")
    if not np.isclose(calib.mm_per_px, sensor.mm_per_px, rtol=1e-3):
        raise CalibrationError(f"{where} has {calib.mm_per_px} mm/px but the sensor delivers "
                               f"{sensor.mm_per_px} mm/px")
    return calib


def write_ground_truth(world: SimWorld, path: str | Path, workspace: WorkspaceMap,
                       shore: ShoreConversion | None = None) -> Path:
    """Write the phantom's ground truth, with platform coordinates, for the demo's scoring.

    The JSON is :meth:`Phantom.ground_truth` (``scene``, ``seed``, ``layer``, ``pad``,
    ``background_stiffness_n_per_mm``, ``tumors`` with ``id``, ``kind``, ``material``,
    ``center_mm`` (phantom), ``depth_mm``, ``radius_mm``, ``modulus_kpa``,
    ``severity_rank``, ``stiffness_n_per_mm``, ...) plus, per tumor, ``center_platform_mm``
    and ``display_k``, and at the top ``severity_order`` (tumor ids, least severe first;
    empty when the scene does not rank), ``background_display_k`` and ``workspace`` (the
    map used).

    Raises:
        ConfigError: the file cannot be written.
    """
    shore = shore or ShoreConversion()
    truth = world.phantom.ground_truth()
    for tumor in truth["tumors"]:
        cx, cy = tumor["center_mm"]
        tumor["center_platform_mm"] = list(workspace.phantom_xy_to_platform((cx, cy)))
        tumor["display_k"] = float(shore.display_k(tumor["stiffness_n_per_mm"]))
    ranked = [t for t in truth["tumors"] if t.get("severity_rank") is not None]
    truth["severity_order"] = [t["id"] for t in sorted(ranked, key=lambda t: t["severity_rank"])]
    truth["background_display_k"] = float(shore.display_k(truth["background_stiffness_n_per_mm"]))
    truth["workspace"] = {k: list(v) if isinstance(v, tuple) else v
                          for k, v in asdict(workspace.config).items()}
    out = Path(path)
    try:
        out.write_text(json.dumps(truth, indent=2, sort_keys=True))
    except OSError as err:
        raise ConfigError(f"cannot write the ground truth to {out}: {err}") from err
    return out
