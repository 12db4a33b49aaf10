"""One backend loader for every device kind: a name -> a class, imported only when asked.

Each device kind declares its base class and a table of built-in backends
(``name -> "module:Class"``) with :func:`register_kind`; the station packages do so where
the tables live (``local_site.devices``, ``remote_site.arm.registry``,
``remote_site.sensor.registry``). :func:`load_backend` then resolves, in this order:

1. a built-in name from the kind's table;
2. an entry point named ``name`` in the group ``teletouch.<kind>`` (python-can's
   ``can.interface`` habit): a lab adds a backend by installing a package whose metadata
   says, for example::

       [project.entry-points."teletouch.arm"]
       ur5 = "mylab.ur5:UR5Arm"

3. a direct ``"module:Class"`` string.

One error behaviour for every kind:

* unknown kind or name                -> :class:`~shared.errors.ConfigError` listing the
  known names;
* the backend's module cannot be imported (a missing optional dependency)
                                      -> :class:`~shared.errors.DeviceInitError` naming it;
* the module lacks the class, or it is not a subclass of the kind's base
                                      -> :class:`~shared.errors.ConfigError`.
"""

from __future__ import annotations

import importlib
import logging
import re
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points

from shared.errors import ConfigError, DeviceInitError

__all__ = ["ENTRY_POINT_GROUP_PREFIX", "backend_names", "is_backend_name", "is_class_path",
           "load_backend", "load_object", "register_kind"]

log = logging.getLogger(__name__)

#: entry-point group of kind ``k`` is ``ENTRY_POINT_GROUP_PREFIX + k``
ENTRY_POINT_GROUP_PREFIX = "teletouch."

_CLASS_PATH = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_][\w.]*$")


@dataclass(frozen=True)
class _Kind:
    base: type | str
    backends: Mapping[str, str]


_KINDS: dict[str, _Kind] = {}
_KINDS_LOCK = threading.Lock()


def register_kind(kind: str, base: type | str, backends: Mapping[str, str]) -> None:
    """Declare a device kind: its base class and its built-in backends.

    Args:
        kind: the kind's name (``platform``, ``display``, ``arm``, ``sensor``); its entry
            points are looked up in the group ``teletouch.<kind>``.
        base: the class every backend must subclass, or its ``"module:Class"`` path
            (imported on the first load, so registering stays cheap).
        backends: ``name -> "module:Class"``; kept by reference, so later additions count.
    """
    with _KINDS_LOCK:
        _KINDS[kind] = _Kind(base, backends)


def is_class_path(text: str) -> bool:
    """True when ``text`` looks like ``"package.module:Class"`` (not a URL or a path)."""
    return bool(_CLASS_PATH.match(text))


def backend_names(kind: str) -> list[str]:
    """The built-in and entry-point backend names of ``kind``, sorted.

    Raises:
        ConfigError: unknown kind.
    """
    table = _kind(kind).backends
    return sorted({*table, *(ep.name for ep in _entry_points(kind))})


def is_backend_name(kind: str, name: str) -> bool:
    """True when ``name`` is a built-in or entry-point backend of ``kind``.

    Raises:
        ConfigError: unknown kind.
    """
    return name in _kind(kind).backends or _entry_point(kind, name) is not None


def load_backend(kind: str, name: str) -> type:
    """Import and return the backend class ``name`` of device kind ``kind``.

    Args:
        kind: a registered kind (see :func:`register_kind`).
        name: a built-in name, an entry-point name, or ``"module:Class"``.

    Returns:
        The backend class, a subclass of the kind's base.

    Raises:
        ConfigError: unknown kind or name, a module without that class, or a class that
            does not subclass the kind's base.
        DeviceInitError: the backend's module (or one it needs) cannot be imported.
    """
    spec = _kind(kind)
    target = spec.backends.get(name)
    if target is None:
        entry = _entry_point(kind, name)
        if entry is not None:
            target = f"{entry.module}:{entry.attr}"
        elif is_class_path(name):
            target = name
        else:
            raise ConfigError(f"unknown {kind} backend {name!r}; known: "
                              f"{backend_names(kind)} or a 'module:Class' path")
    cls = _import(kind, name, target)
    base = spec.base if isinstance(spec.base, type) else _import(kind, "base", spec.base)
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise ConfigError(f"{kind} backend {name!r}: {target} is not a {base.__name__} "
                          "subclass")
    return cls


def _kind(kind: str) -> _Kind:
    with _KINDS_LOCK:
        spec = _KINDS.get(kind)
        known = sorted(_KINDS)
    if spec is None:
        raise ConfigError(f"unknown device kind {kind!r}; known: {known}")
    return spec


def _entry_points(kind: str) -> list[EntryPoint]:
    return list(entry_points(group=ENTRY_POINT_GROUP_PREFIX + kind))


def _entry_point(kind: str, name: str) -> EntryPoint | None:
    for entry in _entry_points(kind):
        if entry.name == name:
            return entry
    return None


def _import(kind: str, name: str, target: str) -> type:
    return load_object(target, f"{kind} backend {name!r}")  # type: ignore[return-value]


def load_object(target: str, what: str = "object") -> object:
    """Import the object named by ``"module:attr"`` (``attr`` may be dotted).

    The one lazy importer of the project: device backends, and the remote station's worlds
    and default calibrations (``"module:function"``), are all found through it.

    Args:
        target: ``"module:attr"``.
        what: what is loaded, for error messages (e.g. ``"arm backend 'sim'"``).

    Raises:
        ConfigError: ``target`` is not ``"module:attr"``, or the module lacks ``attr``.
        DeviceInitError: the module (or one it needs) cannot be imported.
    """
    module_name, sep, attr_path = target.partition(":")
    if not sep or not module_name or not attr_path:
        raise ConfigError(f"{what}: {target!r} is not 'module:attr'")
    try:
        obj: object = importlib.import_module(module_name)
    except ImportError as err:
        missing = getattr(err, "name", None) or module_name
        raise DeviceInitError(f"{what} ({target}) cannot be imported: "
                              f"missing {missing!r} ({err})") from err
    for attr in attr_path.split("."):
        try:
            obj = getattr(obj, attr)
        except AttributeError as err:
            raise ConfigError(f"{what}: {target} does not exist: {err}") from err
    if log.isEnabledFor(logging.DEBUG):
        log.debug("%s loaded from %s", what, target)
    return obj
