"""Codec tests: exact bytes, round trips over the whole field range, every bad-input class.

No event loop and no network: bytes in, messages or typed errors out.
"""

from __future__ import annotations

import contextlib
import math
import struct

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from shared.errors import (
    FieldError,
    LocalProtocolError,
    MalformedMessageError,
    NonFiniteError,
    OversizeError,
    RemoteProtocolError,
    UnknownMessageTypeError,
    VersionError,
)
from shared.protocol import (
    ArmCommand,
    ArmState,
    Bye,
    ClockPing,
    ClockPong,
    DataMessage,
    Error,
    Hello,
    Hop,
    PlatformState,
    Stats,
    TactileFrame,
    Welcome,
    decode,
    encode,
)

U63 = st.integers(min_value=0, max_value=2**63 - 1)
COORD = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False)
STAGE = st.from_regex(r"[a-z][a-z0-9_]{0,31}", fullmatch=True)
HOPS = st.lists(st.builds(Hop, st.sampled_from(["local", "remote", "relay"]), STAGE, U63),
                max_size=32).map(tuple)


def pack(obj: object) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def test_platform_state_exact_bytes() -> None:
    """The wire form is a msgpack map with v, type and the documented fields, in that order."""
    msg = PlatformState(seq=7, ts_us=1_000, hops=(Hop("local", "capture", 999),),
                        position_mm=(1.5, -2.0, 3.25), velocity_mm_s=(0.0, 0.0, 0.0))
    expected = pack({"v": 1, "type": "platform_state", "seq": 7, "ts": 1_000,
                     "hops": [["local", "capture", 999]], "position_mm": [1.5, -2.0, 3.25],
                     "velocity_mm_s": [0.0, 0.0, 0.0]})
    assert encode(msg) == expected
    assert decode(expected) == msg


def test_array_layer_is_raw_little_endian_bytes() -> None:
    height = np.arange(16, dtype=np.float32).reshape(4, 4) / 10
    frame = TactileFrame(seq=1, ts_us=2, layers={"height_mm": height})
    raw = msgpack.unpackb(encode(frame), raw=False)
    layer = raw["layers"]["height_mm"]
    assert layer == {"dtype": "<f4", "shape": [4, 4], "data": height.astype("<f4").tobytes()}


@settings(max_examples=200, deadline=None)
@given(seq=U63, ts=U63, hops=HOPS, pos=st.tuples(COORD, COORD, COORD),
       vel=st.tuples(*[st.floats(-1e5, 1e5, allow_nan=False)] * 3))
def test_platform_state_round_trip(seq, ts, hops, pos, vel) -> None:
    msg = PlatformState(seq=seq, ts_us=ts, hops=hops, position_mm=pos, velocity_mm_s=vel)
    assert decode(encode(msg)) == msg


@settings(max_examples=100, deadline=None)
@given(action=st.sampled_from(["move", "stop", "home", "set_force_limit"]),
       target=st.tuples(COORD, COORD, COORD),
       force=st.floats(0, 1000, exclude_min=True, allow_nan=False))
def test_arm_command_round_trip(action, target, force) -> None:
    msg = ArmCommand(seq=1, ts_us=2, action=action,
                     target_mm=target if action == "move" else None,
                     force_limit_n=force if action == "set_force_limit" else None)
    assert decode(encode(msg)) == msg


@settings(max_examples=100, deadline=None)
@given(shape=st.tuples(st.integers(1, 40), st.integers(1, 40)), data=st.data(),
       dtype=st.sampled_from([np.float32, np.float64]),
       extra=st.sets(st.sampled_from(["stiffness_k", "friction", "stiffness_n_per_mm"])))
