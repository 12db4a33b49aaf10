"""The ``sim`` display backends: the emulated drive board on a fresh link, then the normal
driver connected to it.

- :class:`SimCanArrayTacDisplay` (registry name ``sim``): a new ``virtual`` CAN channel, the
  emulator on one end, :class:`~local_site.display.can_link.CanArrayTacDisplay` on the other.
- :class:`SimSerialArrayTacDisplay` (``sim-serial``): a pty pair, the emulator on the master
  side, :class:`~local_site.display.serial_link.SerialArrayTacDisplay` opening the slave path.

The application never knows: it sees an ``ArrayTacDisplay``. The emulator is reachable as
``.emulator`` (tests and demos set the finger force through it).
"""

from __future__ import annotations

import contextlib
import os
import tty
import uuid
from typing import Any

from local_site.display.can_link import CanArrayTacDisplay
from local_site.display.emulator import (
    CanFirmwareTransport,
    FirmwareEmulator,
    FirmwareTransport,
    PtyFirmwareTransport,
)
from local_site.display.firmware import ArrayTacFirmware, PlantLike, make_plant
from local_site.display.serial_link import SerialArrayTacDisplay
from shared.errors import DeviceInitError

__all__ = ["SimCanArrayTacDisplay", "SimSerialArrayTacDisplay"]


class _EmulatedBoard:
    """Builds and owns the emulator of one simulated display."""

    def __init__(self, plant: PlantLike | None, plant_options: dict[str, Any] | None,
                 feedback_rate_hz: float, firmware_watchdog_ms: int, tick_s: float) -> None:
        # The simulated hardware exists as soon as the backend does: building the plant here
        # (compiling its kernel on a cold cache) keeps that one-off cost out of connect(),
        # which runs in the station's display thread next to its platform reader.
        self._plant = plant if plant is not None else make_plant(**(plant_options or {}))
        self._feedback_period_s = 1.0 / feedback_rate_hz
        self._watchdog_ms = firmware_watchdog_ms
        self._tick_s = tick_s
        self.emulator: FirmwareEmulator | None = None

    def start(self, transport: FirmwareTransport) -> FirmwareEmulator:
        plant = self._plant
        plant.reset()
        firmware = ArrayTacFirmware(plant, default_watchdog_ms=self._watchdog_ms,
                                    feedback_period_s=self._feedback_period_s)
        self.emulator = FirmwareEmulator(firmware, transport, tick_s=self._tick_s)
        self.emulator.start()
        return self.emulator

    def stop(self) -> None:
        if self.emulator is not None:
            self.emulator.stop()


class SimCanArrayTacDisplay(CanArrayTacDisplay):
    """Simulated ArrayTac over a private virtual CAN FD channel.

    Args:
        plant: a plant to use (default: a new ``ArrayTacPlant(**plant_options)``).
        plant_options: keyword arguments for the plant.
        feedback_rate_hz: the emulated board's feedback rate.
        firmware_watchdog_ms: the board's default watchdog (commands carry their own).
        tick_s: the emulator's tick.
        **kwargs: passed to :class:`~local_site.display.base.ArrayTacDisplay`.
    """

    def __init__(self, *, plant: PlantLike | None = None,
                 plant_options: dict[str, Any] | None = None, feedback_rate_hz: float = 500.0,
                 firmware_watchdog_ms: int = 100, tick_s: float = 0.002, **kwargs: Any) -> None:
        super().__init__(channel=f"arraytac-sim-{uuid.uuid4().hex[:12]}", interface="virtual",
                         **kwargs)
        self._board = _EmulatedBoard(plant, plant_options, feedback_rate_hz,
                                     firmware_watchdog_ms, tick_s)

    @property
    def emulator(self) -> FirmwareEmulator | None:
        """The running emulator (None when disconnected)."""
        return self._board.emulator

    def _connect(self) -> None:
        self._board.start(CanFirmwareTransport(self.channel, "virtual"))
        try:
            super()._connect()
        except DeviceInitError:
            self._board.stop()
            raise

    def _disconnect(self) -> None:
        super()._disconnect()
        self._board.stop()


class SimSerialArrayTacDisplay(SerialArrayTacDisplay):
    """Simulated ArrayTac over a pty pair (serial framing).

    Args: as :class:`SimCanArrayTacDisplay`.
    """

    def __init__(self, *, plant: PlantLike | None = None,
                 plant_options: dict[str, Any] | None = None, feedback_rate_hz: float = 500.0,
                 firmware_watchdog_ms: int = 100, tick_s: float = 0.002, **kwargs: Any) -> None:
        super().__init__("pty://sim", **kwargs)
        self._board = _EmulatedBoard(plant, plant_options, feedback_rate_hz,
                                     firmware_watchdog_ms, tick_s)

    @property
    def emulator(self) -> FirmwareEmulator | None:
        """The running emulator (None when disconnected)."""
        return self._board.emulator

    def _connect(self) -> None:
        try:
            master_fd, slave_fd = os.openpty()
        except OSError as err:
            raise DeviceInitError(f"cannot create a pty for the simulated display: {err}") \
                from err
        try:
            tty.setraw(slave_fd)
            os.set_blocking(master_fd, False)
            self.url = os.ttyname(slave_fd)
            self._board.start(PtyFirmwareTransport(master_fd))  # owns master_fd from here
            master_fd = -1
            super()._connect()
        except (OSError, DeviceInitError) as err:
            self._board.stop()
            if master_fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(master_fd)
            if isinstance(err, DeviceInitError):
                raise
            raise DeviceInitError(f"cannot start the simulated display: {err}") from err
        finally:
            os.close(slave_fd)

    def _disconnect(self) -> None:
        super()._disconnect()
        self._board.stop()
