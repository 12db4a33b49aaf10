"""The device layer every device kind shares: lifecycle base, reader thread, backend loader.

- :class:`~shared.devices.base.Device`: ``connect()`` / ``disconnect()`` / ``is_connected``
  / context manager, errors sorted by phase, the ``_connect`` / ``_disconnect`` hooks.
- :class:`~shared.devices.reader.ReaderThread`: a named daemon reader with clean stop/join.
- :func:`~shared.devices.registry.load_backend`: name, entry point or ``"module:Class"`` ->
  backend class, one error behaviour for every kind.
"""

from shared.devices.base import Device
from shared.devices.reader import ReaderThread
from shared.devices.registry import (
    backend_names,
    is_backend_name,
    is_class_path,
    load_backend,
    register_kind,
)

__all__ = ["Device", "ReaderThread", "backend_names", "is_backend_name", "is_class_path",
           "load_backend", "register_kind"]
