"""The relay's settings that made tokens forgeable or its loop spin are refused (the config
audit): ``secret = ""`` (a template's placeholder left empty) was accepted, and a version-2
token MAC'd with the empty key was welcomed into any session."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from relay_server.config import RelayConfig
from shared.config import resolve_config
from shared.errors import ConfigError


@pytest.mark.parametrize(("secret", "said"), [
    ("", r"^relay\.secret is empty: at least 32 characters are needed"),
    (" " * 40, r"^relay\.secret is empty"),
    ("Zq9", r"^relay\.secret is 3 characters long: at least 32"),
    ("s" * 31, r"^relay\.secret is 31 characters long"),
    ("change-me-to-64-hex-chars", r"^relay\.secret is the example file's placeholder"),
])
def test_a_secret_that_makes_tokens_forgeable_is_refused(secret: str, said: str) -> None:
    with pytest.raises(ConfigError, match=said) as refused:
        RelayConfig(secret=secret)
    if secret.strip():
        assert secret not in str(refused.value)
    if secret:  # an empty variable is an unset one (no secret), as for every optional setting
        with pytest.raises(ConfigError, match=said):
            resolve_config(RelayConfig, "relay", environ={"TELETOUCH_RELAY_SECRET": secret})


def test_an_empty_secret_in_the_file_is_refused(tmp_path: Path) -> None:
    """The audit's file: the empty secret next to an explicit token table."""
    path = tmp_path / "relay.toml"
    path.write_text('[relay]\nport = 0\nsecret = ""\n[relay.tokens]\nlab1 = "only-this"\n')
    with pytest.raises(ConfigError, match=r"^relay\.secret is empty"):
        resolve_config(RelayConfig, "relay", toml_path=path, environ={})


def test_no_secret_and_long_ones_pass() -> None:
    from relay_server.config import MIN_SECRET_CHARS

    assert MIN_SECRET_CHARS == 32
    assert RelayConfig().secret is None
    assert RelayConfig(secret="k" * 32).secret == "k" * 32
    RelayConfig(secret="0f" * 32)  # what the example's command prints


@pytest.mark.parametrize("name", ["ping_interval_s", "stats_interval_s"])
def test_a_period_that_spins_the_relay_is_refused(name: str) -> None:
    with pytest.raises(ConfigError, match=rf"^relay\.{name} must be at least 0\.01 s "
                                          r"\(got 1e-07 s\)"):
        resolve_config(RelayConfig, "relay",
                       environ={f"TELETOUCH_RELAY_{name.upper()}": "1e-7"})
    short: dict[str, Any] = {name: 0.009}
    with pytest.raises(ConfigError, match=rf"^relay\.{name} must be at least 0\.01 s"):
        RelayConfig(**short)
    RelayConfig(**{**short, name: 0.01})


@pytest.mark.parametrize("name", ["ping_interval_s", "stats_interval_s"])
def test_a_period_the_welcome_cannot_announce_is_refused(name: str) -> None:
    """7200 s passed the settings, and then the relay refused its own welcome (the protocol
    bounds the announced period at 3600 s) and closed every station with 1011 (found by
    review)."""
    long: dict[str, Any] = {name: 7200.0, "silence_timeout_s": 20_000.0}
    with pytest.raises(ConfigError, match=rf"^relay\.{name} must be at most 3600 s "
                                          r"\(got 7200 s\)"):
        RelayConfig(**long)
    RelayConfig(**{**long, name: 3600.0})
