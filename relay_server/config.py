"""Settings of the relay (TOML table ``[relay]``, env ``TELETOUCH_RELAY_*``, CLI flags)."""

from __future__ import annotations

import ssl
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

from shared.config import check_positive
from shared.errors import ConfigError
from shared.loop_watchdog import check_hang_timeout
from shared.protocol.codec import DEFAULT_MAX_MESSAGE_BYTES

__all__ = ["MIN_PING_INTERVAL_S", "MIN_SECRET_CHARS", "PLACEHOLDER_SECRETS", "RelayConfig"]

#: the shortest secret accepted: a short one (or ``secret = ""``, which a template's empty
#: placeholder leaves) lets anyone who guesses it mint tokens for every session and role
MIN_SECRET_CHARS = 32
#: the placeholders of the example files (``deploy/teletouch.env.example``): never a secret
PLACEHOLDER_SECRETS = frozenset({"change-me-to-64-hex-chars"})
#: the shortest ``ping_interval_s`` / ``stats_interval_s``: shorter spins the relay's loop
MIN_PING_INTERVAL_S = 0.01
#: the longest ``ping_interval_s`` / ``stats_interval_s``: what ``welcome`` can announce
#: (docs/protocol.md; a longer one made the relay refuse its own welcome to every station)
MAX_PING_INTERVAL_S = 3600.0


