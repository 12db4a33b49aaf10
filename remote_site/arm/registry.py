"""Arm backends by name: ``name -> "module:Class"``, imported only when asked for.

The table is registered as device kind ``arm`` with the one loader,
:func:`shared.devices.registry.load_backend`, which also finds backends installed as entry
points in the group ``teletouch.arm`` and accepts a ``"module:Class"`` path.
"""

from __future__ import annotations

from typing import Any

from remote_site.arm.base import Arm
from shared.devices.registry import load_backend, register_kind

__all__ = ["ARM_BACKENDS", "arm_class", "open_arm"]

#: backend name -> "module:Class"
ARM_BACKENDS: dict[str, str] = {
    "sim": "remote_site.arm.sim:SimArm",
    "franka": "remote_site.arm.franka:FrankaArm",
}

register_kind("arm", Arm, ARM_BACKENDS)


def arm_class(name: str) -> type[Arm]:
    """Resolve a backend name, an entry-point name or a ``"module:Class"`` string.

    Raises:
        ConfigError: unknown name, or the path does not name an :class:`Arm` subclass.
        DeviceInitError: the backend's module cannot be imported (missing extra).
    """
    cls: type[Arm] = load_backend("arm", name)
    return cls


def open_arm(name: str, **kwargs: Any) -> Arm:
    """Instantiate a backend by name (not yet connected); ``kwargs`` go to its constructor.

    Raises:
        ConfigError: unknown name or not an :class:`Arm` subclass.
        DeviceInitError: the backend's module cannot be imported.
    """
    return arm_class(name)(**kwargs)
