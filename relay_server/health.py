"""Is the relay this configuration describes up? (``teletouch relay --health-check``)

A container's ``HEALTHCHECK`` (or any supervisor's probe) runs on the relay's own host and
knows only its configuration. The probe asks ``GET /healthz`` on the relay's WebSocket port:
an answer that needs no status token and says nothing but ``ok``, over HTTPS when the relay
serves TLS. It connects to the address the relay binds (the loopback address when that is
every address), so over TLS it checks neither the certificate nor its name: it is a probe of
liveness on this host, not of the relay's identity (the stations check that).
"""

from __future__ import annotations

import http.client
import ssl

from relay_server.config import RelayConfig

__all__ = ["HEALTH_PATH", "health_url", "probe"]

#: the path of the relay's liveness answer (``200``, ``ok``; no token needed)
HEALTH_PATH = "/healthz"


def _probe_host(config: RelayConfig) -> str:
    """The address the probe connects to: the relay's, loopback for every address."""
    return {"0.0.0.0": "127.0.0.1", "": "127.0.0.1", "::": "::1"}.get(config.host, config.host)


def health_url(config: RelayConfig) -> str:
    """Where the relay of ``config`` answers the probe."""
    host = _probe_host(config)
    if ":" in host:
        host = f"[{host}]"
    scheme = "https" if config.tls_cert else "http"
    return f"{scheme}://{host}:{config.port}{HEALTH_PATH}"


def probe(config: RelayConfig, timeout_s: float = 2.0) -> str | None:
    """None when the relay of ``config`` answers ``GET /healthz`` with 200 ``ok``; else what
    went wrong, naming the URL. ``timeout_s`` bounds each step (connect, TLS handshake,
    read), not their sum: a container's probe has its own overall timeout."""
    url, host = health_url(config), _probe_host(config)
    conn: http.client.HTTPConnection
    if config.tls_cert:
        context = ssl.create_default_context()
        context.check_hostname = False  # liveness on this host, not identity (module doc)
        context.verify_mode = ssl.CERT_NONE
        conn = http.client.HTTPSConnection(host, config.port, timeout=timeout_s,
                                           context=context)
    else:
        conn = http.client.HTTPConnection(host, config.port, timeout=timeout_s)
    try:
        conn.request("GET", HEALTH_PATH)
        answer = conn.getresponse()
        body = answer.read(64)
    except (OSError, http.client.HTTPException) as err:
        return f"{url}: {err or type(err).__name__}"
    finally:
        conn.close()
    if answer.status != 200 or body.strip() != b"ok":
        return f"{url}: HTTP {answer.status} {body[:32]!r}, not a relay's 200 ok"
    return None
