"""The view server: the static page over HTTP and live snapshots over a WebSocket.

One ``websockets`` server answers three paths under ``prefix`` (``/`` for a station,
``/view/`` at the relay):

* ``GET {prefix}`` and ``GET {prefix}view.js``: the page (package data, no build step);
* ``{prefix}ws``: the WebSocket. When the server has an ``authorize`` callback the browser's
  first message must be ``{"type": "hello", "session": ..., "token": ...}`` (the page takes
  them from its URL's fragment, which the browser never sends to a server, so the token
  is not in any request line or log); anything else closes the connection (4001).

Rates and back-pressure: a publisher task calls the :class:`ViewSource` ``rate_hz`` times a
second and keeps only the newest snapshot (latest wins), JSON-encoded once. Each browser has
one sender task that sends the newest snapshot whenever the previous send has completed, so
a slow browser skips snapshots and nothing queues; a send stuck longer than
``send_timeout_s`` closes that browser. What a browser sends is read and discarded (messages
above ``max_message_bytes`` close it, 1009); more than ``max_clients`` browsers get
HTTP 503 before the upgrade. With ``authorize`` only browsers whose hello was accepted count
against ``max_clients``. A connection is *pending* from its TCP accept until its WebSocket
is open (without ``authorize``) or its hello was answered (with it): its HTTP request must
arrive within ``open_timeout_s`` and its hello within ``hello_timeout_s``. Pending
connections are capped per client address (``max_pending_per_address``; an IPv6 address
counts by its /64) and in all (``max_pending``); a new connection over a cap closes the
OLDEST pending one of its address (or of all) instead of being refused, so silent sockets
cannot lock out a browser, which sends its request and hello at once, even when every
browser comes through one proxy's address. A refused browser's close handshake may take
``refuse_close_timeout_s``. None of this touches the station's own loops: the server
runs in a thread of its own (:meth:`ViewServer.start_thread`) or, at the relay, as tasks of
the relay's event loop (:meth:`ViewServer.start`).

Each message to a browser::

    {"type": "snapshot", "seq": N, "live": {...}, "trail": {"from": i, "points": [...]},
     "analysis": {...}}            # "analysis" only when it changed since the last send

``trail`` carries the trajectory points this browser has not had yet (at most
``trail_batch`` per message), so a browser that skips snapshots still draws the whole path.
The analysis is encoded once per version; one that cannot be encoded (a NaN) is dropped
(``analysis_dropped``, logged once) and the live stream goes on.

Who may open the WebSocket: a request whose ``Origin`` names another site than its ``Host``
gets HTTP 403 (a web page the operator visits cannot read the view or send play/pause), and
without ``authorize`` (a station's or a replay's view, no token) the ``Host`` must be an IP
address, ``localhost``, the name the server was bound to or one of ``allowed_hosts`` (403
otherwise: DNS rebinding). A token-protected view (the relay's) accepts any host name, as it
is reached by its public name. A single-valued header given twice gets HTTP 400. A token
with an expiry (``authorize`` returning a Unix time) closes its browser with 4001 when it
expires. The WebSocket layer logs through ``shared.view.websockets``, which drops DEBUG
records: frame contents (a hello's token) are never logged.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import math
import re
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib import resources
from typing import Any, ClassVar, Protocol

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from shared.errors import ConfigError
from shared.timebase import now_us

__all__ = ["PAGE_FILES", "ViewAddress", "ViewServer", "ViewServerConfig", "ViewSource",
           "check_host_names", "parse_view_address"]

log = logging.getLogger(__name__)


class _NoDebug(logging.Filter):
    """Drop the WebSocket layer's DEBUG records: they carry frame contents (a hello's token)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno > logging.DEBUG


#: the view's WebSocket layer logs here, never at DEBUG (no frame, no header is logged)
_WS_LOG = logging.getLogger("shared.view.websockets")
_WS_LOG.setLevel(logging.INFO)
_WS_LOG.addFilter(_NoDebug())

#: what ``authorize`` returns: False (refused), True (no expiry) or the Unix time (s) after
#: which the token is no longer valid
Verdict = bool | float

