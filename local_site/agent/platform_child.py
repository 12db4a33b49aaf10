"""The platform process's entry point: ``python -m local_site.agent.platform_child``.

A module of its own, which the package does not import, so that ``-m`` runs it once (see
:mod:`local_site.agent.platform_process` for what the child does and how it ends).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import select
import signal
import sys

from local_site.agent.platform_process import HEARTBEAT_S, ReaderHealth, SampleRecord
from local_site.agent.platform_reader import PlatformReader
from local_site.devices import open_platform
from shared.memlock import memory_locked
from shared.timebase import monotonic_s

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:  # pragma: no cover - runs in the child
    """The child: open the platform, run its reader, publish every sample and the health,
    until a line or the end of its standard input (the station stopped or is gone), or
    until its parent changes.

    Args:
        argv: ``[settings JSON]`` (written by :class:`ProcessPlatformReader`).

    Returns:
        0.
    """
    settings = json.loads((sys.argv[1:] if argv is None else argv)[0])
    logging.basicConfig(level=int(settings["log_level"]),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    # the station stops us through stdin (a Ctrl-C at the terminal, or systemd's SIGTERM to
    # the whole unit, reaches the station, which stops us in order)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    record = SampleRecord(int(settings["record_fd"]))
    record.claim()
    platform = open_platform(settings["spec"], connect=False, **settings["options"])
    # every sample goes to the record from the driver's own reader thread, as it is decoded;
    # the reader watches the health at its usual pace
    platform.sample_listener = record.write_sample
    reader = PlatformReader(platform, **settings["reader"])

    def publish() -> None:
        record.write_health(ReaderHealth(
            healthy=reader.healthy, lost_since_mono_s=reader.lost_since_s, reads=reader.reads,
            errors=reader.errors, reconnects=reader.reconnects, recoveries=reader.recoveries,
            motion_done=reader.motion_done.is_set(), heartbeat_s=monotonic_s(),
            last_error=reader.last_error))

    parent = int(settings["parent"])
    publish()
    process_settings = contextlib.ExitStack()
    process_settings.enter_context(memory_locked(bool(settings.get("lock_memory", False))))
    reader.start()
    try:
        while True:
            publish()
            ready, _, _ = select.select([sys.stdin], [], [], HEARTBEAT_S)
            if ready or os.getppid() != parent:
                break  # "stop", the end of the pipe (the station is gone), or a new parent
    finally:
        reader.stop()
        with contextlib.suppress(Exception):
            platform.disconnect()
        publish()
        with contextlib.suppress(OSError):
            os.write(int(settings["stats_fd"]),
                     json.dumps(dataclasses.asdict(platform.stats())).encode())
        record.close()
        process_settings.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
