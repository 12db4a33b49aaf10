"""Layer files: round trip, orientation and extent, every malformed file rejected."""

from __future__ import annotations

import io
import time
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from local_site.render import Renderer
from local_site.scenes import LayerFileScene, load_layer_file, open_scene, save_layer_file
from local_site.scenes.base import OutsidePolicy
from local_site.scenes.layer_file import MIN_LAYER_SPACING_MM
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


def test_save_refuses_a_description_the_reader_would_refuse(tmp_path: Path) -> None:
    """A description over 262,144 characters (1 MiB as stored) was saved, then refused
    at load by the small-member limit; now it is refused at save, by name."""
    most = 262_144  # local_site.scenes.layer_file.MAX_DESCRIPTION_CHARS
    h = np.zeros((3, 3))
    path = tmp_path / "edge.npz"
    save_layer_file(path, height_mm=h, extent_mm=(0, 1, 0, 1),
                    description="d" * most)
    assert len(load_layer_file(path).description) == most
    long = tmp_path / "long.npz"
    with pytest.raises(InputDataError, match=r"long\.npz: description is 262145 characters; "
                       r"at most 262144"):
        save_layer_file(long, height_mm=h, extent_mm=(0, 1, 0, 1),
                        description="d" * (most + 1))
    assert not long.exists()


# --- hostile files: refused by member name and .npy header before any data is read ---

def _npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr, allow_pickle=False)
    return buf.getvalue()


