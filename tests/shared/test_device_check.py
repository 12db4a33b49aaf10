"""The one line ``teletouch check`` prints per failed device, sorted by the device layer's
error phases, and the report's strict JSON shape."""

from __future__ import annotations

import json

import pytest

from shared.device_check import CheckReport, CheckSettings, DeviceCheck, failed_check, failure_line
from shared.errors import (
    CalibrationError,
    ConfigError,
    DeviceInitError,
    DeviceOperationError,
    DeviceTimeoutError,
)
from shared.report import to_jsonable


def _init_error_from(cause: BaseException) -> DeviceInitError:
    try:
        raise DeviceInitError("board at /dev/ttyX: no answer") from cause
    except DeviceInitError as err:
        return err


def test_phases_map_to_what_to_fix() -> None:
    assert failure_line(DeviceInitError("port /dev/ttyUSB9 missing")).startswith(
        "could not open: port /dev/ttyUSB9 missing; check the cable/port/permissions")
    assert failure_line(DeviceTimeoutError("no frame")).startswith("opened but silent: no frame")
    silent = _init_error_from(DeviceTimeoutError("no feedback"))
    assert failure_line(silent).startswith("opened but silent: board at /dev/ttyX")
    assert failure_line(_init_error_from(TimeoutError())).startswith("opened but silent")
    assert failure_line(_init_error_from(ImportError("franky"))).startswith(
        "backend not installed")
    assert failure_line(_init_error_from(OSError("busy"))).startswith("could not open")
    assert failure_line(DeviceOperationError("bad echo")).startswith("opened but failed")
    assert failure_line(ConfigError("no such backend")).startswith("bad setting")
    assert failure_line(CalibrationError("pitch")).startswith("bad setting")
    assert "\n" not in failure_line(DeviceInitError("two\nlines"))


def test_report_json_is_strict_with_one_entry_per_device() -> None:
    report = CheckReport("local", (
        DeviceCheck("platform", "sim", True, "fine", {"rate_hz": float("nan")}),
        failed_check("display", "can://virtual/x", DeviceInitError("nope"))))
    assert report.exit_code == 1 and not report.ok
    obj = json.loads(json.dumps(to_jsonable(report.to_dict()), allow_nan=False))
    assert obj["devices"]["platform"]["figures"]["rate_hz"] is None
    assert obj["devices"]["display"]["figures"]["error"] == "DeviceInitError"
    assert "FAIL display (can://virtual/x): could not open" in report.to_text()
    assert CheckReport("remote", (DeviceCheck("arm", "sim", True, "ok"),)).exit_code == 0


@pytest.mark.parametrize("field", ["connect_timeout_s", "read_timeout_s", "rate_window_s",
                                   "move_mm", "move_timeout_s"])
def test_settings_refuse_non_positive_bounds(field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        CheckSettings(**{field: 0.0})
    with pytest.raises(ConfigError, match="move_mm"):
        CheckSettings(move_mm=50.0)
