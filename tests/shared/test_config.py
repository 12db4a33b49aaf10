"""Configuration precedence and type checking."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from shared.config import resolve_config
from shared.errors import ConfigError


@dataclass(frozen=True)
class Demo:
    host: str = "127.0.0.1"
    port: int = 8765
    rate_hz: float = 500.0
    verbose: bool = False
    origin_mm: tuple[float, float] = (0.0, 0.0)
    token: str | None = None


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "c.toml"
    p.write_text(text)
    return p


def test_defaults() -> None:
    assert resolve_config(Demo, "demo", environ={}) == Demo()


def test_precedence_explicit_env_file_default(tmp_path: Path) -> None:
    path = write(tmp_path, '[demo]\nport = 1\nhost = "file"\nrate_hz = 100\n')
    env = {"TELETOUCH_DEMO_PORT": "2", "TELETOUCH_DEMO_HOST": "env"}
    cfg = resolve_config(Demo, "demo", explicit={"port": 3, "host": None}, toml_path=path,
                         environ=env)
    assert (cfg.port, cfg.host, cfg.rate_hz, cfg.verbose) == (3, "env", 100.0, False)


def test_config_path_from_environment(tmp_path: Path) -> None:
    path = write(tmp_path, "[demo]\nverbose = true\n")
    assert resolve_config(Demo, "demo", environ={"TELETOUCH_CONFIG": str(path)}).verbose


def test_env_coercion() -> None:
    env = {"TELETOUCH_DEMO_VERBOSE": "yes", "TELETOUCH_DEMO_ORIGIN_MM": "1.5, -2",
           "TELETOUCH_DEMO_TOKEN": "none"}
    cfg = resolve_config(Demo, "demo", environ=env)
    assert cfg.verbose is True and cfg.origin_mm == (1.5, -2.0) and cfg.token is None


def test_dotted_section(tmp_path: Path) -> None:
    path = write(tmp_path, "[local.display]\nport = 9\n")
    assert resolve_config(Demo, "local.display", toml_path=path, environ={}).port == 9


@pytest.mark.parametrize("env, match", [
    ({"TELETOUCH_DEMO_PORT": "eighty"}, "integer"),
    ({"TELETOUCH_DEMO_RATE_HZ": "nan"}, "finite"),
    ({"TELETOUCH_DEMO_VERBOSE": "maybe"}, "true/false"),
    ({"TELETOUCH_DEMO_ORIGIN_MM": "1,2,3"}, "2 values"),
])
def test_bad_values_name_the_setting_and_source(env, match) -> None:
    with pytest.raises(ConfigError, match=match) as info:
        resolve_config(Demo, "demo", environ=env)
    assert "demo." in str(info.value) and "TELETOUCH_DEMO_" in str(info.value)


@pytest.mark.parametrize("line, match", [
    ('verbose = "yes"', "true/false"),
    ('port = "8080"', "integer"),
    ("port = 80.5", "integer"),
    ("port = 80.0", "integer"),
    ('rate_hz = "500"', "number"),
    ("rate_hz = true", "number"),
    ('origin_mm = "1, 2"', "list"),
    ("host = 1", "string"),
    ('token = "none"', None),  # a string setting takes the word as it is
])
def test_a_file_value_must_have_the_setting_type(tmp_path: Path, line: str,
                                                 match: str | None) -> None:
    """TOML values carry their types: one of the wrong type is refused, never parsed as
    the environment's text is (``"yes"`` is not a boolean in a file)."""
    path = write(tmp_path, f"[demo]\n{line}\n")
    if match is None:
        assert resolve_config(Demo, "demo", toml_path=path, environ={}).token == "none"
        return
    with pytest.raises(ConfigError, match=match) as info:
        resolve_config(Demo, "demo", toml_path=path, environ={})
    assert "demo." in str(info.value) and "c.toml" in str(info.value)


def test_file_numbers_and_lists_of_the_right_type(tmp_path: Path) -> None:
    path = write(tmp_path, "[demo]\nrate_hz = 100\norigin_mm = [1, -2.5]\nport = 9\n")
    cfg = resolve_config(Demo, "demo", toml_path=path, environ={})
    assert (cfg.rate_hz, cfg.origin_mm, cfg.port) == (100.0, (1.0, -2.5), 9)


def test_an_integer_setting_never_drops_a_fraction() -> None:
    with pytest.raises(ConfigError, match="integer"):
        resolve_config(Demo, "demo", explicit={"port": 80.5}, environ={})
    with pytest.raises(ConfigError, match="integer"):
        resolve_config(Demo, "demo", environ={"TELETOUCH_DEMO_PORT": "80.5"})


def test_unknown_key_in_file(tmp_path: Path) -> None:
    path = write(tmp_path, "[demo]\nprot = 1\n")
    with pytest.raises(ConfigError, match="prot"):
        resolve_config(Demo, "demo", toml_path=path, environ={})


def test_missing_and_invalid_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        resolve_config(Demo, "demo", toml_path=tmp_path / "nope.toml", environ={})
    with pytest.raises(ConfigError, match="TOML"):
        resolve_config(Demo, "demo", toml_path=write(tmp_path, "[demo\n"), environ={})
