"""Fuzzed frames over real TCP and WebSocket sockets to a relay subprocess (short run)."""

from __future__ import annotations

import pytest

from lab.fuzz.smoke import run_smoke


@pytest.mark.slow  # a relay process and 40 connections
def test_a_fuzzed_relay_process_still_serves_a_good_session() -> None:
    result = run_smoke(connections=40, seed=5)
    assert result.relay_alive, "the relay process died"
    assert not result.relay_log_errors, "\n".join(result.relay_log_errors)
    assert result.good_session, "no platform_state forwarded after the fuzzing"
    assert result.status_ok
    assert result.answers > 0 and result.error_codes, "the relay answered nothing"
    assert result.error_codes.get("tcp:oversize"), result.error_codes  # delivered on TCP