def _declared(shape: tuple[int, ...], descr: str = "<f8", body: bytes = b"\0" * 1024) -> bytes:
    """An .npy member whose header declares ``shape`` but whose data is only ``body``."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue() + body


def _zip(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in members.items():
            z.writestr(name, data)
    return path


def _valid_members(**override: bytes) -> dict[str, bytes]:
    members = {f"{k}.npy": _npy(np.asarray(v)) for k, v in _valid().items()}
    members.update(override)
    return members


def test_a_corrupt_compressed_member_is_an_input_error_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "corrupt.npz"
    np.savez_compressed(path, **_valid())
    raw = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as z:
        info = z.getinfo("height_mm.npy")
    start = info.header_offset + 30 + len(info.filename) + len(info.extra)
    for i in range(start + 5, start + 40):  # garble the deflate stream (zlib.error before)
        raw[i] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(InputDataError, match="cannot read") as err:
        load_layer_file(path)
    assert str(path) in str(err.value)


@pytest.mark.parametrize("member", ["height_mm.npy", "friction.npy", "format_version.npy",
                                    "description.npy"])
def test_a_header_declaring_a_huge_array_is_refused_before_reading(tmp_path: Path,
                                                                   member: str) -> None:
    # 200000 x 200000 float64 is 298 GiB: the loader used to allocate it (MemoryError)
    shape = (200000, 200000) if member != "description.npy" else ()
    descr = "<U100000000" if member == "description.npy" else "<f8"
    path = _zip(tmp_path / "bomb.npz", _valid_members(**{member: _declared(shape, descr)}))
    assert path.stat().st_size < 4096
    start = time.perf_counter()
    with pytest.raises(InputDataError) as err:
        load_layer_file(path)
    assert time.perf_counter() - start < 5.0
    assert str(path) in str(err.value) and member[:-4] in str(err.value)


def test_an_oversized_layer_allocates_nothing_before_it_is_refused(tmp_path: Path) -> None:
    # 5000 x 5000 float64 (200 MB) declared, 1 kB of data: the loader used to allocate the
    # whole array, then fail on the truncated data; now the header alone refuses it
    path = _zip(tmp_path / "big.npz", _valid_members(**{"height_mm.npy": _declared((5000, 5000))}))
    tracemalloc.start()
    try:
        with pytest.raises(InputDataError, match="samples per side"):
            load_layer_file(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 8 * 2**20, f"peak {peak / 2**20:.1f} MiB"


def test_unknown_members_are_refused_by_name_before_any_is_read(tmp_path: Path) -> None:
    # the unknown member declares 298 GiB: refused by its name, its header never read
    path = _zip(tmp_path / "extra.npz",
                _valid_members(**{"depth.npy": _declared((200000, 200000))}))
    with pytest.raises(InputDataError, match=r"unknown key.*depth") as err:
        load_layer_file(path)
    assert str(path) in str(err.value)
    raw = _zip(tmp_path / "raw.npz", _valid_members(**{"notes.txt": b"hello"}))
    with pytest.raises(InputDataError, match=r"notes\.txt"):
        load_layer_file(raw)


@pytest.mark.parametrize("case", ["pickled", "integer layer", "3-D layer", "truncated",
                                  "not npy", "negative shape"])
def test_malformed_members_are_refused(tmp_path: Path, case: str) -> None:
    member = {
        "pickled": _declared((NY, NX), "|O"),
        "integer layer": _npy(np.zeros((NY, NX), np.int32)),
        "3-D layer": _declared((NY, NX, 3)),
        "truncated": _declared((NY, NX), body=b"\0" * 8),
        "not npy": b"this is not an npy member",
        "negative shape": _declared((-3, NX)),
    }[case]
    path = _zip(tmp_path / "bad.npz", _valid_members(**{"height_mm.npy": member}))
    with pytest.raises(InputDataError) as err:
        load_layer_file(path)
    assert str(path) in str(err.value)


def test_a_compressed_file_round_trips_through_the_header_checked_reader(
        tmp_path: Path) -> None:
    path = tmp_path / "c.npz"
    arrays = _valid(height_mm=np.asfortranarray(np.arange(NY * NX, dtype=np.float64)
                                                .reshape(NY, NX) / 10.0))
    np.savez_compressed(path, **arrays)
    data = load_layer_file(path)
    np.testing.assert_array_equal(data.height_mm, arrays["height_mm"])
    np.testing.assert_allclose(data.friction, arrays["friction"])


# --- every file save_layer_file writes loads (docs/layer_files.md) ---

_COORD = st.floats(-1e4, 1e4)


@st.composite
def _extents(draw: st.DrawFn) -> tuple[float, float, float, float]:
    x0, y0 = draw(_COORD), draw(_COORD)
    # spans from the smallest sub-normal float up to the whole range
    sx, sy = draw(st.floats(5e-324, 2e4)), draw(st.floats(5e-324, 2e4))
    x1, y1 = x0 + sx, y0 + sy
    assume(x1 > x0 and y1 > y0 and abs(x1) <= 1e4 and abs(y1) <= 1e4)
    return (x0, x1, y0, y1)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(h=arrays(np.float64, st.tuples(st.integers(2, 6), st.integers(2, 6)),
                elements=st.floats(-1000, 1000)),
       ext=_extents())
@example(h=np.zeros((2, 3)), ext=(0.0, 5e-324, 0.0, 1.0))  # spacing underflowed to 0
@example(h=np.zeros((3, 2)), ext=(0.0, 1.0, 0.0, 1e-300))
def test_every_saved_file_loads_and_its_corners_are_inside(
        tmp_path_factory: pytest.TempPathFactory, h: np.ndarray,
        ext: tuple[float, float, float, float]) -> None:
    path = tmp_path_factory.mktemp("rt") / "t.npz"
    try:
        save_layer_file(path, height_mm=h, extent_mm=ext)
    except InputDataError as err:  # refused up front, nothing written: fine
        assert not path.exists() and str(path) in str(err)
        ny, nx = h.shape
        assert ((ext[1] - ext[0]) / (nx - 1) < MIN_LAYER_SPACING_MM
                or (ext[3] - ext[2]) / (ny - 1) < MIN_LAYER_SPACING_MM)
        return
    scene = LayerFileScene.from_file(path, order=1)
    x0, x1, y0, y1 = ext
    s = scene.sample(np.array([[x0, y0], [x1, y1], [x0, y1], [x1, y0]]))
    assert s.inside.all()
    np.testing.assert_allclose(s.height_mm, [h[0, 0], h[-1, -1], h[-1, 0], h[0, -1]],
                               atol=1e-9 * (1 + np.abs(h).max()))


def test_a_spacing_below_the_minimum_is_refused_with_the_path(tmp_path: Path) -> None:
    path = _write(tmp_path / "tiny.npz", **_valid(extent_mm=np.array([0.0, 5e-324, 0.0, 1.0])))
    with pytest.raises(InputDataError, match="spacing") as err:
        load_layer_file(path)
    assert str(path) in str(err.value)
    with pytest.raises(InputDataError, match="spacing"):
        save_layer_file(tmp_path / "s.npz", height_mm=np.zeros((2, 3)),
                        extent_mm=(0.0, 1e-7, 0.0, 1.0))
    assert not (tmp_path / "s.npz").exists()
