"""Layer files: round trip, orientation and extent, every malformed file rejected."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from local_site.render import Renderer
from local_site.scenes import LayerFileScene, load_layer_file, open_scene, save_layer_file
from local_site.scenes.base import OutsidePolicy
from shared.errors import ConfigError, InputDataError
from shared.hardness import HardnessTable

NY, NX = 5, 7
EXTENT = (-3.0, 3.0, -2.0, 2.0)  # dx = 1.0, dy = 1.0


def _layers() -> dict[str, np.ndarray]:
    gx, gy = np.meshgrid(np.linspace(-3, 3, NX), np.linspace(-2, 2, NY))
    return {"height_mm": (2.0 + 0.25 * gx + 0.5 * gy).astype(np.float32),
            "stiffness_shore00": np.full((NY, NX), 30.0),
            "friction": np.clip(0.1 * (gx + 3.0), 0, 1)}


def _write(path: Path, **arrays) -> Path:
    np.savez(path, **arrays)
    return path


def _valid(**override) -> dict:
    base = {"format_version": np.int64(1), "extent_mm": np.array(EXTENT), **_layers()}
    base.update(override)
    return {k: v for k, v in base.items() if v is not None}


def test_round_trip_and_orientation(tmp_path: Path) -> None:
    path = tmp_path / "scene.npz"
    layers = _layers()
    save_layer_file(path, height_mm=layers["height_mm"], extent_mm=EXTENT,
                    stiffness_shore00=layers["stiffness_shore00"], friction=layers["friction"],
                    description="ramp test")
    data = load_layer_file(path)
    np.testing.assert_allclose(data.height_mm, layers["height_mm"])
    np.testing.assert_allclose(data.stiffness_k, HardnessTable().shore00_to_k(30.0))
    np.testing.assert_allclose(data.friction, layers["friction"])
    assert data.extent_mm == EXTENT and data.stiffness_source == "shore00"
    assert data.description == "ramp test"
    scene = open_scene(str(path))
    assert isinstance(scene, LayerFileScene)
    # row index is +y and column index +x: h = 2 + 0.25 x + 0.5 y at any point
    s = scene.sample(np.array([[1.3, -0.4], [-3.0, 2.0]]))
    np.testing.assert_allclose(s.height_mm, [2.0 + 0.325 - 0.2, 2.0 - 0.75 + 1.0], atol=1e-6)
    assert s.inside.all()


def test_defaults_when_stiffness_and_friction_are_missing(tmp_path: Path) -> None:
    path = tmp_path / "h.npz"
    save_layer_file(path, height_mm=np.zeros((3, 3)), extent_mm=(0, 1, 0, 1))
    data = load_layer_file(path)
    assert data.stiffness_source == "default"
    assert np.all(data.stiffness_k == 1.0) and np.all(data.friction == 0.0)


def test_k_layer_is_used_as_is(tmp_path: Path) -> None:
    path = _write(tmp_path / "k.npz", **_valid(stiffness_shore00=None,
                                                stiffness_k=np.full((NY, NX), 0.6)))
    assert np.all(load_layer_file(path).stiffness_k == 0.6)


def test_outside_the_extent_is_flat_or_edge(tmp_path: Path) -> None:
    path = _write(tmp_path / "s.npz", **_valid())
    flat = LayerFileScene.from_file(path, outside=OutsidePolicy("flat", height_mm=0.5))
    edge = LayerFileScene.from_file(path, outside=OutsidePolicy("edge"))
    p = np.array([[10.0, 0.0]])
    assert flat.sample(p).height_mm[0] == 0.5 and not flat.sample(p).inside[0]
    assert edge.sample(p).height_mm[0] == pytest.approx(2.0 + 0.75)
    # column x = 1.45 and rows y = +-0.85 are inside: 2 of 16 pins
    cmd = Renderer().render(flat, (4.0, 0.0))
    assert cmd.outside_pins == 14


MALFORMED = {
    "missing height": _valid(height_mm=None),
    "missing extent": _valid(extent_mm=None),
    "missing version": _valid(format_version=None),
    "wrong version": _valid(format_version=np.int64(2)),
    "string version": _valid(format_version=np.str_("1")),
    "unknown key": _valid(depth=np.zeros((NY, NX))),
    "3-D height": _valid(height_mm=np.zeros((NY, NX, 3))),
    "integer height": _valid(height_mm=np.zeros((NY, NX), dtype=np.int32)),
    "1 x N": _valid(height_mm=np.zeros((1, NX)), stiffness_shore00=None, friction=None),
    "NaN height": _valid(height_mm=np.where(np.eye(NY, NX) > 0, np.nan, 0.0)),
    "Inf friction": _valid(friction=np.full((NY, NX), np.inf)),
    "huge height": _valid(height_mm=np.full((NY, NX), 2000.0)),
    "shape mismatch": _valid(friction=np.zeros((NY + 1, NX))),
    "k below range": _valid(stiffness_shore00=None, stiffness_k=np.full((NY, NX), 0.3)),
    "shore above range": _valid(stiffness_shore00=np.full((NY, NX), 130.0)),
    "k and shore": _valid(stiffness_k=np.full((NY, NX), 0.7)),
    "friction above 1": _valid(friction=np.full((NY, NX), 1.2)),
    "extent of 3": _valid(extent_mm=np.array([0.0, 1.0, 2.0])),
    "reversed extent": _valid(extent_mm=np.array([3.0, -3.0, -2.0, 2.0])),
    "NaN extent": _valid(extent_mm=np.array([np.nan, 3.0, -2.0, 2.0])),
    "description array": _valid(description=np.array(["a", "b"])),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_layer_files_are_rejected(tmp_path: Path, case: str) -> None:
    path = _write(tmp_path / "bad.npz", **MALFORMED[case])
    with pytest.raises(InputDataError) as err:
        load_layer_file(path)
    assert str(path) in str(err.value)


def test_files_that_are_not_npz_are_rejected(tmp_path: Path) -> None:
    text = tmp_path / "notes.npz"
    text.write_text("not a zip")
    npy = tmp_path / "plain.npy"
    np.save(npy, np.zeros((3, 3)))
    pickled = tmp_path / "obj.npz"
    np.savez(pickled, **_valid(), description=np.array([{"a": 1}], dtype=object))
    for path in (text, npy, pickled):
        with pytest.raises(InputDataError):
            load_layer_file(path)
    with pytest.raises(ConfigError):
        load_layer_file(tmp_path / "missing.npz")


def test_save_refuses_layers_that_would_not_load(tmp_path: Path) -> None:
    with pytest.raises(InputDataError):
        save_layer_file(tmp_path / "x.npz", height_mm=np.full((3, 3), np.nan),
                        extent_mm=(0, 1, 0, 1))
    assert not (tmp_path / "x.npz").exists()
