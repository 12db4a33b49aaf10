"""Configuration resolution refuses what it used to ignore or crash on (the config audit).

A misspelt table header or environment variable stops the command, naming it (before, the
setting under it silently kept its default: ``[arm.saftey] force_limit_n = 2.0`` left the arm's
force limit at 10 N); a file that cannot be read ends in a ConfigError naming it, not a
traceback; a secret given with the wrong type is never echoed in the error.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import pytest

from local_site.agent.config import LocalAgentConfig
from relay_server.config import RelayConfig
from remote_site.agent.config import RemoteAgentConfig
from remote_site.arm.safety import SafetyConfig
from shared.config import resolve_config
from shared.errors import ConfigError
from shared.link_settings import StationLinkConfig

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy" / "config"


def write(tmp_path: Path, text: str, name: str = "c.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# ------------------------------------------------------------------ tables of the file


@pytest.mark.parametrize(("text", "cls", "section", "said"), [
    ("[arm.saftey]\nforce_limit_n = 2.0\n", SafetyConfig, "arm.safety",
     r"unknown table \[arm\.saftey\] in .*c\.toml \(did you mean safety\?\): the tables "
     r"under \[arm\] are safety"),
    ('[remote.links]\nurl = "wss://relay.example.org/"\n', StationLinkConfig, "remote.link",
     r"unknown table \[remote\.links\] .*\(did you mean link\?\)"),
    ('[local.lnik]\ntoken = "T"\n', StationLinkConfig, "local.link",
     r"unknown table \[local\.lnik\]"),
    # a table of no command at all, whatever the command resolving the file
    ("[relya]\nport = 1\n", RelayConfig, "relay", r"unknown table \[relya\] .*\(did you "
                                                  r"mean relay\?\): the tables at the top "
                                                  r"level are "),
    ("[workspaces]\nscale_xy = 2.0\n", StationLinkConfig, "local.link",
     r"unknown table \[workspaces\]"),
    # a key where only tables go
    ('[local]\nlink_url = "ws://relay.example:8765/"\n[local.link]\nsession = "lab1"\n',
     StationLinkConfig, "local.link", r"setting 'local\.link_url' in .* is in no table"),
    ("port = 8765\n[relay]\nhost = \"0.0.0.0\"\n", RelayConfig, "relay",
     r"setting 'port' in .* is in no table"),
    ('local = "x"\n', StationLinkConfig, "local.link",
     r"^local in .* must be a table \(\[local\.<name>\]\), got str"),
    ('[remote]\nlink = 3\n', StationLinkConfig, "remote.link",
     r"^\[remote\.link\] in .* must be a table, got int"),
])
def test_a_table_no_command_reads_is_refused_by_name(tmp_path: Path, text: str, cls: type,
                                                     section: str, said: str) -> None:
    with pytest.raises(ConfigError, match=said):
        resolve_config(cls, section, toml_path=write(tmp_path, text), environ={})


def test_the_misspelt_safety_table_no_longer_leaves_the_default_force_limit(
        tmp_path: Path) -> None:
    """The audit's case: the file's 2 N limit was silently replaced by the default 10 N."""
    path = write(tmp_path, "[arm.safety]\nforce_limit_n = 2.0\n")
    assert resolve_config(SafetyConfig, "arm.safety", toml_path=path,
                          environ={}).force_limit_n == 2.0
    path = write(tmp_path, "[arm.saftey]\nforce_limit_n = 2.0\n")
    with pytest.raises(ConfigError, match=r"arm\.saftey"):
        resolve_config(SafetyConfig, "arm.safety", toml_path=path, environ={})


def test_one_file_may_hold_the_tables_of_every_command(tmp_path: Path) -> None:
    """The relay's, both stations' and the link emulator's tables in one file: every
    command takes its own and leaves the others' alone."""
    text = "\n".join((DEPLOY / name).read_text()
                     for name in ("relay.toml", "local.toml", "remote.toml", "link.toml"))
    text += "\n[check]\nconnect_timeout_s = 3.0\n[stiffness]\n[relay.tokens]\nlab1 = \"T\"\n"
    path = write(tmp_path, text)
    for cls, section in ((RelayConfig, "relay"), (StationLinkConfig, "local.link"),
                         (StationLinkConfig, "remote.link"), (LocalAgentConfig, "local.agent"),
                         (RemoteAgentConfig, "remote.agent"), (SafetyConfig, "arm.safety")):
        resolve_config(cls, section, toml_path=path, environ={})