#: file name -> content type of the page's files (package data of ``shared.view.page``)
PAGE_FILES = {"index.html": "text/html; charset=utf-8",
              "view.js": "text/javascript; charset=utf-8"}


class ViewSource(Protocol):
    """What a view shows; called from the view server's thread (or the relay's loop)."""

    def live(self) -> Mapping[str, Any]:
        """The current state (JSON-able, finite numbers): called ``rate_hz`` times a second."""
        ...

    def trail_since(self, start: int, limit: int) -> tuple[int, list[list[float]]]:
        """Trajectory points from index ``start`` (or the oldest kept), at most ``limit``.

        Returns:
            The index of the first point returned and the points.
        """
        ...

    def analysis(self) -> tuple[int, Mapping[str, Any] | None]:
        """The latest analysis result and its version (changes when a new one is ready)."""
        ...


@dataclass(frozen=True)
class ViewAddress:
    """Where the view listens."""

    host: str
    port: int

    @property
    def is_loopback(self) -> bool:
        """True for 127.0.0.0/8, ::1 and ``localhost``."""
        if self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False


def parse_view_address(text: str) -> ViewAddress:
    """Parse ``HOST:PORT`` (``[::1]:PORT`` for IPv6; a bare ``PORT`` means loopback).

    Raises:
        ConfigError: a malformed address or a port outside 0..65535.
    """
    raw = text.strip()
    host, sep, port_text = raw.rpartition(":")
    if not sep:
        host, port_text = "127.0.0.1", raw
    host = host.strip("[]") or "127.0.0.1"
    try:
        port = int(port_text)
    except ValueError as err:
        raise ConfigError(f"--view wants HOST:PORT, got {text!r}") from err
    if not 0 <= port <= 65535:
        raise ConfigError(f"--view port must lie in 0..65535, got {port}")
    return ViewAddress(host, port)


#: a host name as a browser sends it in ``Host`` (an internationalized name in its xn-- form)
_HOST_NAME = re.compile(r"[a-z0-9_]([a-z0-9_.-]{0,251}[a-z0-9_])?\.?", re.IGNORECASE)


def check_host_names(key: str, names: object) -> None:
    """Host names a view without token may also be reached by (``allowed_hosts``): each a
    bare DNS name (letters, digits, ``-``, ``.``), no scheme, port or path.

    Raises:
        ConfigError: naming ``key`` and the first name that is none.
    """
    if not isinstance(names, tuple | list):
        raise ConfigError(f"{key} must be a list of host names, got {names!r}")
    for name in names:
        if not (isinstance(name, str) and _HOST_NAME.fullmatch(name)):
            raise ConfigError(f"{key}: {name!r} is not a host name (letters, digits, '-' and "
                              "'.', as the browser's address bar shows it, without scheme, "
                              "port or path; an internationalized name in its xn-- form)")


@dataclass(frozen=True)
class ViewServerConfig:
    """Settings of a view server.

    Attributes:
        rate_hz: snapshots per second (the page's update rate; >= 30 for the pins).
        max_clients: browsers at once; more get HTTP 503.
        max_message_bytes: largest message a browser may send (larger closes it, 1009).
        send_timeout_s: a send not finished in this time closes that browser.
        trail_batch: most trajectory points in one message.
        hello_timeout_s: with ``authorize``: the hello must arrive within this time (the
            page sends it as soon as the WebSocket opens).
        open_timeout_s: a connection's HTTP request (and the upgrade) must be done within
            this time of its TCP accept (websockets' ``open_timeout``).
        prefix: path of the page (``/`` at a station, ``/view/`` at the relay).
        max_pending: pending connections (before their upgrade, with ``authorize`` before
            their hello) at once; one more closes the oldest.
        max_pending_per_address: the same, per client address (an IPv6 address: its /64).
        refuse_close_timeout_s: how long a refused browser's close handshake may take.
        allowed_hosts: host names (besides IP addresses, ``localhost`` and the bound name)
            a view without ``authorize`` may be reached by (a tunnel's or proxy's name).
    """

    rate_hz: float = 40.0
    max_clients: int = 8
    max_message_bytes: int = 4096
    send_timeout_s: float = 5.0
    trail_batch: int = 4000
    hello_timeout_s: float = 2.0
    open_timeout_s: float = 3.0
    prefix: str = "/"
    max_pending: int = 64
    max_pending_per_address: int = 8
    refuse_close_timeout_s: float = 1.0
    allowed_hosts: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not 1.0 <= self.rate_hz <= 120.0:
            raise ConfigError("view rate_hz must lie in [1, 120]")
        if self.max_clients < 1 or self.max_message_bytes < 64 or self.trail_batch < 1:
            raise ConfigError("view max_clients >= 1, max_message_bytes >= 64, "
                              "trail_batch >= 1")
        if self.max_pending < 1 or self.max_pending_per_address < 1:
            raise ConfigError("view max_pending and max_pending_per_address must be >= 1")
        if not (self.send_timeout_s > 0 and self.hello_timeout_s > 0
                and self.open_timeout_s > 0 and self.refuse_close_timeout_s > 0):
            raise ConfigError("view timeouts must be > 0")
        if not (self.prefix.startswith("/") and self.prefix.endswith("/")):
            raise ConfigError("view prefix must start and end with '/'")
        check_host_names("view allowed_hosts", self.allowed_hosts)


