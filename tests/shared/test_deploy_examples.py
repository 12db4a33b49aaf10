"""The deploy/ examples stay in step with the code.

Docker and systemd cannot run here, so this is the only automated check of deploy/: every
table of the example TOML files resolves with ``shared.config.resolve_config`` into its
settings dataclass, the environment file's variables name real settings, and the units and
compose file only call subcommands that exist (or are known to be on their way).
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Any

import pytest

from lab.cli import COMMANDS
from lab.linkemu_cli import LinkSettings
from local_site.render.renderer import RendererConfig
from relay_server.config import RelayConfig
from remote_site.agent.background import BackgroundSettings
from remote_site.arm.safety import SafetyConfig
from shared.client import StationLinkConfig
from shared.config import resolve_config
from shared.workspace import WorkspaceConfig

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"

#: TOML table -> settings dataclass
SECTIONS: dict[str, type] = {
    "relay": RelayConfig,
    "link": LinkSettings,
    "local.link": StationLinkConfig,
    "remote.link": StationLinkConfig,
    "local.render": RendererConfig,
    "arm.safety": SafetyConfig,
    "workspace": WorkspaceConfig,
    "remote.background": BackgroundSettings,
}
#: subcommands the deploy files call that the station issues are still adding


def _tables(node: dict[str, Any], prefix: str = "") -> list[str]:
    """Dotted names of the settings tables in a TOML document (known sections are leaves)."""
    out = []
    for key, value in node.items():
        if not isinstance(value, dict):
            continue
        name = f"{prefix}{key}"
        if name in SECTIONS:
            out.append(name)
        else:
            out.extend(_tables(value, name + "."))
    return out


@pytest.mark.parametrize("name", ["relay.toml", "local.toml", "remote.toml", "link.toml",
                                  "relay-cluster.toml"])
def test_every_table_of_the_example_resolves(name: str) -> None:
    path = DEPLOY / "config" / name
    data = tomllib.loads(path.read_text())
    tables = _tables(data)
    assert tables, f"{name} has no settings table"
    top_level_values = [k for k, v in data.items() if not isinstance(v, dict)]
    assert not top_level_values, f"{name}: keys outside any table: {top_level_values}"
    for section in tables:
        cls = SECTIONS[section]
        config: object = resolve_config(cls, section, toml_path=path, environ={})
        assert isinstance(config, cls)
        # every key written in the file reached the dataclass (no silent defaults)
        node: Any = data
        for part in section.split("."):
            node = node[part]
        for key, value in node.items():
            got = getattr(config, key)
            expected = tuple(value) if isinstance(value, list) else value
            assert got == expected or str(got) == str(expected), (section, key)


def test_unknown_key_in_an_example_would_fail(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text((DEPLOY / "config" / "relay.toml").read_text() + "\n[workspace]\nscale = 2\n")
    from shared.errors import ConfigError

    with pytest.raises(ConfigError):
        resolve_config(WorkspaceConfig, "workspace", toml_path=bad, environ={})


def test_environment_file_names_real_settings() -> None:
    env = {}
    for line in (DEPLOY / "teletouch.env.example").read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            key, _, value = line.partition("=")
            env[key.strip()] = value.strip()
    assert set(env) == {"TELETOUCH_RELAY_SECRET", "TELETOUCH_LOCAL_LINK_TOKEN",
                        "TELETOUCH_REMOTE_LINK_TOKEN"}
    relay = resolve_config(RelayConfig, "relay", environ=env)
    assert relay.secret == env["TELETOUCH_RELAY_SECRET"]
    for role in ("local", "remote"):
        link = resolve_config(StationLinkConfig, f"{role}.link", environ=env)
        assert link.token == env[f"TELETOUCH_{role.upper()}_LINK_TOKEN"]


def test_units_and_compose_call_existing_subcommands() -> None:
    texts = [p.read_text() for p in sorted((DEPLOY / "systemd").glob("*.service"))]
    assert len(texts) == 3
    for text in texts:
        assert "Restart=on-failure" in text
        assert "EnvironmentFile=/etc/teletouch/teletouch.env" in text
        # ranked above other jobs for CPU by the slice's weight (docs/speed.md section 35)
        assert re.search(r"^\[Service\][^\[]*^Slice=teletouch\.slice$", text, re.M | re.S)
    slice_unit = (DEPLOY / "systemd" / "teletouch.slice").read_text()
    weight = re.search(r"^\[Slice\][^\[]*^CPUWeight=(\d+)$", slice_unit, re.M | re.S)
    assert weight and int(weight[1]) > 100  # above the default of the groups beside it
    calls = re.findall(r"bin/teletouch (\w+)", "\n".join(texts))
    calls += re.findall(r'"teletouch",\s*"(\w+)"', (DEPLOY / "compose.yaml").read_text())
    calls += re.findall(r'"teletouch",\s*"(\w+)"', (DEPLOY / "Dockerfile").read_text())
    cluster = (DEPLOY / "compose.cluster.yaml").read_text()
    calls += re.findall(r'"teletouch",\s*"(\w+)"', cluster)
    assert {"relay", "link", "local", "remote"} <= set(calls)
    # the cluster's relays read a config that exists, and NATS its own
    for config in re.findall(r"/etc/teletouch/([\w-]+\.toml)", cluster):
        assert (DEPLOY / "config" / config).is_file(), config
    assert (DEPLOY / "config" / "nats.conf").is_file()
    for sub in calls:
        assert sub in COMMANDS, sub
    configs = set(re.findall(r"/etc/teletouch/(\w+\.toml)", "\n".join(texts)))
    assert configs and all((DEPLOY / "config" / c).is_file() for c in configs)


def test_the_image_copies_every_installed_package() -> None:
    """``pip install .`` in the image needs every package the distribution declares (the
    console script lives in ``lab``)."""
    project = tomllib.loads((DEPLOY.parent / "pyproject.toml").read_text())
    packages = [p.rstrip("*") for p in project["tool"]["setuptools"]["packages"]["find"]["include"]]
    assert "lab" in packages
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    for package in packages:
        assert f"COPY {package} ./{package}" in dockerfile, package