def test_the_section_resolved_is_known_even_if_no_command_has_it(tmp_path: Path) -> None:
    @dataclass(frozen=True)
    class Display:
        port: int = 1

    path = write(tmp_path, "[local.display]\nport = 9\n[local.link]\n")
    assert resolve_config(Display, "local.display", toml_path=path, environ={}).port == 9


def test_every_section_resolved_in_the_code_is_a_known_one() -> None:
    """KNOWN_SECTIONS is what a file is checked against: a command whose table is missing
    there would have its own table refused."""
    from shared.config import KNOWN_SECTIONS

    call = re.compile(r"resolve_config\(\s*\w+,\s*f?\"([a-z_.{}]+)\"")
    found: set[str] = set()
    for folder in ("shared", "relay_server", "local_site", "remote_site", "lab"):
        for path in (ROOT / folder).rglob("*.py"):
            found.update(call.findall(path.read_text(encoding="utf-8")))
    found = {s for s in found if "{" not in s}
    assert {"relay", "local.agent", "local.link", "remote.link", "arm.safety"} <= found
    assert found <= KNOWN_SECTIONS, found - KNOWN_SECTIONS


# ------------------------------------------------------------------ environment variables


@pytest.mark.parametrize(("variable", "said"), [
    ("TELETOUCH_LOCAL_LINK_RECONNECT_MAX",
     r"unknown environment variable\(s\) for \[local\.link\]: "
     r"TELETOUCH_LOCAL_LINK_RECONNECT_MAX \(did you mean "
     r"TELETOUCH_LOCAL_LINK_RECONNECT_MAX_S\?\)"),
    ("TELETOUCH_LOCAL_LINK_TOKN", r"TELETOUCH_LOCAL_LINK_TOKN \(did you mean "
                                  r"TELETOUCH_LOCAL_LINK_TOKEN\?\)"),
    # a misspelt section of the group
    ("TELETOUCH_LOCAL_LNIK_TOKEN", r"TELETOUCH_LOCAL_LNIK_TOKEN \(the variables of this "
                                   r"group start with TELETOUCH_LOCAL_AGENT_, "),
])
def test_a_misspelt_variable_of_the_section_is_refused_by_name(variable: str, said: str) -> None:
    with pytest.raises(ConfigError, match=said) as refused:
        resolve_config(StationLinkConfig, "local.link", environ={variable: "secret-value-5"})
    assert "secret-value-5" not in str(refused.value)


def test_misspelt_relay_and_safety_variables_are_refused() -> None:
    with pytest.raises(ConfigError, match="TELETOUCH_RELAY_SECRTE"):
        resolve_config(RelayConfig, "relay", environ={"TELETOUCH_RELAY_SECRTE": "x" * 40})
    with pytest.raises(ConfigError, match="TELETOUCH_ARM_SAFETY_FORCE_LIMIT"):
        resolve_config(SafetyConfig, "arm.safety",
                       environ={"TELETOUCH_ARM_SAFETY_FORCE_LIMIT": "2"})


def test_variables_of_other_sections_commands_and_tools_are_left_alone() -> None:
    env = {"TELETOUCH_TEST_TIMEOUT_SCALE": "3", "TELETOUCH_CONFIG": "",
           "TELETOUCH_NATS_PASSWORD": "pw", "TELETOUCH_FAULT_PROBE": "probe.txt",
           "TELETOUCH_FAULT_CLOCK": "clock.txt", "TELETOUCH_TEST_ARTIFACTS": "artifacts",
           "TELETOUCH_CHROMIUM": "chromium", "TELETOUCH_HW_PLATFORM": "/dev/ttyUSB0",
           "TELETOUCH_RELAY_SECRET": "k" * 32, "TELETOUCH_RELAY_NATS_URL": "nats://n:4222",
           "TELETOUCH_LOCAL_LINK_TOKEN": "T", "TELETOUCH_LOCAL_AGENT_DISPLAY": "sim",
           "TELETOUCH_LOCAL_RENDER_HEIGHT_GAIN": "1.0", "TELETOUCH_REMOTE_LINK_TOKEN": "T",
           "TELETOUCH_REMOTE_AGENT_FRAME_RATE_HZ": "60", "TELETOUCH_ARM_SAFETY_FORCE_LIMIT_N": "5",
           "TELETOUCH_WORKSPACE_SCALE_XY": "1.0", "TELETOUCH_LINK_SEED": "1",
           "TELETOUCH_CHECK_READ_TIMEOUT_S": "1"}
    assert resolve_config(StationLinkConfig, "local.link", environ=env).token == "T"
    assert resolve_config(StationLinkConfig, "remote.link", environ=env).token == "T"
    assert resolve_config(LocalAgentConfig, "local.agent", environ=env).display == "sim"
    assert resolve_config(RemoteAgentConfig, "remote.agent", environ=env).frame_rate_hz == 60
    assert resolve_config(SafetyConfig, "arm.safety", environ=env).force_limit_n == 5.0
    assert resolve_config(RelayConfig, "relay", environ=env).secret == "k" * 32


