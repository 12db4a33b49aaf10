"""Every fuzz target by name."""

from __future__ import annotations

from collections.abc import Callable

from lab.fuzz.sessions import peer, relay, station
from lab.fuzz.targets import decoder, framing

__all__ = ["TARGETS"]

#: target name -> function ``bytes -> None`` (raises on a broken promise)
TARGETS: dict[str, Callable[[bytes], None]] = {
    "decoder": decoder, "framing": framing, "station": station, "peer": peer, "relay": relay}