def test_tactile_frame_round_trip(shape, data, dtype, extra) -> None:
    ranges = {"height_mm": (-10, 10), "stiffness_k": (0.5, 1), "friction": (0, 1),
              "stiffness_n_per_mm": (0, 1e4)}
    layers = {}
    for name in ["height_mm", *sorted(extra)]:
        lo, hi = ranges[name]
        layers[name] = data.draw(hnp.arrays(dtype, shape, elements=st.floats(
            lo, hi, allow_nan=False, width=32 if dtype == np.float32 else 64)))
    msg = TactileFrame(seq=3, ts_us=4, center_mm=(1.0, 2.0), pitch_mm=0.5, layers=layers,
                       contact=True, force_n=1.5, indentation_mm=0.3, source_seq=9,
                       source_ts_us=10)
    out = decode(encode(msg))
    assert isinstance(out, TactileFrame)
    assert set(out.layers) == set(layers)
    for name, arr in layers.items():
        np.testing.assert_array_equal(out.layers[name], arr)
        assert out.layers[name].dtype == arr.dtype
    assert (out.seq, out.center_mm, out.source_seq, out.source_ts_us) == (3, (1.0, 2.0), 9, 10)


@pytest.mark.parametrize("msg", [
    Hello(role="local", session="ward-3", token="t" * 64, name="haptic station"),
    Welcome(session="ward-3", role="remote", server_time_us=5, ping_interval_s=1.0,
            max_message_bytes=1 << 20),
    ClockPing(ping_id=1, t0_us=10),
    ClockPong(ping_id=1, t0_us=10, t1_us=20, t2_us=21),
    Error(code="bad_field", message="platform_state.seq is missing", fatal=False),
    Bye(reason="operator quit"),
    ArmState(seq=1, ts_us=2, position_mm=(1, 2, 3), force_n=0.5, status="ok", source_seq=4),
])
def test_control_round_trip(msg) -> None:
    assert decode(encode(msg)) == msg


def test_stats_round_trip_nested() -> None:
    metrics = {"clock_offset_us": {"local": -12.5, "remote": 3}, "drops": 0, "note": "ok",
               "dir": {"local_to_remote": {"p50_us": 100.0, "p99_us": 400.0}}}
    out = decode(encode(Stats(scope="relay", time_us=1, metrics=metrics)))
    assert isinstance(out, Stats)
    assert out.metrics == metrics


# ----------------------------------------------------------------------------- bad input


def good_platform_map(**over) -> dict:
    base = {"v": 1, "type": "platform_state", "seq": 1, "ts": 2, "hops": [],
            "position_mm": [0.0, 0.0, 0.0], "velocity_mm_s": [0.0, 0.0, 0.0]}
    base.update(over)
    return base


@pytest.mark.parametrize("data", [b"", b"\xc1", b"\x92\x01", b"\xa3abc", b"\x81\xa1v"])
def test_malformed_bytes(data: bytes) -> None:
    with pytest.raises(MalformedMessageError):
        decode(data)


def test_trailing_bytes_are_malformed() -> None:
    with pytest.raises(MalformedMessageError, match="trailing"):
        decode(pack(good_platform_map()) + b"\x00")


def test_non_string_keys_are_malformed() -> None:
    with pytest.raises(MalformedMessageError):
        decode(msgpack.packb({1: 2}))


@pytest.mark.parametrize("v", [None, 0, 3, "1", True, 1.0])  # 2: protocol v2 reads v1 types
def test_bad_version(v) -> None:
    obj = good_platform_map()
    if v is None:
        del obj["v"]
    else:
        obj["v"] = v
    with pytest.raises(VersionError):
        decode(pack(obj))


@pytest.mark.parametrize("t", ["nope", "", 3, None, "x" * 1000])
def test_unknown_type(t) -> None:
    with pytest.raises(UnknownMessageTypeError):
        decode(pack(good_platform_map(type=t)))


