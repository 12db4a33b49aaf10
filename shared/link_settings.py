"""Settings of a station's relay link: the relay URL, the reconnect backoff, the TOML table.

Kept apart from the asyncio link (:mod:`shared.client`) so that configuration code and
tests can use them without the link's machinery.
"""

from __future__ import annotations

import random
import ssl
from dataclasses import dataclass
from typing import Literal
from urllib.parse import urlsplit

from shared.config import check_count, check_positive
from shared.errors import ConfigError
from shared.protocol import DEFAULT_MAX_MESSAGE_BYTES

__all__ = ["Scheme", "StationLinkConfig", "backoff_delay_s", "client_tls_context",
           "parse_link_url"]


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


def parse_link_url(url: str) -> tuple[Scheme, str, int]:
    """Split a relay URL into scheme, host and port.

    Args:
        url: ``ws://host[:port][/path]``, ``wss://...``, ``tcp://host:port`` or
            ``tls://host:port`` (the raw TCP protocol inside TLS).

    Returns:
        ``(scheme, host, port)``; WebSocket ports default to 80 / 443.

    Raises:
        ConfigError: unknown scheme, missing host, or a TCP URL without a port.
    """
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as err:
        raise ConfigError(f"bad relay URL {url!r}: {err}") from err
    scheme = parts.scheme.lower()
    if scheme not in ("ws", "wss", "tcp", "tls"):
        raise ConfigError(f"relay URL {url!r}: scheme must be ws://, wss://, tcp:// or tls://")
    if not parts.hostname:
        raise ConfigError(f"relay URL {url!r} has no host")
    if port is None:
        if scheme in ("tcp", "tls"):
            raise ConfigError(f"relay URL {url!r}: {scheme}:// needs a port")
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
        session: session id shared by the two stations.
        token: session token.
        name: label shown in the relay's status.
        reconnect_min_s: first reconnect delay.
        reconnect_max_s: largest reconnect delay.
        connect_timeout_s: limit for connect + hello -> welcome.
        liveness_timeout_s: silence after which the connection is treated as dead.
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
        check_count("max_message_bytes", self.max_message_bytes)
