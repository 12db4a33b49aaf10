"""The emulated board behind a TCP port (``TcpFirmwareTransport``): the board's side alone
over real sockets, then the ordinary serial driver reaching the emulator through a pyserial
``socket://`` URL (what ``teletouch board`` and ``--display socket://...`` do)."""

from __future__ import annotations

import contextlib
import socket
import time
from collections.abc import Iterator

import numpy as np
import pytest

from local_site.arraytac_sim.plant import ArrayTacPlant
from local_site.devices import open_display
from local_site.display import frames as fr
from local_site.display.base import ArrayTacDisplay
from local_site.display.emulator import FirmwareEmulator, TcpFirmwareTransport
from local_site.display.firmware import ArrayTacFirmware
from local_site.display.serial_framing import LinkFrameDecoder, encode_link_frame
from shared.errors import DeviceInitError
from tests.support import scaled, wait_until


def _command(seq: int, height_mm: float = 2.0, watchdog_ms: int = 100) -> bytes:
    return fr.encode_command(fr.CommandFrame(
        seq=seq, flags=0, height_codes=np.full(16, round(height_mm / fr.HEIGHT_LSB_MM),
                                               np.uint16),
        k_codes=np.full(16, 250, np.uint16), f_codes=np.zeros(16, np.uint16),
        watchdog_ms=watchdog_ms))


@pytest.fixture
def transport() -> Iterator[TcpFirmwareTransport]:
    t = TcpFirmwareTransport("127.0.0.1", 0)
    yield t
    t.close()


def _connect(t: TcpFirmwareTransport) -> socket.socket:
    client = socket.create_connection(t.address, timeout=scaled(2.0))
    wait_until(lambda: _pump(t) or t.connected, 2.0, "the board to accept")
    return client


def _pump(t: TcpFirmwareTransport, timeout_s: float = 0.01) -> list[tuple[int, bytes]]:
    """Run the board's receive side once and drain what it decoded."""
    out = []
    item = t.recv(timeout_s)
    while item is not None:
        out.append(item)
        item = t.recv(0.0)
    return out


def _recv_frames(t: TcpFirmwareTransport, n: int, timeout_s: float = 2.0) \
        -> list[tuple[int, bytes]]:
    got: list[tuple[int, bytes]] = []

    def enough() -> bool:
        got.extend(_pump(t))
        return len(got) >= n

    wait_until(enough, timeout_s, f"{n} frames")
    return got


def test_url_names_the_bound_port_and_a_taken_port_is_a_clear_error(
        transport: TcpFirmwareTransport) -> None:
    host, port = transport.address
    assert host == "127.0.0.1" and port > 0
    assert transport.url == f"socket://127.0.0.1:{port}"
    with pytest.raises(DeviceInitError, match=f"cannot listen on 127.0.0.1:{port}"):
        TcpFirmwareTransport("127.0.0.1", port)


def test_bad_bytes_are_counted_and_the_next_good_frame_still_arrives(
        transport: TcpFirmwareTransport) -> None:
    client = _connect(transport)
    good = encode_link_frame(fr.ARB_ID_COMMAND, _command(7))
    # line noise, a frame whose COBS code runs past its end, a body too long, then a good one
    client.sendall(b"\x05\x01\x00" + b"\xff" * 300 + b"\x00" + bytes([3, 1]) + b"\x00" + good)
    frames = _recv_frames(transport, 1)
    assert frames == [(fr.ARB_ID_COMMAND, _command(7))]
    stats = transport.stream_stats()
    assert stats.frames_ok == 1 and stats.bad_frames >= 2 and stats.garbage_bytes > 300
    client.close()


def test_a_host_that_disconnects_leaves_the_board_listening_and_a_new_one_is_served(
        transport: TcpFirmwareTransport) -> None:
    first = _connect(transport)
    good = encode_link_frame(fr.ARB_ID_COMMAND, _command(1))
    first.sendall(good[:10])  # half a frame, then the host goes away
    first.close()
    wait_until(lambda: _pump(transport) == [] and not transport.connected, 2.0,
               "the board to notice the disconnect")
    assert transport.disconnects == 1
    transport.send(fr.ARB_ID_FEEDBACK, b"x" * 10)  # nobody listens: dropped, no error
    assert transport.dropped == 1
    second = _connect(transport)
    # the new stream starts clean: the old half frame does not join the new bytes
    second.sendall(good[10:] + encode_link_frame(fr.ARB_ID_COMMAND, _command(2)))
    frames = _recv_frames(transport, 1)
    assert frames == [(fr.ARB_ID_COMMAND, _command(2))]
    assert transport.connects == 2
    # and the board's frames reach the new host
    transport.send(fr.ARB_ID_FEEDBACK, b"\x01\x00\x02")
    second.settimeout(scaled(2.0))
    decoder = LinkFrameDecoder()
    got: list[tuple[int, bytes]] = []
    while not got:
        got = decoder.feed(second.recv(4096))
    assert got == [(fr.ARB_ID_FEEDBACK, b"\x01\x00\x02")]
    second.close()


