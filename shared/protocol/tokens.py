"""The public part of a version-2 session token (``docs/protocol.md`` section 3).

``v2.<role>.<expiry_unix_s>.<mac>``: the role and the expiry are readable by anyone; only
the relay, which holds the secret, can check the MAC (:mod:`relay_server.auth`). A station
reads its own token's expiry to tell a token that expired from a relay whose clock is wrong.
"""

from __future__ import annotations

__all__ = ["V2_PREFIX", "V2Fields", "v2_fields"]

from typing import NamedTuple

#: the first field of a version-2 token
V2_PREFIX = "v2"


class V2Fields(NamedTuple):
    """The readable fields of a version-2 token."""

    role: str
    expiry_s: int
    mac: str


def v2_fields(token: str) -> V2Fields | None:
    """The role, expiry and MAC of a well-formed version-2 token; None for anything else
    (a legacy token, or a malformed one). Nothing is verified."""
    parts = token.split(".")
    # isdigit() alone admits "²" or "٣", which int() refuses or reads: ASCII digits only
    if len(parts) != 4 or parts[0] != V2_PREFIX or not parts[2].isascii() \
            or not parts[2].isdigit():
        return None
    return V2Fields(parts[1], int(parts[2]), parts[3])
