"""A named daemon thread that reads a device until told to stop.

Every backend that receives data on its own (a serial port, a CAN bus, a camera) runs the
same loop: call a blocking read with a short timeout, hand the data on, and end when asked
to or when the read fails. :class:`ReaderThread` is that loop; the read itself stays in the
backend.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

__all__ = ["ReaderThread"]

log = logging.getLogger(__name__)


class ReaderThread:
    """Call ``read_once()`` in a named daemon thread until it returns False or stop().

    Args:
        name: the thread's name (shown by debuggers and the leak fixture).
        read_once: one bounded read; returns False to end the thread (read failed, end of
            stream). It should block no longer than a short timeout so stop() is prompt.

    A ReaderThread runs once: build a new one for every connection.
    """

    def __init__(self, name: str, read_once: Callable[[], bool]) -> None:
        self.name = name
        self._read_once = read_once
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    @property
    def stopping(self) -> bool:
        """True once a stop was requested (a read error after that is expected)."""
        return self._stop.is_set()

    @property
    def is_alive(self) -> bool:
        """True while the thread runs."""
        return self._thread.is_alive()

    @property
    def is_current_thread(self) -> bool:
        """True when called from this reader's own thread (a backend's check that a late
        callback comes from its current reader, not from one it abandoned)."""
        return self._thread is threading.current_thread()

    def start(self) -> None:
        """Start the thread."""
        self._thread.start()

    def request_stop(self) -> None:
        """Ask the loop to end after the current read (does not wait)."""
        self._stop.set()

    def join(self, timeout_s: float = 2.0) -> bool:
        """Wait for the thread to end.

        Args:
            timeout_s: longest wait.

        Returns:
            True when the thread has ended.
        """
        if self._thread is threading.current_thread():
            return False  # stopped from its own callback: the loop ends on return
        if self._thread.ident is not None:
            self._thread.join(timeout_s)
        ended = not self._thread.is_alive()
        if not ended:
            log.warning("reader thread %r did not stop within %.1f s", self.name, timeout_s)
        return ended

    def stop(self, timeout_s: float = 2.0) -> bool:
        """Request a stop and wait for the thread to end.

        Args:
            timeout_s: longest wait.

        Returns:
            True when the thread has ended.
        """
        self.request_stop()
        return self.join(timeout_s)

    def _run(self) -> None:
        while not self._stop.is_set():
            if not self._read_once():
                return
