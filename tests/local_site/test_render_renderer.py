"""Renderer: pin layout, height scaling and clamping, skips, rejection, super-resolution."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from numpy.typing import NDArray

from local_site.render import PIN_PITCH_MM, PinCommand, Renderer, RendererConfig, pin_offsets_mm
from local_site.scenes import (
    LayerFileData,
    LayerFileScene,
    SceneSample,
    SceneSource,
    TactileFrameScene,
    make_shape_scene,
)
from shared.errors import ConfigError, InputDataError
from shared.protocol import TactileFrame
from tests.support import scaled


class PlaneScene(SceneSource):
    """h = a x + b y + c, with fixed k and f; version bumps on demand."""

    def __init__(self, a: float = 0.3, b: float = -0.2, c: float = 2.0,
                 k: float = 0.8, f: float = 0.0) -> None:
        super().__init__()
        self.a, self.b, self.c, self.k, self.f = a, b, c, k, f
        self.calls = 0

    def bump(self) -> None:
        self._version += 1

    def _sample(self, p: NDArray[np.float64]) -> SceneSample:
        self.calls += 1
        n = p.shape[0]
        return SceneSample(self.a * p[:, 0] + self.b * p[:, 1] + self.c, np.full(n, self.k),
                           np.full(n, self.f), np.ones(n, dtype=bool))


class BrokenScene(PlaneScene):
    """Returns a configurable bad value at one pin."""

    def __init__(self, layer: str, value: float) -> None:
        super().__init__()
        self.layer, self.value = layer, value

    def _sample(self, p: NDArray[np.float64]) -> SceneSample:
        s = super()._sample(p)
        arrays_ = {"height_mm": s.height_mm.copy(), "stiffness_k": s.stiffness_k.copy(),
                   "friction": s.friction.copy()}
        arrays_[self.layer][5] = self.value
        return SceneSample(arrays_["height_mm"], arrays_["stiffness_k"], arrays_["friction"],
                           s.inside)


def _grid_scene(height: np.ndarray, extent: tuple[float, float, float, float],
                order: int = 1, k: np.ndarray | None = None,
                friction: np.ndarray | None = None) -> LayerFileScene:
    shape = height.shape
    data = LayerFileData(height, np.full(shape, 1.0) if k is None else k,
                         np.zeros(shape) if friction is None else friction, extent)
    return LayerFileScene(data, order=order)


# ------------------------------------------------------------------ layout


def test_pin_layout_convention() -> None:
    off = pin_offsets_mm()
    assert off.shape == (4, 4, 2)
    np.testing.assert_allclose(off[0, 0], [-1.5 * PIN_PITCH_MM, -1.5 * PIN_PITCH_MM])
    np.testing.assert_allclose(off[3, 3], [1.5 * PIN_PITCH_MM, 1.5 * PIN_PITCH_MM])
    np.testing.assert_allclose(off[0, 3], [1.5 * PIN_PITCH_MM, -1.5 * PIN_PITCH_MM])  # col +x
    np.testing.assert_allclose(off[3, 0], [-1.5 * PIN_PITCH_MM, 1.5 * PIN_PITCH_MM])  # row +y


def test_plane_is_rendered_at_each_pin_position() -> None:
    scene = PlaneScene()
    cmd = Renderer().render(scene, (1.0, -2.0, 30.0))
    pins = pin_offsets_mm() + np.array([1.0, -2.0])
    np.testing.assert_allclose(cmd.height_mm, 0.3 * pins[..., 0] - 0.2 * pins[..., 1] + 2.0)
    assert np.all(cmd.stiffness_k == 0.8)
    assert not cmd.friction_active
    assert cmd.position_mm == (1.0, -2.0)


def test_window_offset_shifts_the_window() -> None:
    scene = PlaneScene()
    a = Renderer(RendererConfig(window_offset_x_mm=2.0)).render(scene, (0.0, 0.0))
    b = Renderer().render(scene, (2.0, 0.0))
    np.testing.assert_allclose(a.height_mm, b.height_mm)


@pytest.mark.parametrize("order", [1, 3])
def test_interpolated_grid_scene_matches_a_linear_field_exactly(order: int) -> None:
    xs, ys = np.linspace(-10, 10, 41), np.linspace(-8, 8, 33)
    gx, gy = np.meshgrid(xs, ys)
    scene = _grid_scene(0.1 * gx - 0.05 * gy + 2.0, (-10, 10, -8, 8), order=order)
    rng = np.random.default_rng(3)
    renderer = Renderer()
    for _ in range(20):
        x, y = rng.uniform(-5, 5), rng.uniform(-4, 4)
        cmd = renderer.render(scene, (x, y))
        pins = pin_offsets_mm() + np.array([x, y])
        np.testing.assert_allclose(cmd.height_mm, 0.1 * pins[..., 0] - 0.05 * pins[..., 1] + 2.0,
                                   atol=1e-12)


# ------------------------------------------------------------------ height mapping


def test_absolute_mode_clamps_to_the_stroke() -> None:
    scene = PlaneScene(a=2.0, b=0.0, c=2.5)  # x in [-2.55, 2.55] -> h from -2.6 to 7.6
    cmd = Renderer().render(scene, (0.0, 0.0))
    assert cmd.height_mm.min() == 0.0 and cmd.height_mm.max() == 5.0
    assert cmd.clamped_pins == 8  # columns 0 (below 0) and 3 (above the stroke)
    np.testing.assert_allclose(cmd.height_mm[:, 1], 2.5 - 1.7)
    np.testing.assert_allclose(cmd.height_mm[:, 2], 2.5 + 1.7)


def test_gain_and_offset() -> None:
    scene = PlaneScene(a=1.0, b=0.0, c=0.0)
    cmd = Renderer(RendererConfig(height_gain=0.5, height_offset_mm=2.5)).render(scene, (0, 0))
    np.testing.assert_allclose(cmd.height_mm[0], 2.5 + 0.5 * PIN_PITCH_MM * np.array(
        [-1.5, -0.5, 0.5, 1.5]))
    assert cmd.clamped_pins == 0


def test_relative_mode_puts_the_lowest_point_at_the_offset() -> None:
    scene = PlaneScene(a=0.2, b=0.0, c=40.0)  # far above the stroke in absolute terms
    absolute = Renderer().render(scene, (0.0, 0.0))
    assert np.all(absolute.height_mm == 5.0)
    rel = Renderer(RendererConfig(height_mode="relative", height_offset_mm=1.0)).render(
        scene, (0.0, 0.0))
    assert rel.height_mm.min() == pytest.approx(1.0)
    np.testing.assert_allclose(rel.height_mm[:, 3] - rel.height_mm[:, 0], 0.2 * 3 * PIN_PITCH_MM)


# ------------------------------------------------------------------ skips


def test_unchanged_window_returns_the_same_object_without_sampling() -> None:
    scene = PlaneScene()
    renderer = Renderer(RendererConfig(move_threshold_mm=0.02))
    first = renderer.render(scene, (1.0, 1.0))
    calls = scene.calls
    again = renderer.render(scene, (1.01, 1.01))  # moved 0.014 mm < threshold
    assert again is first and scene.calls == calls
    moved = renderer.render(scene, (1.03, 1.0))  # 0.03 mm from the last rendered point
    assert moved is not first and scene.calls == calls + 1
    assert renderer.stats.rendered == 2 and renderer.stats.skipped == 1


def test_slow_creep_still_rerenders() -> None:
    scene = PlaneScene()
    renderer = Renderer(RendererConfig(move_threshold_mm=0.02))
    first = renderer.render(scene, (0.0, 0.0))
    x, last = 0.0, first
    for _ in range(5):
        x += 0.008
        last = renderer.render(scene, (x, 0.0))
    assert last is not first  # 0.04 mm of creep in 0.008 mm steps is rendered


def test_scene_change_or_another_scene_rerenders() -> None:
    scene, other = PlaneScene(), PlaneScene(c=3.0)
    renderer = Renderer()
    first = renderer.render(scene, (0.0, 0.0))
    scene.bump()
    second = renderer.render(scene, (0.0, 0.0))
    assert second is not first and second.scene_version == 1
    third = renderer.render(other, (0.0, 0.0))
    assert third is not second and third.height_mm[0, 0] == pytest.approx(
        second.height_mm[0, 0] + 1.0)


def test_skip_can_be_disabled() -> None:
    scene = PlaneScene()
    renderer = Renderer(RendererConfig(skip_unchanged=False))
    assert renderer.render(scene, (0, 0)) is not renderer.render(scene, (0, 0))


def test_friction_floor_and_friction_active() -> None:
    tiny = Renderer().render(PlaneScene(f=1e-5), (0, 0))
    assert not tiny.friction_active and np.all(tiny.friction == 0.0)
    real = Renderer().render(PlaneScene(f=0.4), (0, 0))
    assert real.friction_active and np.all(real.friction == 0.4)


# ------------------------------------------------------------------ rejection


@pytest.mark.parametrize("layer,value", [("height_mm", np.nan), ("height_mm", np.inf),
                                         ("height_mm", 5000.0), ("stiffness_k", 0.2),
                                         ("stiffness_k", np.nan), ("friction", 1.5),
                                         ("friction", -0.1)])
def test_bad_scene_values_are_rejected_and_the_last_command_stays(layer: str, value: float) -> None:
    renderer = Renderer()
    good = renderer.render(PlaneScene(), (0, 0))
    with pytest.raises(InputDataError):
        renderer.render(BrokenScene(layer, value), (0, 0))
    assert renderer.last_command is good and renderer.stats.rejected == 1


@pytest.mark.parametrize("position", [(np.nan, 0.0), (0.0, np.inf), (1.0,), "ab", None,
                                      (1.0, 2.0, 3.0, 4.0)])
def test_bad_positions_are_rejected(position) -> None:
    with pytest.raises(InputDataError):
        Renderer().render(PlaneScene(), position)


def test_pin_command_validates_and_is_read_only() -> None:
    with pytest.raises(InputDataError):
        PinCommand(np.full((4, 4), 5.1), np.ones((4, 4)), np.zeros((4, 4)))
    with pytest.raises(InputDataError):
        PinCommand(np.zeros((4, 3)), np.ones((4, 3)), np.zeros((4, 3)))
    with pytest.raises(InputDataError):
        PinCommand.flat(stiffness_k=0.4)
    cmd = PinCommand.flat(height_mm=3.0)
    with pytest.raises(ValueError):
        cmd.height_mm[0, 0] = 1.0
    assert cmd.max_difference(PinCommand.flat(height_mm=2.0)) == pytest.approx(1.0)


@pytest.mark.parametrize("kwargs", [{"height_mode": "log"}, {"pitch_mm": 0.0},
                                    {"stroke_mm": 6.0}, {"height_gain": 0.0},
                                    {"height_offset_mm": 5.5}, {"move_threshold_mm": -1.0},
                                    {"friction_floor": float("nan")}])
def test_bad_config_is_rejected(kwargs) -> None:
    with pytest.raises(ConfigError):
        RendererConfig(**kwargs)


def test_bad_tactile_frame_never_reaches_the_pins() -> None:
    scene = TactileFrameScene()
    renderer = Renderer()
    good = TactileFrame(layers={"height_mm": np.full((8, 8), 2.0)}, pitch_mm=1.0)
    scene.update(good)
    before = renderer.render(scene, (0, 0))
    bad = np.full((8, 8), 2.0)
    bad[3, 3] = np.nan
    with pytest.raises(InputDataError):
        scene.update(TactileFrame(layers={"height_mm": bad}, pitch_mm=1.0))
    assert renderer.render(scene, (0, 0)) is before  # content and version unchanged


# ------------------------------------------------------------------ super-resolution


def _sweep_profile(renderer: Renderer, scene: SceneSource,
                   xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Move the platform along x; collect (pin x, pin height) of the row-1 pins."""
    pos, val = [], []
    offsets = pin_offsets_mm()[1, :, 0]
    for x in xs:
        cmd = renderer.render(scene, (x, 0.0))
        pos.extend(x + offsets)
        val.extend(cmd.height_mm[1])
    order = np.argsort(pos)
    return np.asarray(pos)[order], np.asarray(val)[order]


