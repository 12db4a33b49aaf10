"""A tunnel's or proxy's name for a view without token: the setting reaches the station's and
the replay's view (review: ``allowed_hosts`` had no way in, such a name always got 403)."""

from __future__ import annotations

import asyncio
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from local_site.agent import LocalAgentConfig
from shared.config import resolve_config
from shared.errors import ConfigError
from shared.view import ViewServerConfig
from tests.lab.browser_support import interrupt
from tests.recordings import write_local_recording
from tests.shared.test_view_server import _upgrade_status
from tests.support import REPO_ROOT, scaled, wait_until

CLI = [sys.executable, "-m", "lab.cli"]


def _status(port: int, host: str) -> int:
    """The status of a WebSocket upgrade of /ws sent with ``Host: host:port``."""
    return asyncio.run(_upgrade_status(port, f"Host: {host}:{port}", "Connection: Upgrade"))


def test_the_station_setting_resolves_from_toml_and_environment(tmp_path: Path) -> None:
    env = {"TELETOUCH_LOCAL_AGENT_VIEW_ALLOWED_HOSTS": "lab-pc.example, tunnel.example.org"}
    config = resolve_config(LocalAgentConfig, "local.agent", environ=env)
    assert config.view_allowed_hosts == ("lab-pc.example", "tunnel.example.org")
    path = tmp_path / "c.toml"
    path.write_text('[local.agent]\nview_allowed_hosts = ["view.lab.example"]\n')
    config = resolve_config(LocalAgentConfig, "local.agent", toml_path=path, environ={})
    assert config.view_allowed_hosts == ("view.lab.example",)
    assert LocalAgentConfig().view_allowed_hosts == ()


@pytest.mark.parametrize("name", ["https://lab.example", "lab.example:8780", "lab.example/",
                                  "", "two words", "-lead.example"])
def test_a_name_that_is_no_host_name_is_refused_by_setting(name: str) -> None:
    with pytest.raises(ConfigError, match=r"local\.agent\.view_allowed_hosts: .* is not a host"):
        LocalAgentConfig(view_allowed_hosts=(name,))
    with pytest.raises(ConfigError, match=r"view allowed_hosts: .* is not a host name"):
        ViewServerConfig(allowed_hosts=(name,))


def _url(text: str, prefix: str) -> int:
    match = re.search(rf"{prefix}: http://127\.0\.0\.1:(\d+)/", text)
    assert match, text[-2000:]
    return int(match.group(1))


def test_teletouch_local_serves_its_view_to_an_allowed_name(tmp_path: Path) -> None:
    log = tmp_path / "local.log"
    env = dict(os.environ, TELETOUCH_LOCAL_AGENT_VIEW_ALLOWED_HOSTS="lab-pc.example")
    with log.open("wb") as out:
        proc = subprocess.Popen(
            [*CLI, "local", "--scene", "hemisphere", "--platform", "sim", "--display", "sim",
             "--view", "127.0.0.1:0", "--duration", "120", "--no-status"],
            cwd=REPO_ROOT, env=env, stdout=out, stderr=subprocess.STDOUT,
            start_new_session=True)
        try:
            wait_until(lambda: "live view:" in log.read_text() or proc.poll() is not None, 60,
                       "the station's view")
            assert proc.poll() is None, log.read_text()[-2000:]
            port = _url(log.read_text(), "live view")
            assert _status(port, "lab-pc.example") == 101
            assert _status(port, "LAB-PC.example.") == 101
            assert _status(port, "other.example") == 403  # still refused: DNS rebinding
        finally:
            interrupt(proc, timeout_s=30.0)
    assert proc.returncode == 0, log.read_text()[-2000:]


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "local.mcap"
    write_local_recording(path, seconds=1.0)
    return path


def test_teletouch_replay_serves_its_view_to_an_allowed_name(recording: Path,
                                                             tmp_path: Path) -> None:
    log = tmp_path / "replay.log"
    with log.open("wb") as out:
        proc = subprocess.Popen(
            [*CLI, "replay", str(recording), "--view", "127.0.0.1:0", "--paused",
             "--display", "none", "--no-analysis", "--view-allowed-host", "labpc.test",
             "--view-allowed-host", "tunnel.example.org"],
            cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=out, start_new_session=True)
        try:
            wait_until(lambda: "replay view:" in log.read_text() or proc.poll() is not None,
                       60, "the replay's view")
            assert proc.poll() is None, log.read_text()[-2000:]
            port = _url(log.read_text(), "replay view")
            assert _status(port, "labpc.test") == 101
            assert _status(port, "tunnel.example.org") == 101
            assert _status(port, "evil.example") == 403
        finally:
            ended = interrupt(proc, timeout_s=30.0)
    assert not ended.killed and proc.returncode == 0, log.read_text()[-2000:]


def test_a_bad_allowed_host_or_one_without_view_is_refused_before_the_replay(
        recording: Path) -> None:
    for extra, said in ((["--view", "127.0.0.1:0", "--view-allowed-host", "lab:8790"],
                         "is not a host name"),
                        (["--view-allowed-host", "labpc.test"], "needs --view")):
        done = subprocess.run([*CLI, "replay", str(recording), "--display", "none", *extra],
                              cwd=REPO_ROOT, capture_output=True, text=True,
                              timeout=scaled(60))
        assert done.returncode != 0 and said in done.stderr, done.stderr[-2000:]
        assert "replayed" not in done.stdout
