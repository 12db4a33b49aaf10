"""The compact tactile codec: :class:`TactileFrame` <-> :class:`TactileCompact` (protocol v2).

Sender (:class:`TactileEncoder`):

* every layer is quantized to int16 with a per-layer ``scale`` (the layer's resolution,
  :data:`RESOLUTION`: 1 um for heights, or coarser when the key frame's span needs it) and
  ``offset`` chosen in each key frame;
* a **key frame** carries every layer in full; one is sent first, every ``key_every``
  frames, whenever the layer set or shape changes, when a value would not fit the key
  frame's int16 range, and when a delta would not be smaller than a key frame;
* otherwise a **delta** against the last key frame: per sample, a perceptual deadband
  (Weber's law, as in Hinterseer et al.'s perception-based data reduction for haptics): a
  sample is sent only when it differs from the key frame's value by more than
  ``max(weber * |key value|, floor)``; a layer without such a sample is left out (the
  stiffness layers, which change only between presses, are then not sent at all); a layer
  with many is sent dense.

Because every delta refers to the key frame and not to the previous delta, a delta lost or
superseded on the way (the relay forwards tactile frames latest-wins) costs nothing; a
lost key frame is recovered at the next one. So the error of every decoded sample is at
most ``max(weber * |key value|, floor, scale / 2)`` (quantization), whatever was lost.

Receiver (:class:`TactileDecoder`): holds the newest key frame; a delta whose key frame it
does not hold (joined late, key frame lost) gives ``None``: nothing is rendered from it and
the scene ages into the safe state until the next key frame. A restarted sender numbers its
frames from 1 again: its deltas may name a key ``seq`` the receiver holds from the old
sender, so a receiver forgets its key frame at each new link session (:meth:`reset`; the
local station does, and a replay at each recorded ``welcome``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from shared.errors import ConfigError, InputDataError
from shared.protocol.messages import LAYER_RANGES, CompactLayer, TactileCompact, TactileFrame

__all__ = ["RESOLUTION", "CodecSettings", "DecoderCounters", "TactileDecoder", "TactileEncoder"]

#: finest quantization step per layer (its unit): 1 um for heights; a key frame whose values
#: span more than 64,000 steps uses a coarser one
RESOLUTION: dict[str, float] = {
    "height_mm": 0.001,
    "stiffness_k": 1.0e-4,
    "friction": 1.0e-4,
    "stiffness_n_per_mm": 0.01,
}
_QMAX = 32767
_QSPAN = 2 * 32000  # a key frame's values use at most this many steps (headroom for deltas)


@dataclass(frozen=True)
class CodecSettings:
    """Encoder settings.

    Attributes:
        weber: deadband as a fraction of the key frame's value (0 = lossless but for
            quantization).
        floor: absolute deadband per layer (layer units); default: half the layer's
            quantization step (so ``weber = 0`` is lossless but for quantization).
        key_every: a key frame at least every this many frames.
        dense_fraction: a delta layer with more than this fraction of samples changed is
            sent dense.
    """

    weber: float = 0.0
    floor: Mapping[str, float] = field(default_factory=dict)
    key_every: int = 30
    dense_fraction: float = 0.25

    def __post_init__(self) -> None:
        if not 0.0 <= self.weber < 1.0:
            raise ConfigError(f"weber fraction must lie in [0, 1), got {self.weber}")
        if self.key_every < 1:
            raise ConfigError("key_every must be >= 1")
        if not 0.0 < self.dense_fraction <= 1.0:
            raise ConfigError("dense_fraction must lie in (0, 1]")
        for name, value in self.floor.items():
            if name not in RESOLUTION or not value >= 0.0:
                raise ConfigError(f"deadband floor {name}={value}: unknown layer or negative")

    def floor_of(self, name: str) -> float:
        """The absolute deadband of one layer."""
        return float(self.floor.get(name, RESOLUTION[name] / 2))


@dataclass
class _Key:
    seq: int
    shape: tuple[int, int]
    layers: dict[str, CompactLayer]
    values: dict[str, NDArray[np.float32]]  # dequantized


def _dequantize(layer: CompactLayer) -> NDArray[np.float32]:
    assert layer.scale is not None and layer.offset is not None
    return (np.float32(layer.offset) + np.float32(layer.scale)
            * layer.q.astype(np.float32))


def _quantize(values: NDArray[np.floating], scale: float, offset: float) -> NDArray[np.int64]:
    return np.rint((values - offset) / scale).astype(np.int64)


class TactileEncoder:
    """Turns the remote station's :class:`TactileFrame` stream into compact frames.

    Args:
        settings: deadband and key-frame settings.
    """

    def __init__(self, settings: CodecSettings | None = None) -> None:
        self.settings = settings or CodecSettings()
        self._key: _Key | None = None
        self._since_key = 0
        self.keys_sent = 0
        self.deltas_sent = 0

    def reset(self) -> None:
        """Forget the key frame (the next frame is a key frame), e.g. after a reconnect."""
        self._key = None

    def encode(self, frame: TactileFrame) -> TactileCompact:
        """The compact form of ``frame`` (a key frame or a delta).

        Raises:
            InputDataError: a layer is not a finite 2-D array of the frame's shape.
        """
        arrays = {name: np.asarray(arr) for name, arr in frame.layers.items()}
        height = arrays.get("height_mm")
        if height is None or height.ndim != 2:
            raise InputDataError("a tactile frame needs a 2-D height_mm layer")
        shape = (int(height.shape[0]), int(height.shape[1]))
        for name, arr in arrays.items():
            if name not in RESOLUTION:
                raise InputDataError(f"unknown tactile layer {name!r}")
            if arr.shape != shape or not np.isfinite(arr).all():
                raise InputDataError(f"layer {name} must be finite, of shape {shape}")
        key = self._key
        delta: dict[str, CompactLayer] | None = None
        if (key is not None and key.shape == shape and set(key.layers) == set(arrays)
                and self._since_key < self.settings.key_every - 1 and frame.seq > key.seq):
            delta = self._delta(key, arrays)
        if delta is None:
            key = self._make_key(frame.seq, shape, arrays)
            self._key = key
            self._since_key = 0
            self.keys_sent += 1
            return self._message(frame, True, frame.seq, shape, key.layers)
        assert key is not None
        self._since_key += 1
        self.deltas_sent += 1
        return self._message(frame, False, key.seq, shape, delta)

    def _make_key(self, seq: int, shape: tuple[int, int],
                  arrays: Mapping[str, np.ndarray]) -> _Key:
        layers: dict[str, CompactLayer] = {}
        for name, arr in arrays.items():
            lo, hi = float(arr.min()), float(arr.max())
            scale = max(RESOLUTION[name], (hi - lo) / _QSPAN)
            offset = float(np.rint(0.5 * (lo + hi) / scale) * scale)
            q = np.clip(_quantize(arr, scale, offset), -_QMAX, _QMAX).astype("<i2")
            layers[name] = CompactLayer(q, scale, offset)
        return _Key(seq, shape, layers, {n: _dequantize(v) for n, v in layers.items()})

    def _delta(self, key: _Key, arrays: Mapping[str, np.ndarray]
               ) -> dict[str, CompactLayer] | None:
        """The delta layers, or None when a key frame is due instead."""
        out: dict[str, CompactLayer] = {}
        sent = 0
        total = 0
        weber = self.settings.weber
        for name, arr in arrays.items():
            ref = key.values[name]
            threshold = np.maximum(weber * np.abs(ref), self.settings.floor_of(name))
            changed = np.abs(arr - ref) > threshold
            n = int(np.count_nonzero(changed))
            total += arr.size
            if n == 0:
                continue
            k = key.layers[name]
            assert k.scale is not None and k.offset is not None
            if n > self.settings.dense_fraction * arr.size:
                q = _quantize(arr, k.scale, k.offset)
                if np.abs(q).max() > _QMAX:
                    return None
                out[name] = CompactLayer(q.astype("<i2"))
                sent += arr.size
            else:
                idx = np.flatnonzero(changed)
                q = _quantize(arr.ravel()[idx], k.scale, k.offset)
                if q.size and np.abs(q).max() > _QMAX:
                    return None
                out[name] = CompactLayer(q.astype("<i2"), idx=idx.astype("<i4"))
                sent += 3 * n  # 2 bytes of value + 4 of index = 3 samples' worth
        if sent >= total:
            return None  # no smaller than a key frame: send one
        return out

    @staticmethod
    def _message(frame: TactileFrame, key: bool, key_seq: int, shape: tuple[int, int],
                 layers: dict[str, CompactLayer]) -> TactileCompact:
        return TactileCompact(seq=frame.seq, ts_us=frame.ts_us, hops=frame.hops,
                              center_mm=frame.center_mm, pitch_mm=frame.pitch_mm, key=key,
                              key_seq=key_seq, shape=shape, layers=layers,
                              contact=frame.contact, force_n=frame.force_n,
                              indentation_mm=frame.indentation_mm,
                              source_seq=frame.source_seq, source_ts_us=frame.source_ts_us)


@dataclass
class DecoderCounters:
    """What the decoder did."""

    keys: int = 0
    deltas: int = 0
    waiting_for_key: int = 0
    rejected: int = 0


class TactileDecoder:
    """Rebuilds :class:`TactileFrame` from compact frames (see the module docstring)."""

    def __init__(self) -> None:
        self._key: _Key | None = None
        self.counters = DecoderCounters()

    @property
    def has_key(self) -> bool:
        """True once a key frame is held."""
        return self._key is not None

    def reset(self) -> None:
        """Forget the key frame (e.g. the link was lost): deltas wait for the next key."""
        self._key = None

    def decode(self, msg: TactileCompact) -> TactileFrame | None:
        """The frame ``msg`` stands for, or None when its key frame is not held.

        Raises:
            InputDataError: a key frame or delta that does not fit (counted ``rejected``;
                a bad key frame is not kept).
        """
        if msg.key:
            try:
                values = {name: _dequantize(layer) for name, layer in msg.layers.items()}
                _check_ranges(values, msg.layers)
            except (AssertionError, InputDataError) as err:
                self.counters.rejected += 1
                raise InputDataError(f"tactile key frame seq={msg.seq} refused: {err}") from err
            self._key = _Key(msg.seq, msg.shape, dict(msg.layers), values)
            self.counters.keys += 1
            return _frame(msg, values)
        key = self._key
        if key is None or key.seq != msg.key_seq or key.shape != msg.shape:
            self.counters.waiting_for_key += 1
            return None
        unknown = set(msg.layers) - set(key.layers)
        if unknown:
            self.counters.rejected += 1
            raise InputDataError(f"tactile delta seq={msg.seq} has layers {sorted(unknown)} "
                                 "that its key frame lacks")
        values = dict(key.values)
        for name, layer in msg.layers.items():
            k = key.layers[name]
            assert k.scale is not None and k.offset is not None
            deq = (np.float32(k.offset) + np.float32(k.scale) * layer.q.astype(np.float32))
            if layer.idx is None:
                values[name] = deq.reshape(msg.shape)
            else:
                arr = key.values[name].copy()
                arr.ravel()[layer.idx] = deq
                values[name] = arr
        try:
            _check_ranges({n: values[n] for n in msg.layers}, key.layers)
        except InputDataError as err:
            self.counters.rejected += 1
            raise InputDataError(f"tactile delta seq={msg.seq} refused: {err}") from err
        self.counters.deltas += 1
        return _frame(msg, values)


def _check_ranges(values: Mapping[str, np.ndarray],
                  keys: Mapping[str, CompactLayer]) -> None:
    """Each decoded layer within its range, give or take one step of its key frame's scale
    (at least the layer's resolution): the sender rounds the offset to a whole step, so a
    value at the range's edge may decode up to half a step beyond it (``docs/protocol.md``);
    the decoded frame is clipped to the range."""
    for name, arr in values.items():
        lo, hi = LAYER_RANGES[name]
        vmin, vmax = float(arr.min()), float(arr.max())
        step = max(RESOLUTION[name], keys[name].scale or 0.0)
        if vmin < lo - step or vmax > hi + step:
            raise InputDataError(f"layer {name} decodes to [{vmin!r}, {vmax!r}], allowed "
                                 f"[{lo}, {hi}] with a slack of {step!r}")


def _frame(msg: TactileCompact, values: Mapping[str, NDArray[np.float32]]) -> TactileFrame:
    layers = {}
    for name, arr in values.items():
        lo, hi = LAYER_RANGES[name]
        arr = np.clip(arr, lo, hi) if (arr.min() < lo or arr.max() > hi) else arr
        arr.flags.writeable = False
        layers[name] = arr
    return TactileFrame(seq=msg.seq, ts_us=msg.ts_us, hops=msg.hops, center_mm=msg.center_mm,
                        pitch_mm=msg.pitch_mm, layers=layers, contact=msg.contact,
                        force_n=msg.force_n, indentation_mm=msg.indentation_mm,
                        source_seq=msg.source_seq, source_ts_us=msg.source_ts_us)
