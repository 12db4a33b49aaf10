"""Phantom files: the named scenes are files, every bad field is refused with a clear error."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import pytest

from remote_site.agent.world import build_world
from remote_site.phantom import Phantom, make_scene
from remote_site.phantom.phantom_file import (
    load_phantom,
    phantom_from_dict,
    resolve_phantom,
    shipped_scene_names,
)
from shared.errors import ConfigError

GOOD: dict[str, Any] = {
    "name": "lab-phantom",
    "layer": {"size_mm": [80.0, 60.0], "thickness_mm": 18.0, "modulus_kpa": 40.0,
              "nonlinearity": 1.5},
    "placement": {"half_mm": 20.0, "min_separation_mm": 15.0},
    "inclusion": [
        {"id": "A", "kind": "benign", "center_mm": [10.0, -5.0], "depth_mm": 6.0,
         "radius_mm": 4.0, "modulus_kpa": 200.0, "outline": [[3, 0.1, 0.5]]},
        {"id": "B", "kind": "malignant", "depth_mm": 9.0, "radius_mm": 5.0,
         "modulus_kpa": 900.0, "boundary_width_mm": 1.0,
         "outline": {"orders": [4, 6], "amplitude": [0.05, 0.1]},
         "surface_roughness": 0.1, "severity_rank": 2},
    ],
}

GOOD_TOML = """
name = "lab-phantom"
[layer]
size_mm = [80.0, 60.0]
thickness_mm = 18.0
modulus_kpa = 40.0
nonlinearity = 1.5
[placement]
half_mm = 20.0
min_separation_mm = 15.0
[[inclusion]]
id = "A"
kind = "benign"
center_mm = [10.0, -5.0]
depth_mm = 6.0
radius_mm = 4.0
modulus_kpa = 200.0
outline = [[3, 0.1, 0.5]]
[[inclusion]]
id = "B"
kind = "malignant"
depth_mm = 9.0
radius_mm = 5.0
modulus_kpa = 900.0
boundary_width_mm = 1.0
outline = { orders = [4, 6], amplitude = [0.05, 0.1] }
surface_roughness = 0.1
severity_rank = 2
"""


def test_good_file_builds_the_described_phantom(tmp_path: Path) -> None:
    path = tmp_path / "lab.toml"
    path.write_text(GOOD_TOML)
    assert phantom_from_dict(GOOD, 3).tumors == load_phantom(path, 3).tumors
    ph = load_phantom(path, seed=3)
    assert isinstance(ph, Phantom) and ph.name == "lab-phantom" and ph.seed == 3
    assert ph.layer.size_mm == (80.0, 60.0) and ph.layer.nonlinearity == 1.5
    a, b = ph.tumors
    assert a.center_mm == (10.0, -5.0) and a.harmonics == ((3, 0.1, 0.5),)
    assert math.dist(a.center_mm, b.center_mm) >= 15.0
    assert [h[0] for h in b.harmonics] == [4, 6]
    assert all(0.05 <= h[1] <= 0.1 for h in b.harmonics)
    assert b.severity_rank == 2 and b.kind == "malignant"
    # same file, same seed: same phantom; another seed moves the random inclusion only
    again = load_phantom(path, seed=3)
    assert again.tumors == ph.tumors
    other = load_phantom(path, seed=4)
    assert other.tumors[0] == a and other.tumors[1].center_mm != b.center_mm
    # the remote station's world and the demo take a path as --phantom
    assert build_world(str(path), 3).phantom.tumors == ph.tumors


def test_no_inclusion_is_a_healthy_phantom() -> None:
    data = {"layer": {"size_mm": [50, 50], "thickness_mm": 10, "modulus_kpa": 30}}
    ph = phantom_from_dict(data)
    assert ph.tumors == () and ph.name == "custom"


def test_named_scenes_are_shipped_files() -> None:
    assert {"breast", "severity", "localization"} <= set(shipped_scene_names())
    for name in shipped_scene_names():
        assert resolve_phantom(name, 2).tumors == make_scene(name, 2).tumors
    sev = make_scene("severity", 5)
    assert sorted(t.severity_rank or 0 for t in sev.tumors) == [1, 2, 3, 4]


def _with(path: tuple[Any, ...], value: Any) -> dict[str, Any]:
    data = copy.deepcopy(GOOD)
    target: Any = data
    for key in path[:-1]:
        target = target[key]
    if value is _DELETE:
        del target[path[-1]]
    else:
        target[path[-1]] = value
    return data


_DELETE = object()

BAD = [
    (("layer",), _DELETE, "missing the [layer]"),
    (("layer",), "soft", "must be a table"),
    (("layer", "size_mm"), [80.0], "size_mm must be two finite positive"),
    (("layer", "size_mm"), [80.0, -1.0], "size_mm must be two finite positive"),
    (("layer", "size_mm"), _DELETE, "missing required field 'size_mm'"),
    (("layer", "thickness_mm"), 0.0, "thickness_mm must be > 0"),
    (("layer", "thickness_mm"), "20", "thickness_mm must be a finite number"),
    (("layer", "modulus_kpa"), -5.0, "modulus_kpa must be > 0"),
    (("layer", "modulus_kpa"), float("nan"), "modulus_kpa must be a finite number"),
    (("layer", "nonlinearity"), -0.5, "nonlinearity must be >= 0"),
    (("layer", "colour"), "pink", "unknown field(s) ['colour']"),
    (("placement", "half_mm"), 45.0, "reaches beyond the layer"),
    (("placement", "min_separation_mm"), -1.0, "min_separation_mm must be >= 0"),
    (("placement", "min_separation_mm"), 500.0, "could not place"),
    (("placement", "shuffle"), "yes", "shuffle must be true or false"),
    (("inclusion",), {"kind": "benign"}, "array of tables"),
    (("inclusion", 0, "kind"), "cyst", "kind must be one of"),
    (("inclusion", 0, "kind"), _DELETE, "inclusion 1: missing required field 'kind'"),
    (("inclusion", 0, "center_mm"), [100.0, 0.0], "outside the layer footprint"),
    (("inclusion", 0, "center_mm"), [1.0, "x"], "center_mm must be two finite numbers"),
    (("inclusion", 0, "depth_mm"), -1.0, "depth_mm must be >= 0"),
    (("inclusion", 0, "depth_mm"), 30.0, "deeper than the layer"),
    (("inclusion", 0, "depth_mm"), _DELETE, "missing required field 'depth_mm'"),
    (("inclusion", 0, "radius_mm"), 0.0, "radius_mm must be > 0"),
    (("inclusion", 0, "modulus_kpa"), True, "modulus_kpa must be a finite number"),
    (("inclusion", 0, "boundary_width_mm"), 0.0, "boundary_width_mm must be > 0"),
    (("inclusion", 0, "outline"), [[0, 0.1, 0.0]], "outline harmonic must be"),
    (("inclusion", 0, "outline"), [[3, 0.3, 0.0], [5, 0.3, 0.0]], "sum to < 0.5"),
    (("inclusion", 0, "outline"), "lobulated", "outline must be a list"),
    (("inclusion", 1, "outline"), {"orders": [], "amplitude": [0.1, 0.2]}, "orders must be"),
    (("inclusion", 1, "outline"), {"orders": [3], "amplitude": [0.2, 0.1]}, "amplitude must"),
    (("inclusion", 1, "outline"), {"orders": [3], "amplitude": [0.1, 0.2], "x": 1},
     "unknown field"),
    (("inclusion", 1, "surface_roughness"), 0.5, "surface_roughness must be < 0.5"),
    (("inclusion", 1, "severity_rank"), 0, "severity_rank must be an integer >= 1"),
    (("inclusion", 1, "severity_rank"), 1.5, "severity_rank must be an integer >= 1"),
    (("inclusion", 1, "id"), "A", "duplicate id 'A'"),
    (("inclusion", 1, "id"), "", "id must be a non-empty string"),
    (("inclusion", 1, "hardness"), 3, "unknown field(s) ['hardness']"),
    (("colour",), "pink", "unknown field(s) ['colour']"),
]


@pytest.mark.parametrize(("path", "value", "message"), BAD,
                         ids=[f"{'.'.join(map(str, p))}={v!r}"[:60] for p, v, _ in BAD])
def test_bad_field_is_refused_with_a_clear_error(path: tuple[Any, ...], value: Any,
                                                 message: str) -> None:
    with pytest.raises(ConfigError, match="phantom file lab") as info:
        phantom_from_dict(_with(path, value), source="lab.toml")
    assert message in str(info.value)


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read phantom file"):
        load_phantom(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[layer\nsize_mm = 3")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_phantom(bad)
    with pytest.raises(ConfigError, match="unknown phantom scene 'kidney'"):
        resolve_phantom("kidney")


def test_nonlinear_layer_stiffens_with_depth() -> None:
    linear = phantom_from_dict({"layer": {"size_mm": [60, 60], "thickness_mm": 20,
                                          "modulus_kpa": 50}})
    stiffening = phantom_from_dict({"layer": {"size_mm": [60, 60], "thickness_mm": 20,
                                              "modulus_kpa": 50, "nonlinearity": 2.0}})
    for depth in (0.5, 2.0, 4.0):
        k_lin = linear.force_n((0, 0, -depth)) / depth
        k_nl = stiffening.force_n((0, 0, -depth)) / depth
        assert k_nl > k_lin
    secant = [stiffening.force_n((0, 0, -d)) / d for d in (1.0, 2.0, 4.0)]
    assert secant[0] < secant[1] < secant[2]
