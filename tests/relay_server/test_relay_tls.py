"""TLS on both relay ports (issue 11 item 1): a throwaway CA and server certificate made
with the ``openssl`` command line, a relay serving wss:// and tls:// on 127.0.0.1, stations
connecting with the CA file, and a station without it refused with a clear error."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from relay_server.auth import make_token
from relay_server.config import RelayConfig
from relay_server.server import RelayServer
from shared.client import StationLink
from shared.errors import ConfigError, TlsCertificateError
from shared.link_settings import StationLinkConfig, client_tls_context
from shared.protocol import ArmCommand, PlatformState
from shared.timebase import now_us
from tests.relay_server.relay_clients import SECRET, running_relay
from tests.support import scaled

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


@pytest.fixture(scope="module")
def lab_pki(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The recipe of docs/security.md: a lab CA and a relay certificate for 127.0.0.1."""
    d = tmp_path_factory.mktemp("pki")
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256",
             "-nodes", "-keyout", "ca.key", "-out", "ca.crt", "-days", "2",
             "-subj", "/CN=Tele-Touch test CA", cwd=d)
    _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
             "-keyout", "relay.key", "-out", "relay.csr", "-subj", "/CN=relay", cwd=d)
    (d / "san.ext").write_text("subjectAltName = IP:127.0.0.1, DNS:localhost\n"
                               "extendedKeyUsage = serverAuth\n")
    _openssl("x509", "-req", "-in", "relay.csr", "-CA", "ca.crt", "-CAkey", "ca.key",
             "-CAcreateserial", "-out", "relay.crt", "-days", "2", "-extfile", "san.ext",
             cwd=d)
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256",
             "-nodes", "-keyout", "other.key", "-out", "other.crt", "-days", "2",
             "-subj", "/CN=someone else", cwd=d)
    return {name: d / f"{name}" for name in ("ca.crt", "relay.crt", "relay.key",
                                             "other.crt")}


def _link(url: str, role: str, ca_file: Path | None, **kw: object) -> StationLink:
    config = StationLinkConfig(url=url, session="tls", token=make_token(
        SECRET, "tls", role, int(now_us() / 1e6) + 600), connect_timeout_s=scaled(3.0),
        ca_file=None if ca_file is None else str(ca_file))
    return StationLink.from_config(config, role, seed=1, **kw)


@pytest.mark.parametrize("schemes", [("wss", "tls"), ("tls", "wss")])
async def test_stations_exchange_messages_over_wss_and_tls(
        lab_pki: dict[str, Path], schemes: tuple[str, str]) -> None:
    async with running_relay(tls_cert=lab_pki["relay.crt"], tls_key=lab_pki["relay.key"]
                             ) as relay:
        urls = {"wss": f"wss://127.0.0.1:{relay.ws_port}/",
                "tls": f"tls://127.0.0.1:{relay.tcp_port}"}
        local = _link(urls[schemes[0]], "local", lab_pki["ca.crt"])
        remote = _link(urls[schemes[1]], "remote", lab_pki["ca.crt"])
        async with local, remote:
            await local.wait_connected(scaled(5.0))
            await remote.wait_connected(scaled(5.0))
            await local.send(ArmCommand(seq=1, ts_us=now_us(), action="home"))
            while (msg := await remote.recv(scaled(5.0))).TYPE != "arm_command":
                pass
            assert msg.action == "home"  # type: ignore[attr-defined]
            await local.send(PlatformState(seq=2, ts_us=now_us(), position_mm=(1.0, 2.0, 3.0),
                                           velocity_mm_s=(0.0, 0.0, 0.0)))
            while (got := await remote.recv(scaled(5.0))).TYPE != "platform_state":
                pass
            assert got.position_mm == (1.0, 2.0, 3.0)  # type: ignore[attr-defined]


@pytest.mark.parametrize("scheme", ["wss", "tls"])
async def test_a_station_without_the_ca_is_refused_naming_the_certificate(
        lab_pki: dict[str, Path], scheme: str) -> None:
    async with running_relay(tls_cert=lab_pki["relay.crt"], tls_key=lab_pki["relay.key"]
                             ) as relay:
        url = (f"wss://127.0.0.1:{relay.ws_port}/" if scheme == "wss"
               else f"tls://127.0.0.1:{relay.tcp_port}")
        for ca in (None, lab_pki["other.crt"]):  # the system store; a CA that did not sign it
            link = _link(url, "local", ca)
            async with link:
                with pytest.raises(TlsCertificateError, match="certificate") as info:
                    await link.wait_connected(scaled(5.0))
            assert "verify failed" in str(info.value) or "not trusted" in str(info.value)
            assert isinstance(info.value.__cause__, Exception)
        assert relay.counters["joined"] == 0


async def test_bad_tls_settings_are_config_errors(lab_pki: dict[str, Path],
                                                  tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="together"):
        RelayConfig(tls_cert=lab_pki["relay.crt"])
    with pytest.raises(ConfigError, match="TLS certificate"):
        RelayServer(RelayConfig(secret="x" * 32, tls_cert=lab_pki["relay.crt"],
                                tls_key=lab_pki["ca.crt"]))
    missing = tmp_path / "nope.pem"
    with pytest.raises(ConfigError, match="CA file"):
        client_tls_context(str(missing))
