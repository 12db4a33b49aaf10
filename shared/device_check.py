"""What ``teletouch check`` reports: one result per device, one report per station.

The probes themselves live with the devices they open (``local_site.check``,
``remote_site.check``); this module holds what both share: the settings (TOML table
``[check]``, ``TELETOUCH_CHECK_<FIELD>``), the result types, and the one place a device
error becomes the one line a lab reads before a session. Errors are sorted by the device
layer's phases (:mod:`shared.devices.base`)::

    DeviceInitError                      could not open: ... check the cable/port/permissions
    DeviceInitError from an ImportError  backend not installed: ...
    DeviceTimeoutError (or an init error
      caused by one: opened, no answer)  opened but silent: ... check power, wiring, baud rate
    DeviceOperationError                 opened but failed: ...
    ConfigError / CalibrationError       bad setting: ...

Figures are plain numbers, strings and lists, so ``--json`` prints them as they are
(non-finite numbers become ``null``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from shared.config import check_positive
from shared.errors import (
    CalibrationError,
    ConfigError,
    DeviceInitError,
    DeviceOperationError,
    DeviceTimeoutError,
    TeleTouchError,
)

__all__ = ["CheckReport", "CheckSettings", "DeviceCheck", "failed_check", "failure_line"]

#: exit codes of ``teletouch check``
EXIT_OK, EXIT_DEVICE_FAILED, EXIT_USAGE = 0, 1, 2


@dataclass(frozen=True)
class CheckSettings:
    """Time bounds of the probes (TOML ``[check]``, ``TELETOUCH_CHECK_<FIELD>``).

    Attributes:
        connect_timeout_s: how long a device may take to open and send its first data.
        read_timeout_s: longest wait for one reading of an open device.
        rate_window_s: span over which rates (samples, feedback, frames) are measured.
        move_mm: with ``--move``, how far the arm is lifted (+z) and brought back.
        move_timeout_s: with ``--move``, how long each of the two motions may take.
    """

    connect_timeout_s: float = 3.0
    read_timeout_s: float = 0.5
    rate_window_s: float = 1.0
    move_mm: float = 2.0
    move_timeout_s: float = 5.0

    def __post_init__(self) -> None:
        for name in ("connect_timeout_s", "read_timeout_s", "rate_window_s", "move_mm",
                     "move_timeout_s"):
            check_positive(f"check.{name}", getattr(self, name))
        if self.move_mm > 10.0:
            raise ConfigError(f"check.move_mm must be at most 10 mm, got {self.move_mm}")


@dataclass(frozen=True)
class DeviceCheck:
    """The result of probing one device.

    Attributes:
        device: the role: ``platform``, ``display``, ``arm`` or ``sensor``.
        spec: what the device was named by (``sim``, ``/dev/ttyUSB0``, ``0``...).
        ok: the device opened and behaved.
        message: one line: what was seen, or what to fix.
        figures: measured values (rates, sizes, pose...), JSON-ready.
    """

    device: str
    spec: str
    ok: bool
    message: str
    figures: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The result as a JSON-ready dict."""
        return {"device": self.device, "spec": self.spec, "ok": self.ok,
                "message": self.message, "figures": dict(self.figures)}


@dataclass(frozen=True)
class CheckReport:
    """All devices of one station.

    Attributes:
        station: ``local`` or ``remote``.
        devices: one result per device, in probing order.
    """

    station: str
    devices: tuple[DeviceCheck, ...]

    @property
    def ok(self) -> bool:
        """True when every device passed."""
        return all(d.ok for d in self.devices)

    @property
    def exit_code(self) -> int:
        """0 when every device passed, 1 otherwise (for scripts)."""
        return EXIT_OK if self.ok else EXIT_DEVICE_FAILED

    def to_dict(self) -> dict[str, Any]:
        """The report as one JSON-ready object with one entry per device."""
        return {"station": self.station, "ok": self.ok,
                "devices": {d.device: d.to_dict() for d in self.devices}}

    def to_text(self) -> str:
        """One line per device, then its figures indented, for a terminal."""
        lines = [f"teletouch check {self.station}: {'all good' if self.ok else 'FAILED'}"]
        for d in self.devices:
            lines.append(f"  {'ok  ' if d.ok else 'FAIL'} {d.device} ({d.spec}): {d.message}")
            for key, value in d.figures.items():
                lines.append(f"         {key}: {_format_value(value)}")
        return "\n".join(lines)


def _format_value(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}" if math.isfinite(value) else "n/a"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_format_value(v) for v in value) + "]"
    return str(value)


def _caused_by(err: BaseException, kinds: type | tuple[type, ...]) -> bool:
    cause: BaseException | None = err.__cause__
    while cause is not None:
        if isinstance(cause, kinds):
            return True
        cause = cause.__cause__
    return False


def failure_line(err: TeleTouchError) -> str:
    """The one line that tells a lab what to fix, from a device error's phase.

    Args:
        err: the error a probe raised.

    Returns:
        ``could not open: ...``, ``opened but silent: ...``, ``opened but failed: ...`` or
        ``bad setting: ...``.
    """
    text = str(err).replace("\n", " ")
    if isinstance(err, DeviceInitError) and _caused_by(err, ImportError):
        return f"backend not installed: {text}"
    if isinstance(err, DeviceTimeoutError) or (isinstance(err, DeviceInitError) and _caused_by(
            err, (DeviceTimeoutError, TimeoutError))):
        return f"opened but silent: {text}; check power, wiring, bus/baud settings"
    if isinstance(err, DeviceInitError) and _caused_by(err, ConfigError):
        return f"bad setting: {text}"  # (the device disagrees with its configured setting)
    if isinstance(err, DeviceInitError) and _caused_by(err, DeviceOperationError):
        return f"opened but failed: {text}"  # (it talks, but not as it must)
    if isinstance(err, DeviceInitError):
        return f"could not open: {text}; check the cable/port/permissions"
    if isinstance(err, DeviceOperationError):
        return f"opened but failed: {text}"
    if isinstance(err, ConfigError | CalibrationError):
        return f"bad setting: {text}"
    return f"failed: {text}"


def failed_check(device: str, spec: str, err: TeleTouchError,
                 figures: dict[str, Any] | None = None) -> DeviceCheck:
    """A failed :class:`DeviceCheck` whose message is :func:`failure_line` of ``err``.

    Args:
        device: the role (``platform``, ...).
        spec: what the device was named by.
        err: the error the probe raised.
        figures: whatever was measured before the failure.
    """
    return DeviceCheck(device=device, spec=spec, ok=False, message=failure_line(err),
                       figures={**(figures or {}), "error": type(err).__name__})