@dataclass(frozen=True)
class RelayConfig:
    """Everything the relay can be told.

    Attributes:
        host: address to bind (WebSocket and TCP).
        port: WebSocket port (also serves ``GET /status`` and ``GET /metrics``); 0 = any free.
        tcp_port: raw TCP (length-prefixed) port; None = ``port + 1`` (or any free when
            ``port`` is 0); 0 = any free port.
        secret: shared secret for HMAC-derived tokens
            (``token = hex(HMAC-SHA256(secret, session_id))``); None = no derived tokens.
            At least :data:`MIN_SECRET_CHARS` (32) characters, and not the example file's
            placeholder (``python3 -c "import secrets; print(secrets.token_hex(32))"``).
        tokens: explicit session id -> token table (wins over the secret for that session).
        token_file: TOML file with a ``[tokens]`` table (session -> token), merged into
            ``tokens``.
        allow_any_token: accept any token (development only; logged loudly at start).
        allow_legacy_tokens: also accept the legacy tokens (``tokens``/``token_file`` and
            ``hex(HMAC(secret, session))``), which name no role and never expire; version-2
            tokens (session, role, expiry) are always accepted with a ``secret``.
        tls_cert: PEM certificate chain of the relay; with ``tls_key`` the relay serves
            ``wss://`` on ``port`` (and HTTPS ``/status``) and TLS on ``tcp_port``
            (``tls://`` URLs). None = plain ``ws://`` and ``tcp://``.
        tls_key: PEM private key of ``tls_cert``.
        status_token: when set, ``GET /status`` and ``GET /metrics`` need the header
            ``Authorization: Bearer <status_token>`` (else 401); None = public (a WARNING
            at start says so).
        view: serve the live view to the sessions' observers on ``HOST:PORT`` (a listener
            of its own; a browser needs the session id and an observer token); empty: off.
        hello_timeout_s: a client must send a valid ``hello`` within this time.
        ping_interval_s: period of ``clock_ping`` to every station after the initial burst
            (at least 10 ms).
        ping_burst: number of ``clock_ping`` sent right after ``welcome``.
        ping_burst_spacing_s: spacing of the burst pings.
        stats_interval_s: period of the ``stats`` push to every connected peer (at least
            10 ms).
        silence_timeout_s: a station that sends nothing (it answers every ping) for this long
            is closed (``silent``/4005), freeing its role; a dead or blackholed connection
            would otherwise hold it until TCP gives up, minutes later.
        max_message_bytes: largest accepted message (fatal ``oversize`` beyond).
        ordered_queue_len: per-peer bound of the ordered (command/control) queue.
        bad_message_budget: per-message errors tolerated per connection before it is closed.
        ledger_window: samples kept per latency window (bounded ring buffer).
        max_sessions: sessions accepted at once.
        max_connections: open connections (both ports, any state) accepted at once; one
            more gets ``too_many_connections`` (close 1013). Also the most connections
            still in their opening (a TLS handshake, a WebSocket upgrade) at once: one more
            is closed at the accept (``relay_server.wire.Admission``).
        max_connections_per_ip: the same, from one remote address (behind a load balancer
            that hides the clients' addresses, all of them count as its address).
        max_hello_bytes: the largest message accepted before the hello is accepted (the
            most a connection that has not said hello makes the relay buffer).
        rate_limit_per_s: sustained received messages per second per connection (token
            bucket); excess messages are discarded with ``rate_limited``.
        rate_limit_burst: bucket size; more than this many discarded in one over-rate
            episode closes the connection (``rate_limited``, close 1008).
        nats_url: ``nats://HOST:PORT`` (or ``tls://HOST:PORT``; credentials as
            ``nats://USER:PASSWORD@HOST:PORT``) of the NATS server that joins relay workers
            into one cluster (:mod:`relay_server.cluster`); None = today's single-process
            relay.
        workers: relay worker processes on this host, all on the same ports (SO_REUSEPORT);
            0 = one per core when ``nats_url`` is set (1 without it).
        nats_subject_prefix: NATS subject prefix of this cluster (relays with another prefix
            on the same NATS server are another cluster).
        reuse_port: bind with SO_REUSEPORT (set for the workers of ``--workers``).
        nats_ca_file: PEM CA that signed the NATS server's certificate, for a ``tls://``
            ``nats_url`` (None: the system's trust store); read when the relay starts
            (:meth:`check_nats_ca_file`).
        nats_connect_timeout_s: a worker that cannot reach NATS within this time of its
            start exits with a start error (later losses of NATS are retried for ever).
        hang_timeout_s: a relay process whose event loop makes no progress this long, once
            it serves, writes every thread's stack to its standard error and exits with code
            1, for systemd, a container's restart policy or the workers' supervisor to start
            it again (:mod:`shared.loop_watchdog`); the supervisor of ``workers`` also kills
            a worker whose loop stood still a little longer (one that could not end itself)
            and starts another (:mod:`relay_server.workers`). 0: neither (a debugger's
            breakpoint stops the loop); else at least 1 s.
        lock_memory: keep each relay process's memory in RAM while it serves (``mlockall``
            on fault, :mod:`shared.memlock`, as the stations do): forwarding never waits for
            a page read back from disk on a cloud host under memory pressure. Taken only
            where it cannot make a later allocation fail (``RLIMIT_MEMLOCK`` unlimited or
            ``CAP_IPC_LOCK``); otherwise logged at INFO, and ``/status`` says why
            (``memory_lock``).
    """

    host: str = "127.0.0.1"
    port: int = 8765
    tcp_port: int | None = None
    secret: str | None = None
    tokens: dict[str, str] = field(default_factory=dict)
    token_file: Path | None = None
    allow_any_token: bool = False
    allow_legacy_tokens: bool = True
    tls_cert: Path | None = None
    tls_key: Path | None = None
    status_token: str | None = None
    view: str = ""
    hello_timeout_s: float = 5.0
    ping_interval_s: float = 1.0
    ping_burst: int = 5
    ping_burst_spacing_s: float = 0.02
    stats_interval_s: float = 1.0
    silence_timeout_s: float = 10.0
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    ordered_queue_len: int = 256
    bad_message_budget: int = 20
    ledger_window: int = 4096
    max_sessions: int = 1000
    max_connections: int = 1024
    max_connections_per_ip: int = 16
    max_hello_bytes: int = 64 * 1024
    rate_limit_per_s: float = 5000.0
    rate_limit_burst: int = 10_000
    nats_url: str | None = None
    workers: int = 0
    nats_subject_prefix: str = "teletouch"
    reuse_port: bool = False
    nats_ca_file: Path | None = None
    nats_connect_timeout_s: float = 10.0
    hang_timeout_s: float = 10.0
    lock_memory: bool = True

    def __post_init__(self) -> None:
        for name in ("port",):
            value = getattr(self, name)
            if not 0 <= value <= 65535:
                raise ConfigError(f"relay.{name}={value} is not a TCP port")
        if self.tcp_port is not None and not 0 <= self.tcp_port <= 65535:
            raise ConfigError(f"relay.tcp_port={self.tcp_port} is not a TCP port")
        positive = ("hello_timeout_s", "ping_interval_s", "stats_interval_s",
                    "silence_timeout_s", "rate_limit_per_s")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"relay.{name} must be > 0")
        for name in ("ping_interval_s", "stats_interval_s"):  # each sends to every station
            if not getattr(self, name) >= MIN_PING_INTERVAL_S:
                raise ConfigError(f"relay.{name} must be at least {MIN_PING_INTERVAL_S:g} s "
                                  f"(got {getattr(self, name):g} s): a shorter period keeps "
                                  "the relay busy sending to every station")
            if not getattr(self, name) <= MAX_PING_INTERVAL_S:
                raise ConfigError(f"relay.{name} must be at most {MAX_PING_INTERVAL_S:g} s "
                                  f"(got {getattr(self, name):g} s): the welcome announces it "
                                  "to every station, and the protocol bounds it there")
        self._check_secret()
        if self.port != 0 and self.tcp_port == self.port:
            raise ConfigError(f"relay.tcp_port={self.tcp_port} is relay.port: the TCP listener "
                              "needs a port of its own (or leave relay.tcp_port unset: port + 1)")
        if self.tcp_port is None and self.port == 65535:
            raise ConfigError("relay.port=65535 leaves no port for the TCP listener (port + 1): "
                              "set relay.tcp_port")
        if not self.silence_timeout_s >= 2 * self.ping_interval_s:
            raise ConfigError(
                f"relay.silence_timeout_s ({self.silence_timeout_s:g} s) must be at least twice "
                f"relay.ping_interval_s ({self.ping_interval_s:g} s): a station that only "
                "answers the pings would be closed as silent")
        ints = ("ping_burst", "max_message_bytes", "ordered_queue_len", "bad_message_budget",
                "ledger_window", "max_sessions", "max_connections", "max_connections_per_ip",
                "max_hello_bytes", "rate_limit_burst")
        for name in ints:
            if getattr(self, name) < 1:
                raise ConfigError(f"relay.{name} must be >= 1")
        if not isinstance(self.lock_memory, bool):
            raise ConfigError(f"relay.lock_memory must be true or false, got {self.lock_memory!r}")
        if self.workers < 0:
            raise ConfigError("relay.workers must be >= 0")
        if self.workers > 1 and not self.nats_url:
            raise ConfigError("relay.workers > 1 needs relay.nats_url (--nats nats://HOST:PORT):"
                              " workers pair the stations of a session through NATS")
        if self.nats_url is not None:
            _check_nats_url(self.nats_url)
        if not self.nats_subject_prefix.replace("_", "").replace("-", "").isalnum():
            raise ConfigError("relay.nats_subject_prefix must be letters, digits, - and _")
        check_positive("relay.nats_connect_timeout_s", self.nats_connect_timeout_s)
        check_hang_timeout("relay.hang_timeout_s", self.hang_timeout_s)
        if self.ping_burst_spacing_s < 0:
            raise ConfigError("relay.ping_burst_spacing_s must be >= 0")
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ConfigError("relay.tls_cert and relay.tls_key go together (both or neither)")
        for session, token in self.tokens.items():
            if not isinstance(session, str) or not isinstance(token, str) or not token:
                raise ConfigError("relay.tokens must map session ids to non-empty strings")

    def _check_secret(self) -> None:
        """A secret that makes tokens forgeable is refused (the message never shows it)."""
        secret = self.secret
        if secret is None:
            return
        if not isinstance(secret, str):
            raise ConfigError("relay.secret must be a string")
        if secret.strip() in PLACEHOLDER_SECRETS:
            raise ConfigError("relay.secret is the example file's placeholder: generate one "
                              "with python3 -c \"import secrets; print(secrets.token_hex(32))\"")
        if len(secret.strip()) < MIN_SECRET_CHARS:
            what = "empty" if not secret.strip() else f"{len(secret.strip())} characters long"
            raise ConfigError(
                f"relay.secret is {what}: at least {MIN_SECRET_CHARS} characters are needed "
                "(anyone who can guess it can make tokens for every session; leave it unset "
                "for no derived tokens, or generate one with python3 -c \"import secrets; "
                "print(secrets.token_hex(32))\")")

    def check_nats_ca_file(self) -> None:
        """Load ``nats_ca_file`` as the cluster link will (a file is read where the relay
        starts, not where its settings are read, as ``tls_cert``: the settings of another
        host resolve here).

        Raises:
            ConfigError: naming ``relay.nats_ca_file``: missing, unreadable, not PEM.
        """
        if self.nats_ca_file is None:
            return
        try:
            ssl.create_default_context(cafile=str(self.nats_ca_file))
        except OSError as err:  # ssl.SSLError too: not PEM, no certificate in it
            raise ConfigError(f"relay.nats_ca_file={str(self.nats_ca_file)!r} is not a "
                              f"readable PEM CA certificate: {err}") from err

    @property
    def resolved_tcp_port(self) -> int:
        """The TCP port to bind: ``tcp_port`` or ``port + 1`` (0 when ``port`` is 0)."""
        if self.tcp_port is not None:
            return self.tcp_port
        return self.port + 1 if self.port else 0


