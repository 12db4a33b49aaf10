"""The remote tactile stream: updates, bookkeeping, rejection, extent handling."""

from __future__ import annotations

import numpy as np
import pytest

from local_site.render import Renderer
from local_site.scenes import OutsidePolicy, TactileFrameScene, open_scene
from shared.errors import ConfigError, InputDataError
from shared.hardness import StiffnessShoreCurve, StiffnessToK
from shared.protocol import TactileFrame, decode, encode


def _frame(height: np.ndarray | None = None, *, seq: int = 1, center=(10.0, -5.0),
           pitch: float = 0.5, **layers: np.ndarray) -> TactileFrame:
    h = np.full((12, 16), 2.0) if height is None else height
    return TactileFrame(seq=seq, ts_us=1000 * seq, center_mm=center, pitch_mm=pitch,
                        layers={"height_mm": h, **layers}, contact=True, force_n=1.5,
                        source_seq=seq - 1)


def test_empty_stream_is_flat_and_outside() -> None:
    scene = open_scene("remote")
    assert isinstance(scene, TactileFrameScene)
    s = scene.sample(np.zeros((3, 2)))
    assert not s.inside.any() and np.all(s.height_mm == 0.0) and np.all(s.stiffness_k == 1.0)
    assert scene.age_s() is None and scene.last_seq is None and scene.version == 0


def test_update_replaces_content_and_keeps_bookkeeping() -> None:
    scene = TactileFrameScene()
    ny, nx = 12, 16
    gx, gy = np.meshgrid(np.arange(nx), np.arange(ny))
    h = 0.1 * gx + 0.2 * gy  # column along +x, row along +y
    scene.update(_frame(h, seq=7), now_s=100.0)
    assert scene.version == 1 and scene.last_seq == 7 and scene.last_ts_us == 7000
    assert scene.last_source_seq == 6 and scene.frames_accepted == 1
    assert scene.age_s(now_s=100.25) == pytest.approx(0.25)
    # grid centred at (10, -5), pitch 0.5: column c at x = 10 + (c - 7.5) * 0.5
    x, y = 10.0 + (3 - 7.5) * 0.5, -5.0 + (9 - 5.5) * 0.5
    assert scene.sample(np.array([[x, y]])).height_mm[0] == pytest.approx(0.1 * 3 + 0.2 * 9)
    assert scene.extent_mm() == pytest.approx((6.25, 13.75, -7.75, -2.25))
    scene.update(_frame(np.full((ny, nx), 4.0), seq=8), now_s=101.0)  # latest wins
    assert scene.version == 2 and scene.sample(np.array([[x, y]])).height_mm[0] == 4.0


def test_frames_through_the_wire_codec_render() -> None:
    scene = TactileFrameScene()
    frame = _frame(np.full((12, 16), 3.0), stiffness_k=np.full((12, 16), 0.7, np.float32),
                   friction=np.full((12, 16), 0.25))
    decoded = decode(encode(frame))
    assert isinstance(decoded, TactileFrame)
    scene.update(decoded)
    cmd = Renderer().render(scene, (10.0, -5.0))
    assert np.allclose(cmd.height_mm, 3.0) and np.allclose(cmd.stiffness_k, 0.7)
    assert cmd.friction_active and cmd.outside_pins == 0


def test_measured_stiffness_goes_through_the_shared_mapping() -> None:
    # N/mm -> Shore 00 linear in log N/mm from (0.1, 0) to (10, 100); Shore 10..90 -> k 0.5..1
    to_k = StiffnessToK(StiffnessShoreCurve(((0.1, 0.0), (10.0, 100.0))))
    scene = TactileFrameScene(stiffness_to_k=to_k)
    n = np.full((12, 16), 1.0)
    n[:, 8:] = 50.0  # stiffer than the curve: clamped to k = 1
    scene.update(_frame(stiffness_n_per_mm=n))
    k = scene.sample(np.array([[7.0, -5.0], [13.0, -5.0]])).stiffness_k
    assert k.tolist() == pytest.approx([0.75, 1.0])
    assert k[0] == pytest.approx(float(to_k.k(1.0)))
    scene2 = TactileFrameScene(default_stiffness_k=0.6)
    scene2.update(_frame())
    assert scene2.sample(np.array([[10.0, -5.0]])).stiffness_k[0] == pytest.approx(0.6)
    # without a mapping, a frame with only N/mm renders at the default k (no guessed mapping)
    scene2.update(_frame(stiffness_n_per_mm=n))
    assert scene2.sample(np.array([[7.0, -5.0]])).stiffness_k[0] == pytest.approx(0.6)


def _nan_height() -> np.ndarray:
    h = np.full((12, 16), 1.0)
    h[4, 4] = np.nan
    return h


