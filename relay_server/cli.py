"""Run the Tele-Touch cloud relay: WebSocket and raw TCP, sessions, latency accounting.

Stations connect with a ``hello`` naming a session, a role (local, remote, observer)
and the session token. The relay forwards local <-> remote with per-stream policy,
estimates each station's clock offset (NTP-style) and pushes ``stats`` every second.
Live figures: ``GET http://HOST:PORT/status`` (JSON) and ``GET /metrics`` (Prometheus);
liveness: ``GET /healthz`` (``ok``, no token), or ``teletouch relay --health-check`` on the
relay's host with the same configuration (a container's HEALTHCHECK).

Tokens: with ``--secret``, version-2 tokens bound to a session, a role and an expiry
(``teletouch relay --print-token SESSION --role local --ttl-s 86400`` prints one; a local
token cannot join as remote, an expired one is refused). Legacy tokens (explicit
per-session tokens from ``--token-file`` or ``[relay.tokens]``, and hex HMAC-SHA256(secret,
session_id), printed by ``--print-token SESSION`` without ``--role``) work while
``allow_legacy_tokens`` is true (the default). Prefer ``TELETOUCH_RELAY_SECRET`` over
``--secret`` on shared hosts. See docs/security.md.

examples:
  teletouch relay --host 0.0.0.0 --port 8765 --secret "$SECRET"
  teletouch relay --host 0.0.0.0 --tls-cert relay.crt --tls-key relay.key  # wss://, tls://
  teletouch relay --port 8765 --token-file tokens.toml
  teletouch relay --print-token lab1 --role remote --ttl-s 604800
  teletouch relay --host 0.0.0.0 --workers 2 --nats nats://nats:4222   # one host, 2 cores
  curl http://127.0.0.1:8765/status
  teletouch relay --config relay.toml --health-check    # exit 0 when that relay answers
"""

from __future__ import annotations

import argparse

__all__ = ["configure_parser", "run"]


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """Add the relay's flags (None = not given, so env/TOML/defaults apply)."""
    parser.add_argument("--host", help="address to bind (default 127.0.0.1)")
    parser.add_argument("--port", type=int,
                        help="WebSocket port, also serving /status and /metrics (default 8765)")
    parser.add_argument("--tcp-port", type=int, dest="tcp_port",
                        help="raw TCP (length-prefixed) port (default: --port + 1)")
    parser.add_argument("--config", help="TOML file with a [relay] table (or $TELETOUCH_CONFIG)")
    parser.add_argument("--secret", help="shared secret for HMAC-derived session tokens "
                                         "(or $TELETOUCH_RELAY_SECRET)")
    parser.add_argument("--token-file", dest="token_file",
                        help="TOML file with a [tokens] table: session id -> token")
    parser.add_argument("--tls-cert", dest="tls_cert", metavar="FILE",
                        help="PEM certificate (chain): serve wss:// and TLS on the TCP port "
                             "(tls:// URLs); with --tls-key (docs/security.md)")
    parser.add_argument("--tls-key", dest="tls_key", metavar="FILE",
                        help="PEM private key of --tls-cert")
    parser.add_argument("--allow-any-token", dest="allow_any_token", action="store_true",
                        default=None, help="accept any token (development only)")
    parser.add_argument("--hello-timeout-s", dest="hello_timeout_s", type=float,
                        help="seconds a client has to send hello (default 5)")
    parser.add_argument("--ping-interval-s", dest="ping_interval_s", type=float,
                        help="clock_ping period per station (default 1)")
    parser.add_argument("--stats-interval-s", dest="stats_interval_s", type=float,
                        help="stats push period (default 1)")
    parser.add_argument("--view", metavar="HOST:PORT",
                        help="serve the live view to each session's observers (browser at "
                             "http://HOST:PORT/#session=S&token=OBSERVER_TOKEN; docs/view.md)")
    parser.add_argument("--nats", dest="nats_url", metavar="URL",
                        help="nats://HOST:PORT: join the relay workers on this NATS server into "
                             "one relay (stations may connect to any worker or host; "
                             "docs/operations.md)")
    parser.add_argument("--nats-connect-timeout-s", dest="nats_connect_timeout_s", type=float,
                        help="with --nats: give up starting when NATS cannot be reached "
                             "within this time (default 10)")
    parser.add_argument("--workers", type=int, default=None,
                        help="relay worker processes on this host, sharing the ports "
                             "(SO_REUSEPORT); needs --nats; default with --nats: one per core")
    parser.add_argument("--hang-timeout-s", dest="hang_timeout_s", type=float,
                        help="a relay process whose event loop makes no progress this long "
                             "writes its stacks and exits with code 1, to be restarted (with "
                             "--workers, by the supervisor); 0: no such watchdog (default 10)")
    parser.add_argument("--print-token", dest="print_token", metavar="SESSION",
                        help="print a token of SESSION for the secret and exit: v2 (role, "
                             "expiry) with --role, else the legacy per-session token")
    parser.add_argument("--role", choices=("local", "remote", "observer"),
                        help="with --print-token: the role the token admits")
    parser.add_argument("--health-check", dest="health_check", action="store_true",
                        help="do not serve: ask the relay this configuration describes "
                             "(GET /healthz on its port, over TLS when it has a certificate, "
                             "on the loopback address when it binds all) and exit 0 when it "
                             "answers, 1 otherwise (a container's HEALTHCHECK)")
    parser.add_argument("--ttl-s", dest="ttl_s", type=int, default=None,
                        help="with --print-token --role: validity in seconds "
                             "(default 604800, 7 days)")


def run(args: argparse.Namespace) -> int:
    """Resolve the configuration and serve until SIGINT/SIGTERM."""
    import asyncio
    import sys
    import time

    from relay_server.auth import derive_token, make_token
    from relay_server.config import RelayConfig
    from shared.config import resolve_config
    from shared.errors import ConfigError
    from shared.report import emit

    explicit = {name: getattr(args, name, None) for name in (
        "host", "port", "tcp_port", "secret", "token_file", "allow_any_token", "tls_cert",
        "tls_key", "view", "nats_url", "nats_connect_timeout_s", "workers",
        "hang_timeout_s",
        "hello_timeout_s", "ping_interval_s", "stats_interval_s")}
    config = resolve_config(RelayConfig, "relay", explicit=explicit, toml_path=args.config)
    if args.health_check:
        from relay_server.health import health_url, probe

        problem = probe(config)
        if problem is not None:
            emit(f"relay not healthy: {problem}", stream=sys.stderr)
            return 1
        emit(f"relay healthy: {health_url(config)}")
        return 0
    if args.print_token:
        if not config.secret:
            raise ConfigError("--print-token needs a secret (--secret or $TELETOUCH_RELAY_SECRET)")
        if args.role is not None:
            ttl_s = 604_800 if args.ttl_s is None else args.ttl_s
            if ttl_s <= 0:
                raise ConfigError("--ttl-s must be > 0")
            emit(make_token(config.secret, args.print_token, args.role,
                            int(time.time()) + ttl_s))
        elif args.ttl_s is not None:
            raise ConfigError("--ttl-s needs --role (legacy tokens never expire)")
        else:
            emit(derive_token(config.secret, args.print_token))
        return 0
    from relay_server.server import serve_forever
    from relay_server.workers import run_workers, worker_count

    workers = worker_count(config)
    if workers > 1:
        run_workers(config, workers)  # checks what its workers would load before it starts them
    else:
        config.check_nats_ca_file()  # loaded only once the ports are bound
        asyncio.run(serve_forever(config))
    return 0
