"""``teletouch check remote``: the arm and camera probes (sim passes, a missing camera index
fails naming it, a calibration for another pixel pitch is refused, the arm never moves
unless asked and is halted when the probe lets go)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest

from lab.cli import main
from remote_site.arm.base import Vec3
from remote_site.arm.sim import SimArm
from remote_site.check import check_arm, check_sensor
from shared.device_check import CheckSettings
from tests.support import REPO_ROOT, scaled

SIM_CALIBRATION = REPO_ROOT / "remote_site" / "sensor" / "data" / "sim_calib.npz"


class RecordingArm(SimArm):
    """The sim arm, remembering every target and stop (loaded by its ``module:Class`` path)."""

    moves: ClassVar[list[Vec3]] = []
    stops: ClassVar[int] = 0

    def _move_to(self, target_mm: Vec3) -> None:
        RecordingArm.moves.append(target_mm)
        super()._move_to(target_mm)

    def _stop(self) -> None:
        RecordingArm.stops += 1
        super()._stop()


RECORDING_ARM = f"{__name__}:RecordingArm"


@pytest.fixture
def settings() -> CheckSettings:
    return CheckSettings(connect_timeout_s=scaled(3.0), read_timeout_s=scaled(0.5),
                         rate_window_s=0.3, move_timeout_s=scaled(5.0))


@pytest.fixture
def check_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TELETOUCH_CHECK_CONNECT_TIMEOUT_S", str(scaled(3.0)))
    monkeypatch.setenv("TELETOUCH_CHECK_READ_TIMEOUT_S", str(scaled(0.5)))
    monkeypatch.setenv("TELETOUCH_CHECK_MOVE_TIMEOUT_S", str(scaled(5.0)))
    monkeypatch.setenv("TELETOUCH_CHECK_RATE_WINDOW_S", "0.3")


def test_sim_arm_and_sensor_pass_with_json(check_env: None,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["check", "remote", "--arm", "sim", "--sensor", "sim", "--move",
                 "--calibration", str(SIM_CALIBRATION), "--json"])
    report: dict[str, Any] = json.loads(capsys.readouterr().out)
    assert code == 0, report
    assert report["station"] == "remote" and report["ok"] is True
    assert set(report["devices"]) == {"arm", "sensor"}
    arm = report["devices"]["arm"]["figures"]
    assert arm["status"] in ("ok", "halted") and len(arm["position_mm"]) == 3
    assert arm["move_up_s"] > 0 and arm["move_back_s"] > 0
    sensor = report["devices"]["sensor"]["figures"]
    assert sensor["frame_hw"] == [240, 320] and sensor["dtype"] == "uint8"
    assert sensor["channels"] == 3 and sensor["frame_rate_hz"] >= 10.0
    assert sensor["calibration_hw"] == [240, 320]


def test_missing_camera_index_fails_naming_it(check_env: None,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["check", "remote", "--arm", "sim", "--sensor", "7"])
    out = capsys.readouterr().out
    assert code == 1
    fails = [line for line in out.splitlines() if line.startswith("  FAIL")]
    assert len(fails) == 1
    assert "sensor (7)" in fails[0] and "could not open" in fails[0]
    assert "camera 7" in fails[0]


def test_calibration_for_another_pitch_is_refused(tmp_path: Path,
                                                  settings: CheckSettings) -> None:
    with np.load(SIM_CALIBRATION) as data:
        arrays = {key: data[key] for key in data.files}
    arrays["mm_per_px"] = np.array(0.05)
    other = tmp_path / "other_pitch.npz"
    np.savez(other, **arrays)
    result = check_sensor("sim", settings, calibration=other)
    assert not result.ok
    assert result.message.startswith("bad setting") and "mm/px" in result.message
    assert result.figures["calibration_mm_per_px"] == pytest.approx(0.05)


def test_arm_never_moves_unless_asked_and_is_halted_on_release(
        settings: CheckSettings) -> None:
    RecordingArm.moves, RecordingArm.stops = [], 0
    still = check_arm(RECORDING_ARM, settings)
    assert still.ok, still.message
    assert RecordingArm.moves == []
    assert RecordingArm.stops >= 1  # disconnect halts

    RecordingArm.moves, RecordingArm.stops = [], 0
    moved = check_arm(RECORDING_ARM, settings, move=True)
    assert moved.ok, moved.message
    start = tuple(moved.figures["position_mm"])
    assert len(RecordingArm.moves) == 2
    up, back = RecordingArm.moves
    assert up[2] == pytest.approx(start[2] + settings.move_mm)
    assert back == pytest.approx(start, abs=1e-3)


def test_unknown_or_uninstalled_arm_fails_with_one_line(settings: CheckSettings) -> None:
    unknown = check_arm("no-such-arm", settings)
    assert not unknown.ok and unknown.message.startswith("bad setting")
    if importlib.util.find_spec("franky") is None:
        franka = check_arm("franka", settings)
        assert not franka.ok
        assert franka.message.startswith("backend not installed")