def _page_bytes() -> dict[str, bytes]:
    page = resources.files("shared.view") / "page"
    return {name: (page / name).read_bytes() for name in PAGE_FILES}


def _respond(connection: ServerConnection, status: int, body: bytes | str,
             content_type: str) -> Response:
    response = connection.respond(status, body if isinstance(body, str) else "")
    headers = Headers(response.headers)
    del headers["Content-Type"]
    headers["Content-Type"] = content_type
    headers["Cache-Control"] = "no-store"
    headers["X-Content-Type-Options"] = "nosniff"
    data = body if isinstance(body, bytes) else response.body
    del headers["Content-Length"]
    headers["Content-Length"] = str(len(data))
    return Response(response.status_code, response.reason_phrase, headers, data)


class _BadRequest(ValueError):
    """A malformed request (answered with HTTP 400)."""


def _header(headers: Headers, name: str) -> str | None:
    """The one value of a single-valued header, or None when absent.

    Raises:
        _BadRequest: the header is given more than once.
    """
    values = headers.get_all(name)
    if len(values) > 1:
        raise _BadRequest(f"{name} given {len(values)} times")
    return values[0] if values else None


def _authority(text: str, default_port: int) -> tuple[str, int] | None:
    """(host name in lower case, port) of a ``Host`` header or an origin's authority; None
    when it is malformed."""
    text = text.strip().lower()
    if not text or any(c in text for c in "/\\@?# \t"):
        return None
    if text.startswith("["):  # [IPv6] or [IPv6]:port
        end = text.find("]")
        host, rest = text[1:end], text[end + 1:]
        if end < 0 or (rest and not rest.startswith(":")):
            return None
        port_text = rest[1:]
    else:
        host, _, port_text = text.partition(":")
        if ":" in port_text:
            return None  # an IPv6 address without brackets
    if port_text and not (port_text.isascii() and port_text.isdigit() and len(port_text) <= 5):
        return None
    host = host.rstrip(".")  # "example.org." is "example.org"
    return (host, int(port_text) if port_text else default_port) if host else None


def _is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


