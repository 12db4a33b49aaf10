"""Every display backend through the same calls (polymetis habit): CAN FD + emulator,
serial + emulator. The emulator runs the real plant in real time on the other end of the link.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from local_site.devices import open_display
from local_site.display.base import ArrayTacDisplay, PinFeedback
from shared.errors import DeviceNotConnectedError, InputDataError
from tests.support import scaled

BACKENDS = ["sim", "sim-serial"]


@pytest.fixture(params=BACKENDS)
def display(request: pytest.FixtureRequest) -> Iterator[ArrayTacDisplay]:
    # The board's link-loss watchdog is a product timeout under test: scaled, so a loaded
    # test thread that feeds it a little late does not trip it.
    dev = open_display(request.param, keepalive_interval_s=0.02, watchdog_ms=round(scaled(100)),
                       connect_timeout_s=scaled(3.0))
    yield dev
    dev.disconnect()


def _wait_for(display: ArrayTacDisplay, predicate: Callable[[PinFeedback], bool],
              timeout_s: float, *,
              command: tuple[np.ndarray | float, float, float] | None = None) -> PinFeedback:
    """Poll feedback (commanding ``command`` at ~500 Hz meanwhile) until ``predicate``."""
    deadline = time.monotonic() + scaled(timeout_s)
    fb = display.read_feedback(scaled(1.0))
    while not predicate(fb):
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met; last feedback {fb}")
        if command is not None:
            display.send_command(*command)
        time.sleep(0.002)
        fb = display.read_feedback(scaled(1.0))
    return fb


def test_same_calls_on_every_backend(display: ArrayTacDisplay) -> None:
    # 1. a shape: pins follow the command (closed loop, zero steady-state error)
    target = np.linspace(1.0, 4.0, 16).reshape(4, 4)
    applied = display.send_command(target, 1.0, 0.0)
    np.testing.assert_allclose(applied.height_mm, target.reshape(16), atol=0.001)
    fb = _wait_for(display, lambda f: np.max(np.abs(f.position_mm - applied.height_mm)) < 0.03,
                   1.5, command=(target, 1.0, 0.0))
    assert not fb.safe_state
    # 2. unchanged commands at 1 kHz are mostly skipped, keepalives keep the board fed
    before = display.stats()
    for _ in range(100):
        display.send_command(target, 1.0, 0.0)
        time.sleep(0.001)
    after = display.stats()
    assert after.skipped_unchanged - before.skipped_unchanged >= 70
    assert after.keepalives > before.keepalives
    assert not display.read_feedback(scaled(0.5)).safe_state
    # 3. NaN touches nothing
    sent = after.frames_sent
    with pytest.raises(InputDataError):
        display.send_command(np.full(16, np.nan))
    assert display.stats().frames_sent == sent
    # 4. safe state flat: the pins retract
    display.safe_state("flat")
    fb = _wait_for(display, lambda f: f.safe_state and f.position_mm.max() < 0.05, 1.5)
    assert not fb.watchdog_tripped


def test_link_loss_watchdog_parks_the_pins(display: ArrayTacDisplay) -> None:
    display.send_command(3.0)
    _wait_for(display, lambda f: abs(f.position_mm.mean() - 3.0) < 0.05, 1.5,
              command=(3.0, 1.0, 0.0))
    # the application stops commanding: no keepalive reaches the board for > watchdog_ms
    fb = _wait_for(display, lambda f: f.safe_state and f.watchdog_tripped, 1.0)
    assert fb.watchdog_trips >= 1
    fb = _wait_for(display, lambda f: f.position_mm.max() < 0.05, 1.5)
    # link back: commanding again leaves the safe state even with an unchanged command; the
    # driver has read the trip, so the command carries RESUME (the board's latch)
    assert display.send_command(3.0).sent
    assert display.stats().resumes == 1
    _wait_for(display, lambda f: not f.safe_state, 1.0)


def test_disconnect_then_reconnect(display: ArrayTacDisplay) -> None:
    display.disconnect()
    with pytest.raises(DeviceNotConnectedError):
        display.send_command(1.0)
    display.connect()
    assert display.send_command(1.0).sent
    assert display.read_feedback(scaled(1.0)).position_mm.shape == (16,)