def _check_nats_url(url: str) -> None:
    """Refuse what the NATS client cannot connect to: one ``nats://`` or ``tls://`` URL with
    a host and a port in 1..65535 if one is given (default 4222). The messages never show
    the URL itself: it may hold a password.

    Raises:
        ConfigError: naming ``relay.nats_url`` and what is wrong with it.
    """
    shape = "relay.nats_url must be nats://HOST:PORT or tls://HOST:PORT"
    if not url.startswith(("nats://", "tls://")):
        scheme = url.partition("://")[0] if "://" in url else ""
        raise ConfigError(f"{shape} (scheme {scheme!r} is not supported)")
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as err:  # a port that is not a number or beyond 65535, a bad [IPv6]
        # not the parser's text: it quotes the URL's parts, a password's too (found by review)
        raise ConfigError(f"{shape}: its port is not a number in 1..65535, or its host is "
                          "not a valid name or [IPv6] address") from err
    if not parts.hostname:
        raise ConfigError(f"{shape}: it names no host")
    if parts.path not in ("", "/") or parts.query or parts.fragment:
        # a NATS URL has no path: one is a password holding '/' or '?' (its '@' after the
        # host; the host was then the user name and part of the password shown as a path)
        raise ConfigError(f"{shape} and nothing after the port (a password must not hold "
                          "'/', '?' or '#': use a hex one)")
    if port == 0:
        raise ConfigError(f"{shape}: port 0 is not a NATS server's port")
