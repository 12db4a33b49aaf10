"""The local station's compact-frame decoder forgets its key frame with each new link
session (found by review, 2026-12-07): a restarted sender numbers its frames from 1 again,
and its deltas were applied to the old sender's key frame of the same seq."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from local_site.agent.station import LocalAgent
from shared.protocol import TactileCompact, TactileFrame, decode, encode
from shared.protocol.tactile_codec import CodecSettings, TactileDecoder, TactileEncoder


def _frames(height_mm: float, n: int) -> list[TactileCompact]:
    enc = TactileEncoder(CodecSettings(weber=0.0, key_every=10))
    out = []
    for seq in range(1, n + 1):
        frame = TactileFrame(seq=seq, ts_us=seq, layers={
            "height_mm": np.full((4, 4), height_mm, np.float32)})
        msg = decode(encode(enc.encode(frame)))
        assert isinstance(msg, TactileCompact)
        out.append(msg)
    return out


def test_a_new_link_session_forgets_the_last_ones_key_frame() -> None:
    station = SimpleNamespace(link=SimpleNamespace(counters=SimpleNamespace(connects=1)),
                              tactile_decoder=TactileDecoder(), _decoder_connects=0)
    old, new = _frames(2.0, 3), _frames(-1.0, 3)  # two senders' streams, the same seqs
    assert old[0].key and not old[1].key and old[1].key_seq == new[1].key_seq == 1
    out = LocalAgent._decode_compact(station, old[0])  # type: ignore[arg-type]
    assert out is not None and float(out.layers["height_mm"][0, 0]) > 1.9
    # same link session: the delta decodes against the key frame held
    assert LocalAgent._decode_compact(station, old[1]) is not None  # type: ignore[arg-type]
    # the link reconnects (a relay restart, an outage): a key frame of the new session missed
    station.link.counters.connects = 2
    assert LocalAgent._decode_compact(station, new[1]) is None  # type: ignore[arg-type]
    assert station.tactile_decoder.counters.waiting_for_key == 1
    out = LocalAgent._decode_compact(station, new[0])  # type: ignore[arg-type]
    assert out is not None and float(out.layers["height_mm"][0, 0]) < -0.9
