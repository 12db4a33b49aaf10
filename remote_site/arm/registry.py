"""Arm backends by name: ``name -> "module:Class"``, imported only when asked for."""

from __future__ import annotations

import importlib
from typing import Any

from remote_site.arm.base import Arm
from shared.errors import ConfigError, DeviceInitError

__all__ = ["ARM_BACKENDS", "arm_class", "open_arm"]

#: backend name -> "module:Class"
ARM_BACKENDS: dict[str, str] = {
    "sim": "remote_site.arm.sim:SimArm",
    "franka": "remote_site.arm.franka:FrankaArm",
}


def arm_class(name: str) -> type[Arm]:
    """Resolve a backend name (or a ``"module:Class"`` string) to its class.

    Raises:
        ConfigError: unknown name, or the path does not name an :class:`Arm` subclass.
        DeviceInitError: the backend's module cannot be imported (missing extra).
    """
    path = ARM_BACKENDS.get(name, name)
    if ":" not in path:
        raise ConfigError(f"unknown arm backend {name!r}; known: {sorted(ARM_BACKENDS)}")
    module_name, _, class_name = path.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise DeviceInitError(f"arm backend {name!r}: cannot import {module_name}: {err}") from err
    cls = getattr(module, class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, Arm)):
        raise ConfigError(f"arm backend {name!r}: {path} is not an Arm subclass")
    return cls


def open_arm(name: str, **kwargs: Any) -> Arm:
    """Instantiate a backend by name (not yet connected); ``kwargs`` go to its constructor."""
    return arm_class(name)(**kwargs)
