"""The simulated world of the remote station (simulator code): a phantom for sim backends.

With ``--phantom SCENE --seed N`` the sim arm feels that phantom (force at every 1 kHz step)
and the sim sensor renders that phantom's gel contact depth map at the arm's current pose.
The station reaches this module only by name, through
:data:`remote_site.agent.devices.WORLDS` (``"phantom"`` -> :func:`build_world`), and uses
the world through the :class:`remote_site.agent.devices.World` protocol: product code never
imports it.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from remote_site.arm.base import Arm
from remote_site.phantom.phantom import Phantom, PixelGrid
from remote_site.phantom.reference_presses import sim_stiffness_calibration
from remote_site.phantom.scenes import make_scene
from remote_site.sensor.base import TactileSensor
from shared.errors import ConfigError
from shared.hardness import StiffnessToK
from shared.workspace import WorkspaceMap

__all__ = ["SimWorld", "build_world", "write_ground_truth"]


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

    def write_ground_truth(self, path: str | Path, workspace: WorkspaceMap,
                           stiffness_to_k: StiffnessToK) -> Path:
        """See :func:`write_ground_truth`."""
        return write_ground_truth(self, path, workspace, stiffness_to_k)


def build_world(scene: str, seed: int = 0) -> SimWorld:
    """The simulated world for ``--phantom SCENE --seed N``.

    Raises:
        ConfigError: an unknown scene name.
    """
    return SimWorld(make_scene(scene, seed))


def write_ground_truth(world: SimWorld, path: str | Path, workspace: WorkspaceMap,
                       stiffness_to_k: StiffnessToK | None = None) -> Path:
    """Write the phantom's ground truth, with platform coordinates, for the demo's scoring.

    The JSON is :meth:`Phantom.ground_truth` (``scene``, ``seed``, ``layer``, ``pad``,
    ``background_stiffness_n_per_mm``, ``tumors`` with ``id``, ``kind``, ``material``,
    ``center_mm`` (phantom), ``depth_mm``, ``radius_mm``, ``modulus_kpa``,
    ``severity_rank``, ``stiffness_n_per_mm``, ...) plus, per tumor, ``center_platform_mm``
    and ``display_k``, and at the top ``severity_order`` (tumor ids, least severe first;
    empty when the scene does not rank), ``background_display_k`` and ``workspace`` (the
    map used).

    Args:
        world: the simulated world.
        path: the JSON file to write.
        workspace: the platform <-> phantom map.
        stiffness_to_k: the station's N/mm -> k mapping (default: the simulated probe's
            shipped stiffness calibration).

    Raises:
        ConfigError: the file cannot be written.
    """
    to_k = stiffness_to_k or sim_stiffness_calibration().stiffness_to_k()
    truth = world.phantom.ground_truth()
    for tumor in truth["tumors"]:
        cx, cy = tumor["center_mm"]
        tumor["center_platform_mm"] = list(workspace.phantom_xy_to_platform((cx, cy)))
        tumor["display_k"] = float(to_k.k(tumor["stiffness_n_per_mm"]))
    ranked = [t for t in truth["tumors"] if t.get("severity_rank") is not None]
    truth["severity_order"] = [t["id"] for t in sorted(ranked, key=lambda t: t["severity_rank"])]
    truth["background_display_k"] = float(to_k.k(truth["background_stiffness_n_per_mm"]))
    truth["workspace"] = {k: list(v) if isinstance(v, tuple) else v
                          for k, v in asdict(workspace.config).items()}
    out = Path(path)
    try:
        out.write_text(json.dumps(truth, indent=2, sort_keys=True))
    except OSError as err:
        raise ConfigError(f"cannot write the ground truth to {out}: {err}") from err
    return out
