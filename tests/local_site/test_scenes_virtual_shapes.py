"""The six virtual shapes against their closed forms; spec parsing and the gallery."""

from __future__ import annotations

import math

import numpy as np
import pytest

from local_site.scenes import SHAPE_NAMES, VirtualShapeScene, make_shape_scene, open_scene
from local_site.scenes.factory import parse_shape_spec
from local_site.scenes.shapes import (
    BowPlatform,
    Cone,
    Cube,
    Hemisphere,
    SemiEllipsoid,
    TriangularPrism,
)
from local_site.scenes.virtual_shapes import shape_gallery, shape_parameters
from shared.errors import ConfigError
from shared.hardness import HardnessTable

RNG = np.random.default_rng(7)
POINTS = RNG.uniform(-15.0, 15.0, size=(500, 2))


def _heights(scene: VirtualShapeScene, pts: np.ndarray = POINTS) -> np.ndarray:
    return scene.sample(pts).height_mm


def test_the_six_paper_shapes_are_offered_in_order() -> None:
    assert SHAPE_NAMES == ("hemisphere", "cone", "cube", "bow_platform", "semi_ellipsoid",
                           "triangular_prism")
    gallery = shape_gallery(k=0.75)
    assert list(gallery) == list(SHAPE_NAMES)
    for scene in gallery.values():
        assert scene.version == 0 and scene.stiffness_k == 0.75
        x0, x1, y0, y1 = scene.extent_mm()
        layers = scene.rasterize((x0, x1, y0, y1), 0.5)
        assert layers["height_mm"].max() == pytest.approx(scene.shape.peak_height_mm, rel=0.1)
        assert layers["height_mm"][0, 0] == 0.0  # the extent's corner is on the floor


def test_hemisphere_closed_form() -> None:
    scene = VirtualShapeScene(Hemisphere(radius_mm=4.0, x_mm=2.0, y_mm=-1.0))
    expect = [math.sqrt(max(16.0 - (x - 2.0) ** 2 - (y + 1.0) ** 2, 0.0)) for x, y in POINTS]
    np.testing.assert_allclose(_heights(scene), expect, atol=1e-12)
    assert _heights(scene, np.array([[2.0, -1.0]]))[0] == pytest.approx(4.0)


def test_cone_closed_form() -> None:
    scene = VirtualShapeScene(Cone(radius_mm=6.0, height_mm=3.0))
    r = np.hypot(POINTS[:, 0], POINTS[:, 1])
    np.testing.assert_allclose(_heights(scene), np.where(r < 6.0, 3.0 * (1 - r / 6.0), 0.0),
                               atol=1e-12)
    assert _heights(scene, np.array([[3.0, 0.0], [0.0, 0.0]])).tolist() == pytest.approx(
        [1.5, 3.0])


def test_cube_closed_form_and_rotation() -> None:
    scene = VirtualShapeScene(Cube(side_mm=6.0, height_mm=4.0))
    inside = (np.abs(POINTS[:, 0]) <= 3.0) & (np.abs(POINTS[:, 1]) <= 3.0)
    np.testing.assert_allclose(_heights(scene), np.where(inside, 4.0, 0.0))
    turned = VirtualShapeScene(Cube(side_mm=6.0, height_mm=4.0, angle_deg=45.0))
    # a corner direction becomes an edge direction: (3.5, 0) is outside the square but
    # inside the diamond (half-diagonal 4.24 mm)
    pts = np.array([[3.5, 0.0], [0.0, 4.0], [3.0, 3.0]])
    assert _heights(scene, pts).tolist() == [0.0, 0.0, 4.0]
    assert _heights(turned, pts).tolist() == [4.0, 4.0, 0.0]


def test_semi_ellipsoid_closed_form() -> None:
    scene = VirtualShapeScene(SemiEllipsoid(semi_axis_x_mm=8.0, semi_axis_y_mm=5.0,
                                            height_mm=4.0))
    q = (POINTS[:, 0] / 8.0) ** 2 + (POINTS[:, 1] / 5.0) ** 2
    np.testing.assert_allclose(_heights(scene), 4.0 * np.sqrt(np.clip(1 - q, 0, None)),
                               atol=1e-12)


