"""The audit of the relay's supervisor (``teletouch relay --workers N``) and settings: a bad
setting is one clear error before any worker starts, a worker that cannot start ends the
supervisor with its error, a worker that served and died is restarted after a growing delay
(never in a hot loop, never given up), and the NATS settings are checked where they are
read (``relay_server.config``), without showing a NATS password."""

from __future__ import annotations

import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from relay_server import workers
from relay_server.config import RelayConfig
from shared.errors import ConfigError
from tests.relay_server.test_relay_tls import lab_pki  # noqa: F401 (a fixture)
from tests.support import free_tcp_port, scaled

# --------------------------------------------------------------------------- real processes


def _relay(*args: str, **settings: str) -> tuple[int, str, float]:
    """Run ``teletouch relay ARGS`` (no relay settings from this environment; ``settings``
    as ``TELETOUCH_RELAY_<NAME>``) to its end: (exit code, standard error, seconds taken).
    Fails the test when it has not ended within the allowance (a supervisor that restarts
    its failing workers for ever)."""
    exe = shutil.which("teletouch")
    cmd = [exe] if exe else [sys.executable, "-m", "lab.cli"]
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("TELETOUCH_RELAY_") and k != "TELETOUCH_CONFIG"}
    env.update({f"TELETOUCH_RELAY_{name.upper()}": value for name, value in settings.items()})
    began = time.monotonic()
    proc = subprocess.Popen([*cmd, "relay", "--host", "127.0.0.1", *args], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        _, err = proc.communicate(timeout=scaled(20.0))
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the supervisor and its workers
        _, err = proc.communicate()
        pytest.fail(f"the relay did not end within {scaled(20.0):g} s; its log ends: "
                    f"{err[-2000:]}")
    return proc.returncode, err, time.monotonic() - began


def _ports() -> list[str]:
    return ["--port", str(free_tcp_port()), "--tcp-port", str(free_tcp_port())]


def test_workers_without_credentials_end_at_once_naming_the_setting() -> None:
    """Before: each worker died at its start (no credentials) and was started again for
    ever, a traceback each time. Now the supervisor builds the token authority first."""
    code, err, took_s = _relay(*_ports(), "--workers", "2", "--nats", "nats://127.0.0.1:1")
    assert code == 1, err[-2000:]
    assert "ConfigError: the relay needs credentials: a secret (--secret or " \
           "$TELETOUCH_RELAY_SECRET)" in err, err[-2000:]
    assert "Traceback" not in err and "relay worker" not in err, err[-2000:]  # none started
    assert took_s < scaled(15.0)


def test_the_view_with_several_workers_is_refused_by_name() -> None:
    """Before: every worker bound the view's address, all but one died on EADDRINUSE and were
    started again for ever."""
    view = f"127.0.0.1:{free_tcp_port()}"
    code, err, _ = _relay(*_ports(), "--allow-any-token", "--workers", "2", "--nats",
                          "nats://127.0.0.1:1", "--view", view)
    assert code == 1, err[-2000:]
    assert f"ConfigError: relay.view ({view}) needs a single relay process, not 2 workers " \
           "(relay.workers, --workers" in err, err[-2000:]
    assert "relay worker" not in err, err[-2000:]


def test_a_worker_that_cannot_start_ends_the_supervisor_with_its_error() -> None:
    """A port held by another program (no SO_REUSEPORT): the workers cannot bind it. Before:
    restarted for ever; now the supervisor ends (exit 1) with the worker's own error."""
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        code, err, _ = _relay("--port", str(port), "--tcp-port", str(free_tcp_port()),
                              "--allow-any-token", "--workers", "2", "--nats",
                              "nats://127.0.0.1:1")
    assert code == 1, err[-2000:]
    last = err.strip().splitlines()[-1]
    assert "ConfigError: relay worker " in last and " ended before it served (exit code 1): " \
           "OSError: " in last and "address already in use" in last, err[-2000:]
    assert "starting another" not in err, err[-2000:]


# --------------------------------------------------------------------------- the supervisor


class _Beat:
    value = 0


class _Failure:
    value = b""


class _Clock:
    """``time`` for the supervisor: ``sleep`` advances ``now``; SIGTERM (the supervisor's
    stop) once ``stop_after`` workers were started."""

    def __init__(self, stop_after: int) -> None:
        self.now = 1000.0
        self.spawned: list[float] = []
        self.stop_after = stop_after

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds
        if len(self.spawned) >= self.stop_after:
            signal.raise_signal(signal.SIGTERM)


def _context(process: type) -> Any:
    """A multiprocessing context for the supervisor whose workers are ``process``."""

    class _Context:
        Process = process
        Event = threading.Event
        Value = staticmethod(lambda typecode, value, lock: _Beat())
        Array = staticmethod(lambda typecode, size, lock: _Failure())

    return _Context()


def test_a_worker_that_served_and_died_is_restarted_after_a_growing_delay(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """Workers (faked) that serve, then die half a second later: each replacement starts
    after a delay doubled from 1 s up to 30 s (before: at once, a hot crash loop); one that
    ran a minute resets the delay (1 s, then 2 s again); the supervisor never gives up on
    them."""
    lives = [0.5] * 7 + [70.0, 0.5, 1000.0]
    delays = [1.0, 2.0, 4.0, 8.0, 16.0, 30.0, 30.0, 1.0, 2.0]
    clock = _Clock(len(lives))

    class _Process:
        def __init__(self, target: Any, args: tuple[Any, ...], name: str) -> None:
            self.ready = args[3]
            self.pid: int | None = None
            self.exitcode: int | None = None

        def start(self) -> None:
            clock.spawned.append(clock.now)
            self.pid = len(clock.spawned)
            self.ends = clock.now + lives[self.pid - 1]
            self.ready.set()  # it serves

        def is_alive(self) -> bool:
            if clock.now >= self.ends:
                self.exitcode = 1
            return self.exitcode is None

        def join(self, timeout: float | None = None) -> None:
            pass

        def kill(self) -> None:
            pass

    monkeypatch.setattr(workers.mp, "get_context", lambda method: _context(_Process))
    monkeypatch.setattr(workers, "time", clock)
    caplog.set_level(logging.WARNING, logger="relay_server.workers")
    workers.run_workers(RelayConfig(nats_url="nats://127.0.0.1:1", port=18765, tcp_port=18766,
                                    hang_timeout_s=0, allow_any_token=True), 1)
    assert len(clock.spawned) == len(lives)
    # from a worker's death to its replacement: the delay, found in one of the 0.2 s rounds
    for n, delay in enumerate(delays):
        waited = clock.spawned[n + 1] - (clock.spawned[n] + lives[n])
        assert delay <= waited <= delay + 0.45, (n, waited, clock.spawned)
    said = [r.getMessage() for r in caplog.records]
    assert [m.rpartition(" another in ")[2] for m in said if "exited (code 1" in m] == \
        [f"{d:g} s" for d in delays], said


def test_the_supervisor_does_not_log_the_nats_password(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    class _Process:
        pid = None
        exitcode = None

        def __init__(self, target: Any, args: tuple[Any, ...], name: str) -> None:
            pass

        def start(self) -> None:
            signal.raise_signal(signal.SIGTERM)  # started: the supervisor is asked to stop

        def is_alive(self) -> bool:
            return True

        def join(self, timeout: float | None = None) -> None:
            pass

        def kill(self) -> None:
            pass

    monkeypatch.setattr(workers.mp, "get_context", lambda method: _context(_Process))
    caplog.set_level(logging.INFO, logger="relay_server.workers")
    workers.run_workers(RelayConfig(nats_url="nats://relay:S3cretNatsPw@127.0.0.1:1",
                                    port=18765, tcp_port=18766, allow_any_token=True), 1)
    said = [r.getMessage() for r in caplog.records]
    assert not [m for m in said if "S3cretNatsPw" in m], said
    assert "relay: 1 workers on ports 18765/18766 joined by nats://***@127.0.0.1:1" in said


# --------------------------------------------------------------------------- the settings


def test_the_tcp_port_may_not_be_the_websocket_port() -> None:
    """Before: one process died on EADDRINUSE (a raw OSError); workers (SO_REUSEPORT) bound
    both listeners to one port and the kernel sent WebSocket clients to the TCP one."""
    with pytest.raises(ConfigError, match=r"^relay\.tcp_port=8800 is relay\.port: the TCP "
                                          r"listener needs a port of its own"):
        RelayConfig(port=8800, tcp_port=8800)
    RelayConfig(port=0, tcp_port=0)  # any free port, each
    RelayConfig(port=8800, tcp_port=8801)


_NOT_HOST_PORT = (r": its port is not a number in 1\.\.65535, or its host is not a valid "
                  r"name or \[IPv6\] address$")


@pytest.mark.parametrize(("url", "why"), [
    ("nats://127.0.0.1:abc", _NOT_HOST_PORT),
    ("nats://127.0.0.1:99999", _NOT_HOST_PORT),
    ("tls://127.0.0.1:0", r": port 0 is not a NATS server's port$"),
    ("nats://", r": it names no host$"),
    ("nats://relay:S3cretNatsPw@:4222", r": it names no host$"),
    ("nats://relay:S3cr#tNatsPw@127.0.0.1:4222", _NOT_HOST_PORT),  # '#' ends the netloc
    ("nats://[::1", _NOT_HOST_PORT),
    ("http://relay:S3cretNatsPw@127.0.0.1:4222", r" \(scheme 'http' is not supported\)$"),
    ("ws://127.0.0.1:4222", r" \(scheme 'ws' is not supported\)$"),  # needs aiohttp
    ("127.0.0.1:4222", r" \(scheme '' is not supported\)$"),
])
def test_a_nats_url_the_client_cannot_use_is_refused_by_name(url: str, why: str) -> None:
    """Before: these passed the settings and failed in the NATS client at each worker's
    start, with its own error. The message never shows the URL (its password)."""
    with pytest.raises(ConfigError, match=r"^relay\.nats_url must be nats://HOST:PORT or "
                                          r"tls://HOST:PORT" + why) as refused:
        RelayConfig(nats_url=url)
    assert "S3cr" not in str(refused.value)  # not even a part of the password


def test_good_nats_urls_pass() -> None:
    for url in ("nats://127.0.0.1:4222", "tls://nats:4222", "nats://nats",
                "nats://relay:pw@[::1]:4222", "tls://token@nats.example.org:65535"):
        RelayConfig(nats_url=url)


def test_a_nats_ca_file_that_is_not_a_pem_ca_is_refused_by_name(tmp_path: Path) -> None:
    """Before: FileNotFoundError or ssl.SSLError from each worker, after it bound its ports.
    The file is read where the relay starts (``check_nats_ca_file``), not where the settings
    are read (another host's settings resolve without its files)."""
    missing = tmp_path / "missing.crt"
    config = RelayConfig(nats_url="tls://127.0.0.1:4222", nats_ca_file=missing)
    with pytest.raises(ConfigError, match=rf"^relay\.nats_ca_file='{missing}' is not a "
                                          r"readable PEM CA certificate: \[Errno 2\] "):
        config.check_nats_ca_file()
    text = tmp_path / "ca.crt"
    text.write_text("not a certificate\n")
    with pytest.raises(ConfigError, match=r"^relay\.nats_ca_file=.* is not a readable PEM CA "
                                          r"certificate: .*NO_CERTIFICATE_OR_CRL_FOUND"):
        RelayConfig(nats_url="tls://127.0.0.1:4222", nats_ca_file=text).check_nats_ca_file()


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")
def test_a_pem_nats_ca_file_passes(lab_pki: dict[str, Path]) -> None:  # noqa: F811
    RelayConfig(nats_url="tls://127.0.0.1:4222", nats_ca_file=lab_pki["ca.crt"]
                ).check_nats_ca_file()
    RelayConfig(nats_url="tls://127.0.0.1:4222").check_nats_ca_file()  # none: the system's


@pytest.mark.parametrize("count", ["1", "2"])
def test_the_relay_refuses_a_missing_nats_ca_file_before_it_starts(count: str,
                                                                   tmp_path: Path) -> None:
    """One process and a supervisor of workers alike: the setting by name, no traceback."""
    missing = tmp_path / "missing.crt"
    code, err, _ = _relay(*_ports(), "--allow-any-token", "--workers", count, "--nats",
                          "tls://127.0.0.1:1", nats_ca_file=str(missing))
    assert code == 1, err[-2000:]
    assert err.strip().splitlines()[-1].endswith(
        f"ConfigError: relay.nats_ca_file='{missing}' is not a readable PEM CA certificate: "
        "[Errno 2] No such file or directory"), err[-2000:]
    assert "Traceback" not in err, err[-2000:]


def test_a_stop_while_the_workers_start_is_no_failure(monkeypatch: pytest.MonkeyPatch) -> None:
    """systemd's stop sends SIGTERM to the whole group: workers that had not served yet die
    of it. That is the stop, not a worker that could not start (found by review: the
    supervisor ended with exit 1, 'ended before it served', and the unit failed)."""
    clock = _Clock(1)
    stopped: list[bool] = []

    class _Process:
        def __init__(self, target: Any, args: tuple[Any, ...], name: str) -> None:
            self.pid: int | None = None
            self.exitcode: int | None = None

        def start(self) -> None:  # never serves
            clock.spawned.append(clock.now)
            self.pid = len(clock.spawned)

        def is_alive(self) -> bool:
            if clock.spawned and clock.now > clock.spawned[0]:  # the stop's SIGTERM reached it
                self.exitcode = -signal.SIGTERM
            return self.exitcode is None

        def join(self, timeout: float | None = None) -> None:
            stopped.append(True)

        def kill(self) -> None:
            pass

        def terminate(self) -> None:
            pass

    monkeypatch.setattr(workers.mp, "get_context", lambda method: _context(_Process))
    monkeypatch.setattr(workers, "time", clock)
    workers.run_workers(RelayConfig(nats_url="nats://127.0.0.1:1", port=18767, tcp_port=18768,
                                    hang_timeout_s=0, allow_any_token=True), 2)
    assert len(clock.spawned) == 2
