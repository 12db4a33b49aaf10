"""Session tokens: explicit per-session tokens or HMAC-derived ones, compared in constant time.

A derived token is ``hex(HMAC-SHA256(secret, session_id))`` (64 lowercase hex digits), so
an operator who holds the secret can hand out a token per session without a table, and a
token for one session is useless for another.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import tomllib
from collections.abc import Mapping
from pathlib import Path

from shared.errors import AuthError, ConfigError

__all__ = ["TokenAuthority", "derive_token", "load_token_file"]

log = logging.getLogger(__name__)


def derive_token(secret: str, session_id: str) -> str:
    """Return the HMAC-derived token of a session.

    Args:
        secret: the relay's shared secret.
        session_id: the session id.

    Returns:
        ``hex(HMAC-SHA256(secret, session_id))``.
    """
    return hmac.new(secret.encode(), session_id.encode(), hashlib.sha256).hexdigest()


def load_token_file(path: str | Path) -> dict[str, str]:
    """Read the ``[tokens]`` table (session id -> token) of a TOML file.

    Raises:
        ConfigError: missing file, invalid TOML, or a table of the wrong shape.
    """
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError as err:
        raise ConfigError(f"token file not found: {path}") from err
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"token file {path} is not valid TOML: {err}") from err
    table = data.get("tokens")
    if not isinstance(table, dict) or not all(
            isinstance(k, str) and isinstance(v, str) and v for k, v in table.items()):
        raise ConfigError(f"token file {path} needs a [tokens] table of session = \"token\"")
    return dict(table)


class TokenAuthority:
    """Decides whether a token opens a session.

    Args:
        tokens: explicit session -> token table (checked first).
        secret: shared secret for derived tokens, or None.
        allow_any: accept every token (development only).

    Raises:
        ConfigError: no way to authenticate anyone (no tokens, no secret, not allow_any).
    """

    def __init__(self, tokens: Mapping[str, str], secret: str | None, *,
                 allow_any: bool = False) -> None:
        if not tokens and not secret and not allow_any:
            raise ConfigError("the relay needs credentials: a secret (--secret or "
                              "$TELETOUCH_RELAY_SECRET), a token file (--token-file), or "
                              "--allow-any-token for development")
        self._tokens = dict(tokens)
        self._secret = secret
        self._allow_any = allow_any

    def check(self, session_id: str, token: str) -> None:
        """Accept or refuse ``token`` for ``session_id``.

        Raises:
            AuthError: the token is missing or wrong (same message either way for unknown
                sessions and wrong tokens, so a client learns nothing about which exist).
        """
        if self._allow_any:
            return
        if not token:
            raise AuthError(f"missing token for session {session_id!r}")
        expected = self._tokens.get(session_id)
        if expected is None and self._secret:
            expected = derive_token(self._secret, session_id)
        if expected is None or not hmac.compare_digest(expected.encode(), token.encode()):
            raise AuthError(f"wrong token for session {session_id!r}")
