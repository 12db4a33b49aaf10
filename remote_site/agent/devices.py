"""Device factory of the remote station: arm, sensor, calibrations, and an optional world.

A *world* is what simulated backends act on (a phantom pressed by the sim arm and seen by
the sim sensor). Product code never imports one: worlds are named in :data:`WORLDS`, a
name -> ``"module:function"`` table imported lazily, like device backends, and used through
the :class:`World` protocol only. A backend receives the world's options when its
constructor accepts them all (an arm's ``phantom``, a sensor's ``depth_provider``); a real
backend asked to act on a world is refused with a clear :class:`ConfigError`.

Calibrations: ``--calibration PATH`` / ``--stiffness-calibration PATH`` always win; without
them a backend may have a default in :data:`DEFAULT_CALIBRATIONS` /
:data:`DEFAULT_STIFFNESS_CALIBRATIONS` (the shipped simulator calibrations for ``sim``),
otherwise start-up fails (:class:`CalibrationError` for the sensor calibration,
:class:`ConfigError` for the stiffness calibration). A sensor calibration made for another
frame size or pixel pitch than the sensor delivers is refused.
"""

from __future__ import annotations

import inspect
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from remote_site.arm.base import Arm
from remote_site.arm.registry import arm_class
from remote_site.reconstruction.calibration import Calibration
from remote_site.sensor.base import TactileSensor
from remote_site.sensor.registry import SENSORS, open_sensor, sensor_class
from shared.devices.registry import load_object
from shared.errors import CalibrationError, ConfigError
from shared.stiffness_calibration import StiffnessCalibration

__all__ = ["DEFAULT_CALIBRATIONS", "DEFAULT_STIFFNESS_CALIBRATIONS", "WORLDS", "World",
           "load_calibration", "load_stiffness_calibration", "open_world",
           "open_world_arm", "open_world_sensor"]

log = logging.getLogger(__name__)

#: world kind -> "module:function(scene, seed, *, ideal) -> World"
WORLDS: dict[str, str] = {
    "phantom": "remote_site.agent.world:build_world",
}

#: sensor backend name -> "module:function" returning its default Calibration
DEFAULT_CALIBRATIONS: dict[str, str] = {
    "sim": "remote_site.sensor.sim_calibration:simulated_calibration",
    "sim-camera": "remote_site.sensor.sim_calibration:simulated_calibration",
}

#: sensor backend name -> "module:function" returning its default StiffnessCalibration
DEFAULT_STIFFNESS_CALIBRATIONS: dict[str, str] = {
    "sim": "remote_site.phantom.reference_presses:sim_stiffness_calibration",
    "sim-camera": "remote_site.phantom.reference_presses:sim_stiffness_calibration",
}


class World(Protocol):
    """What the station needs from a simulated world (see the module docstring)."""

    def arm_options(self) -> dict[str, Any]:
        """Constructor options that wire an arm backend to the world."""
        ...

    def sensor_options(self, arm: Arm,
                       sensor: Callable[[], TactileSensor]) -> dict[str, Any]:
        """Constructor options that wire a sensor backend to the world at ``arm``'s pose.

        ``sensor`` returns the built sensor (for its frame size) once it exists.
        """
        ...

    def prepare_sensor(self, sensor: TactileSensor) -> None:
        """Precompute what the first frames need (called once the sensor is built)."""
        ...


def _resolve(target: str, what: str) -> Any:
    return load_object(target, what)


def open_world(kind: str, scene: str, seed: int = 0, *, ideal: bool = False) -> World:
    """Build the world ``kind`` (see :data:`WORLDS`) for ``scene`` and ``seed``.

    ``ideal`` asks for the noise-free world instead of the realistic default.

    Raises:
        ConfigError: an unknown world kind or scene.
        DeviceInitError: the world's module cannot be imported.
    """
    target = WORLDS.get(kind, kind if ":" in kind else None)
    if target is None:
        raise ConfigError(f"unknown world {kind!r}; known: {sorted(WORLDS)}")
    world: World = _resolve(target, "world")(scene, seed, ideal=ideal)
    return world


def _accepts(cls: type, names: list[str]) -> bool:
    try:
        params = inspect.signature(cls).parameters
    except (TypeError, ValueError):
        return False
    return all(name in params for name in names)


def open_world_arm(name: str, world: World | None, **options: Any) -> Arm:
    """Build (not connect) the arm backend ``name``, wired to the world if given.

    Raises:
        ConfigError: unknown backend, or a world given to a backend that cannot act on it.
        DeviceInitError: the backend's module cannot be imported.
    """
    cls = arm_class(name)
    if world is not None:
        wiring = world.arm_options()
        if not _accepts(cls, list(wiring)):
            raise ConfigError(f"arm backend {name!r} is real hardware and cannot act on a "
                              "simulated phantom; drop --phantom or use --arm sim")
        options = {**options, **wiring}
    try:
        return cls(**options)
    except TypeError as err:
        raise ConfigError(f"bad options for arm {name!r}: {err}") from err


def open_world_sensor(name: str, world: World | None, arm: Arm, **options: Any
                      ) -> TactileSensor:
    """Build (not connect) the sensor ``name`` (or a camera), wired to the world if given.

    With a world, the sensor renders the world at ``arm``'s pose.

    Raises:
        ConfigError: unknown sensor, or a world given to a sensor that cannot render it.
    """
    holder: list[TactileSensor] = []
    if world is not None:
        wiring = world.sensor_options(arm, lambda: holder[0])
        cls = sensor_class(name) if name in SENSORS else None
        if cls is None or not _accepts(cls, list(wiring)):
            raise ConfigError(f"sensor {name!r} is a real camera and cannot render a simulated "
                              "phantom; drop --phantom or use --sensor sim")
        options = {**options, **wiring}
    sensor = open_sensor(name, **options)
    holder.append(sensor)
    if world is not None:  # precompute now, not on the first pressed frame
        world.prepare_sensor(sensor)
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
        calib = _resolve(target, "calibration")()
        where = f"the default calibration of {sensor_name!r}"
    if tuple(calib.shape_hw) != tuple(sensor.shape_hw):
        raise CalibrationError(f"{where} is for {calib.shape_hw[1]}x{calib.shape_hw[0]} frames "
                               f"but the sensor delivers {sensor.shape_hw[1]}x"
                               f"{sensor.shape_hw[0]}")
    if not np.isclose(calib.mm_per_px, sensor.mm_per_px, rtol=1e-3):
        raise CalibrationError(f"{where} has {calib.mm_per_px} mm/px but the sensor delivers "
                               f"{sensor.mm_per_px} mm/px")
    return calib


def load_stiffness_calibration(sensor_name: str,
                               path: str | Path | None) -> StiffnessCalibration:
    """The probe's stiffness calibration: ``path`` if given, else the backend's default.

    Args:
        sensor_name: the sensor backend name given on the command line.
        path: ``--stiffness-calibration`` (wins), or None for the backend's default.

    Raises:
        ConfigError: no path and no default for this sensor (a real sensor needs one).
        CalibrationError: a missing, unreadable or invalid file.
    """
    if path is not None:
        return StiffnessCalibration.load(path)
    target = DEFAULT_STIFFNESS_CALIBRATIONS.get(sensor_name)
    if target is None:
        raise ConfigError(f"sensor {sensor_name!r} has no default stiffness calibration: pass "
                          "--stiffness-calibration stiffness_calib.json (made by `teletouch "
                          "sensor calibrate-stiffness` from presses on reference blocks)")
    calib: StiffnessCalibration = _resolve(target, "stiffness calibration")()
    return calib
