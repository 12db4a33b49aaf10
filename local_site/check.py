"""Probes of the local station's devices, for ``teletouch check local``.

Each probe opens one device through the station's registry (:mod:`local_site.devices`),
measures what a session relies on, and always closes it again (context manager), within
bounded times (:class:`~shared.device_check.CheckSettings`):

* the XYZ encoder board: opens, sample rate over ``rate_window_s`` (from the board's sample
  numbers, so samples the host skipped still count), link errors, position and counts;
  with ``push_s`` the operator is asked to push the platform and the counts must move;
* the ArrayTac drive board: opens, feedback rate, the safe state is applied, a zero command
  (all pins retracted) is echoed back, and the link-loss watchdog trips once commands stop,
  after the timeout the command asked for: the trip time is measured on the board's clock
  (``board_t_us`` of the feedback, wrap-aware) from the feedback echoing the command to the
  first one showing the trip, and a board still untripped more than two feedback periods
  past the timeout, or provably tripped more than two periods before it, fails (a board
  that ignores the command's timeout would otherwise pass).

A probe returns a :class:`~shared.device_check.DeviceCheck`; device errors become its one-line
message (:func:`shared.device_check.failure_line`), never an exception.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from local_site.devices import open_display, open_platform
from shared.device_check import CheckReport, CheckSettings, DeviceCheck, failed_check
from shared.errors import DeviceOperationError, DeviceTimeoutError, TeleTouchError
from shared.timebase import monotonic_s, now_us

__all__ = ["MIN_PLATFORM_RATE_HZ", "check_display", "check_local", "check_platform"]

log = logging.getLogger(__name__)

#: the station's display loop needs platform samples at least this often
MIN_PLATFORM_RATE_HZ = 500.0
#: counts an axis must move during the push window to count as moved
MIN_PUSH_COUNTS = 2


def check_platform(spec: str, settings: CheckSettings | None = None, *, push_s: float = 0.0,
                   notify: Callable[[str], None] | None = None,
                   **options: Any) -> DeviceCheck:
    """Probe the XYZ encoder board named by ``spec``.

    Args:
        spec: platform spec (``sim``, ``/dev/ttyUSB0``, ...; see :mod:`local_site.devices`).
        settings: time bounds (defaults: :class:`CheckSettings`).
        push_s: if > 0, ask the operator (through ``notify``) to push the platform and check
            that the encoder counts move during this many seconds.
        notify: where the push request goes (the CLI prints it); None: not shown.
        **options: backend keyword arguments (``baudrate``, ``geometry``, ...).

    Returns:
        The result; ``ok`` when the board opened, sampled at >= 500 Hz and (with ``push_s``)
        its counts moved.
    """
    cfg = settings or CheckSettings()
    figures: dict[str, Any] = {}
    try:
        platform = open_platform(spec, connect=False,
                                 connect_timeout_s=cfg.connect_timeout_s, **options)
        with platform:
            first = platform.read_state(cfg.read_timeout_s)
            info = platform.board_info
            if info is not None:
                figures["board_sample_rate_hz"] = info.sample_rate_hz
                figures["board_firmware"] = info.firmware_version
            start_s, last = monotonic_s(), first
            while monotonic_s() - start_s < cfg.rate_window_s:
                last = platform.read_state(cfg.read_timeout_s)
            elapsed_s = monotonic_s() - start_s
            rate_hz = (last.seq - first.seq) / elapsed_s
            stats = platform.stats()
            figures.update(sample_rate_hz=round(rate_hz, 1),
                           samples_missed=stats.samples_missed, crc_errors=stats.crc_errors,
                           position_mm=[round(v, 4) for v in last.position_mm],
                           counts=list(platform.geometry.mm_to_counts(last.position_mm)))
            if rate_hz < MIN_PLATFORM_RATE_HZ:
                return DeviceCheck("platform", spec, False,
                                   f"opened but too slow: {rate_hz:.0f} samples/s, the station "
                                   f"needs >= {MIN_PLATFORM_RATE_HZ:.0f}; check the board's "
                                   "rate setting and the USB link", figures)
            if push_s > 0:
                moved = _counts_moved(platform, push_s, cfg.read_timeout_s, notify)
                figures["push_counts_moved"] = moved
                if max(moved) < MIN_PUSH_COUNTS:
                    return DeviceCheck("platform", spec, False,
                                       f"opened, but no encoder count moved while the platform "
                                       f"was to be pushed for {push_s:g} s; check the encoder "
                                       "cables and the board's axis inputs", figures)
    except TeleTouchError as err:
        return failed_check("platform", spec, err, figures)
    return DeviceCheck("platform", spec, True,
                       f"{figures['sample_rate_hz']:.0f} samples/s, at "
                       f"{tuple(figures['position_mm'])} mm"
                       + (", counts moved when pushed" if push_s > 0 else ""), figures)


def _counts_moved(platform: Any, push_s: float, read_timeout_s: float,
                  notify: Callable[[str], None] | None) -> list[int]:
    """Range of each axis's counts while the operator pushes, over ``push_s`` seconds."""
    if notify is not None:
        notify(f"push the platform along each axis now ({push_s:g} s)...")
    geometry = platform.geometry
    start = geometry.mm_to_counts(platform.read_state(read_timeout_s).position_mm)
    low, high = list(start), list(start)
    deadline = monotonic_s() + push_s
    while monotonic_s() < deadline:
        counts = geometry.mm_to_counts(platform.read_state(read_timeout_s).position_mm)
        low = [min(a, b) for a, b in zip(low, counts, strict=True)]
        high = [max(a, b) for a, b in zip(high, counts, strict=True)]
    return [h - lo for h, lo in zip(high, low, strict=True)]