def test_triangular_prism_closed_form_and_rotation() -> None:
    scene = VirtualShapeScene(TriangularPrism(width_mm=8.0, length_mm=10.0, height_mm=4.0))
    x, y = POINTS[:, 0], POINTS[:, 1]
    expect = np.where((np.abs(x) <= 4.0) & (np.abs(y) <= 5.0),
                      4.0 * np.clip(1 - np.abs(x) / 4.0, 0, None), 0.0)
    np.testing.assert_allclose(_heights(scene), expect, atol=1e-12)
    turned = VirtualShapeScene(TriangularPrism(width_mm=8.0, length_mm=10.0, height_mm=4.0,
                                               angle_deg=90.0))
    # ridge now along x: height depends on |y|
    assert _heights(turned, np.array([[4.0, 2.0]]))[0] == pytest.approx(2.0)
    assert _heights(scene, np.array([[4.0, 2.0]]))[0] == pytest.approx(0.0, abs=1e-12)


def test_bow_platform_is_a_flat_annular_sector() -> None:
    shape = BowPlatform(inner_radius_mm=6.0, outer_radius_mm=10.0, span_deg=90.0,
                        height_mm=3.0)
    scene = VirtualShapeScene(shape)
    ring_centre = np.array([0.0, -8.0])
    polar = []
    for radius, angle_deg in [(8.0, 0.0), (6.5, 40.0), (9.9, -44.0), (5.5, 0.0), (10.5, 0.0),
                              (8.0, 50.0), (8.0, -60.0), (8.0, 180.0)]:
        a = math.radians(angle_deg)  # measured from +y towards +x
        polar.append(ring_centre + radius * np.array([math.sin(a), math.cos(a)]))
    h = _heights(scene, np.array(polar))
    assert h.tolist() == [3.0, 3.0, 3.0, 0.0, 0.0, 0.0, 0.0, 0.0]


def test_stiffness_and_friction_live_on_the_footprint() -> None:
    table = HardnessTable()
    scene = make_shape_scene("hemisphere", radius_mm=3.0, shore00=50.0, friction=0.4,
                             floor_k=0.9, floor_friction=0.1)
    s = scene.sample(np.array([[0.0, 0.0], [5.0, 0.0]]))
    assert s.stiffness_k.tolist() == pytest.approx([float(table.shore00_to_k(50.0)), 0.9])
    assert s.friction.tolist() == pytest.approx([0.4, 0.1])
    assert s.inside.all()


@pytest.mark.parametrize("kwargs", [{"shore00": 30, "k": 0.7}, {"k": 0.4}, {"k": 1.2},
                                    {"friction": -0.1}, {"friction": 1.1}, {"shore00": 120},
                                    {"radius_mm": -1.0}, {"radius_mm": float("nan")},
                                    {"depth_mm": 3.0}])
def test_invalid_shape_parameters_are_rejected(kwargs) -> None:
    with pytest.raises(ConfigError):
        make_shape_scene("hemisphere", **kwargs)


def test_bow_needs_outer_beyond_inner() -> None:
    with pytest.raises(ConfigError):
        BowPlatform(inner_radius_mm=8.0, outer_radius_mm=6.0)


def test_spec_strings() -> None:
    assert parse_shape_spec("hemisphere:radius_mm=10, shore00=30") == (
        "hemisphere", {"radius_mm": 10.0, "shore00": 30.0})
    scene = open_scene("semi-ellipsoid:semi_axis_x_mm=9,k=0.6,friction=0.25")
    assert isinstance(scene, VirtualShapeScene) and isinstance(scene.shape, SemiEllipsoid)
    assert scene.name == "semi_ellipsoid" and scene.shape.semi_axis_x_mm == 9.0
    assert scene.stiffness_k == 0.6 and scene.friction == 0.25
    assert "radius_mm" in shape_parameters("cone")
    for bad in ("pyramid", "cone:radius_mm", "cone:radius_mm=abc", "cone:radius_mm=1,radius_mm=2",
                "cone:colour=3", ""):
        with pytest.raises(ConfigError):
            open_scene(bad)
