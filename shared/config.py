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
import difflib
import math
import os
import tomllib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from shared.errors import ConfigError

__all__ = ["ENV_PREFIX", "KNOWN_SECTIONS", "check_count", "check_positive", "load_toml_section",
           "resolve_config"]

ENV_PREFIX = "TELETOUCH_"

#: Every settings table of every command (``teletouch relay``, ``local``, ``remote``, ``link``,
#: ``check``). One file may hold the tables of several commands; a table or a
#: ``TELETOUCH_<SECTION>_*`` variable under none of these (nor the section being resolved) is
#: a typo, refused by name: a misspelt ``[arm.saftey]`` would otherwise leave its force limit
#: at the default without a word.
KNOWN_SECTIONS: frozenset[str] = frozenset({
    "relay",
    "local.agent", "local.link", "local.render",
    "remote.agent", "remote.link", "remote.background",
    "arm.safety", "stiffness", "workspace",
    "link", "check",
})

#: settings whose values are never shown in an error (a token given with the wrong type);
#: a URL may carry a password (``relay.nats_url``: ``tls://user:password@host``)
_SECRET_WORDS = ("token", "secret", "password", "url")

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


def _load_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The whole TOML document of ``path``.

    Raises:
        ConfigError: naming the file: missing, a directory, unreadable, not UTF-8, not TOML.
    """
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError as err:
        raise ConfigError(f"config file not found: {path}") from err
    except IsADirectoryError as err:
        raise ConfigError(f"config file {path} is a directory, not a TOML file") from err
    except UnicodeDecodeError as err:
        raise ConfigError(f"config file {path} is not UTF-8 text (byte {err.start}): "
                          "TOML files are UTF-8") from err
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"config file {path} is not valid TOML: {err}") from err
    except ValueError as err:  # an integer of more digits than Python converts
        raise ConfigError(f"config file {path} holds a number too long to read: "
                          f"{str(err).partition(':')[0]}") from err
    except OSError as err:  # permission denied, a device, an I/O error
        raise ConfigError(f"cannot read config file {path}: "
                          f"{err.strerror or type(err).__name__}") from err


def _table(data: dict[str, Any], path: str | os.PathLike[str], section: str) -> dict[str, Any]:
    """Table ``[section]`` of a loaded document; empty when absent."""
    node: Any = data
    for part in section.split("."):
        if not isinstance(node, dict) or part not in node:
            return {}
        node = node[part]
    if not isinstance(node, dict):
        raise ConfigError(f"[{section}] in {path} must be a table, got {type(node).__name__}")
    return dict(node)


def load_toml_section(path: str | os.PathLike[str] | None, section: str) -> dict[str, Any]:
    """Read table ``[section]`` of a TOML file (dotted sections allowed, e.g. ``local.display``).

    Args:
        path: the TOML file, or None for no file.
        section: table name.

    Returns:
        The table as a dict; empty when ``path`` is None or the table is absent.

    Raises:
        ConfigError: the file is missing, unreadable, not UTF-8 or not valid TOML.
    """
    if path is None:
        return {}
    return _table(_load_toml(path), path, section)


def _hint(name: str, candidates: typing.Iterable[str]) -> str:
    """`` (did you mean X?)`` for a close candidate, else empty."""
    close = difflib.get_close_matches(name, list(candidates), n=1, cutoff=0.6)
    return f" (did you mean {close[0]}?)" if close else ""


def _check_tables(data: dict[str, Any], path: str | os.PathLike[str], section: str) -> None:
    """Refuse a table (or a value outside any table) that no command reads.

    A file may hold the tables of several commands (one file for the relay and both
    stations): each table is checked against :data:`KNOWN_SECTIONS` (and ``section``) by its
    place only; the keys inside a section are checked by the command that resolves it.

    Raises:
        ConfigError: naming the file and the unknown table or key.
    """
    known = KNOWN_SECTIONS | {section}
    tree: dict[str, Any] = {}  # group -> {sub: ...}; a section (a leaf) maps to None
    for name in sorted(known, key=lambda n: n.count(".")):
        node = tree
        parts = name.split(".")
        for part in parts[:-1]:
            child = node.setdefault(part, {})
            if child is None:  # a section's own sub-table (a dict setting): its keys
                break
            node = child
        else:
            node[parts[-1]] = None

    def walk(node: dict[str, Any], known_here: dict[str, Any], prefix: str) -> None:
        for key, value in node.items():
            dotted = f"{prefix}{key}"
            if key not in known_here:
                where = f"under [{prefix[:-1]}]" if prefix else "at the top level"
                names = ", ".join(sorted(known_here))
                if isinstance(value, dict):
                    raise ConfigError(
                        f"unknown table [{dotted}] in {path}{_hint(key, known_here)}: the "
                        f"tables {where} are {names}")
                raise ConfigError(
                    f"setting {dotted!r} in {path} is in no table{_hint(key, known_here)}: "
                    f"the tables {where} are {names}")
            sub = known_here[key]
            if sub is None:
                continue  # a section: its keys are checked where it is resolved
            if not isinstance(value, dict):
                raise ConfigError(f"{dotted} in {path} must be a table ([{dotted}.<name>]), "
                                  f"got {type(value).__name__}")
            walk(value, sub, dotted + ".")

    walk(data, tree, "")


def _env_prefix(section: str) -> str:
    return ENV_PREFIX + section.replace(".", "_").upper() + "_"


def _check_environment(env: Mapping[str, str], section: str, names: typing.Iterable[str]
                       ) -> None:
    """Refuse a ``TELETOUCH_<SECTION>_*`` variable that names no setting of ``section``.

    Variables of another known section whose prefix extends this one's are left to it; in a
    group of sections (``local.agent``, ``local.link``...), a ``TELETOUCH_LOCAL_*`` variable
    of no known section of the group is refused too. Other ``TELETOUCH_*`` variables
    (``TELETOUCH_CONFIG``, the tests' and the lab's) are not looked at. Values are never shown.

    Raises:
        ConfigError: naming the variable(s).
    """
    known = KNOWN_SECTIONS | {section}
    prefix = _env_prefix(section)
    others = [_env_prefix(s) for s in known if s != section]
    expected = {prefix + n.upper() for n in names}
    unknown: list[str] = []
    for var in env:
        if not var.startswith(prefix) or var in expected:
            continue
        if any(p.startswith(prefix) and var.startswith(p) for p in others):
            continue  # another section's (a longer prefix)
        unknown.append(var + _hint(var, expected))
    if "." in section:  # the group: TELETOUCH_LOCAL_LNIK_TOKEN
        group = _env_prefix(section.split(".")[0])
        prefixes = [_env_prefix(s) for s in known]
        for var in env:
            if var.startswith(group) and not any(var.startswith(p) for p in prefixes):
                subs = sorted(p[len(group):] for p in prefixes if p.startswith(group))
                unknown.append(f"{var} (the variables of this group start with "
                               f"{', '.join(group + s for s in subs)})")
    if unknown:
        raise ConfigError(f"unknown environment variable(s) for [{section}]: "
                          f"{', '.join(sorted(unknown))}; its settings are "
                          f"{prefix}<{'|'.join(sorted(n.upper() for n in names))}>")


def _show(value: Any, *, secret: bool) -> str:
    """``value`` for an error message: a secret's only by its type, a long one cut short."""
    if secret:
        return f"a value of type {type(value).__name__} (not shown: a secret)"
    try:
        text = repr(value)
    except ValueError:  # an integer of more digits than Python converts to text
        return f"a value of type {type(value).__name__} too long to show"
    return text if len(text) <= 80 else f"{text[:60]}... ({len(text)} characters)"


