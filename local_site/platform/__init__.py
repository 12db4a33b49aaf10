"""XYZ sliding-platform driver: base class, encoder-board protocol, serial and ``sim`` backends,
and the simulated operator's motion sources. Open one with :func:`local_site.devices.open_platform`.
"""

from local_site.platform.base import PlatformSample, PlatformStats, XYZPlatform
from local_site.platform.kinematics import PlatformGeometry
from local_site.platform.motion import (
    HoldMotion,
    MotionSource,
    RandomWalk,
    RasterSweep,
    RasterSweepParams,
    ReplayMotion,
    make_motion,
)

__all__ = [
    "HoldMotion",
    "MotionSource",
    "PlatformGeometry",
    "PlatformSample",
    "PlatformStats",
    "RandomWalk",
    "RasterSweep",
    "RasterSweepParams",
    "ReplayMotion",
    "XYZPlatform",
    "make_motion",
]