@pytest.mark.parametrize("over, match", [
    ({"seq": -1}, "seq"), ({"seq": "1"}, "seq"), ({"seq": True}, "seq"), ({"seq": 1.0}, "seq"),
    ({"ts": 2**64 - 1}, "ts"), ({"position_mm": [0, 0]}, "position_mm"),
    ({"position_mm": [0, "a", 0]}, r"position_mm\[1\]"), ({"position_mm": [0, 0, 1e9]}, "outside"),
    ({"hops": [["mars", "capture", 1]]}, "hops"), ({"hops": [["local", "Bad Stage", 1]]}, "hops"),
    ({"hops": [["local", "x", 1]] * 33}, "hops"), ({"hops": "x"}, "hops"),
])
def test_wrong_fields(over, match) -> None:
    with pytest.raises(FieldError, match=match):
        decode(pack(good_platform_map(**over)))


def test_missing_field_names_type_and_field() -> None:
    obj = good_platform_map()
    del obj["position_mm"]
    with pytest.raises(FieldError, match=r"platform_state\.position_mm is missing"):
        decode(pack(obj))


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_numbers(bad) -> None:
    with pytest.raises(NonFiniteError):
        decode(pack(good_platform_map(position_mm=[0.0, bad, 0.0])))


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_array_rejected(bad) -> None:
    height = np.zeros((4, 4), np.float32)
    height[2, 1] = bad
    layer = {"dtype": "<f4", "shape": [4, 4], "data": height.tobytes()}
    obj = {"v": 1, "type": "tactile_frame", "seq": 1, "ts": 1, "center_mm": [0, 0],
           "pitch_mm": 1.7, "layers": {"height_mm": layer}, "contact": False, "force_n": 0.0,
           "indentation_mm": 0.0}
    with pytest.raises(NonFiniteError, match="height_mm"):
        decode(pack(obj))


def _with_pairs(pairs: list[tuple[str, object]]) -> bytes:
    """A msgpack map of ``pairs`` as given (a key may come twice)."""
    return bytes([0x80 | len(pairs)]) + b"".join(pack(k) + pack(v) for k, v in pairs)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("where", ["top", "nested_map", "nested_list", "metrics_list"])
def test_a_non_finite_number_under_an_unknown_key_is_refused(bad, where) -> None:
    """§2: NaN and infinities are refused everywhere, unknown keys too (a relay forwards a
    data message's unknown keys as the sender wrote them)."""
    value = {"top": bad, "nested_map": {"a": {"b": bad}}, "nested_list": [1.0, [2.0, bad]],
             "metrics_list": [{"x": bad}]}[where]
    with pytest.raises(NonFiniteError, match="finite"):
        decode(pack(good_platform_map(future=value)))


def test_a_non_finite_number_keeps_the_earlier_checks_first() -> None:
    """The checks' order holds with a NaN anywhere: a bad key or a key twice (even after
    the NaN), the version, the type, then the field's own error naming it."""
    nan = math.nan
    with pytest.raises(MalformedMessageError, match="given twice"):
        decode(_with_pairs([*good_platform_map(future=nan).items(), ("seq", 2)]))
    with pytest.raises(VersionError):
        decode(pack(good_platform_map(v=7, future=nan)))
    with pytest.raises(UnknownMessageTypeError):
        decode(pack(good_platform_map(type="nope", future=nan)))
    with pytest.raises(NonFiniteError, match=r"position_mm\[1\]"):
        decode(pack(good_platform_map(position_mm=[0.0, nan, 0.0], future=nan)))


@pytest.mark.parametrize("where", ["top", "nested"])
def test_a_key_given_twice_is_malformed(where) -> None:
    """A map giving a key twice: which copy a reader keeps is not defined, and the relay
    forwards the bytes it validated, so another reader could take a copy nobody checked."""
    if where == "top":
        data = _with_pairs([*good_platform_map().items(), ("position_mm", [9.0, 9.0, 9.0])])
    else:
        def frame(second: str) -> bytes:  # a tactile frame whose layers map is given as is
            layers = _with_pairs([("height_mm", f4(np.zeros((2, 2)))),
                                  (second, f4(np.full((2, 2), 0.5)))])
            head = {k: v for k, v in tactile_map({}).items() if k != "layers"}
            return (bytes([0x80 | (len(head) + 1)])
                    + b"".join(pack(k) + pack(v) for k, v in head.items())
                    + pack("layers") + layers)
        assert isinstance(decode(frame("friction")), TactileFrame)  # the control
        data = frame("height_mm")
    with pytest.raises(MalformedMessageError, match="given twice"):
        decode(data)


