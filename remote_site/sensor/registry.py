"""Sensor sources by name: ``"sim"``, ``"camera"``, or a camera given directly.

``SENSORS`` maps a name to ``"module:Class"``; the module is imported only when that
sensor is opened. :func:`open_sensor` also accepts what a user types for a real camera: a
device index (``"0"``), a URL (``"rtsp://..."``, ``"http://..."``) or a video file path.
"""

from __future__ import annotations

import importlib
from typing import Any

from remote_site.sensor.base import TactileSensor
from shared.errors import ConfigError

__all__ = ["SENSORS", "open_sensor"]

SENSORS: dict[str, str] = {
    "sim": "remote_site.sensor.simulator:SimulatedSensor",
    "camera": "remote_site.sensor.camera:OpenCVCameraSensor",
}


def _load(target: str) -> type[TactileSensor]:
    module_name, _, class_name = target.partition(":")
    try:
        cls = getattr(importlib.import_module(module_name), class_name)
    except (ImportError, AttributeError) as err:
        raise ConfigError(f"sensor backend {target!r} cannot be imported: {err}") from err
    if not (isinstance(cls, type) and issubclass(cls, TactileSensor)):
        raise ConfigError(f"{target!r} is not a TactileSensor")
    return cls


def open_sensor(name_or_camera: str | int, **options: Any) -> TactileSensor:
    """Build (not connect) a sensor source.

    Args:
        name_or_camera: a registered name (``"sim"``, ``"camera"``), a device index, a URL
            or a video file path (the last three open the OpenCV camera source).
        **options: keyword arguments of the backend's constructor.

    Returns:
        The sensor; use it as a context manager or call ``connect()``.

    Raises:
        ConfigError: an unknown name, or options the backend does not accept.
    """
    if isinstance(name_or_camera, str) and name_or_camera in SENSORS:
        cls = _load(SENSORS[name_or_camera])
    elif isinstance(name_or_camera, int) or (isinstance(name_or_camera, str) and (
            name_or_camera.isdigit() or "://" in name_or_camera or "/" in name_or_camera
            or "." in name_or_camera)):
        cls = _load(SENSORS["camera"])
        options = {"source": name_or_camera, **options}
    else:
        raise ConfigError(f"unknown sensor {name_or_camera!r}; known: {sorted(SENSORS)} or a "
                          "camera index / URL / video file")
    try:
        return cls(**options)
    except TypeError as err:
        raise ConfigError(f"bad options for sensor {name_or_camera!r}: {err}") from err
