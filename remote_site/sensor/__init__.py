"""Visuotactile sensor sources: one base class, an OpenCV camera and a photometric simulator.

Typical use::

    from remote_site.sensor import open_sensor
    with open_sensor("sim") as sensor:          # or open_sensor(0), open_sensor("rtsp://...")
        frame = sensor.read_latest(max_age_ms=50)

Backends are imported lazily through :data:`~remote_site.sensor.registry.SENSORS`.
"""

from remote_site.sensor.base import SensorFrame, TactileSensor
from remote_site.sensor.registry import SENSORS, open_sensor, sensor_class

__all__ = ["SENSORS", "SensorFrame", "TactileSensor", "open_sensor", "sensor_class"]