FINITE_TREE = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.text(max_size=3)
    | st.floats(allow_nan=False, allow_infinity=False) | st.binary(max_size=4),
    lambda kids: st.lists(kids, max_size=3) | st.dictionaries(st.text(max_size=3), kids,
                                                               max_size=3),
    max_leaves=12)


def _plant(tree: object, path: list[int], bad: float) -> object:
    """``tree`` with one more leaf, ``bad``, in the list or map ``path`` picks (or beside it)."""
    if isinstance(tree, list):
        if path and tree:
            i = path[0] % len(tree)
            return [*tree[:i], _plant(tree[i], path[1:], bad), *tree[i + 1:]]
        return [*tree, bad]
    if isinstance(tree, dict):
        if path and tree:
            key = sorted(tree)[path[0] % len(tree)]
            return {**tree, key: _plant(tree[key], path[1:], bad)}
        return {**tree, "\x00planted": bad}
    return [tree, bad]


@settings(max_examples=300, deadline=None)
@given(tree=FINITE_TREE, path=st.lists(st.integers(0, 5), max_size=6),
       bad=st.sampled_from([math.nan, -math.nan, math.inf, -math.inf]),
       single=st.booleans())
def test_any_non_finite_number_anywhere_is_refused(tree, path, bad, single) -> None:
    """Property: a valid message with any finite value under an unknown key decodes; the
    same with one NaN or infinity planted anywhere in that value (a float32 or a float64 on
    the wire) is refused as ``non_finite``."""
    assert isinstance(decode(pack(good_platform_map(future=tree))), PlatformState)
    planted = pack(good_platform_map(future=_plant(tree, path, bad)))
    if single:  # the same number as a msgpack float32
        planted = planted.replace(b"\xcb" + struct.pack(">d", bad),
                                  b"\xca" + struct.pack(">f", bad))
    with pytest.raises(NonFiniteError):
        decode(planted)


def tactile_map(layers: dict) -> dict:
    return {"v": 1, "type": "tactile_frame", "seq": 1, "ts": 1, "center_mm": [0, 0],
            "pitch_mm": 1.7, "layers": layers, "contact": False, "force_n": 0.0,
            "indentation_mm": 0.0}


def f4(arr) -> dict:
    a = np.asarray(arr, dtype="<f4")
    return {"dtype": "<f4", "shape": list(a.shape), "data": a.tobytes()}


@pytest.mark.parametrize("layers, match", [
    ({}, "height_mm is missing"),
    ({"height_mm": f4(np.zeros((2, 2))), "colour": f4(np.zeros((2, 2)))}, "unknown layer"),
    ({"height_mm": f4(np.zeros((2, 2))), "friction": f4(np.zeros((3, 3)))}, "shape"),
    ({"height_mm": f4(np.zeros((2, 2))), "stiffness_k": f4(np.full((2, 2), 0.2))}, "allowed"),
    ({"height_mm": {"dtype": ">f4", "shape": [1], "data": b"\0" * 4}}, "dtype"),
    ({"height_mm": {"dtype": "<f4", "shape": [2, 2], "data": b"\0" * 15}}, "bytes"),
    ({"height_mm": {"dtype": "<f4", "shape": [2, -2], "data": b""}}, "shape"),
    ({"height_mm": {"dtype": "<f4", "shape": [5000, 1], "data": b""}}, "shape"),
    ({"height_mm": f4(np.zeros(4))}, "dimensions"),
    ({"height_mm": {"dtype": "|u1", "shape": [1, 1], "data": b"\0"}}, "float"),
    ({"height_mm": "not an array"}, "array map"),
])
def test_bad_layers(layers, match) -> None:
    with pytest.raises(FieldError, match=match):
        decode(pack(tactile_map(layers)))


