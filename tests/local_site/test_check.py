"""``teletouch check local``: the encoder board and drive-board probes, through the CLI as a
lab runs it (simulated devices pass; a missing serial device and a silent CAN channel fail
with one line naming the device), and one real subprocess; a drive board whose watchdog
ignores the command's timeout (trips late, or early) fails, the trip time measured on the
board's clock."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import uuid
from types import SimpleNamespace
from typing import Any

import pytest

from lab.cli import main
from local_site.check import check_display, check_platform
from local_site.display.firmware import ArrayTacFirmware
from shared.device_check import CheckSettings
from tests.support import REPO_ROOT, scaled


def _strict_json(text: str) -> dict[str, Any]:
    def refuse(constant: str) -> None:
        raise AssertionError(f"non-strict JSON constant {constant}")

    obj: dict[str, Any] = json.loads(text, parse_constant=refuse)
    return obj


@pytest.fixture
def check_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """Probe time bounds scaled for this machine (the product reads TELETOUCH_CHECK_*)."""
    monkeypatch.setenv("TELETOUCH_CHECK_CONNECT_TIMEOUT_S", str(scaled(3.0)))
    monkeypatch.setenv("TELETOUCH_CHECK_READ_TIMEOUT_S", str(scaled(0.5)))
    monkeypatch.setenv("TELETOUCH_CHECK_RATE_WINDOW_S", "0.5")


def test_sim_devices_pass_with_json_one_entry_per_device(
        check_env: None, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["check", "local", "--platform", "sim", "--display", "sim", "--json"])
    report = _strict_json(capsys.readouterr().out)
    assert code == 0, report
    assert report["station"] == "local" and report["ok"] is True
    assert set(report["devices"]) == {"platform", "display"}
    for name, entry in report["devices"].items():
        assert set(entry) == {"device", "spec", "ok", "message", "figures"}
        assert entry["device"] == name and entry["spec"] == "sim" and entry["ok"] is True
    platform = report["devices"]["platform"]["figures"]
    assert platform["sample_rate_hz"] >= 500.0
    assert len(platform["position_mm"]) == 3 and len(platform["counts"]) == 3
    display = report["devices"]["display"]["figures"]
    assert display["feedback_rate_hz"] > 100.0
    assert display["safe_state_applied"] and display["zero_command_echoed"]
    assert display["watchdog_tripped"] and display["watchdog_ms"] == 100
    low, high = display["watchdog_trip_bounds_ms"]
    assert low <= display["watchdog_trip_ms"] <= high and high > 100


@pytest.mark.parametrize("watchdog_ms", [1, 15])
def test_a_watchdog_shorter_than_the_driver_s_keepalive_is_probed(
        watchdog_ms: int, check_env: None, capsys: pytest.CaptureFixture[str]) -> None:
    """--watchdog-ms under the driver's 20 ms keepalive failed the display with a setting no
    user gives ("keepalive_interval_s (0.02) must be ... shorter than the watchdog")."""
    code = main(["check", "local", "--platform", "sim", "--display", "sim", "--json",
                 "--watchdog-ms", str(watchdog_ms)])
    report = _strict_json(capsys.readouterr().out)
    assert code == 0, report
    display = report["devices"]["display"]["figures"]
    assert display["watchdog_tripped"] and display["watchdog_ms"] == watchdog_ms


def test_missing_serial_device_and_silent_can_channel_fail_naming_them(
        check_env: None, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("TELETOUCH_CHECK_CONNECT_TIMEOUT_S", str(scaled(0.5)))
    channel = f"nobody-{uuid.uuid4().hex[:8]}"
    code = main(["check", "local", "--platform", "/dev/ttyUSB9",
                 "--display", f"can://virtual/{channel}"])
    out = capsys.readouterr().out
    assert code == 1
    lines = {line.split()[1]: line for line in out.splitlines() if line.startswith("  FAIL")}
    assert set(lines) == {"platform", "display"}
    assert "/dev/ttyUSB9" in lines["platform"] and "could not open" in lines["platform"]
    assert "cable/port/permissions" in lines["platform"]
    assert channel in lines["display"] and "opened but silent" in lines["display"]


def test_push_window_sees_moving_counts_and_flags_a_still_platform() -> None:
    settings = CheckSettings(connect_timeout_s=scaled(3.0), read_timeout_s=scaled(0.5),
                             rate_window_s=0.2)
    asked: list[str] = []
    moving = check_platform("sim", settings, push_s=0.3, notify=asked.append)
    assert moving.ok, moving.message
    assert asked and "push" in asked[0]
    assert max(moving.figures["push_counts_moved"]) >= 2

    still = check_platform("sim", settings, push_s=0.3, motion="hold")
    assert not still.ok
    assert "no encoder count moved" in still.message
    assert still.figures["push_counts_moved"] == [0, 0, 0]


def test_usage_errors_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["check", "local", "--platform", "sim"])
    assert info.value.code == 2
    assert main(["check", "local", "--platform", "sim", "--display", "sim",
                 "--push-s", "-1"]) == 2
    for bad in ("0", "11", "nan"):
        assert main(["check", "local", "--platform", "sim", "--display", "sim",
                     "--feedback-timeout-s", bad]) == 2
    assert "--feedback-timeout-s in (0, 10]" in capsys.readouterr().err


def test_the_feedback_timeout_reaches_the_probed_driver(
        check_env: None, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """A board set to feed back slower than the driver's 0.2 s default needs the station's
    ``display_feedback_timeout_s``: the check had no way to take it, so it failed a board
    the station ran fine (found by review)."""
    import local_site.check as check

    seen: list[float] = []
    real = check.open_display

    def spy(spec: str, **kwargs: Any) -> Any:
        display = real(spec, **kwargs)
        seen.append(display._feedback_timeout_s)
        return display

    monkeypatch.setattr(check, "open_display", spy)
    code = main(["check", "local", "--platform", "sim", "--display", "sim", "--json",
                 "--feedback-timeout-s", "1.5"])
    assert code == 0, capsys.readouterr()
    assert seen == [1.5]


def test_cli_subprocess_json() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "lab.cli", "--log-level", "WARNING", "check", "local",
         "--platform", "sim", "--display", "sim", "--json",
         "--timeout-s", str(scaled(3.0))],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=scaled(60.0), check=False,
        env={**os.environ, "TELETOUCH_CHECK_READ_TIMEOUT_S": str(scaled(0.5))})
    assert done.returncode == 0, done.stderr
    report = _strict_json(done.stdout)
    assert report["ok"] is True
    assert [report["devices"][d]["ok"] for d in ("platform", "display")] == [True, True]


def _board_watchdog(monkeypatch: pytest.MonkeyPatch, timeout_s: float) -> None:
    """The simulated board arms its watchdog with ``timeout_s``, whatever the command asks."""
    apply = ArrayTacFirmware._apply_command

    def ignoring_the_frame(self: ArrayTacFirmware, frame: Any, now_s: float) -> None:
        apply(self, frame, now_s)
        self._watchdog_s = timeout_s

    monkeypatch.setattr(ArrayTacFirmware, "_apply_command", ignoring_the_frame)


def _settings() -> CheckSettings:
    return CheckSettings(connect_timeout_s=scaled(3.0), read_timeout_s=scaled(1.0),
                         rate_window_s=0.2)


def test_a_board_whose_watchdog_trips_late_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any trip within watchdog_ms + read_timeout_s passed: a board tripping at 600 ms when
    asked for 100 ms was reported as "100 ms watchdog trips"."""
    _board_watchdog(monkeypatch, 0.6)
    result = check_display("sim", _settings(), watchdog_ms=100)
    assert not result.ok, result.message
    assert "watchdog trips late" in result.message
    assert result.figures["watchdog_tripped"] is True
    assert result.figures["watchdog_trip_bounds_ms"][0] > 104
    assert result.figures["watchdog_trip_ms"] >= 550


def test_a_board_whose_watchdog_trips_early_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    _board_watchdog(monkeypatch, 0.01)
    result = check_display("sim", _settings(), watchdog_ms=300)
    assert not result.ok, result.message
    assert "watchdog trips early" in result.message
    assert result.figures["watchdog_trip_bounds_ms"][1] < 296


def test_the_trip_time_is_measured_across_the_board_clock_s_wrap() -> None:
    from local_site.check import _watchdog_timing

    def fb(board_t_us: int) -> SimpleNamespace:
        return SimpleNamespace(board_t_us=board_t_us & 0xFFFFFFFF)

    # the uint32 board clock wraps between the echo and the trip
    trip_ms, low_ms, high_ms = _watchdog_timing(fb(-4_096), fb(-1_000), fb(97_000),
                                                fb(99_000))
    assert trip_ms == pytest.approx(100.0)
    assert low_ms == pytest.approx(98.0) and high_ms == pytest.approx(103.096)
    # the echo already showed the trip (the host read late): nothing proves it was late
    assert _watchdog_timing(fb(0), fb(150_000), None, fb(150_000)) == (0.0, 0.0, 150.0)