@pytest.mark.parametrize("kind", ["analytic", "grid"])
def test_two_ridges_closer_than_the_pitch_are_resolved_by_moving(kind: str) -> None:
    """Ridges 1.0 mm apart (< 1.7 mm pitch): a still window misses them, moving resolves."""
    centres, half_width, peak = (-0.5, 0.5), 0.2, 3.0

    def ridges(x: np.ndarray) -> np.ndarray:
        return np.sum([peak * np.clip(1.0 - np.abs(x - c) / half_width, 0.0, None)
                       for c in centres], axis=0)

    if kind == "grid":
        xs = np.arange(-8.0, 8.0 + 1e-9, 0.05)
        gx, _ = np.meshgrid(xs, np.arange(-8.0, 8.0 + 1e-9, 0.5))
        scene: SceneSource = _grid_scene(ridges(gx), (-8.0, 8.0, -8.0, 8.0), order=1)
    else:
        scene = PlaneScene()

        def sample(p: NDArray[np.float64]) -> SceneSample:
            n = p.shape[0]
            return SceneSample(ridges(p[:, 0]), np.ones(n), np.zeros(n), np.ones(n, dtype=bool))

        scene._sample = sample  # type: ignore[method-assign]
    renderer = Renderer()
    still = renderer.render(scene, (0.0, 0.0))
    assert still.height_mm.max() < 0.01  # pins at +-0.85, +-2.55 mm fall between the ridges
    pos, val = _sweep_profile(renderer, scene, np.arange(-0.85, 0.85 + 1e-9, 0.05))
    window = (pos > -1.2) & (pos < 1.2)
    p, v = pos[window], val[window]
    left = p[np.argmax(np.where(p < 0, v, -1))]
    right = p[np.argmax(np.where(p > 0, v, -1))]
    assert left == pytest.approx(-0.5, abs=0.06) and right == pytest.approx(0.5, abs=0.06)
    assert v.max() == pytest.approx(peak, abs=0.05)
    dip = v[np.abs(p) < 0.1].max()
    assert dip < 0.1 * peak  # the valley between the ridges is felt too


