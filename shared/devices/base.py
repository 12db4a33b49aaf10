"""The one device lifecycle every device kind shares (python-can / lerobot habit).

:class:`Device` owns the public lifecycle: ``connect()``, ``disconnect()``,
``is_connected`` and the context manager. It checks state, logs, and sorts errors by phase
so that callers catch the same errors whatever the device::

    phase        vendor error (serial, CAN, OpenCV, franky, OSError, ...) becomes
    connect      DeviceInitError        (raised by connect() and the context manager)
    operation    DeviceOperationError   (or DeviceTimeoutError for a TimeoutError)
    not open     DeviceNotConnectedError

Errors that already belong to the project's tree (:class:`~shared.errors.TeleTouchError`)
pass through unchanged, so a backend may raise a more precise one itself.

Hooks, all private. A *backend* implements the two the same way for every kind:

    ``_connect()``         open the link, start reader threads
    ``_disconnect()``      stop them and release the link (called once per connect)

A *kind* base class (platform, display, arm, sensor) may override the optional steps
around them; each defaults to doing nothing:

    ``_before_connect()``      reset per-connection state
    ``_after_connect()``       wait until the device is usable (first sample, first
                               feedback); an error here disconnects and propagates
    ``_is_healthy()``          False when an open link broke: ``connect()`` then reopens
    ``_before_disconnect()``   leave the hardware safe (stop the arm, park the pins)
    ``_after_disconnect()``    wake threads waiting on the device
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import contextmanager
from types import TracebackType
from typing import Self

from shared.errors import (
    DeviceInitError,
    DeviceNotConnectedError,
    DeviceOperationError,
    DeviceTimeoutError,
    TeleTouchError,
)

__all__ = ["Device"]

log = logging.getLogger(__name__)


class Device(ABC):
    """Base of every device kind: one lifecycle, one set of hook names, one error tree."""

    def __init__(self) -> None:
        self._connected = False

    # ------------------------------------------------------------------ identity

    @property
    def name(self) -> str:
        """Human-readable device name for messages (backends may override)."""
        return type(self).__name__

    @property
    def is_connected(self) -> bool:
        """True between a successful ``connect()`` and ``disconnect()``."""
        return self._connected

    # ------------------------------------------------------------------ lifecycle

    def connect(self) -> None:
        """Open the device and wait until it is usable.

        Calling it again on a healthy connection does nothing; on a connection whose link
        broke it disconnects and reopens (this is how a station retries).

        Raises:
            DeviceInitError: the device cannot be opened or does not become usable (vendor
                errors are wrapped, with the cause kept).
            TeleTouchError: a more precise project error raised by the backend.
        """
        if self._connected:
            if self._is_healthy():
                return
            log.info("%s: link broken, reconnecting", self.name)
            self.disconnect()
        self._before_connect()
        try:
            self._connect()
        except TeleTouchError:
            raise
        except Exception as err:  # vendor errors of any backend: wrap, keep the cause
            raise DeviceInitError(f"{self.name}: cannot open: {err}") from err
        self._connected = True
        try:
            self._after_connect()
        except BaseException:
            self._disconnect_quietly()
            raise
        log.info("%s connected", self.name)

    def disconnect(self) -> None:
        """Leave the device safe, stop its threads and release it (idempotent).

        Raises:
            DeviceOperationError: releasing the link failed (the device counts as
                disconnected anyway).
        """
        if not self._connected:
            return
        try:
            self._before_disconnect()
        finally:
            self._connected = False
            try:
                self._disconnect()
            except TeleTouchError:
                raise
            except Exception as err:  # vendor errors: wrap, keep the cause
                raise DeviceOperationError(f"{self.name}: cannot close: {err}") from err
            finally:
                self._after_disconnect()
                log.info("%s disconnected", self.name)

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.disconnect()

    # ------------------------------------------------------------------ for subclasses

    def _require_connected(self, message: str | None = None) -> None:
        """Raise :class:`DeviceNotConnectedError` unless connected.

        Args:
            message: the error's text (default: "<name> is not connected").
        """
        if not self._connected:
            raise DeviceNotConnectedError(message or f"{self.name} is not connected")

    @contextmanager
    def _operation(self, what: str) -> Iterator[None]:
        """Wrap vendor errors raised inside the block as operation-phase errors.

        Args:
            what: the operation, for the message (``"send"``, ``"state read"``).

        Raises:
            DeviceTimeoutError: the block raised :class:`TimeoutError`.
            DeviceOperationError: the block raised any other non-project exception.
        """
        try:
            yield
        except TeleTouchError:
            raise
        except TimeoutError as err:
            raise DeviceTimeoutError(f"{self.name}: {what} timed out: {err}") from err
        except Exception as err:  # vendor errors of any backend: wrap, keep the cause
            raise DeviceOperationError(f"{self.name}: {what} failed: {err}") from err

    def _disconnect_quietly(self) -> None:
        """Disconnect after a failed connect without hiding the original error."""
        try:
            self.disconnect()
        except TeleTouchError:
            log.warning("%s: cleanup after a failed connect failed", self.name, exc_info=True)

    # ------------------------------------------------------------------ backend hooks

    @abstractmethod
    def _connect(self) -> None:
        """Open the link and start delivering data."""

    @abstractmethod
    def _disconnect(self) -> None:
        """Stop delivering data and release the link."""

    # ------------------------------------------------------------------ kind hooks

    def _before_connect(self) -> None:
        """Reset per-connection state (kind bases override)."""
        return None

    def _after_connect(self) -> None:
        """Wait until the device is usable (kind bases override)."""
        return None

    def _is_healthy(self) -> bool:
        """False when an open link broke and ``connect()`` should reopen it."""
        return True

    def _before_disconnect(self) -> None:
        """Leave the hardware in a safe state (kind bases override)."""
        return None

    def _after_disconnect(self) -> None:
        """Wake anything waiting on the device (kind bases override)."""
        return None
