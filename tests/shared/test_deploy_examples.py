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
    from shared.errors import ConfigError

    # the placeholder is refused by name (tokens made with it would be forgeable), never shown
    with pytest.raises(ConfigError, match=r"relay\.secret is the example file's placeholder") \
            as refused:
        resolve_config(RelayConfig, "relay", environ=env)
    assert env["TELETOUCH_RELAY_SECRET"] not in str(refused.value)
    env["TELETOUCH_RELAY_SECRET"] = "0f" * 32  # what the comment's command prints
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
        # started once ready, restarted when the event loop hangs (shared/sd_notify.py)
        assert re.search(r"^Type=notify$", text, re.M) and re.search(r"^WatchdogSec=\d+$",
                                                                     text, re.M)
        if "bin/teletouch relay" not in text:  # a station: numba caches where it may write
            assert "CacheDirectory=teletouch\n" in text
            assert "Environment=NUMBA_CACHE_DIR=/var/cache/teletouch/numba\n" in text
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


def _lock_tool() -> Any:
    """``deploy/lock.py``, a script beside the lock (not a package of the project)."""
    import importlib.util
    import sys

    if "deploy_lock" not in sys.modules:
        spec = importlib.util.spec_from_file_location("deploy_lock", DEPLOY / "lock.py")
        assert spec is not None and spec.loader is not None
        sys.modules["deploy_lock"] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(sys.modules["deploy_lock"])  # dataclasses look it up there
    return sys.modules["deploy_lock"]


def test_the_lock_pins_every_dependency_within_its_range() -> None:
    """The image installs from ``deploy/requirements.lock``: every runtime dependency, the
    cluster extra and the build requirements are pinned, each to a release pyproject.toml
    allows, each with the hashes of its files."""
    lock = _lock_tool()
    pins = lock.parse_lock((DEPLOY / "requirements.lock").read_text())
    names = {r.name for r in lock.wanted()}
    assert {"numpy", "websockets", "nats-py", "setuptools"} <= names
    lock.check(pins, lock.wanted())
    # nothing stale: every pin is needed by the project or its build, or by a pin that is
    reached = {"teletouch", "build"}
    while True:
        more = {name for name, pin in pins.items() if set(pin.via) & reached} - reached
        if not more:
            break
        reached |= more
    assert set(pins) <= reached, set(pins) - reached


def test_a_lock_that_no_longer_fits_is_refused() -> None:
    lock = _lock_tool()
    good = f"numpy==2.0.1 \\\n    --hash=sha256:{'a' * 64}\n    # via\n    #   teletouch\n"
    assert lock.parse_lock(good)["numpy"].version == "2.0.1"
    two = good.replace("\n    # via", " \\\n    --hash=sha256:" + "b" * 64 + "\n    # via")
    assert lock.parse_lock(two)["numpy"].hashes == ["a" * 64, "b" * 64]
    scipy = good.replace("numpy==2.0.1", "scipy==1.0")
    for text, error in ((good.replace(" \\\n    --hash", "\n    --hash"), "line 1"),
                        ("numpy==2.0.1 \\\n", "ends in a backslash"),
                        (good + good, "pinned twice"),
                        (good.replace("a" * 64, "a" * 63), "line 2"),
                        ("numpy>=2 \\\n", "line 1"),
                        # pip would drop this hash: no backslash joins it to the pin
                        (two.replace("a" * 64 + " \\", "a" * 64), "line 3"),
                        # pip would join scipy's line to numpy's and lose scipy
                        (good.replace("a" * 64, "a" * 64 + " \\") + scipy, "line 3"),
                        ("numpy==2.0.1; python_version<'3' \\\n    --hash=sha256:" + "a" * 64,
                         "line 1"),
                        (good.replace("==", "==="), "line 1")):
        with pytest.raises(lock.LockError, match=error):
            lock.parse_lock(text)
    from packaging.requirements import Requirement

    with pytest.raises(lock.LockError, match=r"numpy<2 but the lock pins 2\.0\.1.*scipy>=1 "
                                             r"is not in the lock"):
        lock.check(lock.parse_lock(good), [Requirement("numpy<2"), Requirement("scipy>=1")])
    with pytest.raises(lock.LockError, match=r"numpy>=2 but the lock pins 2\.1rc1"):
        lock.check(lock.parse_lock(good.replace("2.0.1", "2.1rc1")), [Requirement("numpy>=2")])


def test_the_lock_reads_back_as_written() -> None:
    lock = _lock_tool()
    pins = {"a-b": lock.Pin("1.0", ["0" * 64, "f" * 64], ["build"]),
            "c": lock.Pin("2.post1", ["1" * 64], ["a-b", "teletouch"])}
    assert lock.parse_lock(lock.render(pins)) == pins


def test_the_image_installs_the_lock_with_its_hashes() -> None:
    dockerfile = (DEPLOY / "Dockerfile").read_text()
    locked = dockerfile.index("pip install --require-hashes --no-deps -r "
                              "deploy/requirements.lock")
    project = dockerfile.index("pip install --no-deps --no-build-isolation .")
    assert locked < project and "pip check" in dockerfile[project:]
    # pip check ignores extras and the build: the lock is checked against pyproject.toml too
    assert "python deploy/lock.py --check" in dockerfile[project:]
    assert "COPY deploy/lock.py" in dockerfile
    assert "COPY deploy/requirements.lock" in dockerfile[:locked]


