"""XYZ sliding-platform driver: base class, encoder-board protocol, serial and ``sim`` backends.

Open one with :func:`local_site.devices.open_platform`. The simulated operator's motion sources
(:mod:`.motion`, :mod:`.motion_spec`) are simulator code, imported only by the ``sim`` backend.
"""

from local_site.platform.base import PlatformSample, PlatformStats, XYZPlatform
from local_site.platform.kinematics import PlatformGeometry

__all__ = [
    "PlatformGeometry",
    "PlatformSample",
    "PlatformStats",
    "XYZPlatform",
]