class ViewServer:
    """Serves the page and live snapshots of one :class:`ViewSource` (module docstring).

    Args:
        source: what to show (a station's view: one source, published all the time).
        config: rates and limits.
        authorize: checks a browser's hello (session, token): returns False (refused),
            True (accepted) or the Unix time (s) the token expires at (the browser is then
            closed, 4001); None: no hello required (a station's view, bound to loopback by
            default).
        source_for: with ``authorize`` (the relay): the source of a session, or None when
            the session is unknown; published only while a browser watches it.
        control: called (on the server's loop; must be quick) with each
            ``{"type": "control", ...}`` object a browser sends (a replay's play / pause);
            None: what browsers send is ignored (a station's and the relay's view).
    """

    def __init__(self, source: ViewSource | None, config: ViewServerConfig | None = None, *,
                 authorize: Callable[[str, str], Verdict] | None = None,
                 source_for: Callable[[str], ViewSource | None] | None = None,
                 control: Callable[[Mapping[str, Any]], None] | None = None) -> None:
        if (source is None) == (source_for is None) or (source_for is not None
                                                        and authorize is None):
            raise ConfigError("a view server needs one source, or source_for with authorize")
        self.source = source
        self.config = config or ViewServerConfig()
        self._authorize = authorize
        self._source_for = source_for
        self._control = control
        self._page = _page_bytes()
        self.counters: Counter[str] = Counter()
        self._server: Server | None = None
        self._publisher: asyncio.Task[None] | None = None
        self._feeds: dict[str, _Feed] = {}
        if source is not None:
            self._feeds[""] = _Feed(source, keep=True)
        self._clients = 0
        #: pending connections (module docstring) per client address key, oldest first
        self._pending: dict[str, dict[ServerConnection, None]] = {}
        #: every pending connection and its address key, oldest first
        self._pending_all: dict[ServerConnection, str] = {}
        #: host names (besides IP addresses and localhost) a view without token may be
        #: reached by (set by start())
        self._host_names: frozenset[str] = frozenset()
        #: CPU seconds this server's thread spent building, encoding and composing snapshots
        self.cpu_s = 0.0
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping: asyncio.Event | None = None
        self._error_logged = False
        self.port: int | None = None

    # ------------------------------------------------------------------ life

    async def start(self, host: str, port: int) -> None:
        """Listen on ``host:port`` (0: any free port, see :attr:`port`) in the running loop.

        Raises:
            ConfigError: the address cannot be bound.
        """
        names = {name.lower().rstrip(".") for name in self.config.allowed_hosts}
        if not _is_ip(host.strip("[]")):
            names.add(host.lower().rstrip("."))
        if not ViewAddress(host, port).is_loopback:  # reachable by the machine's own name
            machine = socket.gethostname().lower()
            names |= {machine, machine + ".local"}
        self._host_names = frozenset(names - {""})
        view = self

        class _Connection(_ViewConnection):
            owner = view

        try:
            self._server = await serve(
                self._handler, host, port, process_request=self._process_request,
                max_size=self.config.max_message_bytes, max_queue=4,
                write_limit=64 * 1024, compression=None, ping_interval=20, ping_timeout=20,
                open_timeout=self.config.open_timeout_s, create_connection=_Connection,
                logger=_WS_LOG)
        except OSError as err:
            raise ConfigError(f"the view cannot listen on {host}:{port}: {err}") from err
        sock = next(iter(self._server.sockets))
        self.port = int(sock.getsockname()[1])
        self._publisher = asyncio.create_task(self._publish(), name="view-publisher")

    async def close(self) -> None:
        """Stop publishing, close every browser and the listener."""
        if self._publisher is not None:
            self._publisher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._publisher
            self._publisher = None
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None

    def start_thread(self, host: str, port: int, timeout_s: float = 10.0) -> int:
        """Run the server in a thread of its own with its own event loop.

        Returns:
            The bound port.

        Raises:
            ConfigError: the address cannot be bound, or the thread did not start in time.
        """
        ready = threading.Event()
        failure: list[BaseException] = []

        async def main() -> None:
            self._stopping = asyncio.Event()
            try:
                await self.start(host, port)
            except ConfigError as err:
                failure.append(err)
                ready.set()
                return
            ready.set()
            try:
                await self._stopping.wait()
            finally:
                await self.close()

        def run() -> None:
            loop = asyncio.new_event_loop()
            self._loop = loop
            try:
                loop.run_until_complete(main())
            finally:
                loop.close()

        self._thread = threading.Thread(target=run, name="view-server", daemon=True)
        self._thread.start()
        if not ready.wait(timeout_s):
            raise ConfigError("the view server did not start in time")
        if failure:
            self._thread.join(timeout_s)
            raise ConfigError(str(failure[0]))
        assert self.port is not None  # set by start() before ready
        return self.port

    def stop_thread(self, timeout_s: float = 10.0) -> None:
        """Stop a server started with :meth:`start_thread` (idempotent)."""
        loop, stopping, thread = self._loop, self._stopping, self._thread
        if thread is None:
            return
        if loop is not None and stopping is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stopping.set)
        thread.join(timeout_s)
        if thread.is_alive():
            log.warning("the view server thread did not stop within %.1f s", timeout_s)
        self._thread = None

    @property
    def clients(self) -> int:
        """Browsers connected now."""
        return self._clients

    @property
    def pending(self) -> int:
        """Pending connections now (before their upgrade or, with ``authorize``, their
        hello)."""
        return len(self._pending_all)

    # ------------------------------------------------------------------ publishing

    async def _publish(self) -> None:
        period_s = 1.0 / self.config.rate_hz
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        while True:
            for key, feed in list(self._feeds.items()):
                if feed.clients == 0 and not feed.keep:
                    del self._feeds[key]
                    continue
                self._publish_feed(feed)
            next_t += period_s
            now = loop.time()
            if next_t < now:
                next_t = now
            await asyncio.sleep(next_t - now)

    def _publish_feed(self, feed: _Feed) -> None:
        t0 = time.thread_time()
        try:
            self._build(feed)
        finally:
            self.cpu_s += time.thread_time() - t0

    def _build(self, feed: _Feed) -> None:
        try:
            live = dict(feed.source.live())
            live["view"] = {"clients": feed.clients, "t_us": now_us()}
            text = json.dumps(live, allow_nan=False, separators=(",", ":"))
        except Exception as err:  # a view bug must never reach the station
            self.counters["source_errors"] += 1
            if not self._error_logged:
                self._error_logged = True
                log.exception("view snapshot failed (logged once): %s", err)
            return
        self._encode_analysis(feed)
        feed.live_json = text
        feed.seq += 1
        self.counters["snapshots"] += 1
        fresh, feed.fresh = feed.fresh, asyncio.Event()
        fresh.set()

    def _encode_analysis(self, feed: _Feed) -> None:
        """Encode the source's analysis once per version; one that cannot be encoded (a
        non-finite number) is dropped, counted and logged once, and never sent."""
        try:
            version, analysis = feed.source.analysis()
        except Exception as err:  # a view bug must never reach the station
            self.counters["source_errors"] += 1
            log.debug("view analysis unavailable: %s", err)
            return
        if version == feed.analysis_version:
            return
        feed.analysis_version = version
        feed.analysis_json = None
        if analysis is None:
            return
        try:
            feed.analysis_json = json.dumps(analysis, allow_nan=False, separators=(",", ":"))
        except (ValueError, TypeError, RecursionError) as err:
            self.counters["analysis_dropped"] += 1
            if self.counters["analysis_dropped"] == 1:
                log.warning("view: analysis version %s cannot be sent (%s); dropped, the live "
                            "view goes on (logged once)", version, err)

    def _message(self, client: _Client) -> str:
        t0 = time.thread_time()
        try:
            return self._compose(client)
        finally:
            self.cpu_s += time.thread_time() - t0

    def _compose(self, client: _Client) -> str:
        feed = client.feed
        first, points = feed.source.trail_since(client.trail_next, self.config.trail_batch)
        client.trail_next = first + len(points)
        try:
            trail = json.dumps(points, allow_nan=False, separators=(",", ":"))
        except ValueError:  # a non-finite coordinate: sent as null, as num() does
            self.counters["trail_nonfinite"] += 1
            trail = json.dumps([[v if math.isfinite(v) else None for v in p] for p in points],
                               separators=(",", ":"))
        parts = [f'{{"type":"snapshot","seq":{feed.seq},"live":{feed.live_json}',
                 f',"trail":{{"from":{first},"points":{trail}}}']
        if client.analysis_version != feed.analysis_version:
            client.analysis_version = feed.analysis_version
            if feed.analysis_json is not None:
                parts.append(',"analysis":' + feed.analysis_json)
        parts.append("}")
        return "".join(parts)

    # ------------------------------------------------------------------ HTTP and WebSocket

    def _process_request(self, connection: ServerConnection, request: Request
                         ) -> Response | None:
        try:
            return self._route(connection, request)
        except _BadRequest as err:  # a client's mistake: 400, never a 500 and a traceback
            self.counters["http_bad_request"] += 1
            log.debug("view: bad request: %s", err)
            return _respond(connection, 400, "Tele-Touch view: bad request\n",
                            "text/plain; charset=utf-8")

    def _route(self, connection: ServerConnection, request: Request) -> Response | None:
        prefix = self.config.prefix
        path = request.path.split("?", 1)[0].split("#", 1)[0]
        if path == prefix.rstrip("/") and prefix != "/":
            response = _respond(connection, 301, "", "text/plain; charset=utf-8")
            response.headers["Location"] = prefix
            return response
        if path in (prefix, prefix + "index.html"):
            return _respond(connection, 200, self._page["index.html"], PAGE_FILES["index.html"])
        if path == prefix + "view.js":
            return _respond(connection, 200, self._page["view.js"], PAGE_FILES["view.js"])
        if path != prefix + "ws":
            self.counters["http_not_found"] += 1
            return _respond(connection, 404, "Tele-Touch view: not found\n",
                            "text/plain; charset=utf-8")
        host, origin = _header(request.headers, "Host"), _header(request.headers, "Origin")
        # Connection is a list header: several lines are one list (as websockets reads it)
        if "upgrade" not in ",".join(request.headers.get_all("Connection")).lower():
            return _respond(connection, 426, "Tele-Touch view: WebSocket endpoint\n",
                            "text/plain; charset=utf-8")
        refusal = self._forbidden(host, origin)
        if refusal is not None:
            self.counters[refusal] += 1
            if self.counters[refusal] == 1:
                log.warning("view: WebSocket refused (%s): Host %r, Origin %r (logged once)",
                            refusal, host, origin)
            return _respond(connection, 403, "Tele-Touch view: forbidden\n",
                            "text/plain; charset=utf-8")
        if self._clients >= self.config.max_clients:
            self._refuse_logged()
            return _respond(connection, 503, "Tele-Touch view: too many viewers\n",
                            "text/plain; charset=utf-8")
        return None

    def _forbidden(self, host: str | None, origin: str | None) -> str | None:
        """Why a WebSocket upgrade with these headers is refused (a counter's name), or None.

        The ``Origin`` (sent by every browser) must name the page's own site, its ``Host``:
        another site's page gets nothing. Without a token the ``Host`` must be a name this
        server is known by (an IP address, localhost, the bound name, ``allowed_hosts``):
        a rebound DNS name of another site gets nothing either.
        """
        if host is None:
            return "ws_forbidden_host"
        if origin is not None:
            scheme, sep, rest = origin.strip().lower().partition("://")
            if not sep or scheme not in ("http", "https"):
                return "ws_forbidden_origin"  # "null", file://, extensions ...
            default = 443 if scheme == "https" else 80
            own, theirs = _authority(host, default), _authority(rest, default)
            if own is None or theirs is None or own != theirs:
                return "ws_forbidden_origin"
        if self._authorize is not None:
            return None  # the token protects it; reached by its public name
        name = _authority(host, 0)
        if name is None:
            return "ws_forbidden_host"
        hostname = name[0]
        if (_is_ip(hostname) or hostname == "localhost" or hostname.endswith(".localhost")
                or hostname in self._host_names):
            return None
        return "ws_forbidden_host"

    def _admit(self, connection: _ViewConnection) -> None:
        """A new TCP connection: pending until :meth:`_settle`; over a cap, the oldest
        pending connection of its address (or of all) is closed to make room."""
        key = _address_key(connection.remote_address)
        mine = self._pending.setdefault(key, {})
        mine[connection] = None
        self._pending_all[connection] = key
        if len(mine) > self.config.max_pending_per_address:
            self._evict(next(iter(mine)), "pending_evicted_address",
                        f"{len(mine)} connections from {key} wait for their request or hello")
        elif len(self._pending_all) > self.config.max_pending:
            self._evict(next(iter(self._pending_all)), "pending_evicted",
                        f"{len(self._pending_all)} connections wait for their request or hello")

    def _settle(self, connection: ServerConnection) -> None:
        """``connection`` is no longer pending (served, refused or gone); idempotent."""
        key = self._pending_all.pop(connection, None)
        if key is None:
            return
        mine = self._pending.get(key)
        if mine is not None:
            mine.pop(connection, None)
            if not mine:
                del self._pending[key]

    def _evict(self, connection: ServerConnection, counter: str, why: str) -> None:
        """Close a pending connection at once (it never answers a close handshake)."""
        self._settle(connection)
        if isinstance(connection, _ViewConnection):
            connection.evicted = True
        self.counters[counter] += 1
        if self.counters[counter] == 1:
            log.warning("view: %s; the oldest is closed (logged once)", why)
        connection.transport.abort()

    def _refuse_logged(self) -> None:
        self.counters["clients_refused"] += 1
        if self.counters["clients_refused"] == 1:
            log.warning("view: %d browsers connected, refusing more (logged once)",
                        self.config.max_clients)

    async def _refuse(self, ws: ServerConnection, code: int, reason: str) -> None:
        """Close a refused browser; one that does not answer the close is cut soon."""
        ws.close_timeout = self.config.refuse_close_timeout_s
        await ws.close(code, reason)

    async def _hello(self, ws: ServerConnection) -> tuple[_Feed, float | None] | None:
        """The feed this browser may watch and when its token expires (Unix time, None:
        never), after its hello when tokens are needed; None: refused (and closed)."""
        authorize = self._authorize
        if authorize is None:
            return self._feeds[""], None
        try:
            async with asyncio.timeout(self.config.hello_timeout_s):
                raw = await ws.recv()
            doc = json.loads(raw)
        except (TimeoutError, ValueError, RecursionError, ConnectionClosed):
            doc = None  # RecursionError: a deeply nested hello of a few KiB
        session = doc.get("session") if isinstance(doc, dict) else None
        token = doc.get("token") if isinstance(doc, dict) else None
        feed = None
        verdict: Verdict = False
        if (isinstance(doc, dict) and doc.get("type") == "hello" and isinstance(session, str)
                and isinstance(token, str)):
            verdict = authorize(session, token)
        expiry = None if isinstance(verdict, bool) else float(verdict)
        if verdict is not False and (expiry is None or time.time() < expiry):
            assert isinstance(session, str)
            feed = self._feeds.get(session)
            if feed is None and self._source_for is not None:
                source = self._source_for(session)
                if source is not None:
                    feed = self._feeds[session] = _Feed(source, keep=False)
            elif feed is None and self.source is not None:
                feed = self._feeds.get("")
        if feed is None:
            if not getattr(ws, "evicted", False):
                self.counters["clients_unauthorized"] += 1
            await self._refuse(ws, 4001, "view needs a valid session and token")
            return None
        return feed, expiry

    async def _drain(self, ws: ServerConnection) -> None:
        """Read what the browser sends (so control frames keep flowing): control messages go
        to the ``control`` callback when there is one, anything else is discarded."""
        with contextlib.suppress(ConnectionClosed):
            async for raw in ws:
                if self._control is None or not self._controlled(raw):
                    self.counters["client_messages_ignored"] += 1

    def _controlled(self, raw: str | bytes) -> bool:
        try:
            doc = json.loads(raw)
        except (ValueError, RecursionError):
            return False
        if not (isinstance(doc, dict) and doc.get("type") == "control"):
            return False
        assert self._control is not None
        try:
            self._control(doc)
        except Exception as err:  # a bad control message must not end the server
            self.counters["control_errors"] += 1
            log.info("view: control message refused: %s", err)
            return False
        self.counters["control_messages"] += 1
        return True

    async def _handler(self, ws: ServerConnection) -> None:
        if self._authorize is None:
            self._settle(ws)
            await self._serve_browser(ws, self._feeds[""], None)
            return
        # before the hello: still pending (a slot of the pending caps, not of max_clients)
        try:
            granted = await self._hello(ws)
        finally:
            self._settle(ws)
        if granted is not None:
            await self._serve_browser(ws, *granted)

    async def _serve_browser(self, ws: ServerConnection, feed: _Feed,
                             expiry: float | None) -> None:
        # counted here, not before the upgrade: an upgrade that fails never holds a slot;
        # a burst that passed the HTTP check together is cut here (no await in between)
        if self._clients >= self.config.max_clients:
            self._refuse_logged()
            await self._refuse(ws, 1013, "too many viewers")
            return
        self._clients += 1
        try:
            self.counters["clients_served"] += 1
            client = _Client(feed)
            feed.clients += 1
            drain = asyncio.create_task(self._drain(ws), name="view-drain")
            try:
                await self._send_loop(ws, client, drain, expiry)
            finally:
                feed.clients -= 1
                drain.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await drain
        finally:
            self._clients -= 1

    async def _send_loop(self, ws: ServerConnection, client: _Client,
                         drain: asyncio.Task[None], expiry: float | None) -> None:
        feed = client.feed
        while not drain.done():
            if expiry is not None and time.time() >= expiry:
                self.counters["clients_expired"] += 1
                await self._refuse(ws, 4001, "the token expired")
                return
            if client.seq == feed.seq:
                waiter = asyncio.ensure_future(feed.fresh.wait())
                remaining = None if expiry is None else max(0.0, expiry - time.time())
                await asyncio.wait({waiter, drain}, timeout=remaining,
                                   return_when=asyncio.FIRST_COMPLETED)
                if not waiter.done():
                    waiter.cancel()
                    if drain.done():
                        break
                    continue  # the token's expiry: checked at the top
            if client.seq and feed.seq > client.seq + 1:
                self.counters["snapshots_skipped"] += feed.seq - client.seq - 1
            client.seq = feed.seq
            try:
                text = self._message(client)
            except Exception as err:  # a view bug must never reach the station
                self.counters["source_errors"] += 1
                log.warning("view message failed: %s", err)
                await ws.close(1011, "view error")
                return
            try:
                async with asyncio.timeout(self.config.send_timeout_s):
                    await ws.send(text)
            except TimeoutError:
                self.counters["clients_too_slow"] += 1
                log.info("view: a browser took > %.1f s for one snapshot; closing it",
                         self.config.send_timeout_s)
                ws.transport.abort()
                return
            except ConnectionClosed:
                return
            self.counters["messages_sent"] += 1