# ------------------------------------------------------------------ properties


@settings(max_examples=80, deadline=None)
@given(height=arrays(np.float64, st.tuples(st.integers(2, 7), st.integers(2, 7)),
                     elements=st.floats(-1000.0, 1000.0)),
       k_unit=st.floats(0.0, 1.0), friction=st.floats(0.0, 1.0),
       order=st.sampled_from([0, 1, 3]),
       x=st.floats(-1e4, 1e4), y=st.floats(-1e4, 1e4),
       mode=st.sampled_from(["absolute", "relative"]),
       gain=st.floats(-50.0, 50.0).filter(lambda g: abs(g) > 1e-6),
       offset=st.floats(0.0, 5.0), edge=st.booleans(), data=st.data())
def test_random_layers_and_positions_give_valid_commands(height, k_unit, friction, order, x, y,
                                                         mode, gain, offset, edge,
                                                         data) -> None:
    shape = height.shape
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    k = np.clip(0.5 + 0.5 * k_unit * rng.random(shape), 0.5, 1.0)
    f = friction * rng.random(shape)
    k[0, 0], f[-1, -1] = 0.5, 1.0  # hit the range ends
    span = data.draw(st.floats(0.5, 50.0))
    from local_site.scenes import OutsidePolicy
    data_ = LayerFileData(height, k, f, (-span, span, -span / 2, span))
    scene = LayerFileScene(data_, order=order,
                           outside=OutsidePolicy("edge" if edge else "flat"))
    cfg = RendererConfig(height_mode=mode, height_gain=gain, height_offset_mm=offset)
    near = (data.draw(st.floats(-span, span)), data.draw(st.floats(-span, span)))
    for pos in ((x, y), near):
        renderer = Renderer(cfg)
        cmd = renderer.render(scene, pos)
        for arr in (cmd.height_mm, cmd.stiffness_k, cmd.friction):
            assert np.isfinite(arr).all()
            assert arr.shape == (4, 4) and arr.dtype == np.float64 and not arr.flags.writeable
        assert cmd.height_mm.min() >= 0.0 and cmd.height_mm.max() <= 5.0
        assert cmd.stiffness_k.min() >= 0.5 and cmd.stiffness_k.max() <= 1.0
        assert cmd.friction.min() >= 0.0 and cmd.friction.max() <= 1.0
        # the compiled pass against the numpy arithmetic it replaced, and the checking
        # constructor accepts what it built
        expected = _numpy_render(scene.sample(renderer.pin_positions_mm(pos)), cfg)
        for got, want in zip((cmd.height_mm, cmd.stiffness_k, cmd.friction), expected[:3],
                             strict=True):
            np.testing.assert_array_equal(got, want)
        assert cmd.clamped_pins == expected[3]
        sample = scene.sample(renderer.pin_positions_mm(pos))
        assert cmd.outside_pins == int(np.count_nonzero(~sample.inside))
        again = PinCommand(cmd.height_mm, cmd.stiffness_k, cmd.friction)
        assert again.friction_active == cmd.friction_active


