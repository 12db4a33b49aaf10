"""Runs :class:`~local_site.display.firmware.ArrayTacFirmware` in real time on a link.

:class:`FirmwareEmulator` is the drive board's main loop in a thread: it applies every frame
as soon as it arrives, advances the plant on a fixed tick (2 ms by default) and sends the
feedback the firmware produces. The link is a :class:`FirmwareTransport`: the other end of
a python-can bus (:class:`CanFirmwareTransport`) or of a pty (:class:`PtyFirmwareTransport`).
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import select
import threading
import time
from abc import ABC, abstractmethod
from types import TracebackType

import can

from local_site.display import frames as fr
from local_site.display.firmware import ArrayTacFirmware
from local_site.display.serial_framing import LinkFrameDecoder, encode_link_frame
from shared.errors import DeviceInitError

__all__ = ["CanFirmwareTransport", "FirmwareEmulator", "FirmwareTransport",
           "PtyFirmwareTransport"]

log = logging.getLogger(__name__)


class FirmwareTransport(ABC):
    """The board's side of the link."""

    @abstractmethod
    def recv(self, timeout_s: float) -> tuple[int, bytes] | None:
        """Next frame ``(arb_id, payload)``, waiting up to ``timeout_s``; None if none."""

    @abstractmethod
    def send(self, arb_id: int, payload: bytes) -> None:
        """Send one frame; drop it silently when the link is congested (as a board would)."""

    @abstractmethod
    def close(self) -> None:
        """Release the link."""


class CanFirmwareTransport(FirmwareTransport):
    """The board on a python-can bus (``virtual`` for the simulator).

    Args:
        channel: the bus channel.
        interface: python-can interface.
    """

    def __init__(self, channel: str, interface: str = "virtual") -> None:
        try:
            self._bus = can.Bus(interface=interface, channel=channel, fd=True, can_filters=[
                {"can_id": fr.ARB_ID_COMMAND, "can_mask": 0x7FF, "extended": False},
                {"can_id": fr.ARB_ID_SAFE_STATE, "can_mask": 0x7FF, "extended": False}])
        except (can.CanError, OSError, ValueError) as err:
            raise DeviceInitError(f"emulated ArrayTac board: cannot open {interface}:"
                                  f"{channel}: {err}") from err
        self.dropped = 0

    def recv(self, timeout_s: float) -> tuple[int, bytes] | None:
        msg = self._bus.recv(timeout=timeout_s)
        if msg is None or msg.is_error_frame:
            return None
        return msg.arbitration_id, bytes(msg.data)

    def send(self, arb_id: int, payload: bytes) -> None:
        try:
            self._bus.send(can.Message(arbitration_id=arb_id, data=payload, is_fd=True,
                                       bitrate_switch=True, is_extended_id=False), timeout=0.0)
        except can.CanError:
            self.dropped += 1

    def close(self) -> None:
        self._bus.shutdown()


class PtyFirmwareTransport(FirmwareTransport):
    """The board on the master side of a pty (the driver opens the slave path).

    Args:
        master_fd: non-blocking master descriptor; closed by :meth:`close`.
    """

    def __init__(self, master_fd: int) -> None:
        self._fd = master_fd
        self._decoder = LinkFrameDecoder()
        self._pending: collections.deque[tuple[int, bytes]] = collections.deque()
        self.dropped = 0

    @property
    def decoder(self) -> LinkFrameDecoder:
        """The board's stream decoder (its counters)."""
        return self._decoder

    def recv(self, timeout_s: float) -> tuple[int, bytes] | None:
        if not self._pending:
            ready, _, _ = select.select([self._fd], [], [], max(0.0, timeout_s))
            if ready:
                try:
                    data = os.read(self._fd, 4096)
                except (BlockingIOError, InterruptedError):
                    data = b""
                except OSError:  # slave closed (EIO): nothing to read until it reopens
                    time.sleep(min(timeout_s, 0.01))
                    data = b""
                self._pending.extend(self._decoder.feed(data))
        return self._pending.popleft() if self._pending else None

    def send(self, arb_id: int, payload: bytes) -> None:
        try:
            os.write(self._fd, encode_link_frame(arb_id, payload))
        except OSError:  # buffer full (driver not reading) or slave closed
            self.dropped += 1

    def close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self._fd)


class FirmwareEmulator:
    """The emulated board's main loop, in a thread, in real time.

    Args:
        firmware: the firmware (with its plant).
        transport: the board's end of the link; closed by :meth:`stop`.
        tick_s: plant/watchdog/feedback tick.
    """

    def __init__(self, firmware: ArrayTacFirmware, transport: FirmwareTransport, *,
                 tick_s: float = 0.002) -> None:
        self.firmware = firmware
        self.transport = transport
        self._tick_s = tick_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._finger_force_n: float | None = None
        self.error: BaseException | None = None

    def start(self) -> None:
        """Start the board loop."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="arraytac-firmware", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the loop and close the transport (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
            self.transport.close()

    def __enter__(self) -> FirmwareEmulator:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    def set_finger_force(self, force_n: float) -> None:
        """The simulated fingertip's pressing force, applied at the next tick."""
        with self._lock:
            self._finger_force_n = float(force_n)

    def _run(self) -> None:
        fw, link, tick = self.firmware, self.transport, self._tick_s
        clock = time.perf_counter
        next_tick = clock()
        try:
            while not self._stop.is_set():
                item = link.recv(max(0.0, next_tick - clock()))
                while item is not None:
                    fw.receive(item[0], item[1], clock())
                    item = link.recv(0.0)
                now = clock()
                if now < next_tick:
                    continue
                with self._lock:
                    force, self._finger_force_n = self._finger_force_n, None
                if force is not None:
                    fw.plant.set_finger_force(force)
                for arb_id, payload in fw.poll(now):
                    link.send(arb_id, payload)
                next_tick += tick
                if now - next_tick > 10 * tick:  # starved: skip ahead, do not burst
                    next_tick = now + tick
        except Exception as err:  # keep the cause for the owner; the link goes silent
            self.error = err
            log.exception("emulated ArrayTac firmware stopped")
