"""Settings of a station's relay link: the relay URL, the reconnect backoff, the TOML table.

Kept apart from the asyncio link (:mod:`shared.client`) so that configuration code and
tests can use them without the link's machinery.
"""

from __future__ import annotations

import ipaddress
import random
import re
import ssl
from dataclasses import dataclass
from typing import Literal
from urllib.parse import urlsplit

from shared.config import check_count, check_positive
from shared.errors import ConfigError
from shared.protocol import DEFAULT_MAX_MESSAGE_BYTES
from shared.protocol.messages import SESSION_ID_PATTERN

__all__ = ["HELLO_NAME_MAX_CHARS", "HELLO_TOKEN_MAX_CHARS", "MAX_LINK_TIMEOUT_S", "Scheme",
           "StationLinkConfig", "backoff_delay_s", "check_hello", "client_tls_context",
           "parse_link_url"]

#: the longest ``token`` and ``name`` the relay reads in a ``hello``
#: (:meth:`shared.protocol.messages.Hello.from_wire`; a longer one is refused at every attempt)
HELLO_TOKEN_MAX_CHARS = 512
HELLO_NAME_MAX_CHARS = 64
#: the longest reconnect delay, connect timeout and liveness timeout: a station never gives up
#: on a transient fault, and one that waits minutes between attempts (or to notice a dead
#: link) as good as has (a value in ms written as seconds)
MAX_LINK_TIMEOUT_S = 60.0


def backoff_delay_s(attempt: int, *, min_s: float, max_s: float, jitter: float,
                    rng: random.Random) -> float:
    """Delay before reconnect attempt ``attempt`` (0 = first retry).

    The base doubles from ``min_s`` up to ``max_s``; jitter scales it down by a random
    factor in ``[1 - jitter, 1]`` so stations cut off together do not retry in lockstep.

    Args:
        attempt: number of failed attempts since the last good connection, from 0.
        min_s: first delay.
        max_s: largest delay.
        jitter: fraction in [0, 1] of the base that may be taken off at random.
        rng: random source (seedable for tests).

    Returns:
        The delay in seconds, in ``[(1 - jitter) * base, base]``.
    """
    base = min(max_s, min_s * 2.0 ** min(attempt, 60))
    return base * (1.0 - jitter * rng.random())


Scheme = Literal["ws", "wss", "tcp", "tls"]


def _shown_url(url: str) -> str:
    """``url`` for a message: when it holds any ``@``, everything from after ``scheme:``
    (and ``//``) up to the last ``@`` is replaced by ``***`` (a password may hold ``/``,
    ``:`` or ``@``, so no split at the first ``/`` finds where it ends)."""
    if "@" not in url:
        return url
    match = re.match(r"[A-Za-z][A-Za-z0-9+.-]*:(//)?", url)
    head = match.group(0) if match else ""
    return f"{head}***@{url.rpartition('@')[2]}"


def parse_link_url(url: str) -> tuple[Scheme, str, int]:
    """Split a relay URL into scheme, host and port.

    Args:
        url: ``ws://host[:port][/path]``, ``wss://...``, ``tcp://host:port`` or
            ``tls://host:port`` (the raw TCP protocol inside TLS).

    Returns:
        ``(scheme, host, port)``; WebSocket ports default to 80 / 443.

    Raises:
        ConfigError: unknown scheme, missing host, a host name that cannot be looked up (a
            label over 63 characters, an empty label), user information (any ``@`` in the
            URL, ``user:password@``: the relay takes none, and it would be shown wherever the
            URL is; a password holding ``/`` would end the host early), or a TCP URL
            without a port. The message never shows user information.
    """
    shown = _shown_url(url)
    if "@" in url:  # anywhere: a password holding '/' puts its '@' past urlsplit's host
        raise ConfigError(f"relay URL {shown!r} holds user information (user:password@): the "
                          "relay takes none (the station's token goes in its own setting)")
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as err:
        raise ConfigError(f"bad relay URL {shown!r}: its port is not a number in 0..65535, or "
                          "its host is not a valid name or [IPv6] address") from err
    scheme = parts.scheme.lower()
    if scheme not in ("ws", "wss", "tcp", "tls"):
        raise ConfigError(f"relay URL {shown!r}: scheme must be ws://, wss://, tcp:// or tls://")
    if not parts.hostname:
        raise ConfigError(f"relay URL {shown!r} has no host")
    try:
        ipaddress.ip_address(parts.hostname)
    except ValueError:  # a name: it is looked up IDNA-encoded
        try:
            parts.hostname.encode("idna")
        except UnicodeError as err:
            raise ConfigError(f"relay URL {shown!r}: host {parts.hostname[:80]!r} is not a "
                              "valid host name (each dot-separated label 1 to 63 characters)"
                              ) from err
    if port is None:
        if scheme in ("tcp", "tls"):
            raise ConfigError(f"relay URL {shown!r}: {scheme}:// needs a port")
        port = 443 if scheme == "wss" else 80
    return scheme, parts.hostname, port  # type: ignore[return-value]


