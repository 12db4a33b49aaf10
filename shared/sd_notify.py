"""Tell systemd how a service is doing: ready, alive (its watchdog), stopping.

A unit with ``Type=notify`` counts a Tele-Touch process as started when it says ``READY=1``
(the relay once its ports are bound, a station once its loops run), not when it was merely
spawned; with ``WatchdogSec=`` systemd restarts the process when the ``WATCHDOG=1`` pings
stop, which ``Restart=on-failure`` alone cannot do for a process that hangs without exiting.
The pings come from the process's asyncio event loop (:func:`service`), so they stop when
that loop is stuck; the loops that keep hardware safe (the display loop, the arm's halt) have
their own watchdogs and do not depend on this one.

The protocol is ``sd_notify(3)``: newline-separated ``KEY=value`` lines in one datagram to
the ``AF_UNIX`` socket named by ``$NOTIFY_SOCKET`` (a leading ``@`` is the abstract
namespace); the watchdog period is ``$WATCHDOG_USEC`` (for the process ``$WATCHDOG_PID``,
when set). Without ``$NOTIFY_SOCKET`` (not run by systemd) everything here does nothing. The
variables are taken out of the environment when read, so that the processes a service
starts (relay workers, a station's children) do not speak for it: ``teletouch`` reads them
first thing (:func:`process_notifier`, from ``lab.cli.main``), before any thread or child.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
from collections.abc import AsyncIterator, MutableMapping

__all__ = ["SAY_WAIT_S", "Notifier", "process_notifier", "service"]

log = logging.getLogger(__name__)


class Notifier:
    """The service manager's notification socket of this process, if any.

    Args:
        environ: where ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID`` are read
            and taken out (default: this process's environment).
    """

    def __init__(self, environ: MutableMapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        address = env.pop("NOTIFY_SOCKET", "")
        usec, pid = env.pop("WATCHDOG_USEC", ""), env.pop("WATCHDOG_PID", "")
        self.address: str | None = None
        if address.startswith("@"):
            self.address = "\0" + address[1:]
        elif address.startswith("/"):
            self.address = address
        elif address:
            log.warning("NOTIFY_SOCKET=%r is not a unix socket path: systemd is not told "
                        "this service's state", address)
        #: the period of ``WATCHDOG=1`` pings (half the manager's timeout); None: no watchdog
        self.watchdog_period_s: float | None = None
        if self.address is not None and usec and (not pid or pid == str(os.getpid())):
            try:
                timeout_us = int(usec)
            except ValueError:
                timeout_us = 0
            if timeout_us > 0:
                self.watchdog_period_s = timeout_us / 2e6
            else:
                log.warning("WATCHDOG_USEC=%r is not a positive integer: no watchdog pings",
                            usec)
        self._failed = False
        #: messages not sent (no socket there, or its queue full)
        self.dropped = 0

    @property
    def active(self) -> bool:
        """Whether a service manager listens."""
        return self.address is not None

    def notify(self, *fields: str, wait_s: float = 0.0) -> bool:
        """Send ``fields`` (``"READY=1"``, ``"STATUS=..."``) in one message; False when no
        manager listens or the message could not be sent (logged once: a service never stops
        for its manager's socket).

        A unix datagram socket blocks its sender while the reader's queue is full
        (``net.unix.max_dgram_qlen``, 10 on this host; systemd's socket serves every unit), so
        a send waits at most ``wait_s``: 0 for the watchdog's pings (a manager slow to read
        must not stall the event loop; a late ping is dropped, the next one follows), up to a
        second for ``READY=1`` and ``STOPPING=1``, which are said once (a lost ``READY=1``
        would leave the unit starting until systemd kills it).
        """
        if self.address is None:
            return False
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
                data = "\n".join(fields).encode()
                if wait_s > 0:
                    sock.settimeout(wait_s)
                    sock.sendto(data, self.address)
                else:
                    sock.sendto(data, socket.MSG_DONTWAIT, self.address)
        except OSError as err:
            self.dropped += 1
            if not self._failed:
                self._failed = True
                why = "its queue is full (it is not reading)" if isinstance(
                    err, BlockingIOError | TimeoutError) else str(err)
                log.warning("cannot notify the service manager at %r: %s; dropped (said once)",
                            self.address.replace("\0", "@"), why)
            return False
        return True


#: the notifier of this process (:func:`process_notifier`)
_PROCESS: Notifier | None = None

#: how long ``READY=1`` and ``STOPPING=1`` may wait for room in the manager's queue
SAY_WAIT_S = 1.0


def process_notifier() -> Notifier:
    """This process's notifier, read from (and taken out of) the environment on the first
    call; ``teletouch`` makes it first thing, before any thread or child is started."""
    global _PROCESS
    if _PROCESS is None:
        _PROCESS = Notifier()
    return _PROCESS


@contextlib.asynccontextmanager
async def service(status: str, notifier: Notifier | None = None) -> AsyncIterator[Notifier]:
    """While the block runs the service is ready: ``READY=1`` with ``status`` on entry,
    ``WATCHDOG=1`` from this event loop every half watchdog timeout, ``STOPPING=1`` on exit.

    Args:
        status: a one-line description for ``systemctl status``.
        notifier: the manager's socket (default: this process's, :func:`process_notifier`).
    """
    notifier = process_notifier() if notifier is None else notifier
    notifier.notify("READY=1", f"STATUS={status}", wait_s=SAY_WAIT_S)
    pinger = None
    period_s = notifier.watchdog_period_s
    if period_s is not None:
        async def ping() -> None:
            while True:
                notifier.notify("WATCHDOG=1")
                await asyncio.sleep(period_s)

        pinger = asyncio.get_running_loop().create_task(ping(), name="sd-watchdog")
    try:
        yield notifier
    finally:
        if pinger is not None:
            pinger.cancel()
            try:
                await pinger
            except asyncio.CancelledError:
                task = asyncio.current_task()
                if task is not None and task.cancelling():  # ours, not the pinger's: on
                    notifier.notify("STOPPING=1", wait_s=SAY_WAIT_S)
                    raise
        notifier.notify("STOPPING=1", wait_s=SAY_WAIT_S)