class _LooseScene(PlaneScene):
    """Returns what a careless scene might: float32, a strided view, a list, ints."""

    def _sample(self, p: NDArray[np.float64]) -> SceneSample:
        s = super()._sample(p)
        wide = np.repeat(s.stiffness_k, 2)[::2]  # the same values, not contiguous
        return SceneSample(s.height_mm.astype(np.float32), wide,
                           s.friction.tolist(), s.inside.astype(int))


def test_sample_flat_is_sample_at_flat_points_as_contiguous_float_arrays() -> None:
    """The renderer's ``sample_flat`` gives what ``sample`` gives at the same points, with
    the arrays of the types its compiled pass takes, whatever the scene returned."""
    points = np.random.default_rng(3).uniform(-5, 5, (16, 2))
    for scene in (PlaneScene(f=0.2), _LooseScene(f=0.2),
                  _grid_scene(np.arange(20.0).reshape(4, 5), (-3.0, 3.0, -2.0, 2.0), order=3)):
        flat, full = scene.sample_flat(points), scene.sample(points)
        for got, want, dtype in zip(flat, full, (np.float64,) * 3 + (np.bool_,), strict=True):
            assert got.shape == (16,) and got.dtype == dtype and got.flags.c_contiguous
            np.testing.assert_array_equal(got, want)
    assert Renderer().render(_LooseScene(f=0.2), (1.0, 1.0)).friction_active


