"""The device layer: every kind's simulated backend through the same lifecycle calls
(polymetis habit), the one backend loader and its errors, entry points, the reader thread.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from importlib.metadata import EntryPoint
from typing import Any

import pytest

import shared.devices.registry as registry
from local_site.devices import open_display, open_platform, parse_display_spec
from local_site.display.sim import SimCanArrayTacDisplay
from local_site.platform.sim import SimulatedPlatform
from remote_site.arm.registry import open_arm
from remote_site.arm.sim import SimArm, SimArmConfig
from remote_site.sensor.registry import open_sensor
from remote_site.sensor.simulator import SimulatedSensor
from shared.devices import Device, ReaderThread, backend_names, load_backend
from shared.errors import (
    ConfigError,
    DeviceInitError,
    DeviceNotConnectedError,
    DeviceOperationError,
    DeviceTimeoutError,
    TeleTouchError,
)
from tests.support import scaled


@dataclass(frozen=True)
class KindCase:
    """One device kind's simulated backend and one operation that needs a connection."""

    kind: str
    name: str
    options: Callable[[], dict[str, Any]]
    operate: Callable[[Any], object]


CASES = [
    KindCase("platform", "sim", lambda: {"motion": "hold", "connect_timeout_s": scaled(3.0)},
             lambda dev: dev.read_state(scaled(1.0))),
    KindCase("display", "sim", lambda: {"connect_timeout_s": scaled(3.0)},
             lambda dev: dev.read_feedback(scaled(1.0))),
    KindCase("arm", "sim", lambda: {"config": SimArmConfig(realtime=False)},
             lambda dev: dev.state()),
    KindCase("sensor", "sim", dict, lambda dev: dev.read_latest(max_age_ms=1000.0)),
]
KINDS = [case.kind for case in CASES]


def _device_threads() -> set[threading.Thread]:
    return {t for t in threading.enumerate() if t.is_alive()}


@pytest.mark.parametrize("case", CASES, ids=KINDS)
def test_every_kind_follows_the_same_lifecycle(case: KindCase) -> None:
    cls = load_backend(case.kind, case.name)
    device = cls(**case.options())
    assert isinstance(device, Device)
    threads_before = _device_threads()
    assert not device.is_connected
    with pytest.raises(DeviceNotConnectedError):
        case.operate(device)

    device.connect()
    try:
        assert device.is_connected
        device.connect()  # idempotent on a healthy connection
        assert device.is_connected
        case.operate(device)
    finally:
        device.disconnect()
    assert not device.is_connected
    device.disconnect()  # idempotent
    assert not device.is_connected
    with pytest.raises(DeviceNotConnectedError):
        case.operate(device)

    with device as same:  # reconnect through the context manager
        assert same is device
        assert device.is_connected
        case.operate(device)
    assert not device.is_connected
    device.disconnect()

    leaked = [t for t in _device_threads() - threads_before if t.is_alive()]
    assert leaked == [], f"{case.kind} backend left threads running: {leaked}"


# --------------------------------------------------------------------------- loader


@pytest.mark.parametrize("kind", KINDS)
def test_unknown_name_lists_the_known_ones(kind: str) -> None:
    with pytest.raises(ConfigError, match="known") as info:
        load_backend(kind, "no-such-backend")
    assert "'sim'" in str(info.value)
    assert "sim" in backend_names(kind)


@pytest.mark.parametrize("kind", KINDS)
def test_missing_module_is_an_init_error_naming_it(kind: str) -> None:
    with pytest.raises(DeviceInitError, match="no_such_module_xyz"):
        load_backend(kind, "no_such_module_xyz.drivers:Driver")


@pytest.mark.parametrize("kind", KINDS)
def test_not_a_subclass_or_missing_class_is_a_config_error(kind: str) -> None:
    with pytest.raises(ConfigError, match="not a"):
        load_backend(kind, "shared.errors:ConfigError")
    with pytest.raises(ConfigError, match="does not exist"):
        load_backend(kind, "shared.errors:NoSuchClass")


def test_a_backend_of_another_kind_is_refused() -> None:
    with pytest.raises(ConfigError, match="TactileSensor"):
        load_backend("sensor", "remote_site.arm.sim:SimArm")
    assert load_backend("arm", "remote_site.arm.sim:SimArm") is SimArm


def test_unknown_kind() -> None:
    with pytest.raises(ConfigError, match="device kind"):
        load_backend("toaster", "sim")


# --------------------------------------------------------------------------- entry points


class LabPlatform(SimulatedPlatform):
    """A lab's own platform, shipped in another package."""


class LabDisplay(SimCanArrayTacDisplay):
    """A lab's own display."""


class LabArm(SimArm):
    """A lab's own arm."""


class LabSensor(SimulatedSensor):
    """A lab's own sensor."""


_LAB_BACKENDS = {"platform": LabPlatform, "display": LabDisplay, "arm": LabArm,
                 "sensor": LabSensor}


