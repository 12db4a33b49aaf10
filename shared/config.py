"""Configuration resolved in one place.

Precedence, highest first: explicit arguments (for example CLI flags) > environment
variables ``TELETOUCH_<SECTION>_<FIELD>`` > a TOML file (table ``[section]``) > the
dataclass defaults. Every component describes its settings as a frozen dataclass and
calls :func:`resolve_config` once; nothing else reads the environment. Environment values
are text and are parsed; TOML values carry their types and must match (:func:`_coerce`).

Example::

    @dataclass(frozen=True)
    class RelayConfig:
        host: str = "127.0.0.1"
        port: int = 8765

    cfg = resolve_config(RelayConfig, "relay", explicit={"port": args.port},
                         toml_path=args.config)
    # TELETOUCH_RELAY_HOST=0.0.0.0 overrides the default, --port overrides everything.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from shared.errors import ConfigError

__all__ = ["ENV_PREFIX", "check_count", "check_positive", "load_toml_section", "resolve_config"]

ENV_PREFIX = "TELETOUCH_"

T = TypeVar("T")


def check_positive(key: str, value: object) -> None:
    """A setting that must be a finite number > 0 (not a bool).

    Raises:
        ConfigError: anything else, naming ``key``.
    """
    if isinstance(value, bool) or not isinstance(value, int | float) \
            or not math.isfinite(value) or value <= 0:
        raise ConfigError(f"{key} must be a finite number > 0, got {value!r}")


def check_count(key: str, value: object) -> None:
    """A setting that must be an integer >= 1 (not a bool).

    Raises:
        ConfigError: anything else, naming ``key``.
    """
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"{key} must be an integer >= 1, got {value!r}")


def load_toml_section(path: str | os.PathLike[str] | None, section: str) -> dict[str, Any]:
    """Read table ``[section]`` of a TOML file (dotted sections allowed, e.g. ``local.display``).

    Args:
        path: the TOML file, or None for no file.
        section: table name.

    Returns:
        The table as a dict; empty when ``path`` is None or the table is absent.

    Raises:
        ConfigError: the file is missing or is not valid TOML.
    """
    if path is None:
        return {}
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError as err:
        raise ConfigError(f"config file not found: {path}") from err
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"config file {path} is not valid TOML: {err}") from err
    node: Any = data
    for part in section.split("."):
        if not isinstance(node, dict) or part not in node:
            return {}
        node = node[part]
    if not isinstance(node, dict):
        raise ConfigError(f"[{section}] in {path} must be a table, got {type(node).__name__}")
    return dict(node)


def _coerce(value: Any, annotation: Any, name: str, *, typed: bool = False) -> Any:
    """Convert ``value`` to the annotated type.

    Text (the environment's strings) is parsed: ``yes``/``no`` for booleans, ``1.5, -2`` for
    tuples, ``none`` for an optional setting. A ``typed`` value (from a TOML file, whose
    values carry their own types) must already have the setting's type: ``"yes"`` for a
    boolean, ``"8080"`` for an integer or ``"1, 2"`` for a list is refused, not guessed at
    (an integer counts as a number). A number with a fraction is never an integer.
    """
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        if not typed and isinstance(value, str) and value.lower() in ("", "none", "null") \
                and type(None) in args:
            return None
        last: Exception | None = None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, name, typed=typed)
            except ConfigError as err:
                last = err
        raise ConfigError(f"{name}: cannot use {value!r}") from last
    if origin in (tuple, list):
        items = value
        if isinstance(value, str) and not typed:
            items = [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(items, list | tuple):
            raise ConfigError(f"{name}: expected a list, got {value!r}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(items) != len(args):
                raise ConfigError(f"{name}: expected {len(args)} values, got {value!r}")
            return tuple(_coerce(v, t, name, typed=typed)
                         for v, t in zip(items, args, strict=True))
        inner = args[0] if args else str
        converted = [_coerce(v, inner, name, typed=typed) for v in items]
        return tuple(converted) if origin is tuple else converted
    if origin is dict or annotation is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{name}: expected a table, got {value!r}")
        return dict(value)
    if annotation is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and not typed:
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
        raise ConfigError(f"{name}: expected true/false, got {value!r}")
    if annotation is int:
        if isinstance(value, bool) or (typed and not isinstance(value, int)) \
                or (isinstance(value, float) and not value.is_integer()):
            raise ConfigError(f"{name}: expected an integer, got {value!r}")
        try:
            return int(value)
        except (TypeError, ValueError, OverflowError) as err:
            raise ConfigError(f"{name}: expected an integer, got {value!r}") from err
    if annotation is float:
        if isinstance(value, bool) or (typed and not isinstance(value, int | float)):
            raise ConfigError(f"{name}: expected a number, got {value!r}")
        try:
            out = float(value)
        except (TypeError, ValueError) as err:
            raise ConfigError(f"{name}: expected a number, got {value!r}") from err
        if out != out or out in (float("inf"), float("-inf")):
            raise ConfigError(f"{name}: must be finite, got {value!r}")
        return out
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"{name}: expected a string, got {value!r}")
        return value
    if annotation is Path:
        if typed and not isinstance(value, str):
            raise ConfigError(f"{name}: expected a path (a string), got {value!r}")
        return Path(value)
    return value


def resolve_config(
    cls: type[T],
    section: str,
    *,
    explicit: Mapping[str, Any] | None = None,
    toml_path: str | os.PathLike[str] | None = None,
    environ: Mapping[str, str] | None = None,
) -> T:
    """Build a settings dataclass from explicit values, environment, TOML file and defaults.

    Args:
        cls: a dataclass type whose fields are the settings, with defaults.
        section: the TOML table and the environment infix (``relay`` ->
            ``TELETOUCH_RELAY_PORT``; dots become underscores).
        explicit: values given directly (CLI flags); ``None`` values are ignored, so an
            argparse default of None means "not given".
        toml_path: optional TOML file; ``TELETOUCH_CONFIG`` is used when None.
        environ: the environment (``os.environ`` when None).

    Returns:
        An instance of ``cls``.

    Raises:
        ConfigError: an unknown key in the TOML table, a value of the wrong type, a
            required field with no value anywhere, or values the settings refuse (named with
            the table unless the message names the setting).
    """
    if not dataclasses.is_dataclass(cls):
        raise ConfigError(f"{cls!r} is not a dataclass")
    env = os.environ if environ is None else environ
    if toml_path is None:
        toml_path = env.get(ENV_PREFIX + "CONFIG") or None
    from_file = load_toml_section(toml_path, section)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(from_file) - set(fields))
    if unknown:
        raise ConfigError(f"unknown setting(s) in [{section}] of {toml_path}: {', '.join(unknown)}")
    prefix = ENV_PREFIX + section.replace(".", "_").upper() + "_"
    values: dict[str, Any] = {}
    for name, field in fields.items():
        if not field.init:
            continue
        raw: Any = dataclasses.MISSING
        where = ""
        typed = False  # a TOML value carries its own type; text is parsed
        if explicit is not None and explicit.get(name) is not None:
            raw, where = explicit[name], "argument"
        elif prefix + name.upper() in env:
            raw, where = env[prefix + name.upper()], f"${prefix + name.upper()}"
        elif name in from_file:
            raw, where, typed = from_file[name], f"{toml_path} [{section}]", True
        if raw is dataclasses.MISSING:
            continue
        values[name] = _coerce(raw, hints[name], f"{section}.{name} (from {where})",
                               typed=typed)
    try:
        return cls(**values)
    except TypeError as err:
        raise ConfigError(f"[{section}]: {err}") from err
    except ConfigError as err:  # named with its table, unless it names it already
        if str(err).startswith((f"{section}.", f"{section}:", f"[{section}]")):
            raise
        raise ConfigError(f"[{section}]: {err}") from err
