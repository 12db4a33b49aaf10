"""Helpers shared by the test suite.

Timeouts scale with ``TELETOUCH_TEST_TIMEOUT_SCALE`` (default 1) so slow or loaded
machines do not flake: write ``scaled(2.0)`` instead of ``2.0``.
"""

from __future__ import annotations

import os
import socket

TIMEOUT_SCALE = float(os.environ.get("TELETOUCH_TEST_TIMEOUT_SCALE", "1"))


def scaled(seconds: float) -> float:
    """Return ``seconds`` times the timeout scale of this machine."""
    return seconds * TIMEOUT_SCALE


def free_tcp_port() -> int:
    """Return a TCP port on 127.0.0.1 that is free right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])