@pytest.fixture
def lab_entry_points(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Pretend an installed package declares ``lab-<kind>`` in every ``teletouch.<kind>``."""
    def fake_entry_points(*, group: str) -> list[EntryPoint]:
        kind = group.removeprefix("teletouch.")
        cls = _LAB_BACKENDS.get(kind)
        if not group.startswith("teletouch.") or cls is None:
            return []
        return [EntryPoint(name=f"lab-{kind}", value=f"{__name__}:{cls.__name__}",
                           group=group)]

    monkeypatch.setattr(registry, "entry_points", fake_entry_points)
    yield


@pytest.mark.usefixtures("lab_entry_points")
def test_entry_point_backends_open_by_name() -> None:
    for kind, cls in _LAB_BACKENDS.items():
        assert f"lab-{kind}" in backend_names(kind)
        assert load_backend(kind, f"lab-{kind}") is cls
    assert parse_display_spec("lab-display") == ("lab-display", {})
    platform = open_platform("lab-platform", connect=False)
    display = open_display("lab-display", connect=False)
    arm = open_arm("lab-arm", config=SimArmConfig(realtime=False))
    sensor = open_sensor("lab-sensor")
    assert (type(platform), type(display), type(arm), type(sensor)) == \
        (LabPlatform, LabDisplay, LabArm, LabSensor)
    with sensor:
        assert sensor.read_latest(max_age_ms=1000.0).rgb.shape == (*sensor.shape_hw, 3)


@pytest.mark.usefixtures("lab_entry_points")
def test_builtin_names_win_over_entry_points() -> None:
    assert load_backend("arm", "sim") is SimArm


def test_class_paths_are_specs_too() -> None:
    assert isinstance(open_sensor(f"{__name__}:LabSensor"), LabSensor)
    assert isinstance(open_platform(f"{__name__}:LabPlatform", connect=False), LabPlatform)


# --------------------------------------------------------------------------- the base


class FakeDevice(Device):
    """A device whose hooks do what the test says."""

    def __init__(self, connect_error: BaseException | None = None,
                 ready_error: BaseException | None = None,
                 close_error: BaseException | None = None) -> None:
        super().__init__()
        self.connect_error = connect_error
        self.ready_error = ready_error
        self.close_error = close_error
        self.opened = 0
        self.closed = 0
        self.healthy = True

    def _connect(self) -> None:
        if self.connect_error is not None:
            raise self.connect_error
        self.opened += 1

    def _after_connect(self) -> None:
        if self.ready_error is not None:
            raise self.ready_error

    def _is_healthy(self) -> bool:
        return self.healthy

    def _disconnect(self) -> None:
        self.closed += 1
        if self.close_error is not None:
            raise self.close_error

    def operate(self, error: BaseException) -> None:
        self._require_connected()
        with self._operation("poke"):
            raise error


def test_vendor_error_on_connect_is_an_init_error_with_its_cause() -> None:
    cause = OSError("no such device")
    device = FakeDevice(connect_error=cause)
    with pytest.raises(DeviceInitError, match="no such device") as info:
        device.connect()
    assert info.value.__cause__ is cause
    assert not device.is_connected and device.closed == 0


def test_project_errors_pass_through_connect() -> None:
    device = FakeDevice(connect_error=DeviceTimeoutError("no first frame"))
    with pytest.raises(DeviceTimeoutError):
        device.connect()


def test_failure_while_getting_ready_disconnects() -> None:
    device = FakeDevice(ready_error=DeviceInitError("silent board"))
    with pytest.raises(DeviceInitError, match="silent board"):
        device.connect()
    assert not device.is_connected
    assert (device.opened, device.closed) == (1, 1)


def test_a_broken_link_is_reopened_by_connect() -> None:
    device = FakeDevice()
    device.connect()
    device.connect()
    assert (device.opened, device.closed) == (1, 0)
    device.healthy = False
    device.connect()
    assert (device.opened, device.closed) == (2, 1)
    device.disconnect()


@pytest.mark.parametrize(("raised", "expected"), [
    (OSError("bus off"), DeviceOperationError),
    (TimeoutError("no answer"), DeviceTimeoutError),
    (ConfigError("bad value"), ConfigError),
])
def test_operation_errors_by_phase(raised: BaseException,
                                   expected: type[TeleTouchError]) -> None:
    device = FakeDevice()
    with pytest.raises(DeviceNotConnectedError):
        device.operate(raised)
    with device, pytest.raises(expected) as info:
        device.operate(raised)
    if expected is not type(raised):
        assert info.value.__cause__ is raised


def test_vendor_error_on_disconnect_still_disconnects() -> None:
    device = FakeDevice(close_error=OSError("already gone"))
    device.connect()
    with pytest.raises(DeviceOperationError, match="already gone"):
        device.disconnect()
    assert not device.is_connected
    device.disconnect()  # idempotent: nothing left to close
    assert device.closed == 1


# --------------------------------------------------------------------------- reader thread


def test_reader_thread_runs_until_stopped() -> None:
    reads: list[int] = []

    def read_once() -> bool:
        reads.append(1)
        time.sleep(0.001)
        return True

    reader = ReaderThread("test-reader", read_once)
    reader.start()
    deadline = time.monotonic() + scaled(2.0)
    while not reads and time.monotonic() < deadline:
        time.sleep(0.005)
    assert reader.is_alive and reads
    assert reader.stop(timeout_s=scaled(2.0))
    assert reader.stopping and not reader.is_alive
    assert "test-reader" not in {t.name for t in threading.enumerate()}


def test_reader_thread_ends_when_the_read_fails() -> None:
    reader = ReaderThread("test-reader-once", lambda: False)
    reader.start()
    assert reader.join(timeout_s=scaled(2.0))
    assert not reader.stopping
