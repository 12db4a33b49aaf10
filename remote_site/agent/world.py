"""The simulated world of the remote station (simulator code): a phantom for sim backends.

With ``--phantom SCENE|FILE.toml --seed N`` the sim arm feels that phantom (force at every
1 kHz step) and the sim sensor renders that phantom's gel contact depth map at the arm's
current pose.
The station reaches this module only by name, through
:data:`remote_site.agent.devices.WORLDS` (``"phantom"`` -> :func:`build_world`), and uses
the world through the :class:`remote_site.agent.devices.World` protocol: product code never
imports it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from remote_site.arm.base import Arm
from remote_site.phantom.phantom import Phantom, PixelGrid
from remote_site.phantom.phantom_file import resolve_phantom
from remote_site.sensor.base import TactileSensor

__all__ = ["SimWorld", "build_world"]


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

    def arm_options(self) -> dict[str, Any]:
        """The sim arm presses the phantom."""
        return {"phantom": self.phantom}

    def sensor_options(self, arm: Arm,
                       sensor: Callable[[], TactileSensor]) -> dict[str, Any]:
        """The sim sensor renders the phantom's contact at ``arm``'s pose."""

        def grid() -> PixelGrid:
            built = sensor()
            return PixelGrid(width_px=built.shape_hw[1], height_px=built.shape_hw[0],
                             mm_per_px=built.mm_per_px)

        return {"depth_provider": self.depth_provider(arm, grid)}

    def prepare_sensor(self, sensor: TactileSensor) -> None:
        """Build the contact table now, not on the first pressed frame."""
        self.phantom.modulus_table(sensor.mm_per_px)


def build_world(scene: str, seed: int = 0) -> SimWorld:
    """The simulated world for ``--phantom SCENE|FILE.toml --seed N``.

    Raises:
        ConfigError: an unknown scene name, or an unreadable or invalid phantom file.
    """
    return SimWorld(resolve_phantom(scene, seed))
