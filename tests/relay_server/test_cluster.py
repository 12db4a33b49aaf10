"""Relay workers joined by a real nats-server (subprocesses): pairing across workers, the
NATS hop stamps, ordered streams kept in order, /status of the whole cluster, and a killed
worker's stations coming back through another worker."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import os
import re
import shutil
import signal
from collections import Counter
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from shared.client import StationLink
from shared.errors import ConfigError
from shared.motion_to_touch import trace_hops
from shared.protocol import ArmCommand, ArmState, Message, PlatformState
from shared.timebase import now_us
from tests.relay_server.test_relay_isolation_and_status import http_get
from tests.relay_server.test_relay_tls import lab_pki  # noqa: F401 (a fixture)
from tests.support import MachineStalls, NotifySocket, free_tcp_port, scaled, teletouch_cmd

pytest.importorskip("nats", reason="the cluster needs nats-py (pip install -e '.[cluster]')")
from lab.bench.load_impl import nats_server_binary

pytestmark = pytest.mark.slow


@contextlib.asynccontextmanager
async def _process(*cmd: str, env: dict[str, str] | None = None, stderr: Any = None
                   ) -> AsyncIterator[asyncio.subprocess.Process]:
    proc = await asyncio.create_subprocess_exec(*cmd, stdout=asyncio.subprocess.DEVNULL,
                                                stderr=stderr or asyncio.subprocess.DEVNULL,
                                                env=None if env is None else
                                                {**os.environ, **env})
    try:
        yield proc
    finally:
        if proc.returncode is None:
            proc.terminate()
            try:
                await asyncio.wait_for(proc.wait(), scaled(15.0))
            except TimeoutError:
                proc.kill()
                await proc.wait()


@contextlib.asynccontextmanager
async def nats_server(*extra: str) -> AsyncIterator[str]:
    try:
        binary = nats_server_binary()
    except RuntimeError as err:
        pytest.skip(str(err))
    port = free_tcp_port()
    async with _process(binary, "-a", "127.0.0.1", "-p", str(port), *extra):
        async with asyncio.timeout(scaled(15.0)):
            while True:
                try:
                    _, w = await asyncio.open_connection("127.0.0.1", port)
                    w.close()
                    break
                except OSError:
                    await asyncio.sleep(0.05)
        yield f"nats://127.0.0.1:{port}"


async def status(port: int) -> dict[str, Any]:
    code, _, body = await http_get(port, "/status")
    assert code == 200
    return dict(json.loads(body))


async def wait_workers(port: int, count: int) -> dict[str, Any]:
    """Wait until the relay on ``port`` answers and sees ``count`` live workers."""
    async with asyncio.timeout(scaled(30.0)):
        while True:
            with contextlib.suppress(OSError, AssertionError, ValueError):
                doc = await status(port)
                if len(doc["cluster"]["workers"]) == count:
                    return doc
            await asyncio.sleep(0.1)


@contextlib.asynccontextmanager
async def relay(nats_url: str, workers: int = 1, env: dict[str, str] | None = None,
                extra: tuple[str, ...] = (), stderr: Any = None) -> AsyncIterator[int]:
    """``teletouch relay --workers N --nats URL`` on fresh ports; yields the WebSocket port."""
    port, tcp_port = free_tcp_port(), free_tcp_port()
    async with _process(*teletouch_cmd(), "--log-level", "WARNING", "relay", "--host",
                        "127.0.0.1", "--port", str(port), "--tcp-port", str(tcp_port),
                        "--allow-any-token", "--workers", str(workers), "--nats", nats_url,
                        *extra, env=env, stderr=stderr):
        yield port


async def recv_type(link: StationLink, kind: str) -> Message:
    async with asyncio.timeout(scaled(10.0)):
        while True:
            msg = await link.recv()
            if kind == msg.TYPE:
                return msg


async def first_forwarded(local: StationLink, remote: StationLink) -> Message:
    """Send platform states from ``local`` until one reaches ``remote``; the one received."""
    async with asyncio.timeout(scaled(10.0)):
        seq = 0
        while True:
            seq += 1
            await local.send(PlatformState(seq=seq, ts_us=now_us()))
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.2):
                    return await recv_type(remote, "platform_state")


def station(port: int, role: str, session: str = "c1") -> StationLink:
    return StationLink(f"ws://127.0.0.1:{port}/", session=session, role=role, token="x",
                       name=f"test-{role}")


async def wait_paired(port: int, session: str) -> None:
    """Until the worker on ``port`` sees both stations of ``session`` somewhere."""
    async with asyncio.timeout(scaled(10.0)):
        while True:
            doc = await status(port)
            roles = {r for w in doc["cluster"]["workers"].values()
                     for r in w["sessions"].get(session, {}).get("stations", [])}
            if roles == {"local", "remote"}:
                return
            await asyncio.sleep(0.05)


async def test_stations_on_two_workers_exchange_messages() -> None:
    async with nats_server() as url, relay(url) as port_a, relay(url) as port_b:
        await wait_workers(port_a, 2)
        await wait_workers(port_b, 2)
        async with station(port_a, "local") as local, station(port_b, "remote") as remote:
            await local.wait_connected(scaled(10.0))
            await remote.wait_connected(scaled(10.0))
            await wait_paired(port_a, "c1")
            await wait_paired(port_b, "c1")
            await local.send(PlatformState(seq=1, ts_us=now_us(), position_mm=(1.0, 2.0, 3.0)))
            got = await recv_type(remote, "platform_state")
            assert got.position_mm == (1.0, 2.0, 3.0)  # type: ignore[attr-defined]
            stages = [h.stage for h in got.hops if h.clock == "relay"]  # type: ignore[attr-defined]
            assert stages == ["relay_in", "nats_out", "nats_in", "relay_out"]
            t = [h.t_us for h in got.hops if h.clock == "relay"]  # type: ignore[attr-defined]
            assert t == sorted(t)  # one host, one clock: the stamps are in time order
            # the motion-to-touch ledger counts the hop inside the relay's forwarding
            relay_hops = [h for h in got.hops if h.clock == "relay"]  # type: ignore[attr-defined]
            trace = trace_hops(relay_hops, {})
            assert trace.skipped is None
            assert trace.stages_us == (("relay_forward_platform", t[-1] - t[0]),)
            await remote.send(ArmState(seq=1, ts_us=now_us(), position_mm=(4.0, 5.0, 6.0)))
            back = await recv_type(local, "arm_state")
            assert back.position_mm == (4.0, 5.0, 6.0)  # type: ignore[attr-defined]
            # ordered stream across workers: every command, in order
            for seq in range(1, 41):
                await local.send(ArmCommand(seq=seq, ts_us=now_us(), action="stop"))
            seqs = [(await recv_type(remote, "arm_command")).seq for _ in range(40)]  # type: ignore[attr-defined]
            assert seqs == list(range(1, 41))
            doc_a, doc_b = await status(port_a), await status(port_b)
            assert doc_a["cluster"]["sessions"] == 1
            assert set(doc_a["cluster"]["workers"]) == set(doc_b["cluster"]["workers"])
            # one kernel: the two processes' clocks differ by their wall anchors (read when
            # each started: microseconds apart unless the wall clock was set in between)
            clocks = [(w["same_kernel"], w["clock_uncertainty_us"]) for w in
                      doc_a["cluster"]["workers"].values()]
            assert clocks == [(True, 0)] * 2, clocks
            assert all(abs(w["clock_offset_us"]) < 1_000
                       for w in doc_a["cluster"]["workers"].values())
            # books: uplink on the sender's worker, NATS leg on the receiver's
            assert doc_b["sessions"]["c1"]["nats_us"]["local_to_remote"]["p50"] is not None
            assert doc_b["sessions"]["c1"]["forwarded"]["local_to_remote"] >= 41


async def test_same_worker_forwards_without_nats() -> None:
    async with nats_server() as url, relay(url) as port_a, relay(url) as port_b:
        await wait_workers(port_a, 2)
        async with station(port_a, "local", "c2") as local, \
                station(port_a, "remote", "c2") as remote:
            await local.wait_connected(scaled(10.0))
            await remote.wait_connected(scaled(10.0))
            await local.send(PlatformState(seq=1, ts_us=now_us()))
            got = await recv_type(remote, "platform_state")
            stages = [h.stage for h in got.hops if h.clock == "relay"]  # type: ignore[attr-defined]
            assert stages == ["relay_in", "relay_out"]
            doc = await status(port_b)
            counters = doc["cluster"]["workers"]
            assert all(w["counters"].get("nats_sent", 0) == 0 for w in counters.values())


async def test_role_held_on_another_worker_is_refused() -> None:
    async with nats_server() as url, relay(url) as port_a, relay(url) as port_b:
        await wait_workers(port_a, 2)
        await wait_workers(port_b, 2)
        async with station(port_a, "local", "c3") as first:
            await first.wait_connected(scaled(10.0))
            async with asyncio.timeout(scaled(5.0)):
                while "c3" not in str((await status(port_b))["cluster"]["workers"]):
                    await asyncio.sleep(0.05)
            async with station(port_b, "local", "c3") as second:
                # refused (the other may leave, so the link keeps retrying, never joining)
                async with asyncio.timeout(scaled(10.0)):
                    while second.counters.role_taken_refusals < 2:
                        await asyncio.sleep(0.05)
                assert not second.is_connected and second.final_error is None
                assert first.is_connected


async def paired_pair(port: int, local: StationLink, remote: StationLink, session: str
                      ) -> tuple[Message, dict[str, Any]]:
    """Both stations connected and paired; the first state forwarded, and the status of the
    worker that holds the local station."""
    await local.wait_connected(scaled(10.0))
    await remote.wait_connected(scaled(10.0))
    await wait_paired(port, session)
    # the status answered by one worker may show the pair before the other worker's view
    # has caught up (heartbeats): a latest-wins state sent in between is dropped (no_peer,
    # by design), so send until one is forwarded (this failed once beside two CPU burners
    # with a single send)
    first = await first_forwarded(local, remote)
    doc = await status(port)
    holder = next(w for w in doc["cluster"]["workers"].values()
                  if "local" in w["sessions"].get(session, {}).get("stations", []))
    return first, holder


async def forwarded_again(local: StationLink, remote: StationLink, first: Message) -> None:
    """Send states from ``local`` until a new one (numbered past ``first``) reaches
    ``remote``: the session carries on after its worker was lost."""
    after = seq = first.seq + 1000  # type: ignore[attr-defined]
    async with asyncio.timeout(scaled(30.0)):
        while True:
            seq += 1
            with contextlib.suppress(Exception):
                await local.send(PlatformState(seq=seq, ts_us=now_us()))
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.5):
                    msg = await recv_type(remote, "platform_state")
                if msg.seq > after:  # type: ignore[attr-defined]
                    return


async def test_killed_worker_stations_reconnect_and_session_resumes() -> None:
    async with nats_server() as url, relay(url, workers=2) as port:
        doc = await wait_workers(port, 2)
        async with station(port, "local", "c4") as local, \
                station(port, "remote", "c4") as remote:
            first, holder = await paired_pair(port, local, remote, "c4")
            os.kill(holder["pid"], signal.SIGKILL)
            # the local station reconnects through the shared port to a live worker (the
            # supervisor also starts a replacement) and the session carries on
            await forwarded_again(local, remote, first)
            await remote.send(ArmState(seq=2, ts_us=now_us()))
            assert (await recv_type(local, "arm_state")).seq == 2  # type: ignore[attr-defined]
            # the dead worker leaves the cluster's status when its heartbeats expire
            async with asyncio.timeout(scaled(15.0)):
                while True:
                    doc = await status(port)
                    pids = {w["pid"] for w in doc["cluster"]["workers"].values()}
                    if holder["pid"] not in pids:
                        break
                    await asyncio.sleep(0.2)


async def test_a_worker_that_hangs_is_replaced_and_its_stations_come_back(
        tmp_path: Path) -> None:
    """A worker that stops serving without dying and cannot end itself (here: SIGSTOP, so
    the kernel still hands it new connections on the shared port) is killed by its
    supervisor once its beat has stood still for ``--hang-timeout-s`` and the margin; it is
    woken first to write its stacks; another worker takes its place, and a session whose
    stations were on it carries on."""
    log_path = tmp_path / "relay.log"
    with log_path.open("wb") as log_file, log_path.open("rb") as log_text:
        await _a_stopped_worker_is_replaced(log_file)
        text = log_text.read().decode(errors="replace")
    found = re.search(r"relay worker (\d+) made no progress for ", text)
    assert found, text[-3000:]
    victim = found.group(1)
    assert "(most recent call first)" in text, text[-3000:]  # its stacks, once woken
    assert f"relay worker {victim} killed (the stacks it wrote" in text, text[-3000:]


async def _a_stopped_worker_is_replaced(log_file: Any) -> None:
    async with nats_server() as url, relay(url, workers=2, extra=(
            "--hang-timeout-s", str(scaled(4.0))), stderr=log_file) as port:
        doc = await wait_workers(port, 2)
        before = {w["pid"] for w in doc["cluster"]["workers"].values()}
        async with station(port, "local", "c9") as local, \
                station(port, "remote", "c9") as remote:
            first, holder = await paired_pair(port, local, remote, "c9")
            victim = holder["pid"]
            os.kill(victim, signal.SIGSTOP)
            try:
                async with asyncio.timeout(scaled(30.0)):
                    while True:  # a stopped process never ends by itself
                        try:
                            os.kill(victim, 0)
                        except ProcessLookupError:
                            break  # killed and reaped by the supervisor
                        await asyncio.sleep(0.1)
            finally:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(victim, signal.SIGCONT)
            # woken to write its stacks, the victim may have sent a last heartbeat: the
            # directory keeps it until that expires
            async with asyncio.timeout(scaled(15.0)):
                while True:
                    doc = await wait_workers(port, 2)
                    after = {w["pid"] for w in doc["cluster"]["workers"].values()}
                    if victim not in after:
                        break
                    await asyncio.sleep(0.1)
            assert len(after - before) == 1, (before, after)
            # the local station, whose connection the stopped worker held, is back
            await forwarded_again(local, remote, first)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")
async def test_workers_join_over_tls_nats(lab_pki: dict[str, Path]) -> None:  # noqa: F811
    """nats-server with TLS (the lab CA's certificate for 127.0.0.1); the relays verify it
    with nats_ca_file and pair stations across workers as over plain NATS."""
    conf = lab_pki["ca.crt"].parent / "nats-tls.conf"  # (the relay starts TLS first)
    conf.write_text(f'tls {{ cert_file: "{lab_pki["relay.crt"]}", key_file: '
                    f'"{lab_pki["relay.key"]}", handshake_first: true }}\n')
    env = {"TELETOUCH_RELAY_NATS_CA_FILE": str(lab_pki["ca.crt"])}
    async with nats_server("-c", str(conf)) as url:
        url = url.replace("nats://", "tls://")
        async with relay(url, env=env) as port_a, relay(url, env=env) as port_b:
            await wait_workers(port_a, 2)
            await wait_workers(port_b, 2)
            async with station(port_a, "local", "t1") as local, \
                    station(port_b, "remote", "t1") as remote:
                await local.wait_connected(scaled(10.0))
                await remote.wait_connected(scaled(10.0))
                await wait_paired(port_a, "t1")
                await wait_paired(port_b, "t1")
                await local.send(PlatformState(seq=7, ts_us=now_us()))
                got = await recv_type(remote, "platform_state")
                assert "nats_in" in [h.stage for h in got.hops]  # type: ignore[attr-defined]
            doc = await status(port_a)
            assert doc["cluster"]["nats_url"].startswith("tls://")
            assert doc["cluster"]["nats_connected"] is True


async def test_a_tls_url_never_sends_the_password_to_a_plain_server(
        lab_pki: dict[str, Path]) -> None:  # noqa: F811
    """A NATS server (or a machine in the middle) that does not ask for TLS in its INFO: the
    relay sent its CONNECT, password included, in clear, and called itself connected; now it
    starts TLS before reading anything, and the start fails by name."""
    from relay_server.cluster import ClusterLink
    from relay_server.config import RelayConfig

    received = bytearray()

    async def plain_nats(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(b'INFO {"server_id":"x","version":"2.10.0","proto":1,"host":"127.0.0.1",'
                     b'"port":4222,"max_payload":1048576,"auth_required":true}\r\n')
        await writer.drain()
        with contextlib.suppress(OSError, asyncio.IncompleteReadError):
            while chunk := await reader.read(4096):
                received.extend(chunk)
                if b"CONNECT" in received:
                    writer.write(b"PONG\r\n")
                    await writer.drain()
        writer.close()

    server = await asyncio.start_server(plain_nats, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    config = RelayConfig(nats_url=f"tls://relay:S3cretPw@127.0.0.1:{port}",
                         nats_ca_file=lab_pki["ca.crt"], nats_connect_timeout_s=scaled(3.0))
    link = ClusterLink(config, {}, Counter(), lambda: {"ws": 1, "tcp": 2}, worker_id="a")
    try:
        with pytest.raises(ConfigError, match="cannot reach the NATS server"):
            await link.start()
    finally:
        await link.close()
        server.close()
        await server.wait_closed()
    assert b"S3cretPw" not in received and b"CONNECT" not in received


async def test_observer_on_another_worker_sees_the_session() -> None:
    async with nats_server() as url, relay(url) as port_a, relay(url) as port_b:
        await wait_workers(port_a, 2)
        await wait_workers(port_b, 2)
        async with station(port_b, "observer", "o1") as observer:
            await observer.wait_connected(scaled(10.0))
            async with asyncio.timeout(scaled(10.0)):  # worker A learns of the observer
                while not any(w["sessions"].get("o1", {}).get("observers") for w in
                              (await status(port_a))["cluster"]["workers"].values()):
                    await asyncio.sleep(0.05)
            async with station(port_a, "local", "o1") as local, \
                    station(port_a, "remote", "o1") as remote:
                await local.wait_connected(scaled(10.0))
                await remote.wait_connected(scaled(10.0))
                await local.send(PlatformState(seq=3, ts_us=now_us()))
                seen = await recv_type(observer, "platform_state")
                assert seen.seq == 3  # type: ignore[attr-defined]
                assert [h.stage for h in seen.hops if h.clock == "relay"] == [  # type: ignore[attr-defined]
                    "relay_in", "nats_out", "nats_in", "relay_out"]
                # the stations, on one worker, still meet without NATS
                direct = await recv_type(remote, "platform_state")
                assert "nats_in" not in [h.stage for h in direct.hops]  # type: ignore[attr-defined]


async def test_unreachable_nats_is_a_clear_start_error() -> None:
    port = free_tcp_port()
    proc = await asyncio.create_subprocess_exec(
        *teletouch_cmd(), "relay", "--host", "127.0.0.1", "--port", str(free_tcp_port()),
        "--tcp-port", str(free_tcp_port()), "--allow-any-token", "--workers", "1", "--nats",
        f"nats://127.0.0.1:{port}", "--nats-connect-timeout-s", "1.5",
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
    _, err = await asyncio.wait_for(proc.communicate(), scaled(60.0))
    assert proc.returncode != 0
    # with the connection's own error (nothing listens on the port), not the deadline's
    assert (f"cannot reach the NATS server nats://127.0.0.1:{port} within 1.5 s "
            f"(nats_connect_timeout_s): [Errno {errno.ECONNREFUSED}]") in err.decode(), \
        err.decode()


class _Ledger:
    def __init__(self) -> None:
        self.legs: list[int] = []

    def record(self, _: object, t_out: int, t_in: int) -> None:
        self.legs.append(t_in - t_out)


class _Direction:
    def __init__(self) -> None:
        self.nats = _Ledger()
        self.uplink: dict[str, Any] = {}


class _Sink:
    """A worker's session as its cluster link sees it: the roles it holds, what it gets."""

    def __init__(self, *stations: str) -> None:
        from types import SimpleNamespace

        from shared.clocksync import ClockFilter

        self.stations = {role: SimpleNamespace(clock=ClockFilter()) for role in stations}
        self.observers: list[Any] = []
        self.directions = {"local_to_remote": _Direction(), "remote_to_local": _Direction()}
        self.delivered: list[tuple[int, int | None, tuple[tuple[str, str, int], ...]]] = []

    def deliver(self, sender_role: str, msg: Message, t_in_us: int, sent_ref_us: int | None,
                mid_hops: tuple[tuple[str, str, int], ...], to_station: bool) -> None:
        self.delivered.append((t_in_us, sent_ref_us, mid_hops))


@contextlib.asynccontextmanager
async def _two_links(url: str, sink: _Sink, offset_us: int, same_kernel: bool
                     ) -> AsyncIterator[tuple[Any, Any]]:
    """Cluster links ``a`` and ``b`` in this process over NATS at ``url``; ``b``'s clock
    ``offset_us`` ahead, on this kernel or (``same_kernel`` False) as if on another."""
    from relay_server.cluster import ClusterLink
    from relay_server.config import RelayConfig
    from shared.timebase import wall_anchor_ns

    config = RelayConfig(nats_url=url)
    a = ClusterLink(config, {}, Counter(), lambda: {"ws": 1, "tcp": 2}, worker_id="a")
    b = ClusterLink(config, {"s": sink}, Counter(),  # type: ignore[dict-item]
                    lambda: {"ws": 3, "tcp": 4}, anchor_ns=wall_anchor_ns() + offset_us * 1000,
                    worker_id="b")
    if not same_kernel:
        b.clocks.boot_id = "another-kernel"
    await a.start()
    try:
        await b.start()
        try:
            yield a, b
        finally:
            await b.close()
    finally:
        await a.close()


@pytest.mark.parametrize("same_kernel", [False, True])
async def test_a_forwarded_message_reaches_a_worker_40_ms_ahead_on_its_clock(
        same_kernel: bool) -> None:
    """Two cluster links in this process over a real NATS server, one of them on a clock
    40 ms ahead, measured on their heartbeats (as if on two hosts) or known exactly from the
    anchors once an exchange agrees with them (one kernel): a message's stamps reach the
    receiver on its own clock, its NATS leg short (not 40 ms long; above zero within the
    measure's error)."""
    theta_us = 40_000
    tolerance_us = 2_000 if not same_kernel else 2
    sink = _Sink("remote")
    async with nats_server() as url, _two_links(url, sink, theta_us, same_kernel) as (a, b):
        async with asyncio.timeout(scaled(20.0)):
            while True:
                ab, ba = a.clocks.offset_us("b"), b.clocks.offset_us("a")
                if ab is not None and ba is not None and abs(ab - theta_us) < \
                        tolerance_us and abs(ba + theta_us) < tolerance_us:
                    break
                await asyncio.sleep(0.05)
        doc = a.status()["workers"]["b"]
        assert doc["same_kernel"] is same_kernel
        if same_kernel:  # the anchors' figure, once an exchange agreed with it: exact
            assert (doc["clock_offset_us"], doc["clock_uncertainty_us"]) == (theta_us, 0)
        else:  # the truth within the bound
            assert abs(doc["clock_offset_us"] - theta_us) <= doc["clock_uncertainty_us"] + 2
        assert 0 < doc["nats_rtt_min_us"] < scaled(50_000), doc  # through NATS on this host
        with MachineStalls() as stalls:  # the one message's trip, which a stall lengthens
            t_in_a = now_us()
            assert a.forward("s", "local", PlatformState(seq=1, ts_us=t_in_a), t_in_a,
                             t_in_a - 100, need_station=True)
            async with asyncio.timeout(scaled(10.0)):
                while not sink.delivered:
                    await asyncio.sleep(0.01)
    t_in_b, sent_ref_b, mid = sink.delivered[0]
    # A's stamps on B's clock: 40 ms later, within the estimate's error
    assert abs(t_in_b - (t_in_a + theta_us)) < tolerance_us
    assert sent_ref_b is not None and abs(sent_ref_b - (t_in_a - 100 + theta_us)) < \
        tolerance_us
    (_, out_stage, t_out), (_, in_stage, t_nats_in) = mid
    assert (out_stage, in_stage) == ("nats_out", "nats_in")
    assert t_in_b <= t_out  # relay_in before nats_out, both put on B's clock
    leg = t_nats_in - t_out  # without the correction about 40 ms
    assert -tolerance_us < leg < scaled(20_000) + stalls.total_s * 1e6, (leg, stalls.stalls_s)
    assert sink.directions["local_to_remote"].nats.legs == [leg]


async def test_a_malformed_envelope_is_counted_not_delivered() -> None:
    from types import SimpleNamespace

    import msgpack

    from relay_server.cluster import ClusterLink
    from relay_server.config import RelayConfig
    from shared.protocol import encode

    sink = _Sink("remote")
    counters: Counter[str] = Counter()
    link = ClusterLink(RelayConfig(nats_url="nats://127.0.0.1:1"), {"s": sink},  # type: ignore[dict-item]
                       counters, lambda: {"ws": 1, "tcp": 2}, worker_id="b")
    data = encode(PlatformState(seq=1, ts_us=5))
    t = link._now()  # an envelope older than 0.5 s is dropped (nats_stale)
    for times in ((t, None, t + 1), ("x", None, t + 1), (t, 2**64 - 1, t + 1),
                  (t, None, True), (-5, None, t + 1)):
        t_in, sent_ref, t_out = times
        await link._on_data(SimpleNamespace(data=msgpack.packb(
            ["s", "local", t_in, sent_ref, data, True, t_out])))
    assert len(sink.delivered) == 1 and sink.delivered[0][0] == t
    assert counters["nats_bad_envelope"] == 4


def test_a_worker_silent_for_a_minute_is_forgotten_with_its_clock() -> None:
    import time

    from relay_server.cluster import ClusterLink
    from relay_server.config import RelayConfig

    link = ClusterLink(RelayConfig(nats_url="nats://127.0.0.1:1"), {}, Counter(),
                       lambda: {"ws": 1, "tcp": 2}, worker_id="a")
    for worker, age_s in (("dead", 61.0), ("quiet", 30.0)):
        hb = {"w": worker, "boot": link.clocks.boot_id, "anchor": link.clocks.anchor_ns}
        link.workers[worker] = (time.monotonic() - age_s, hb)
        link.clocks.heard(worker, hb, 0)
    assert link.clocks.known() == {"dead", "quiet"}
    link._forget_silent()
    assert set(link.workers) == {"quiet"} and link.clocks.known() == {"quiet"}


async def test_the_heartbeat_forgets_a_silent_worker() -> None:
    """A worker killed without a word is dropped, with its clock, by the next heartbeat."""
    import time

    from relay_server.cluster import ClusterLink
    from relay_server.config import RelayConfig

    async with nats_server() as url:
        link = ClusterLink(RelayConfig(nats_url=url), {}, Counter(),
                           lambda: {"ws": 1, "tcp": 2}, worker_id="a")
        await link.start()
        try:
            hb = {"w": "dead", "boot": link.clocks.boot_id, "anchor": link.clocks.anchor_ns}
            link.workers["dead"] = (time.monotonic() - 61.0, hb)
            link.clocks.heard("dead", hb, 0)
            link.changed()
            async with asyncio.timeout(scaled(10.0)):
                while "dead" in link.workers or "dead" in link.clocks.known():
                    await asyncio.sleep(0.01)
        finally:
            await link.close()


async def test_the_supervisor_alone_tells_systemd() -> None:
    """Under systemd (``Type=notify``, ``WatchdogSec=``) ``--workers N`` is one service: its
    supervisor says it is ready, pings the watchdog from its loop and says it stops; the
    workers it spawns do not speak (systemd would refuse them: ``NotifyAccess=main``)."""
    notify = NotifySocket()
    try:
        async with nats_server() as url, relay(url, workers=2,
                                               env=notify.env(200_000)) as port:
            doc = await wait_workers(port, 2)
            workers = {w["pid"] for w in doc["cluster"]["workers"].values()}
            await notify.wait_for(
                lambda got: sum(text == "WATCHDOG=1" for _, text in got) >= 2, scaled(10.0))
        await notify.wait_for(lambda got: bool(got) and got[-1][1] == "STOPPING=1",
                              scaled(10.0))
        senders = {pid for pid, _ in notify.messages}
        assert len(senders) == 1 and not senders & workers, (senders, workers)
        # ready once both workers serve (pings from the start: a slow start is no hang)
        said = [text for text in notify.texts() if text != "WATCHDOG=1"]
        assert len(said) == 2 and said[-1] == "STOPPING=1", said
        assert said[0].startswith(f"READY=1\nSTATUS=relay supervisor: 2 workers on ports "
                                  f"{port}/"), said
    finally:
        notify.close()