def test_the_lock_keeps_the_files_cpython_3_11_on_linux_installs() -> None:
    lock = _lock_tool()
    names = ["x-1.0-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
             "x-1.0-cp311-cp311-manylinux_2_28_aarch64.whl",
             "x-1.0-cp38-abi3-manylinux1_x86_64.whl",
             "x-1.0-py3-none-any.whl", "x-1.0.tar.gz",
             "x-1.0-cp312-cp312-manylinux_2_17_x86_64.whl", "x-1.0-cp311-cp311-win_amd64.whl",
             "x-1.0-cp311-cp311-musllinux_1_2_x86_64.whl",
             "x-1.0-cp311-cp311-macosx_11_0_arm64.whl", "x-1.1-py3-none-any.whl", "x-1.1.tar.gz",
             "x-1.0-cp311-cp311-manylinux_2_17_x86_64.whl", "not a distribution.exe"]
    files: list[dict[str, Any]] = [{"filename": n, "hashes": {"sha256": f"{i:064x}"}}
                                   for i, n in enumerate(names)]
    files[-2]["yanked"] = "broken build"
    assert lock.select_files(files, "1.0", lock.target_tags()) == [f"{i:064x}" for i in range(5)]
    # a pure-Python wheel serves both architectures
    assert lock.select_files(files[3:4], "1.0", lock.target_tags()) == [f"{3:064x}"]
    # an architecture left to build from the source archive is refused, by name
    with pytest.raises(lock.LockError, match=r"no wheel for CPython 3\.11 on Linux aarch64$"):
        lock.select_files([files[0], files[4]], "1.0", lock.target_tags())
    with pytest.raises(lock.LockError, match="aarch64, x86_64"):
        lock.select_files(files[4:9], "1.0", lock.target_tags())


def _exec_form(line: str) -> list[str]:
    """The JSON array of a Dockerfile instruction's exec form."""
    import json

    return list(json.loads(line[line.index("["):]))


def test_every_container_has_the_health_check_of_what_it_runs() -> None:
    """The image's HEALTHCHECK asks a relay (``teletouch relay --health-check``) with the very
    arguments of the image's command, so it resolves the same configuration (port, address,
    TLS); every compose service of the image that runs a relay probes with its own command's
    arguments, and every other one disables the probe (it would ask a relay that is not
    there and call the container unhealthy)."""
    import yaml

    dockerfile = (DEPLOY / "Dockerfile").read_text()
    instructions = dockerfile.replace("\\\n", " ")
    health = _exec_form(re.search(r"^HEALTHCHECK [^\[]*CMD (\[.*\])$", instructions, re.M)[1])  # type: ignore[index]
    command = _exec_form(re.search(r"^CMD (\[.*\])$", instructions, re.M)[1])  # type: ignore[index]
    assert command[:2] == ["teletouch", "relay"] and health == [*command, "--health-check"]
    checked = 0
    for name in ("compose.yaml", "compose.cluster.yaml"):
        services = yaml.safe_load((DEPLOY / name).read_text())["services"]
        for service, spec in services.items():
            if spec.get("image") != "teletouch:latest":
                assert "healthcheck" not in spec, service  # another image, its own probe
                continue
            argv = spec["command"]
            probe = spec.get("healthcheck", {})
            if argv[:2] == ["teletouch", "relay"]:
                test = probe.get("test", ["CMD", *health])
                assert test == ["CMD", *argv, "--health-check"], (name, service)
                assert not probe.get("disable"), (name, service)
                config = argv[argv.index("--config") + 1]
                assert (DEPLOY / "config" / Path(config).name).is_file()
                checked += 1
            else:
                assert probe == {"disable": True}, (name, service)
    assert checked == 3  # the relay, and the cluster's two


def test_the_stations_import_from_a_read_only_install_with_the_units_cache() -> None:
    """Under ``ProtectSystem=strict`` (and in the image, as its unprivileged user) the install
    and the home are read-only: numba then refuses to cache a kernel and a station does not
    even import. With ``NUMBA_CACHE_DIR`` where the units and the image put it, it does.
    Checked in a mount namespace with the tree and the home bound read-only (root only)."""
    import os
    import shutil
    import subprocess
    import sys
    import tempfile

    if os.geteuid() != 0 or shutil.which("unshare") is None:
        pytest.skip("needs root and unshare(1) for a read-only bind mount")
    tree = DEPLOY.parent
    with tempfile.TemporaryDirectory() as home, tempfile.TemporaryDirectory() as cache:
        read_only = " && ".join(f"mount --bind {d} {d} && mount -o remount,bind,ro {d}"
                                for d in (tree, home))
        station = f"{sys.executable} -c 'import local_site.render.interpolation; print(1)'"

        def run(env: str) -> subprocess.CompletedProcess[str]:
            return subprocess.run(["unshare", "-m", "sh", "-c",
                                   f"{read_only} && cd / && {env} HOME={home} {station}"],
                                  capture_output=True, text=True, timeout=300,
                                  env={**os.environ, "PYTHONPATH": str(tree)})

        bare = run("")
        if bare.returncode != 0 and "mount" in bare.stderr and "permitted" in bare.stderr:
            pytest.skip(f"no mount namespace here: {bare.stderr.strip()[:200]}")
        assert bare.returncode != 0 and "no locator available" in bare.stderr, bare
        cached = run(f"NUMBA_CACHE_DIR={cache}/numba")
        assert cached.returncode == 0 and cached.stdout.strip() == "1", cached.stderr[-2000:]