def test_a_window_centre_that_overflows_is_refused() -> None:
    """Position and window offset each finite, their sum not: refused and counted, never a
    command (the pins would otherwise get the scene's outside values)."""
    renderer = Renderer(RendererConfig(window_offset_x_mm=1e308))
    with pytest.raises(InputDataError, match="NaN or Inf"):
        renderer.render(PlaneScene(), (1.7e308, 0.0))
    assert renderer.stats.rejected == 1 and renderer.last_command is None


def test_sample_flat_refuses_arrays_of_the_wrong_length() -> None:
    class Short(PlaneScene):
        def _sample(self, p: NDArray[np.float64]) -> SceneSample:
            s = super()._sample(p)
            return SceneSample(s.height_mm[:-1], s.stiffness_k, s.friction, s.inside)

    with pytest.raises(InputDataError, match="height_mm of shape"):
        Short().sample_flat(np.zeros((16, 2)))


def _numpy_render(sample, cfg: RendererConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The renderer's arithmetic as numpy array operations (its implementation before the
    compiled pass): an independent reference."""
    h, k, f = sample.height_mm, sample.stiffness_k, sample.friction
    ref = h.min() if cfg.height_mode == "relative" else 0.0
    target = cfg.height_offset_mm + cfg.height_gain * (h - ref)
    height = np.clip(target, 0.0, cfg.stroke_mm)
    clamped = int(np.count_nonzero(np.abs(target - height) > 1e-9))
    friction = np.clip(f, 0.0, 1.0)
    friction[friction < cfg.friction_floor] = 0.0
    return height, np.clip(k, 0.5, 1.0), friction, clamped


@settings(max_examples=40, deadline=None)
@given(name=st.sampled_from(["hemisphere", "cone", "cube", "bow_platform", "semi_ellipsoid",
                             "triangular_prism"]),
       x=st.floats(-100.0, 100.0), y=st.floats(-100.0, 100.0),
       shore=st.floats(0.0, 100.0), friction=st.floats(0.0, 1.0))
def test_virtual_shapes_give_valid_commands_everywhere(name, x, y, shore, friction) -> None:
    scene = make_shape_scene(name, shore00=shore, friction=friction)
    cmd = Renderer().render(scene, (x, y))
    assert cmd.height_mm.min() >= 0.0 and cmd.height_mm.max() <= 5.0
    assert cmd.stiffness_k.min() >= 0.5 and cmd.stiffness_k.max() <= 1.0
    assert cmd.friction.min() >= 0.0 and cmd.friction.max() <= 1.0


def test_the_compiled_pass_is_ready_before_the_first_render() -> None:
    """Compiling inside the 1 kHz loop would stall its first render (~1 s without numba's
    cache): the renderer compiles at construction, for the argument types every render
    uses, whatever number types the settings were given in."""
    import subprocess
    import sys

    from local_site.render.renderer import _finish_kernel

    # a fresh process: constructing a renderer is what compiles it
    code = ("from local_site.render import Renderer; "
            "from local_site.render.renderer import _finish_kernel as k; "
            "Renderer(); print(len(k.signatures))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=scaled(120.0))
    assert out.stdout.strip() == "1"
    renderer = Renderer(RendererConfig(height_gain=1, height_offset_mm=0, stroke_mm=5))
    compiled = list(_finish_kernel.signatures)
    renderer.render(PlaneScene(0.3, 0.0, 0.0), (0.5, 0.5))
    Renderer().render(PlaneScene(0.1, 0.0, 0.0), (1.0, 2.0))
    assert list(_finish_kernel.signatures) == compiled and len(compiled) == 1


@pytest.mark.parametrize(("key", "value"), [("pitch_mm", 0.0), ("height_gain", 0.0),
                                            ("friction_floor", 1.0), ("height_mode", "x"),
                                            ("stroke_mm", float("nan"))])
def test_a_bad_render_setting_is_refused_under_its_table_s_name(key: str, value: object) -> None:
    """Named as the file and the environment name it (``[local.render]``), once."""
    from shared.config import resolve_config

    with pytest.raises(ConfigError, match=rf"^local\.render\.{key} must "):
        RendererConfig(**{key: value})  # type: ignore[arg-type]
    env = {f"TELETOUCH_LOCAL_RENDER_{key.upper()}": str(value)}
    with pytest.raises(ConfigError, match=rf"^local\.render\.{key}\b") as refused:
        resolve_config(RendererConfig, "local.render", environ=env)
    assert "[local.render]" not in str(refused.value), refused.value