def _coerce(value: Any, annotation: Any, name: str, *, typed: bool = False,
            secret: bool = False) -> Any:
    """Convert ``value`` to the annotated type.

    Text (the environment's strings) is parsed: ``yes``/``no`` for booleans, ``1.5, -2`` for
    tuples, ``none`` for an optional setting. A ``typed`` value (from a TOML file, whose
    values carry their own types) must already have the setting's type: ``"yes"`` for a
    boolean, ``"8080"`` for an integer or ``"1, 2"`` for a list is refused, not guessed at
    (an integer counts as a number). A number with a fraction is never an integer. A
    ``secret`` value (a token, a secret, a password, a URL) is never shown in an error, only
    its type.
    """
    shown = _show(value, secret=secret)
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
                return _coerce(value, arg, name, typed=typed, secret=secret)
            except ConfigError as err:
                last = err
        raise ConfigError(f"{name}: cannot use {shown}") from last
    if origin in (tuple, list):
        items = value
        if isinstance(value, str) and not typed:
            items = [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(items, list | tuple):
            raise ConfigError(f"{name}: expected a list, got {shown}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(items) != len(args):
                raise ConfigError(f"{name}: expected {len(args)} values, got {shown}")
            return tuple(_coerce(v, t, name, typed=typed, secret=secret)
                         for v, t in zip(items, args, strict=True))
        inner = args[0] if args else str
        converted = [_coerce(v, inner, name, typed=typed, secret=secret) for v in items]
        return tuple(converted) if origin is tuple else converted
    if origin is dict or annotation is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{name}: expected a table, got {shown}")
        return dict(value)
    if annotation is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and not typed:
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
        raise ConfigError(f"{name}: expected true/false, got {shown}")
    if annotation is int:
        if isinstance(value, bool) or (typed and not isinstance(value, int)) \
                or (isinstance(value, float) and not value.is_integer()):
            raise ConfigError(f"{name}: expected an integer, got {shown}")
        try:
            return int(value)
        except (TypeError, ValueError, OverflowError) as err:
            raise ConfigError(f"{name}: expected an integer, got {shown}") from err
    if annotation is float:
        if isinstance(value, bool) or (typed and not isinstance(value, int | float)):
            raise ConfigError(f"{name}: expected a number, got {shown}")
        try:
            out = float(value)
        except OverflowError as err:  # an integer beyond a float's range (10**400 in TOML)
            raise ConfigError(f"{name}: must be finite, got {shown} (too large for a number)"
                              ) from err
        except (TypeError, ValueError) as err:
            raise ConfigError(f"{name}: expected a number, got {shown}") from err
        if out != out or out in (float("inf"), float("-inf")):
            raise ConfigError(f"{name}: must be finite, got {shown}")
        return out
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"{name}: expected a string, got {shown}")
        return value
    if annotation is Path:
        if typed and not isinstance(value, str):
            raise ConfigError(f"{name}: expected a path (a string), got {shown}")
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
        ConfigError: an unknown key in the TOML table, a table of the file or a
            ``TELETOUCH_<SECTION>_*`` variable that no command reads (a typo: see
            :data:`KNOWN_SECTIONS`), an unreadable file, a value of the wrong type, a
            required field with no value anywhere, or values the settings refuse (named with
            the table unless the message names the setting).
    """
    if not dataclasses.is_dataclass(cls):
        raise ConfigError(f"{cls!r} is not a dataclass")
    env = os.environ if environ is None else environ
    if toml_path is None:
        toml_path = env.get(ENV_PREFIX + "CONFIG") or None
    from_file: dict[str, Any] = {}
    if toml_path is not None:
        document = _load_toml(toml_path)
        _check_tables(document, toml_path, section)
        from_file = _table(document, toml_path, section)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(from_file) - set(fields))
    if unknown:
        hints_text = "".join(_hint(u, fields) for u in unknown)
        raise ConfigError(f"unknown setting(s) in [{section}] of {toml_path}: "
                          f"{', '.join(unknown)}{hints_text}")
    _check_environment(env, section, [n for n, f in fields.items() if f.init])
    prefix = _env_prefix(section)
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
                               typed=typed, secret=any(w in name for w in _SECRET_WORDS))
    try:
        return cls(**values)
    except TypeError as err:
        raise ConfigError(f"[{section}]: {err}") from err
    except ConfigError as err:  # named with its table, unless it names it already
        if str(err).startswith((f"{section}.", f"{section}:", f"[{section}]")):
            raise
        raise ConfigError(f"[{section}]: {err}") from err
