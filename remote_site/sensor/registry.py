"""Sensor sources by name: ``"sim"``, ``"sim-camera"``, ``"camera"``, or a camera given directly.

``SENSORS`` maps a name to ``"module:Class"``; the module is imported only when that
sensor is opened. The table is registered as device kind ``sensor`` with the one loader,
:func:`shared.devices.registry.load_backend`, which also finds backends installed as entry
points in the group ``teletouch.sensor`` and accepts a ``"module:Class"`` path.
:func:`open_sensor` also accepts what a user types for a real camera: a device index
(``"0"``), a URL (``"rtsp://..."``, ``"http://..."``) or a video file path.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from remote_site.sensor.base import TactileSensor
from shared.devices.registry import is_backend_name, is_class_path, load_backend, register_kind
from shared.errors import ConfigError

__all__ = ["SENSORS", "check_sensor_source", "open_sensor", "sensor_class"]

SENSORS: dict[str, str] = {
    "sim": "remote_site.sensor.simulator:SimulatedSensor",
    "sim-camera": "remote_site.sensor.simulator:StreamingSimulatedSensor",
    "camera": "remote_site.sensor.camera:OpenCVCameraSensor",
}


register_kind("sensor", TactileSensor, SENSORS)


def sensor_class(name: str) -> type[TactileSensor]:
    """Resolve a backend name, an entry-point name or a ``"module:Class"`` string.

    Raises:
        ConfigError: unknown name, or not a :class:`TactileSensor` subclass.
        DeviceInitError: the backend's module cannot be imported (missing extra).
    """
    cls: type[TactileSensor] = load_backend("sensor", name)
    return cls


def _is_camera_source(name: str) -> bool:
    return name.isdigit() or "://" in name or "/" in name or "." in name


def check_sensor_source(name_or_camera: str | int) -> None:
    """Check what a user typed for ``--sensor`` before anything else is loaded or opened, so
    a typo is named first (not after, say, a missing calibration for that sensor).

    Raises:
        ConfigError: an unknown name, or a video file path that does not exist.
    """
    if isinstance(name_or_camera, int):
        return
    name = name_or_camera
    if is_backend_name("sensor", name) or is_class_path(name):
        return
    if not _is_camera_source(name):
        raise ConfigError(f"unknown sensor {name!r}; known: {sorted(SENSORS)} or a camera "
                          "index / URL / video file")
    if "!" in name or " " in name:  # a GStreamer pipeline: OpenCV's to judge at connect
        return
    if not name.isdigit() and "://" not in name and not Path(name).exists():
        raise ConfigError(f"sensor {name!r}: no such video file (a camera index, a URL such as "
                          "rtsp://..., or an existing video file)")


def open_sensor(name_or_camera: str | int, **options: Any) -> TactileSensor:
    """Build (not connect) a sensor source.

    Args:
        name_or_camera: a registered name (``"sim"``, ``"camera"``), an entry-point name, a
            ``"module:Class"`` path, a device index, a URL or a video file path (the last
            three open the OpenCV camera source).
        **options: keyword arguments of the backend's constructor.

    Returns:
        The sensor; use it as a context manager or call ``connect()``.

    Raises:
        ConfigError: an unknown name, or options the backend does not accept.
        DeviceInitError: the backend's module cannot be imported.
    """
    if isinstance(name_or_camera, str) and (is_backend_name("sensor", name_or_camera)
                                            or is_class_path(name_or_camera)):
        cls = sensor_class(name_or_camera)
    elif isinstance(name_or_camera, int) or (isinstance(name_or_camera, str)
                                             and _is_camera_source(name_or_camera)):
        cls = sensor_class("camera")
        options = {"source": name_or_camera, **options}
    else:
        raise ConfigError(f"unknown sensor {name_or_camera!r}; known: {sorted(SENSORS)} or a "
                          "camera index / URL / video file")
    try:
        return cls(**options)
    except TypeError as err:
        raise ConfigError(f"bad options for sensor {name_or_camera!r}: {err} (on the command "
                          "line --sensor-preset and --sensor-loop are a camera's options; "
                          "--sensor-fps and --sensor-latency-ms a camera's or sim-camera's)"
                          ) from err
