"""The phantom's ground truth the lab writes for scoring: platform coordinates, k, severity."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from lab.ground_truth import write_ground_truth
from remote_site.agent.world import build_world
from shared.errors import ConfigError
from shared.workspace import WorkspaceMap

WS = WorkspaceMap()


def test_ground_truth_file_has_platform_coordinates_and_severity(tmp_path: Path) -> None:
    world = build_world("severity", 4)
    assert world is not None
    path = write_ground_truth(world, tmp_path / "truth.json", WS)
    truth: dict[str, Any] = json.loads(path.read_text())
    assert truth["scene"] == "severity" and truth["seed"] == 4
    assert len(truth["tumors"]) == 4
    for tumor in truth["tumors"]:
        cx, cy = tumor["center_mm"]
        assert tumor["center_platform_mm"] == pytest.approx([cx + 30.0, cy + 30.0])
        assert tumor["stiffness_n_per_mm"] == pytest.approx(
            world.phantom.tissue_stiffness_n_per_mm(cx, cy))
        assert 0.5 <= tumor["display_k"] <= 1.0
    ranks = {t["id"]: t["severity_rank"] for t in truth["tumors"]}
    assert [ranks[i] for i in truth["severity_order"]] == [1, 2, 3, 4]
    assert truth["workspace"]["scale_xy"] == 1.0
    with pytest.raises(ConfigError):
        write_ground_truth(world, tmp_path / "no" / "such" / "dir.json", WS)
