"""Field readers for wire maps: each returns a clean value or raises a typed error.

Used by :mod:`shared.protocol.messages` to validate a decoded msgpack map. They raise
:class:`~shared.errors.FieldError` (or :class:`~shared.errors.NonFiniteError`) naming
the message type and the field, so the peer learns exactly what it got wrong.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from shared.errors import FieldError, NonFiniteError

__all__ = [
    "ALLOWED_DTYPES",
    "MAX_ARRAY_DIM",
    "MAX_ARRAY_NDIM",
    "MAX_INT",
    "array_to_wire",
    "describe",
    "read_array",
    "read_bool",
    "read_float",
    "read_int",
    "read_optional",
    "read_str",
    "read_vector",
]

MAX_INT = 2**63 - 1
MAX_ARRAY_NDIM = 3
MAX_ARRAY_DIM = 4096

#: wire dtype string -> numpy dtype (always little-endian on the wire)
ALLOWED_DTYPES: dict[str, np.dtype[Any]] = {
    "<f4": np.dtype("<f4"),
    "<f8": np.dtype("<f8"),
    "|u1": np.dtype("|u1"),
    "<u2": np.dtype("<u2"),
    "<i2": np.dtype("<i2"),
    "<i4": np.dtype("<i4"),
}

_MISSING = object()


def describe(value: Any) -> str:
    """A short, safe rendering of a received value for an error message: the repr of a scalar
    (a string cut to 40 characters), else only the type (the repr of a received list or map
    can be megabytes, or nest deeper than Python's recursion limit)."""
    if isinstance(value, str):
        return repr(value[:40])
    if value is None or isinstance(value, bool | int | float):
        return repr(value)
    return f"a {type(value).__name__}"


def _where(msg_type: str, name: str) -> str:
    return f"{msg_type}.{name}"


def _get(d: Mapping[str, Any], msg_type: str, name: str) -> Any:
    value = d.get(name, _MISSING)
    if value is _MISSING:
        raise FieldError(f"{_where(msg_type, name)} is missing")
    return value


def read_optional(d: Mapping[str, Any], name: str) -> bool:
    """True when ``name`` is present and not None."""
    return d.get(name) is not None


def read_str(d: Mapping[str, Any], msg_type: str, name: str, *, max_len: int = 256,
             pattern: re.Pattern[str] | None = None, choices: frozenset[str] | None = None) -> str:
    """Read a string field, checking its length, pattern or allowed values."""
    value = _get(d, msg_type, name)
    if not isinstance(value, str):
        raise FieldError(f"{_where(msg_type, name)} must be a string, got {type(value).__name__}")
    if len(value) > max_len:
        raise FieldError(f"{_where(msg_type, name)} is longer than {max_len} characters")
    if choices is not None and value not in choices:
        raise FieldError(
            f"{_where(msg_type, name)} must be one of {sorted(choices)}, got {value[:40]!r}")
    if pattern is not None and not pattern.fullmatch(value):
        raise FieldError(
            f"{_where(msg_type, name)} {value[:40]!r} does not match {pattern.pattern}")
    return value


def read_int(d: Mapping[str, Any], msg_type: str, name: str, *, lo: int = 0,
             hi: int = MAX_INT) -> int:
    """Read an integer field in ``[lo, hi]`` (booleans are not integers here)."""
    value = _get(d, msg_type, name)
    if isinstance(value, bool) or not isinstance(value, int):
        raise FieldError(f"{_where(msg_type, name)} must be an integer, got {type(value).__name__}")
    if not lo <= value <= hi:
        raise FieldError(f"{_where(msg_type, name)}={value} is outside [{lo}, {hi}]")
    return value


def read_float(d: Mapping[str, Any], msg_type: str, name: str, *, lo: float = -math.inf,
               hi: float = math.inf) -> float:
    """Read a finite number in ``[lo, hi]`` (integers are accepted and converted)."""
    value = _get(d, msg_type, name)
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise FieldError(f"{_where(msg_type, name)} must be a number, got {type(value).__name__}")
    out = float(value)
    if not math.isfinite(out):
        raise NonFiniteError(f"{_where(msg_type, name)} is {out}")
    if not lo <= out <= hi:
        raise FieldError(f"{_where(msg_type, name)}={out} is outside [{lo}, {hi}]")
    return out


def read_bool(d: Mapping[str, Any], msg_type: str, name: str) -> bool:
    """Read a boolean field."""
    value = _get(d, msg_type, name)
    if not isinstance(value, bool):
        raise FieldError(f"{_where(msg_type, name)} must be true/false, got {type(value).__name__}")
    return value


def read_vector(d: Mapping[str, Any], msg_type: str, name: str, length: int, *,
                lo: float = -math.inf, hi: float = math.inf) -> tuple[float, ...]:
    """Read a fixed-length list of finite numbers, each in ``[lo, hi]``."""
    value = _get(d, msg_type, name)
    if not isinstance(value, list | tuple) or len(value) != length:
        raise FieldError(f"{_where(msg_type, name)} must be a list of {length} numbers")
    out = []
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise FieldError(f"{_where(msg_type, name)}[{i}] must be a number")
        f = float(v)
        if not math.isfinite(f):
            raise NonFiniteError(f"{_where(msg_type, name)}[{i}] is {f}")
        if not lo <= f <= hi:
            raise FieldError(f"{_where(msg_type, name)}[{i}]={f} is outside [{lo}, {hi}]")
        out.append(f)
    return tuple(out)


def read_array(value: Any, where: str, *, lo: float = -math.inf, hi: float = math.inf,
               ndim: int | None = None) -> np.ndarray:
    """Decode a wire array map ``{"dtype", "shape", "data"}`` into a read-only ndarray.

    The result is a zero-copy view on the received bytes. Float arrays must be finite,
    and every element must lie in ``[lo, hi]``.

    Raises:
        FieldError: bad map, dtype, shape, byte count or range.
        NonFiniteError: a NaN or Inf element.
    """
    if not isinstance(value, Mapping):
        raise FieldError(f"{where} must be an array map with dtype, shape and data")
    dtype_s, shape, data = value.get("dtype"), value.get("shape"), value.get("data")
    if not isinstance(dtype_s, str) or dtype_s not in ALLOWED_DTYPES:
        raise FieldError(f"{where}.dtype must be one of {sorted(ALLOWED_DTYPES)}, "
                         f"got {describe(dtype_s)}")
    if (not isinstance(shape, list | tuple) or not 1 <= len(shape) <= MAX_ARRAY_NDIM
            or any(isinstance(s, bool) or not isinstance(s, int) or not 0 <= s <= MAX_ARRAY_DIM
                   for s in shape)):
        raise FieldError(f"{where}.shape must be 1-{MAX_ARRAY_NDIM} integers in "
                         f"[0, {MAX_ARRAY_DIM}], got {describe(shape)}")
    if ndim is not None and len(shape) != ndim:
        raise FieldError(f"{where} must have {ndim} dimensions, got shape {list(shape)}")
    if not isinstance(data, bytes | bytearray | memoryview):
        raise FieldError(f"{where}.data must be binary, got {type(data).__name__}")
    dtype = ALLOWED_DTYPES[dtype_s]
    expected = math.prod(shape) * dtype.itemsize
    if len(data) != expected:
        raise FieldError(f"{where}.data has {len(data)} bytes, shape {list(shape)} of {dtype_s} "
                         f"needs {expected}")
    arr = np.frombuffer(data, dtype=dtype).reshape(shape)
    if arr.size:
        float_kind = dtype.kind == "f"
        if float_kind or lo != -math.inf or hi != math.inf:
            # two passes, no temporary: min and max propagate NaN, and an Inf is the min or
            # the max, so both are finite exactly when every element is
            amin, amax = float(arr.min()), float(arr.max())
            if float_kind and not (math.isfinite(amin) and math.isfinite(amax)):
                raise NonFiniteError(f"{where} contains NaN or Inf")
            if amin < lo or amax > hi:
                raise FieldError(f"{where} values span [{amin:.6g}, {amax:.6g}], "
                                 f"allowed [{lo}, {hi}]")
    return arr


def array_to_wire(arr: np.ndarray) -> dict[str, Any]:
    """Encode an ndarray as the wire map (little-endian, C order)."""
    a = np.asarray(arr)
    if a.dtype.byteorder == ">" or (a.dtype.byteorder == "=" and not np.little_endian):
        a = a.astype(a.dtype.newbyteorder("<"))
    dtype_s = a.dtype.str
    if dtype_s not in ALLOWED_DTYPES:
        raise FieldError(f"dtype {a.dtype} cannot be sent; use one of {sorted(ALLOWED_DTYPES)}")
    return {"dtype": dtype_s, "shape": list(a.shape), "data": np.ascontiguousarray(a).tobytes()}