def test_a_new_connection_replaces_a_half_open_one(transport: TcpFirmwareTransport) -> None:
    stale = _connect(transport)
    fresh = socket.create_connection(transport.address, timeout=scaled(2.0))
    wait_until(lambda: _pump(transport) == [] and transport.replaced == 1, 2.0,
               "the second connection to replace the first")
    stale.settimeout(scaled(2.0))
    assert stale.recv(100) == b""  # the board closed the old one
    fresh.sendall(encode_link_frame(fr.ARB_ID_COMMAND, _command(3)))
    assert _recv_frames(transport, 1) == [(fr.ARB_ID_COMMAND, _command(3))]
    fresh.close()
    stale.close()


def test_a_host_that_does_not_read_makes_the_board_drop_whole_frames(
        transport: TcpFirmwareTransport) -> None:
    client = socket.socket()
    client.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # before the window opens
    client.settimeout(scaled(2.0))
    client.connect(transport.address)
    wait_until(lambda: _pump(transport) == [] and transport.connected, 2.0, "the accept")
    payload = bytes(range(1, 61))
    sent = 0
    while transport.dropped == 0:
        transport.send(fr.ARB_ID_FEEDBACK, payload)
        sent += 1
        assert sent < 5_000, "the board queued over 300 kB for a host that does not read"
    # the host reads everything now: only whole, valid frames, in order, nothing torn
    client.settimeout(0.5)
    decoder = LinkFrameDecoder()
    frames: list[tuple[int, bytes]] = []
    deadline = time.monotonic() + scaled(5.0)
    while len(frames) < sent - transport.dropped and time.monotonic() < deadline:
        _pump(transport, 0.0)  # flushes what the board still holds
        with contextlib.suppress(TimeoutError):
            frames += decoder.feed(client.recv(65536))
    assert decoder.stats.bad_frames == 0 and decoder.stats.garbage_bytes == 0
    assert frames and all(f == (fr.ARB_ID_FEEDBACK, payload) for f in frames)
    assert len(frames) == sent - transport.dropped
    client.close()


@pytest.fixture
def board() -> Iterator[FirmwareEmulator]:
    firmware = ArrayTacFirmware(ArrayTacPlant(), default_watchdog_ms=100)
    emulator = FirmwareEmulator(firmware, TcpFirmwareTransport("127.0.0.1", 0))
    emulator.start()
    yield emulator
    emulator.stop()


def test_the_serial_driver_reaches_the_board_through_a_socket_url_and_reconnects(
        board: FirmwareEmulator) -> None:
    transport = board.transport
    assert isinstance(transport, TcpFirmwareTransport)
    # the watchdog longer than a stall of this process between two commands (100 ms tripped
    # it early, and the trip awaited below was a second one)
    display = open_display(transport.url, keepalive_interval_s=0.02,
                           watchdog_ms=round(scaled(500)), connect_timeout_s=scaled(3.0))
    try:
        deadline = time.monotonic() + scaled(3.0)
        while abs(display.read_feedback(scaled(1.0)).position_mm.mean() - 3.0) > 0.05:
            assert time.monotonic() < deadline, "the pins never reached 3 mm"
            display.send_command(3.0)
            time.sleep(0.005)
        # the driver stops commanding (a frozen station): the board's own watchdog parks
        wait_until(lambda: display.read_feedback(scaled(1.0)).watchdog_tripped, 2.0,
                   "the board's watchdog")
        assert board.firmware.watchdog_trips == 1 and board.firmware.safe_state
        # the station restarts: a new connection, commands again, the board never stopped
        display.disconnect()
        display.connect()
        display.send_command(1.0)
        wait_until(lambda: not display.read_feedback(scaled(1.0)).safe_state, 2.0,
                   "the board to leave the safe state")
        assert transport.connects == 2 and board.error is None
    finally:
        display.disconnect()
    # a garbage-spewing peer neither kills the board nor moves the pins
    applied = board.firmware.commands_applied
    with socket.create_connection(transport.address, timeout=scaled(2.0)) as peer:
        peer.sendall(bytes(range(1, 256)) * 64 + b"\x00" * 10)
        wait_until(lambda: transport.stream_stats().garbage_bytes > 0, 2.0, "garbage counted")
    assert board.firmware.commands_applied == applied and board.error is None


