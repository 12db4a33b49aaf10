"""Device registry of the local station: a name or a URL -> a platform or display backend.

Like python-can's interface table, each kind maps names to ``"module:Class"`` strings and
imports the backend only when it is opened, so ``import local_site.devices`` stays cheap and a
missing optional dependency only hurts the backend that needs it. The tables are registered
with the one loader, :func:`shared.devices.registry.load_backend` (kinds ``platform`` and
``display``), which also finds backends a lab installs as entry points in the groups
``teletouch.platform`` / ``teletouch.display``; such a name, or a ``"module:Class"`` path,
is a spec too.

Platform specs (:func:`open_platform`):
    ``sim``                      simulated encoder board on a pty, scripted raster operator
    ``sim-process``              the same, the board in a process of its own (as a real board)
    an entry-point name, ``package.module:Class``   that backend, no arguments
    ``serial:<url>``             explicit serial backend
    anything else                a pyserial device or URL: ``/dev/ttyUSB0``, ``COM3``,
                                 ``socket://host:port``, ``rfc2217://...``, ``loop://``

Display specs (:func:`open_display`):
    ``sim``                      emulated drive board on a fresh virtual CAN FD channel
    ``sim-serial``               emulated drive board on a pty, serial framing
    an entry-point name, ``package.module:Class``   that backend, no arguments
    ``can://<interface>/<channel>``  any python-can interface, e.g. ``can://socketcan/can0``,
                                 ``can://virtual/bench``, ``can://pcan/PCAN_USBBUS1``
    ``socketcan:can0``           shorthand ``<interface>:<channel>`` for a python-can interface
    ``serial:<url>``, ``/dev/...``, ``COM3``, ``socket://...``, ``rfc2217://...``
                                 serial link (COBS framing)
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from shared.devices.registry import (
    is_backend_name,
    is_class_path,
    load_backend,
    register_kind,
)
from shared.errors import ConfigError

if TYPE_CHECKING:
    from local_site.display.base import ArrayTacDisplay
    from local_site.platform.base import XYZPlatform

__all__ = ["DISPLAY_BACKENDS", "PLATFORM_BACKENDS", "open_display", "open_platform",
           "parse_display_spec", "parse_platform_spec"]

#: platform backend name -> "module:Class"
PLATFORM_BACKENDS: dict[str, str] = {
    "sim": "local_site.platform.sim:SimulatedPlatform",
    "sim-process": "local_site.platform.sim_process:ProcessSimulatedPlatform",
    "serial": "local_site.platform.serial_board:SerialEncoderPlatform",
}

#: display backend name -> "module:Class"
DISPLAY_BACKENDS: dict[str, str] = {
    "sim": "local_site.display.sim:SimCanArrayTacDisplay",
    "sim-serial": "local_site.display.sim:SimSerialArrayTacDisplay",
    "can": "local_site.display.can_link:CanArrayTacDisplay",
    "serial": "local_site.display.serial_link:SerialArrayTacDisplay",
}

_SERIAL_SCHEMES = ("socket://", "rfc2217://", "loop://", "spy://", "alt://", "hwgrep://")
_CAN_INTERFACES = ("socketcan", "virtual", "pcan", "kvaser", "vector", "ixxat", "slcan",
                   "gs_usb", "canalystii", "nican", "neovi", "etas", "udp_multicast")


register_kind("platform", "local_site.platform.base:XYZPlatform", PLATFORM_BACKENDS)
register_kind("display", "local_site.display.base:ArrayTacDisplay", DISPLAY_BACKENDS)

def _is_serial_url(spec: str) -> bool:
    return (spec.startswith(_SERIAL_SCHEMES) or spec.startswith("/dev/")
            or spec.upper().startswith("COM"))


def parse_platform_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """Backend name and constructor arguments for a platform spec (see module docstring).

    Raises:
        ConfigError: empty spec.
    """
    spec = spec.strip()
    if not spec:
        raise ConfigError("empty platform spec; use 'sim' or a serial device/URL")
    if spec.startswith("serial:"):
        return "serial", {"url": spec[len("serial:"):]}
    if spec != "serial" and (is_backend_name("platform", spec) or is_class_path(spec)):
        return spec, {}
    return "serial", {"url": spec}


def parse_display_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """Backend name and constructor arguments for a display spec (see module docstring).

    Raises:
        ConfigError: a spec that names no backend.
    """
    spec = spec.strip()
    if spec not in ("can", "serial") and is_backend_name("display", spec):
        return spec, {}
    if spec.startswith("can://"):
        interface, _, channel = spec[len("can://"):].partition("/")
        if not interface or not channel:
            raise ConfigError(f"CAN spec {spec!r} must be can://<interface>/<channel>")
        return "can", {"interface": interface, "channel": channel}
    if spec.startswith("serial:"):
        return "serial", {"url": spec[len("serial:"):]}
    if _is_serial_url(spec):
        return "serial", {"url": spec}
    interface, sep, channel = spec.partition(":")
    if sep and interface in _CAN_INTERFACES and channel:
        return "can", {"interface": interface, "channel": channel}
    if is_class_path(spec):
        return spec, {}
    raise ConfigError(f"display spec {spec!r} names no backend: use sim, sim-serial, "
                      f"can://<interface>/<channel>, <interface>:<channel>, or a serial "
                      f"device/URL")


def open_platform(spec: str, *, connect: bool = True, **options: Any) -> XYZPlatform:
    """Build (and by default connect) the XYZ platform named by ``spec``.

    Args:
        spec: ``sim`` or a serial device/URL (see module docstring).
        connect: call ``connect()`` before returning.
        **options: backend keyword arguments (``geometry``, ``motion``, ``baudrate``, ...).

    Raises:
        ConfigError: bad spec or options.
        DeviceInitError: the backend cannot be imported or the device cannot be opened.
    """
    name, args = parse_platform_spec(spec)
    cls = load_backend("platform", name)
    try:
        platform: XYZPlatform = cls(**args, **options)
    except TypeError as err:
        raise ConfigError(f"platform backend {name!r}: bad options {sorted(options)}: "
                          f"{err}") from err
    if connect:
        platform.connect()
    return platform


def open_display(spec: str, *, connect: bool = True, **options: Any) -> ArrayTacDisplay:
    """Build (and by default connect) the ArrayTac display named by ``spec``.

    Args:
        spec: ``sim``, ``sim-serial``, a CAN spec or a serial device/URL (see module
            docstring).
        connect: call ``connect()`` before returning.
        **options: backend keyword arguments (``keepalive_interval_s``, ``watchdog_ms``,
            ``watchdog_mode``, ``plant_options``, ...).

    Raises:
        ConfigError: bad spec or options.
        DeviceInitError: the backend cannot be imported, or the device cannot be opened or
            stays silent.
    """
    name, args = parse_display_spec(spec)
    cls = load_backend("display", name)
    try:
        display: ArrayTacDisplay = cls(**args, **options)
    except TypeError as err:
        raise ConfigError(f"display backend {name!r}: bad options {sorted(options)}: "
                          f"{err}") from err
    if connect:
        display.connect()
    return display