def test_oversize_rejected_before_parsing() -> None:
    data = pack(good_platform_map())
    with pytest.raises(OversizeError):
        decode(data, max_message_bytes=len(data) - 1)
    assert isinstance(decode(data, max_message_bytes=len(data)), PlatformState)


def test_hello_rejects_bad_session_and_role() -> None:
    base = {"v": 1, "type": "hello", "role": "local", "session": "s1", "token": "x"}
    with pytest.raises(FieldError, match="session"):
        decode(pack({**base, "session": "../etc"}))
    with pytest.raises(FieldError, match="role"):
        decode(pack({**base, "role": "admin"}))


@pytest.mark.parametrize("metrics", [{"a": math.nan}, {"a": [1, 2]}, {"a": {"b": {"c": {"d": {
    "e": {"f": 1}}}}}}, {1: 2}])
def test_bad_stats(metrics) -> None:
    data = msgpack.packb({"v": 1, "type": "stats", "scope": "relay", "time_us": 1,
                          "metrics": metrics}, strict_types=False)
    with pytest.raises(RemoteProtocolError):
        decode(data)


def test_every_error_has_code_and_close_code() -> None:
    for cls in (MalformedMessageError, VersionError, UnknownMessageTypeError, FieldError,
                NonFiniteError, OversizeError):
        err = cls("x")
        assert isinstance(err, RemoteProtocolError)
        assert err.code and 1000 <= err.close_code < 5000


# ----------------------------------------------------------------------------- sending side


def test_encode_refuses_invalid_message_as_local_error() -> None:
    with pytest.raises(LocalProtocolError, match=r"is nan"):
        encode(PlatformState(position_mm=(0.0, math.nan, 0.0)))
    with pytest.raises(LocalProtocolError):
        encode(TactileFrame(layers={"height_mm": np.full((2, 2), 50.0, np.float32)}))


def test_encode_refuses_oversize() -> None:
    frame = TactileFrame(layers={"height_mm": np.zeros((100, 100), np.float32)})
    with pytest.raises(LocalProtocolError, match="exceeds"):
        encode(frame, max_message_bytes=1000)


def test_with_hop_keeps_at_most_max_hops() -> None:
    msg: DataMessage = PlatformState()
    for i in range(40):
        msg = msg.with_hop("relay", "relay_in", i)
    assert len(msg.hops) == 32
    assert msg.hops[-1].t_us == 39
    assert isinstance(decode(encode(msg)), PlatformState)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_random_bytes_never_crash(data: bytes) -> None:
    """Arbitrary bytes give a message or a RemoteProtocolError, nothing else."""
    with contextlib.suppress(RemoteProtocolError):
        decode(data)


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(st.sampled_from(["v", "type", "seq", "ts", "hops", "position_mm",
                                        "velocity_mm_s", "layers", "role", "metrics"]),
                       st.one_of(st.integers(-5, 2**64 - 1), st.floats(), st.text(max_size=5),
                                 st.lists(st.integers(-(2**63), 2**64 - 1), max_size=4),
                                 st.none(), st.booleans(),
                                 st.sampled_from(["platform_state", "tactile_frame", "stats",
                                                  "hello"]))))
def test_random_maps_never_crash(obj: dict) -> None:
    obj.setdefault("v", 1)
    with contextlib.suppress(RemoteProtocolError):
        decode(msgpack.packb(obj))


def test_length_prefix_header_is_big_endian() -> None:
    from shared.protocol import frame

    assert frame(b"abc")[:4] == struct.pack(">I", 3)