@pytest.fixture
def commanding(board: FirmwareEmulator) -> Iterator[ArrayTacDisplay]:
    """The serial driver on the board's socket:// URL, its first command applied."""
    transport = board.transport
    assert isinstance(transport, TcpFirmwareTransport)
    display = open_display(transport.url, keepalive_interval_s=0.02,
                           watchdog_ms=round(scaled(100)), connect_timeout_s=scaled(3.0))
    try:
        display.send_command(3.0)
        wait_until(lambda: board.firmware.commands_applied >= 1, 2.0, "the first command")
        yield display
    finally:
        display.disconnect()


def _assert_held_command_refused(fw: ArrayTacFirmware, applied_before: int,
                                 held_seq: int) -> None:
    """The board took the held command (applied or refused) and the pins did not move."""
    wait_until(lambda: fw.commands_applied > applied_before or fw.commands_refused_latched > 0,
               2.0, "the board to take the held command")
    assert fw.seq_echo != held_seq and fw.safe_state, "the held command moved the pins"
    assert fw.targets_mm.max() == 0.0 and fw.commands_refused_latched == 1


def test_a_command_held_by_a_frozen_host_cannot_undo_the_boards_park(
        board: FirmwareEmulator, commanding: ArrayTacDisplay,
        monkeypatch: pytest.MonkeyPatch) -> None:
    # The station checks a command's deadline, then freezes (SIGSTOP, a VM pause) before the
    # write; the board's watchdog parks the pins meanwhile. When the station wakes, the held
    # command must not put its old touch on the pins: the board refuses it (no RESUME), and
    # only the driver's next command, decided after it has read the trip, leaves the park.
    display, fw = commanding, board.firmware
    write = display._send_frame

    def frozen_write(arb_id: int, payload: bytes) -> None:
        # the freeze lands between the deadline check and the write
        wait_until(lambda: fw.watchdog_tripped, 3.0, "the board's watchdog")
        write(arb_id, payload)

    monkeypatch.setattr(display, "_send_frame", frozen_write)
    applied = fw.commands_applied
    held = display.send_command(4.0, not_after_s=time.monotonic() + 60.0)
    monkeypatch.setattr(display, "_send_frame", write)
    _assert_held_command_refused(fw, applied, held.seq)
    # the driver reads the trip, and its next command carries RESUME
    wait_until(lambda: display.read_feedback(scaled(1.0)).watchdog_tripped, 2.0,
               "the driver to read the trip")
    fresh = display.send_command(1.0)
    assert fresh.sent and display.stats().resumes == 1
    wait_until(lambda: fw.seq_echo == fresh.seq, 2.0, "the fresh command")
    assert not fw.safe_state and not fw.watchdog_tripped and board.error is None


def test_the_device_check_works_on_a_board_its_previous_run_left_latched(
        board: FirmwareEmulator) -> None:
    # `teletouch check` trips the board's watchdog on purpose; the next check (or station)
    # finds the board latched, and its zero command, sent with RESUME, is still applied
    from local_site.check import check_display
    from shared.device_check import CheckSettings

    transport = board.transport
    assert isinstance(transport, TcpFirmwareTransport)
    settings = CheckSettings(connect_timeout_s=scaled(3.0), read_timeout_s=scaled(1.0))
    first = check_display(transport.url, settings)
    assert first.ok, first.message
    assert first.figures["watchdog_latched_at_start"] is False
    assert board.firmware.watchdog_tripped
    second = check_display(transport.url, settings)
    assert second.ok, second.message
    assert second.figures["watchdog_latched_at_start"] is True
    assert second.figures["zero_command_echoed"] and board.firmware.commands_refused_latched == 0


def test_a_freeze_right_after_the_deadline_check_cannot_borrow_a_resume_read_later(
        board: FirmwareEmulator, commanding: ArrayTacDisplay,
        monkeypatch: pytest.MonkeyPatch) -> None:
    # The freeze lands just after the deadline check; when the station wakes, its reader
    # thread reads the trip before the held command is built. RESUME must follow what the
    # driver knew before the check, or the held command would leave the park.
    from local_site.display import base

    display, fw = commanding, board.firmware
    real = base.monotonic_s
    calls = 0

    def frozen_clock() -> float:
        nonlocal calls
        calls += 1
        t = real()
        if calls == 2:  # send_command's deadline check read the clock, then froze
            wait_until(lambda: fw.watchdog_tripped, 3.0, "the board's watchdog")
            wait_until(lambda: (fb := display.latest_feedback()) is not None
                       and fb.watchdog_tripped, 3.0, "the driver to read the trip")
        return t

    monkeypatch.setattr(base, "monotonic_s", frozen_clock)
    applied = fw.commands_applied
    held = display.send_command(4.0, not_after_s=real() + 60.0)
    monkeypatch.setattr(base, "monotonic_s", real)
    _assert_held_command_refused(fw, applied, held.seq)
    assert display.stats().resumes == 0