def client_tls_context(ca_file: str | None) -> ssl.SSLContext:
    """A TLS client context verifying the relay's certificate and host name.

    Args:
        ca_file: PEM file of the CA(s) to trust; None = the system's trust store.

    Raises:
        ConfigError: the CA file is missing or not a PEM certificate.
    """
    try:
        return ssl.create_default_context(cafile=ca_file)
    except (OSError, ssl.SSLError) as err:
        raise ConfigError(f"cannot load the CA file {ca_file!r}: {err}") from err


@dataclass(frozen=True)
class StationLinkConfig:
    """Link settings of a station: TOML table ``[local.link]`` / ``[remote.link]``.

    Resolve with ``resolve_config(StationLinkConfig, "local.link", ...)``; the token then
    comes best from ``TELETOUCH_LOCAL_LINK_TOKEN`` (an environment file), not the TOML.

    Attributes:
        url: relay URL (``ws://``, ``wss://``, ``tcp://`` or ``tls://``).
        ca_file: PEM file of the CA(s) to trust for ``wss://``/``tls://`` instead of the
            system's (a lab CA, ``docs/security.md``); None = the system's trust store.
        session: session id shared by the two stations (a letter or digit, then up to 63
            letters, digits, ``_``, ``.`` or ``-``: the relay's rule).
        token: session token (at most 512 characters).
        name: label shown in the relay's status (at most 64 characters).
        reconnect_min_s: first reconnect delay.
        reconnect_max_s: largest reconnect delay (at most 60 s).
        connect_timeout_s: limit for connect + hello -> welcome (at most 60 s).
        liveness_timeout_s: silence after which the connection is treated as dead (at most
            60 s).
        max_message_bytes: size limit of one message.
    """

    url: str = "ws://127.0.0.1:8765/"
    session: str = "lab1"
    token: str = ""
    name: str = ""
    reconnect_min_s: float = 0.1
    reconnect_max_s: float = 0.5
    connect_timeout_s: float = 5.0
    liveness_timeout_s: float = 3.0
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    ca_file: str | None = None

    def __post_init__(self) -> None:
        # checked where they are read (the resolver names the table): a station then
        # refuses them before any device opens, not when its link is built
        if not 0.0 < self.reconnect_min_s <= self.reconnect_max_s:
            raise ConfigError(f"reconnect_min_s ({self.reconnect_min_s!r}) must be > 0 and <= "
                              f"reconnect_max_s ({self.reconnect_max_s!r})")
        for name in ("connect_timeout_s", "liveness_timeout_s"):
            check_positive(name, getattr(self, name))
        for name in ("reconnect_max_s", "connect_timeout_s", "liveness_timeout_s"):
            if not getattr(self, name) <= MAX_LINK_TIMEOUT_S:
                raise ConfigError(f"{name} ({getattr(self, name)!r}) must be <= "
                                  f"{MAX_LINK_TIMEOUT_S:g} s")
        check_count("max_message_bytes", self.max_message_bytes)
        parse_link_url(self.url)  # the URL's own errors (never showing a password)
        self._check_hello()

    def _check_hello(self) -> None:
        check_hello(self.session, self.token, self.name)


def check_hello(session: object, token: object, name: object) -> None:
    """Refuse the ``hello`` fields the relay refuses (``Hello.from_wire``): such a hello would
    be sent at every reconnect, for ever. Named by setting; the token is never shown.

    Raises:
        ConfigError: the session id, the token or the name.
    """
    if not isinstance(session, str) or not SESSION_ID_PATTERN.fullmatch(session):
        raise ConfigError(f"session {str(session)[:80]!r} is not a session id: a letter or "
                          "digit, then up to 63 letters, digits, '_', '.' or '-'")
    if not isinstance(token, str) or len(token) > HELLO_TOKEN_MAX_CHARS:
        raise ConfigError(f"token is longer than {HELLO_TOKEN_MAX_CHARS} characters (the "
                          "relay refuses such a hello)")
    if not isinstance(name, str) or len(name) > HELLO_NAME_MAX_CHARS:
        raise ConfigError(f"name is longer than {HELLO_NAME_MAX_CHARS} characters (the "
                          "relay refuses such a hello)")