# ------------------------------------------------------------------ files that cannot be read


def test_a_directory_as_the_file_is_refused_by_name(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=f"config file {re.escape(str(tmp_path))} is a "
                                          "directory"):
        resolve_config(RelayConfig, "relay", toml_path=tmp_path, environ={})


def test_a_file_that_is_not_utf8_is_refused_by_name(tmp_path: Path) -> None:
    path = tmp_path / "latin1.toml"
    path.write_bytes('[relay]\nhost = "caf\xe9"\n'.encode("latin-1"))
    with pytest.raises(ConfigError, match=r"latin1\.toml is not UTF-8 text"):
        resolve_config(RelayConfig, "relay", toml_path=path, environ={})


def test_an_unreadable_file_is_refused_by_name(tmp_path: Path) -> None:
    path = write(tmp_path, "[relay]\n")
    path.chmod(0)
    try:
        if path.read_bytes() is not None:  # root reads it anyway
            pytest.skip("running as root: every file is readable")
    except PermissionError:
        pass
    try:
        with pytest.raises(ConfigError, match=r"cannot read config file .*c\.toml"):
            resolve_config(RelayConfig, "relay", toml_path=path, environ={})
    finally:
        path.chmod(0o600)


@pytest.mark.parametrize("digits", [400, 5000])
def test_an_integer_too_large_for_a_number_is_refused_by_name(tmp_path: Path,
                                                              digits: int) -> None:
    """1e400 as a TOML integer raised OverflowError from float(); 5,000 digits a ValueError
    from the TOML reader (Python's limit on integer text)."""
    path = write(tmp_path, "[local.link]\nconnect_timeout_s = 1" + "0" * digits + "\n")
    with pytest.raises(ConfigError, match=r"connect_timeout_s|too long") as refused:
        resolve_config(StationLinkConfig, "local.link", toml_path=path, environ={})
    assert "c.toml" in str(refused.value)
    assert len(str(refused.value)) < 400


# ------------------------------------------------------------------ secrets never echoed


@pytest.mark.parametrize(("cls", "section", "text", "needle"), [
    (StationLinkConfig, "local.link", "[local.link]\ntoken = 31415926535\n", "31415926535"),
    (RelayConfig, "relay", "[relay]\nsecret = 27182818284\n", "27182818284"),
    (RelayConfig, "relay", '[relay]\nstatus_token = ["SUPERSECRET"]\n', "SUPERSECRET"),
    (RelayConfig, "relay", '[relay]\ntokens = ["lab1", "SUPERSECRET"]\n', "SUPERSECRET"),
    # a URL may carry the NATS password (it was echoed: "cannot use ['tls://...']")
    (RelayConfig, "relay", '[relay]\nnats_url = ["tls://relay:SECRETPW@nats:4222"]\n',
     "SECRETPW"),
    (StationLinkConfig, "local.link", '[local.link]\nurl = ["ws://u:SECRETPW@relay/"]\n',
     "SECRETPW"),
])
def test_a_secret_of_the_wrong_type_is_not_shown(tmp_path: Path, cls: type, section: str,
                                                 text: str, needle: str) -> None:
    with pytest.raises(ConfigError, match="not shown: a secret") as refused:
        resolve_config(cls, section, toml_path=write(tmp_path, text), environ={})
    assert needle not in str(refused.value)


def test_a_token_table_given_as_text_is_not_shown() -> None:
    with pytest.raises(ConfigError, match=r"relay\.tokens .*expected a table") as refused:
        resolve_config(RelayConfig, "relay",
                       environ={"TELETOUCH_RELAY_TOKENS": "lab1=SUPERSECRETTOKEN"})
    assert "SUPERSECRETTOKEN" not in str(refused.value)


def test_other_settings_still_show_the_value() -> None:
    with pytest.raises(ConfigError, match=r"expected an integer, got 'eighty'"):
        resolve_config(RelayConfig, "relay", environ={"TELETOUCH_RELAY_PORT": "eighty"})