BAD_FRAMES = {
    "NaN height": lambda: _frame(_nan_height()),
    "height out of range": lambda: _frame(np.full((12, 16), 11.0)),
    "k out of range": lambda: _frame(stiffness_k=np.full((12, 16), 1.5)),
    "friction negative": lambda: _frame(friction=np.full((12, 16), -0.2)),
    "shape mismatch": lambda: _frame(friction=np.zeros((12, 15))),
    "1-D layer": lambda: _frame(np.zeros(16)),
    "1 x N": lambda: _frame(np.zeros((1, 16))),
    "integer layer": lambda: _frame(np.zeros((12, 16), dtype=np.int16)),
    "list layer": lambda: _frame([[0.0, 1.0], [1.0, 0.0]]),  # type: ignore[arg-type]
    "unknown layer": lambda: _frame(temperature=np.zeros((12, 16))),
    "no height": lambda: TactileFrame(layers={"friction": np.zeros((4, 4))}),
    "zero pitch": lambda: _frame(pitch=0.0),
    "NaN centre": lambda: _frame(center=(np.nan, 0.0)),
    "short centre": lambda: _frame(center=(1.0,)),
}


@pytest.mark.parametrize("case", sorted(BAD_FRAMES))
def test_bad_frames_are_rejected_and_content_is_kept(case: str) -> None:
    scene = TactileFrameScene()
    scene.update(_frame(np.full((12, 16), 2.0)), now_s=5.0)
    renderer = Renderer()
    before = renderer.render(scene, (10.0, -5.0))
    with pytest.raises(InputDataError):
        scene.update(BAD_FRAMES[case](), now_s=6.0)
    assert scene.version == 1 and scene.frames_rejected == 1 and scene.last_update_s == 5.0
    assert renderer.render(scene, (10.0, -5.0)) is before


def test_not_a_frame_is_rejected() -> None:
    with pytest.raises(InputDataError):
        TactileFrameScene().update("frame")  # type: ignore[arg-type]


def test_window_partly_outside_the_frame_degrades_per_pin() -> None:
    scene = TactileFrameScene()
    scene.update(_frame(np.full((12, 16), 3.0)))  # x in [6.25, 13.75]
    cmd = Renderer().render(scene, (13.0, -5.0))  # pin columns at 10.45, 12.15, 13.85, 15.55
    assert cmd.outside_pins == 8
    assert np.all(cmd.height_mm[:, :2] == 3.0) and np.all(cmd.height_mm[:, 2:] == 0.0)
    held = TactileFrameScene(outside=OutsidePolicy("edge"))
    held.update(_frame(np.full((12, 16), 3.0)))
    assert np.all(Renderer().render(held, (13.0, -5.0)).height_mm == 3.0)


def test_clear_empties_the_scene() -> None:
    scene = TactileFrameScene()
    scene.update(_frame())
    scene.clear()
    assert scene.version == 2 and scene.last_frame is None and scene.extent_mm() is None
    assert Renderer().render(scene, (10.0, -5.0)).outside_pins == 16


def test_bad_settings_are_rejected() -> None:
    with pytest.raises(ConfigError):
        TactileFrameScene(default_stiffness_k=0.2)
    with pytest.raises(ConfigError):
        TactileFrameScene(stiffness_to_k=(2.0, 1.0))  # type: ignore[arg-type]
    with pytest.raises(ConfigError):
        TactileFrameScene(order=2)
    with pytest.raises(ConfigError):
        open_scene("hemisphere", default_stiffness_k=0.7)


@pytest.mark.parametrize(("layers", "message"), [
    ({"height_mm": np.nan}, "'height_mm' contains NaN or Inf"),
    ({"height_mm": np.inf}, "'height_mm' contains NaN or Inf"),
    ({"friction": -np.inf}, "'friction' contains NaN or Inf"),
    ({"stiffness_k": 1.5}, r"'stiffness_k' must lie in \[0.5, 1.0\], got \[0.7, 1.5\]"),
    ({"height_mm": -10.5}, r"'height_mm' must lie in \[-10.0, 10.0\], got \[-10.5, 1\]"),
])
def test_a_bad_layer_value_gets_its_own_message(layers: dict[str, float], message: str) -> None:
    # the range check runs first (NaN and Inf fail it too); the message still names which
    base = {"height_mm": np.full((12, 16), 1.0), "stiffness_k": np.full((12, 16), 0.7),
            "friction": np.full((12, 16), 0.3)}
    for name, value in layers.items():
        base[name][4, 4] = value
    with pytest.raises(InputDataError, match=message):
        TactileFrameScene().update(TactileFrame(layers=base, center_mm=(0.0, 0.0),
                                                pitch_mm=0.5), now_s=1.0)

