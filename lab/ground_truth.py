"""The simulated phantom's ground truth, in platform coordinates, for scoring a session.

Evaluation code: the demo writes it beside a session's files and :mod:`lab.scoring` reads it.
No station writes or reads it.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from remote_site.agent.world import SimWorld
from remote_site.phantom.reference_presses import sim_stiffness_calibration
from shared.errors import ConfigError
from shared.hardness import StiffnessToK
from shared.workspace import WorkspaceMap

__all__ = ["write_ground_truth"]


def write_ground_truth(world: SimWorld, path: str | Path, workspace: WorkspaceMap,
                       stiffness_to_k: StiffnessToK | None = None) -> Path:
    """Write the phantom's ground truth, with platform coordinates, for the demo's scoring.

    The JSON is :meth:`Phantom.ground_truth` (``scene``, ``seed``, ``layer``, ``pad``,
    ``background_stiffness_n_per_mm``, ``tumors`` with ``id``, ``kind``, ``material``,
    ``center_mm`` (phantom), ``depth_mm``, ``radius_mm``, ``modulus_kpa``,
    ``severity_rank``, ``stiffness_n_per_mm``, ...) plus, per tumor, ``center_platform_mm``
    and ``display_k``, and at the top ``severity_order`` (tumor ids, least severe first;
    empty when the scene does not rank), ``background_display_k``, ``world`` (the simulated
    world's noise levels and the session's hidden registration error) and ``workspace``
    (the map used).

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
    truth["world"] = world.describe()
    truth["workspace"] = {k: list(v) if isinstance(v, tuple) else v
                          for k, v in asdict(workspace.config).items()}
    out = Path(path)
    try:
        out.write_text(json.dumps(truth, indent=2, sort_keys=True))
    except OSError as err:
        raise ConfigError(f"cannot write the ground truth to {out}: {err}") from err
    return out
