"""Session tokens, compared in constant time.

Version 2 (recommended) binds a session, a role and an expiry::

    v2.<role>.<expiry_unix_s>.<base64url(HMAC-SHA256(secret, "v2|<session>|<role>|<expiry>"))>

so a token for one session or role is useless for another, and a leaked one stops working at
its expiry (``teletouch relay --print-token SESSION --role ROLE --ttl-s N``).

Legacy (version 1) tokens, accepted only while ``allow_legacy_tokens`` is set: the derived
``hex(HMAC-SHA256(secret, session_id))`` and the explicit per-session token table. They name
neither a role nor an expiry.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import logging
import time
import tomllib
from collections.abc import Mapping
from pathlib import Path

from shared.errors import AuthError, ConfigError, TokenExpiredError
from shared.protocol.tokens import V2_PREFIX as _V2
from shared.protocol.tokens import v2_fields

__all__ = ["TOKEN_ROLES", "TokenAuthority", "derive_token", "load_token_file", "make_token"]

#: roles a version-2 token can name
TOKEN_ROLES = frozenset({"local", "remote", "observer"})

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


def _v2_mac(secret: str, session_id: str, role: str, expiry_s: int) -> str:
    mac = hmac.new(secret.encode(), f"{_V2}|{session_id}|{role}|{expiry_s}".encode(),
                   hashlib.sha256).digest()
    return base64.urlsafe_b64encode(mac).rstrip(b"=").decode()


def make_token(secret: str, session_id: str, role: str, expiry_s: int) -> str:
    """Return a version-2 token for one session and role, valid until ``expiry_s``.

    Args:
        secret: the relay's shared secret.
        session_id: the session id.
        role: ``local``, ``remote`` or ``observer``.
        expiry_s: Unix time (seconds) after which the relay refuses it.

    Raises:
        ConfigError: an unknown role or a negative expiry.
    """
    if role not in TOKEN_ROLES:
        raise ConfigError(f"token role must be one of {sorted(TOKEN_ROLES)}, got {role!r}")
    if expiry_s < 0:
        raise ConfigError("token expiry must be >= 0")
    return f"{_V2}.{role}.{expiry_s}.{_v2_mac(secret, session_id, role, expiry_s)}"


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
        tokens: explicit session -> token table (legacy).
        secret: shared secret for version-2 and derived tokens, or None.
        allow_any: accept every token (development only).
        allow_legacy: also accept the legacy tokens (the table and the derived hex ones).

    Raises:
        ConfigError: no way to authenticate anyone (no tokens, no secret, not allow_any).
    """

    def __init__(self, tokens: Mapping[str, str], secret: str | None, *,
                 allow_any: bool = False, allow_legacy: bool = True) -> None:
        if not tokens and not secret and not allow_any:
            raise ConfigError("the relay needs credentials: a secret (--secret or "
                              "$TELETOUCH_RELAY_SECRET), a token file (--token-file), or "
                              "--allow-any-token for development")
        self._tokens = dict(tokens)
        self._secret = secret
        self._allow_any = allow_any
        self._allow_legacy = allow_legacy
        if not allow_legacy and not secret and not allow_any:
            raise ConfigError("allow_legacy_tokens = false needs a secret for version-2 tokens")

    def check(self, session_id: str, token: str, role: str | None = None,
              now_s: float | None = None, *, legacy: bool = True) -> int | None:
        """Accept or refuse ``token`` for ``session_id`` and ``role``.

        Args:
            session_id: the session asked for.
            token: the token presented (never logged, never put in an error message).
            role: the role asked for; a version-2 token must name it.
            now_s: Unix time for the expiry check (default: now).
            legacy: False: refuse legacy tokens here even where the relay accepts them
                (they name no role: the observers' live view wants an observer token).

        Returns:
            The token's expiry (Unix time, s): a version-2 token stops being valid then,
            and whoever keeps a connection open on it must check again. None: no expiry
            (a legacy token, or ``allow_any``).

        Raises:
            AuthError: the token is missing, wrong, for another role, expired, or a
                legacy token while legacy tokens are off (the same message for unknown
                sessions and wrong tokens, so a client learns nothing about which exist).
        """
        if self._allow_any:
            return None
        if not token:
            raise AuthError(f"missing token for session {session_id!r}")
        if token.startswith(_V2 + "."):
            return self._check_v2(session_id, token, role,
                                  time.time() if now_s is None else now_s)
        if not legacy:
            raise AuthError(f"legacy token refused for session {session_id!r}: it names no "
                            f"role; this needs a v2 {role or 'role'} token")
        if not self._allow_legacy:
            raise AuthError(f"legacy token refused for session {session_id!r}: this relay "
                            "accepts only v2 tokens (session, role and expiry)")
        expected = self._tokens.get(session_id)
        if expected is None and self._secret:
            expected = derive_token(self._secret, session_id)
        if expected is None or not hmac.compare_digest(expected.encode(), token.encode()):
            raise AuthError(f"wrong token for session {session_id!r}")
        return None

    def _check_v2(self, session_id: str, token: str, role: str | None, now_s: float) -> int:
        fields = v2_fields(token)
        if self._secret is None or fields is None:
            raise AuthError(f"wrong token for session {session_id!r}")
        token_role, expiry_s, mac = fields
        if token_role not in TOKEN_ROLES:
            raise AuthError(f"wrong token for session {session_id!r}")
        expected = _v2_mac(self._secret, session_id, token_role, expiry_s)
        if not hmac.compare_digest(expected.encode(), mac.encode()):
            raise AuthError(f"wrong token for session {session_id!r}")
        if role is not None and token_role != role:
            raise AuthError(f"the token for session {session_id!r} is for role "
                            f"{token_role!r}, not {role!r}")
        if now_s > expiry_s:
            raise TokenExpiredError(f"the token for session {session_id!r} ({token_role}) "
                                    f"expired at {expiry_s} (Unix time, {now_s - expiry_s:.0f} "
                                    "s ago by the relay's clock); ask for a new one")
        return expiry_s