def check_display(spec: str, settings: CheckSettings | None = None, *,
                  watchdog_ms: int = 100, **options: Any) -> DeviceCheck:
    """Probe the ArrayTac drive board named by ``spec``.

    Pins only ever go to their safe state and to zero height (retracted).

    Args:
        spec: display spec (``sim``, ``can://socketcan/can0``, ...).
        settings: time bounds (defaults: :class:`CheckSettings`).
        watchdog_ms: the link-loss watchdog written into the zero command; the probe checks
            that the board trips it once commands stop, after that long (within two feedback
            periods; see :func:`_watchdog_timing`).
        **options: backend keyword arguments.

    Returns:
        The result; ``ok`` when the board opened, sent feedback, parked, applied the zero
        command and tripped its watchdog after ``watchdog_ms``. Its figures include
        ``watchdog_trip_ms`` (board clock, from the feedback echoing the zero command to
        the first feedback seen showing the trip) and ``watchdog_trip_bounds_ms`` (what the
        feedback proves about the delay from the command's application to the trip).
    """
    cfg = settings or CheckSettings()
    figures: dict[str, Any] = {"watchdog_ms": watchdog_ms}
    # the driver's keepalive must be shorter than the watchdog (this probe sends no stream
    # of commands for it to keep alive): its default, or half a shorter watchdog
    options.setdefault("keepalive_interval_s", min(0.02, watchdog_ms / 2000.0))
    try:
        display = open_display(spec, connect=False, connect_timeout_s=cfg.connect_timeout_s,
                               watchdog_ms=watchdog_ms, watchdog_mode="flat",
                               disconnect_mode="flat", **options)
        with display:
            n0, start_s = display.stats().feedback_frames, monotonic_s()
            last = display.read_feedback(cfg.read_timeout_s)
            # parked by its watchdog before this check (a station that stopped commanding
            # without a safe state): the board's latch holds the pins until a command
            # carries RESUME, which the driver sets itself (docs/arraytac_can.md)
            figures["watchdog_latched_at_start"] = last.watchdog_tripped
            while monotonic_s() - start_s < cfg.rate_window_s:
                last = display.read_feedback(cfg.read_timeout_s, newer_than_us=last.t_us)
            rate_hz = (display.stats().feedback_frames - n0) / (monotonic_s() - start_s)
            figures["feedback_rate_hz"] = round(rate_hz, 1)

            display.safe_state("flat")
            parked, _ = _wait_feedback(display, lambda fb: fb.safe_state, cfg.read_timeout_s,
                                       "the safe state")
            figures["safe_state_applied"] = parked.safe_state
            applied = display.send_command(0.0)
            echoed, before_echo = _wait_feedback(
                display, lambda fb: fb.seq_echo == applied.seq, cfg.read_timeout_s,
                f"zero command seq {applied.seq}", previous=parked)
            figures["zero_command_echoed"] = True
            figures["pin_position_max_mm"] = round(float(echoed.position_mm.max()), 4)
            if echoed.watchdog_tripped:  # read late: the echo already shows the trip
                tripped, before_trip = echoed, None
            else:
                tripped, before_trip = _wait_feedback(
                    display, lambda fb: fb.watchdog_tripped,
                    watchdog_ms / 1000.0 + cfg.read_timeout_s,
                    f"the {watchdog_ms} ms watchdog to trip", previous=echoed)
            figures["watchdog_tripped"] = tripped.watchdog_tripped
            figures["commands_rejected"] = tripped.commands_rejected
            period_ms = 1000.0 / rate_hz if rate_hz > 0 else float(watchdog_ms)
            trip_ms, low_ms, high_ms = _watchdog_timing(before_echo, echoed, before_trip,
                                                        tripped)
            figures["watchdog_trip_ms"] = round(trip_ms, 1)
            figures["watchdog_trip_bounds_ms"] = [round(low_ms, 1), round(high_ms, 1)]
            slack_ms = 2 * period_ms
            if low_ms > watchdog_ms + slack_ms:
                return DeviceCheck(
                    "display", spec, False,
                    f"watchdog trips late: asked for {watchdog_ms} ms, the board was still "
                    f"untripped {low_ms:.0f} ms after it echoed the zero command (tripped "
                    f"{trip_ms:.0f} ms after the echo); check the firmware's watchdog",
                    figures)
            if high_ms < watchdog_ms - slack_ms:
                return DeviceCheck(
                    "display", spec, False,
                    f"watchdog trips early: asked for {watchdog_ms} ms, the board tripped at "
                    f"most {high_ms:.0f} ms after it applied the zero command; check the "
                    "firmware's watchdog", figures)
    except TeleTouchError as err:
        return failed_check("display", spec, err, figures)
    return DeviceCheck("display", spec, True,
                       f"{figures['feedback_rate_hz']:.0f} feedback frames/s, safe state and a "
                       f"zero command applied, the {watchdog_ms} ms watchdog tripped "
                       f"{figures['watchdog_trip_ms']:.0f} ms after the echo (board clock)",
                       figures)