def _address_key(peer: Any) -> str:
    """The key of the per-address cap of a peer address (``remote_address``): its IP
    address; for IPv6 its /64 (one host usually holds a whole /64), an IPv4-mapped IPv6
    address as the IPv4 address."""
    text = str(peer[0]) if isinstance(peer, tuple) and peer else str(peer)
    try:
        ip = ipaddress.ip_address(text.split("%", 1)[0])
    except ValueError:
        return text
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            return str(ip.ipv4_mapped)
        return str(ipaddress.IPv6Network((ip, 64), strict=False))
    return str(ip)


class _ViewConnection(ServerConnection):
    """A connection that registers with its :class:`ViewServer` (``owner``, set by a
    subclass per server) from its TCP accept: pending until served, refused or gone."""

    owner: ClassVar[ViewServer | None] = None
    #: closed by a pending cap (not counted as an unauthorized browser)
    evicted = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        if self.owner is not None:
            self.owner._admit(self)

    def connection_lost(self, exc: Exception | None) -> None:
        super().connection_lost(exc)
        if self.owner is not None:
            self.owner._settle(self)


class _Feed:
    """One source's newest snapshot (JSON) and the event its browsers wait on."""

    __slots__ = ("analysis_json", "analysis_version", "clients", "fresh", "keep", "live_json",
                 "seq", "source")

    def __init__(self, source: ViewSource, keep: bool) -> None:
        self.source = source
        #: the source's analysis version seen last and its JSON (None: none or not sendable)
        self.analysis_version: int | None = None
        self.analysis_json: str | None = None
        self.keep = keep
        self.seq = 0
        self.live_json = "{}"
        self.clients = 0
        self.fresh = asyncio.Event()


class _Client:
    """What one browser has had."""

    __slots__ = ("analysis_version", "feed", "seq", "trail_next")

    def __init__(self, feed: _Feed) -> None:
        self.feed = feed
        self.seq = 0
        self.trail_next = 0
        self.analysis_version: int | None = None


def token_authorizer(check: Callable[[str, str], float | None],
                     errors: tuple[type[BaseException], ...]
                     ) -> Callable[[str, str], Verdict]:
    """Adapt a raising check(session, token) into the server's ``authorize`` callback.

    ``check`` returns the token's expiry (Unix time, s) or None when it has none.
    """
    def authorize(session: str, token: str) -> Verdict:
        try:
            expiry = check(session, token)
        except errors:
            return False
        return True if expiry is None else float(expiry)
    return authorize