def _board_dt_ms(later: Any, earlier: Any) -> float:
    """Board-clock time from ``earlier`` to ``later`` feedback, ms (uint32 us, wraps)."""
    return ((int(later.board_t_us) - int(earlier.board_t_us)) & 0xFFFFFFFF) / 1000.0


def _watchdog_timing(before_echo: Any, echoed: Any, before_trip: Any | None,
                     tripped: Any) -> tuple[float, float, float]:
    """The watchdog's trip time, from the board's clock in its feedback.

    The host reads only the latest feedback, so it may skip frames when it runs late; the
    frames it did read bracket the two instants on the board's clock: the command was
    applied after ``before_echo`` (its old ``seq_echo``) and by ``echoed``; the watchdog
    tripped after ``before_trip`` (None: not seen, the echo already showed the trip) and by
    ``tripped``. Skipped frames only widen the bracket, never move it past the truth.

    Returns:
        ``(trip_ms, low_ms, high_ms)``: ``tripped`` minus ``echoed`` (the measured time),
        and the least and the most the delay from application to trip can have been.
    """
    trip_ms = _board_dt_ms(tripped, echoed)
    low_ms = 0.0 if before_trip is None else _board_dt_ms(before_trip, echoed)
    return trip_ms, low_ms, _board_dt_ms(tripped, before_echo)


def _wait_feedback(display: Any, done: Callable[[Any], bool], timeout_s: float,
                   what: str, *, previous: Any = None) -> tuple[Any, Any]:
    """Wait for a feedback frame for which ``done`` holds.

    Returns:
        That frame, and the last frame read before it for which ``done`` did not hold
        (``previous`` when it was the first one read).

    Raises:
        DeviceOperationError: the board kept answering, but never so (within ``timeout_s``).
        DeviceTimeoutError: the board stopped answering.
    """
    deadline = monotonic_s() + timeout_s
    since_us = now_us()
    answered = False
    while True:
        remaining = deadline - monotonic_s()
        if remaining <= 0:
            if not answered:
                raise DeviceTimeoutError(f"{display.name}: no feedback while waiting for "
                                         f"{what} ({timeout_s * 1e3:.0f} ms)")
            raise DeviceOperationError(f"{display.name}: feedback never showed {what} "
                                       f"within {timeout_s * 1e3:.0f} ms")
        try:
            fb = display.read_feedback(remaining, newer_than_us=since_us)
        except DeviceTimeoutError:
            continue  # the loop reports the missing condition
        answered = True
        if done(fb):
            return fb, previous
        previous, since_us = fb, fb.t_us


def check_local(platform: str, display: str, settings: CheckSettings | None = None, *,
                push_s: float = 0.0, notify: Callable[[str], None] | None = None,
                watchdog_ms: int = 100,
                feedback_timeout_s: float | None = None) -> CheckReport:
    """Probe the local station's platform and display, one after the other.

    Args:
        platform: platform spec.
        display: display spec.
        settings: time bounds.
        push_s: see :func:`check_platform`.
        notify: see :func:`check_platform`.
        watchdog_ms: see :func:`check_display`.
        feedback_timeout_s: the display driver's silent-board limit, as the station's
            ``display_feedback_timeout_s`` (None: the driver's default).

    Returns:
        The report (``exit_code`` 0 when both passed).
    """
    options = {} if feedback_timeout_s is None else {"feedback_timeout_s": feedback_timeout_s}
    return CheckReport("local", (
        check_platform(platform, settings, push_s=push_s, notify=notify),
        check_display(display, settings, watchdog_ms=watchdog_ms, **options)))
