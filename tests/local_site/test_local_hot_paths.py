"""The local station's cheaper hot paths behave exactly as the per-sample code they replace.

- the simulated encoder board computes its frames a block at a time: the same bytes as
  :meth:`SimulatedEncoderBoard.frame` sample by sample (hypothesis, wrap-arounds included);
- ``ArrayTacDisplay.send_command`` validates and quantises the three layers as one array:
  the same wire codes, applied values, clamping flag and refusals as an independent
  per-layer reference; ``keepalive`` returns early when not due and counts as before;
- the firmware hands the targets to the plant once per tick: several commands within a tick
  leave the plant where the last one alone leaves it, and are each counted;
- the serial reader takes a burst in one wake-up (one callback), where ``read(1)`` took two;
- the platform reader's ``latest`` is the driver's newest sample, not one 5 ms old;
- the display loop thread's priority is raised for the loop and restored, or left alone
  with a log line when the OS refuses.
"""

from __future__ import annotations

import os
import socket
import threading
import tty
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from local_site.agent import LocalAgentConfig
from local_site.agent.display_loop import (
    DisplayLoop,
    opening_scheduling,
    thread_priority,
    thread_realtime,
)
from local_site.agent.platform_reader import PlatformReader
from local_site.arraytac_sim.plant import ArrayTacPlant
from local_site.devices import open_display
from local_site.display import frames as fr
from local_site.display.base import ArrayTacDisplay
from local_site.display.firmware import ArrayTacFirmware
from local_site.platform.motion import HoldMotion, RandomWalk, make_motion
from local_site.platform.motion_spec import parse_motion_spec
from local_site.platform.sim import SimulatedPlatform
from local_site.platform.sim_board import BLOCK_SAMPLES, SimulatedEncoderBoard
from local_site.render import Renderer
from local_site.scenes import TactileFrameScene
from local_site.serial_port import SerialPortReader
from shared.errors import ConfigError, InputDataError
from shared.timebase import monotonic_s, now_us
from tests.support import scaled, wait_until

# ---------------------------------------------------------------- simulated encoder board


@settings(max_examples=60, deadline=None)
@given(spec=st.sampled_from(["raster", "random:seed=3", "random:seed=11", "hold"]),
       first=st.integers(0, 200_000), count=st.integers(1, 3 * BLOCK_SAMPLES),
       initial=st.tuples(*[st.integers(-2**31, 2**31 - 1)] * 3),
       start_t=st.integers(0, 2**32 - 1), start_seq=st.integers(0, 2**32 - 1),
       rate=st.sampled_from([250.0, 1000.0, 1234.5]))
def test_block_frames_are_the_per_sample_frames(spec: str, first: int, count: int,
                                                initial: tuple[int, int, int], start_t: int,
                                                start_seq: int, rate: float) -> None:
    board = SimulatedEncoderBoard(make_motion(parse_motion_spec(spec)), lambda _d: None,
                                  sample_rate_hz=rate, initial_counts=initial,
                                  start_board_t_us=start_t, start_seq=start_seq)
    block = board.frames(first, count)
    assert block == [board.frame(first + i) for i in range(count)]


def test_board_streams_block_frames_in_order_over_a_pty() -> None:
    """End to end: the driver decodes consecutive samples at the motion's positions."""
    motion = RandomWalk(seed=5)
    platform = SimulatedPlatform(motion)
    platform.connect()
    try:
        seqs: list[int] = []
        while len(seqs) < 3 * BLOCK_SAMPLES:
            sample = platform.read_state(timeout_s=scaled(1.0))
            seqs.append(sample.seq)
            expected = platform.geometry.counts_to_mm(platform.geometry.mm_to_counts(
                motion.position_mm(sample.board_t_us * 1e-6)))
            assert np.allclose(sample.position_mm, expected, atol=1e-9)
        assert seqs == sorted(seqs) and platform.stats().samples_missed == 0
        assert platform.stats().crc_errors == 0 and platform.stats().garbage_bytes == 0
    finally:
        platform.disconnect()


# ---------------------------------------------------------------- display command path


class _CaptureDisplay(ArrayTacDisplay):
    """A display whose link is a list: every frame sent is kept."""

    def __init__(self, **kwargs: object) -> None:
        super().__init__(require_feedback=False, **kwargs)  # type: ignore[arg-type]
        self.sent: list[tuple[int, bytes]] = []

    @property
    def name(self) -> str:
        return "capture"

    def _connect(self) -> None:
        pass

    def _disconnect(self) -> None:
        pass

    def _send_frame(self, arb_id: int, payload: bytes) -> None:
        self.sent.append((arb_id, payload))


def _reference(h: Any, k: Any, f: Any) -> tuple[np.ndarray, bool]:
    """The per-layer quantisation, written independently: codes (3, 16) and clamped."""
    rows, clamped = [], False
    for value, low, high, lsb, offset in ((h, 0.0, 5.0, 1.25e-3, 0.0),
                                          (k, 0.5, 1.0, 0.002, 0.5),
                                          (f, 0.0, 1.0, 0.004, 0.0)):
        arr = np.broadcast_to(np.asarray(value, dtype=float).reshape(-1), (16,)) \
            if np.ndim(value) == 0 else np.asarray(value, dtype=float).reshape(16)
        clamped |= bool(np.any(arr < low) or np.any(arr > high))
        rows.append([round((min(max(v, low), high) - offset) / lsb) for v in arr.tolist()])
    return np.asarray(rows, dtype=np.int64), clamped


layer = st.one_of(
    st.floats(-1.0, 6.0, allow_nan=False),
    st.lists(st.floats(-1.0, 6.0, allow_nan=False), min_size=16, max_size=16)
    .map(np.asarray),
    st.lists(st.floats(-1.0, 6.0, allow_nan=False), min_size=16, max_size=16)
    .map(lambda v: np.asarray(v).reshape(4, 4)))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(h=layer, k=layer, f=layer)
def test_send_command_matches_the_per_layer_reference(h: object, k: object, f: object) -> None:
    display = _CaptureDisplay()
    display.connect()
    applied = display.send_command(h, k, f)  # type: ignore[arg-type]
    codes, clamped = _reference(h, k, f)
    assert applied.sent and applied.clamped == clamped
    ((arb_id, payload),) = display.sent
    frame = fr.decode_command(payload)
    assert arb_id == fr.ARB_ID_COMMAND
    assert frame.height_codes.tolist() == codes[0].tolist()
    assert frame.k_codes.tolist() == codes[1].tolist()
    assert frame.f_codes.tolist() == codes[2].tolist()
    assert np.array_equal(applied.height_mm, codes[0] * fr.HEIGHT_LSB_MM)
    assert np.array_equal(applied.stiffness_k, fr.K_MIN + codes[1] * fr.K_LSB)
    assert np.array_equal(applied.friction, codes[2] * fr.F_LSB)
    # the same command again: not re-sent, same applied values
    again = display.send_command(h, k, f)  # type: ignore[arg-type]
    assert not again.sent and np.array_equal(again.height_mm, applied.height_mm)
    assert len(display.sent) == 1


@pytest.mark.parametrize(("args", "message"), [
    ((np.ones(15), 1.0, 0.0), "height_mm: shape (15,)"),
    ((1.0, np.ones((2, 8)), 0.0), "stiffness_k: shape (2, 8)"),
    ((1.0, 1.0, np.ones(1)), "friction: shape (1,)"),
    ((np.r_[np.ones(15), np.nan], 1.0, 0.0), "height_mm: NaN or Inf at pin(s) [15]"),
    ((1.0, 1.0, np.r_[np.inf, np.zeros(15)]), "friction: NaN or Inf at pin(s) [0]"),
    ((1.0, "stiff", 0.0), "stiffness_k: not numeric"),
    # all three float64 arrays: the compiled pass finds the NaN, the message is the same
    ((np.ones(16), np.r_[np.nan, np.ones(15)].reshape(4, 4), np.zeros(16)),
     "stiffness_k: NaN or Inf at pin(s) [0]"),
    ((np.ones((4, 4)), np.ones(16), np.r_[np.zeros(3), -np.inf, np.zeros(12)]),
     "friction: NaN or Inf at pin(s) [3]"),
])
def test_send_command_refuses_bad_input_naming_the_layer(args: tuple[object, ...],
                                                         message: str) -> None:
    display = _CaptureDisplay()
    display.connect()
    with pytest.raises(InputDataError) as err:
        display.send_command(*args)  # type: ignore[arg-type]
    assert message in str(err.value)
    assert display.sent == [] and display.stats().rejected_inputs == 1


def test_the_send_paths_kernels_are_compiled_once_before_the_first_command() -> None:
    """Compiling inside the 1 kHz loop would stall its first command: the display loop has
    its display compile the send path's kernels (or load numba's cache) when the loop is
    built, and a display does at ``connect()`` at the latest, for the types every command,
    keepalive and (4, 4) or (16,) layer uses, the renderer's read-only ones included. Not
    when it is only built (a station whose loop runs in another process builds one to check
    its settings). Other layouts and types take the numpy path instead of compiling another
    version."""
    import subprocess
    import sys

    def signatures(steps: str, spec: str = "socket://127.0.0.1:9") -> list[str]:
        code = ("from local_site.devices import open_display; "
                "from local_site.display.base import _quantise_kernel as q; "
                "from local_site.display.frames import _command_body_kernel as e; "
                f"d = open_display({spec!r}, connect=False); {steps}; "
                "print(len(q.signatures), len(e.signatures))")
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             check=True, timeout=scaled(120.0))
        return out.stdout.split()

    assert signatures("pass") == ["0", "0"]  # built only: nothing compiled
    assert signatures("d.warm_up()") == ["2", "1"]  # writable and read-only layers
    assert signatures("d.connect(); d.disconnect()", "sim") == ["2", "1"]  # at connect
    assert signatures(  # the loop's construction warms its display
        "from local_site.agent.display_loop import DisplayLoop; "
        "from local_site.render import Renderer; "
        "from local_site.scenes import TactileFrameScene; "
        "DisplayLoop(d, Renderer(), TactileFrameScene(), positions=lambda: None, "
        "platform_ok=lambda: True)"
    ) == ["2", "1"]
    from local_site.display.base import _quantise_kernel
    from local_site.display.frames import _command_body_kernel

    display = _CaptureDisplay(keepalive_interval_s=0.001)
    display.connect()
    compiled = (list(_quantise_kernel.signatures), list(_command_body_kernel.signatures))
    strided = np.full((16, 2), 0.5)[:, 0]  # a non-contiguous column
    display.send_command(np.full((4, 4), 1.0), np.full(16, 0.8), np.zeros((4, 4)))
    display.send_command(strided, np.full(16, 0.8), np.zeros(16))
    command = Renderer().render(TactileFrameScene(), (0.0, 0.0))  # read-only layers
    display.send_command(*command.arrays())
    display.send_command(command.height_mm, np.full(16, 0.9), command.friction)  # a mix
    display.send_command(np.full(16, 2, dtype=np.float32), 0.8, [0.1] * 16)  # type: ignore[arg-type]
    wait_until(lambda: display.keepalive(), 1.0, "a keepalive once due")
    assert len(display.sent) == 6
    assert (list(_quantise_kernel.signatures), list(_command_body_kernel.signatures)) \
        == compiled and (len(compiled[0]), len(compiled[1])) == (2, 1)


def test_the_applied_values_cannot_be_edited_into_the_keepalive() -> None:
    """The applied command's layers are the ones the keepalive re-sends: read-only, so a
    caller cannot change what the pins get next."""
    display = _CaptureDisplay(keepalive_interval_s=0.001)
    display.connect()
    applied = display.send_command(np.full(16, 1.0), 0.8, 0.0)
    for layer in (applied.height_mm, applied.stiffness_k, applied.friction):
        with pytest.raises(ValueError, match="read-only"):
            layer[:] = 4.0
    wait_until(lambda: display.keepalive(), 1.0, "a keepalive once due")
    first, again = (fr.decode_command(p) for _, p in display.sent)
    assert np.array_equal(again.height_codes, first.height_codes)


def test_keepalive_returns_early_until_due_and_counts_as_before() -> None:
    display = _CaptureDisplay(keepalive_interval_s=0.05)
    display.connect()
    assert display.keepalive() is False  # nothing sent yet: nothing to keep alive
    display.send_command(np.linspace(0, 4, 16), 0.75, 0.5)
    assert display.keepalive() is False and len(display.sent) == 1
    stats = display.stats()
    assert stats.commands == 2 and stats.skipped_unchanged == 1
    wait_until(lambda: display.keepalive(), 1.0, "a keepalive once the interval passed")
    arb_id, payload = display.sent[-1]
    assert arb_id == fr.ARB_ID_COMMAND
    frame = fr.decode_command(payload)
    first = fr.decode_command(display.sent[0][1])
    assert frame.flags & fr.FLAG_KEEPALIVE and frame.seq == first.seq + 1
    assert np.array_equal(frame.height_codes, first.height_codes)
    assert np.array_equal(frame.k_codes, first.k_codes)
    assert np.array_equal(frame.f_codes, first.f_codes)
    # after a safe state the withdrawn command is forgotten: no keepalive sends it again
    # (found by review: it went out at once, old touch after the safe state)
    display.safe_state("flat")
    n = len(display.sent)
    assert display.keepalive() is False and len(display.sent) == n
    # and the next command goes out at once, even one equal to the withdrawn command
    assert display.send_command(np.linspace(0, 4, 16), 0.75, 0.5).sent
    assert len(display.sent) == n + 1


# ---------------------------------------------------------------- firmware


def _command(height_mm: float, seq: int) -> bytes:
    return fr.encode_command(fr.CommandFrame(
        seq=seq, flags=0, height_codes=np.full(16, round(height_mm / fr.HEIGHT_LSB_MM),
                                               np.uint16),
        k_codes=np.full(16, 200, np.uint16), f_codes=np.zeros(16, np.uint16),
        watchdog_ms=100))


def test_commands_within_one_tick_leave_the_plant_where_the_last_alone_does() -> None:
    many = ArrayTacFirmware(ArrayTacPlant(), feedback_period_s=0.002)
    last_only = ArrayTacFirmware(ArrayTacPlant(), feedback_period_s=0.002)
    for fw in (many, last_only):
        fw.poll(0.0)
    t = 0.0
    for tick in range(200):
        t += 0.002
        heights = [1.0 + 0.01 * tick, 4.0 - 0.01 * tick, 2.0 + 0.005 * tick]
        for i, h in enumerate(heights):
            many.receive(fr.ARB_ID_COMMAND, _command(h, 3 * tick + i + 1), t)
        last_only.receive(fr.ARB_ID_COMMAND, _command(heights[-1], 3 * tick + 3), t)
        out_many, out_last = many.poll(t), last_only.poll(t)
        assert out_many == out_last  # the same feedback bytes, seq echo included
    assert np.array_equal(many.plant.position_mm, last_only.plant.position_mm)
    assert many.commands_applied == 600 and last_only.commands_applied == 200


# ---------------------------------------------------------------- serial reader


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    yield master, path
    os.close(master)
    os.close(slave)


def _collector(n_bytes: int) -> tuple[list[bytes], threading.Event,
                                      Callable[[bytes], None]]:
    """A reader callback keeping every chunk; the event is set once ``n_bytes`` arrived."""
    chunks: list[bytes] = []
    got = threading.Event()

    def on_data(data: bytes) -> None:
        chunks.append(data)
        if sum(map(len, chunks)) >= n_bytes:
            got.set()

    return chunks, got, on_data


def test_a_burst_reaches_the_callback_in_one_piece(pty_pair: tuple[int, int | str]) -> None:
    master, path = pty_pair
    chunks, got, on_data = _collector(78)
    errors: list[BaseException] = []
    reader = SerialPortReader(str(path), name="test pty", thread_name="test-pty-rx",
                              on_data=on_data, on_error=errors.append, timeout_s=0.05)
    reader.open()
    try:
        burst = bytes(range(78))
        os.write(int(master), burst)
        assert got.wait(scaled(2.0)), "the burst never arrived"
        assert chunks == [burst]  # one wake-up, one callback (read(1) made it two)
        assert errors == []
    finally:
        reader.close()


def test_the_peer_going_away_is_reported_once(pty_pair: tuple[int, int | str]) -> None:
    master, path = pty_pair
    errors: list[BaseException] = []
    reader = SerialPortReader(str(path), name="test pty", thread_name="test-pty-rx",
                              on_data=lambda _d: None, on_error=errors.append, timeout_s=0.05)
    reader.open()
    try:
        os.close(int(master))
        wait_until(lambda: errors, 2.0, "the read error")
        assert len(errors) == 1
    finally:
        reader.close()
        os.dup2(os.open(os.devnull, os.O_RDONLY), int(master))  # the fixture closes it


def test_a_socket_url_burst_reaches_the_callback_in_one_piece_and_a_close_is_reported() -> None:
    # pyserial's socket:// says in_waiting == 1 whenever anything is there, so read(1)
    # took one byte per wake-up: 78 callbacks for this burst, 68 per drive-board frame
    server = socket.create_server(("127.0.0.1", 0))
    chunks, got, on_data = _collector(78)
    errors: list[BaseException] = []
    host, port = server.getsockname()
    reader = SerialPortReader(f"socket://{host}:{port}", name="test socket",
                              thread_name="test-socket-rx", on_data=on_data,
                              on_error=errors.append, timeout_s=0.05)
    reader.open()
    try:
        server.settimeout(scaled(2.0))
        peer, _ = server.accept()
        burst = bytes(range(78))
        peer.sendall(burst)
        assert got.wait(scaled(2.0)), "the burst never arrived"
        assert chunks == [burst]  # one wake-up, one callback
        peer.close()  # the board went away: reported once
        wait_until(lambda: errors, 2.0, "the read error")
        assert len(errors) == 1 and "disconnected" in str(errors[0])
    finally:
        reader.close()
        server.close()


# ---------------------------------------------------------------- platform reader


def test_platform_reader_latest_is_the_drivers_newest_sample() -> None:
    platform = SimulatedPlatform(HoldMotion((20.0, 30.0, 100.0)))
    # polls far slower than the 1 kHz board; a long read timeout keeps it healthy below
    reader = PlatformReader(platform, poll_s=0.05, read_timeout_s=scaled(5.0))
    reader.start()
    try:
        wait_until(lambda: reader.healthy and reader.latest is not None, 3.0, "a sample")
        wait_until(lambda: reader.reads >= 100, 2.0, "reads counting the board's samples")
        assert platform.board is not None
        platform.board.stop()  # no sample after this one
        newest = platform.latest()
        assert newest is not None and reader.latest is newest
        assert reader.healthy
    finally:
        reader.stop()
        platform.disconnect()
    assert reader.latest is not None  # the last sample stays readable after a stop


def _silence(board: Any) -> Callable[[], None]:
    """Make a running simulated board drop every frame (a silent board, port open); returns
    the function that makes it talk again."""
    write = board._write

    def drop(_data: bytes) -> None:
        raise BlockingIOError  # the board counts the frame as dropped and goes on

    board._write = drop
    return lambda: setattr(board, "_write", write)


def test_a_short_platform_silence_ends_on_the_open_port_without_a_reopen() -> None:
    """A board silent for less than ``reopen_after_s`` (a late board, a starved thread)
    makes the reader unhealthy (pins safe), and its next sample healthy again, on the
    same open port: no close/reopen gap (before, the first read timeout reopened it)."""
    platform = SimulatedPlatform(HoldMotion((20.0, 30.0, 100.0)))
    reader = PlatformReader(platform, poll_s=0.005, read_timeout_s=scaled(0.1),
                            reopen_after_s=scaled(10.0))
    reader.start()
    try:
        wait_until(lambda: reader.healthy and reader.reads > 10, 3.0, "samples")
        board = platform.board
        talk = _silence(board)
        wait_until(lambda: not reader.healthy, 3.0, "the silence judged (by the sample's age)")
        wait_until(lambda: reader.errors >= 1, 3.0, "the silence noticed by the reader thread")
        assert "no new valid sample" in (reader.last_error or "")
        talk()
        wait_until(lambda: reader.healthy, 3.0, "healthy again on the next sample")
        assert reader.recoveries >= 1 and reader.reconnects == 0
        assert platform.board is board  # never closed and reopened
    finally:
        reader.stop()
        platform.disconnect()


def test_a_backlog_of_old_samples_is_not_healthy_however_recently_it_was_decoded() -> None:
    """A driver that drains a backlog (a full pty buffer keeps the oldest frames, after its
    thread was starved) decodes samples latched long ago: the reader thread takes them as the
    device being back, but health judges the newest sample by its capture stamp."""
    platform = SimulatedPlatform(HoldMotion((20.0, 30.0, 100.0)))
    timeout_s = scaled(0.1)
    reader = PlatformReader(platform, poll_s=0.005, read_timeout_s=timeout_s,
                            reopen_after_s=scaled(100.0))
    reader.start()
    try:
        wait_until(lambda: reader.healthy and reader.reads > 10, 3.0, "samples")
        board = platform.board
        assert board is not None
        write = board._write
        held: list[bytes] = []
        board._write = held.append  # the frames wait in a buffer nobody reads
        wait_until(lambda: not reader.healthy, 3.0, "the silence noticed")
        assert reader.lost_since_s is not None
        threading.Event().wait(3 * timeout_s)  # the held frames grow older than the timeout
        assert len(held) > 10
        _silence(board)  # nothing new after the backlog
        write(b"".join(held[:10]))  # the oldest frames, decoded now
        wait_until(lambda: reader.recoveries >= 1, 3.0, "the reader took the backlog")
        newest = reader.latest
        assert newest is not None and reader.latest is platform.latest()
        assert not reader.healthy  # decoded just now, captured more than a timeout ago
        lost = reader.lost_since_s
        assert lost is not None and lost <= monotonic_s() - timeout_s
        board._write = write  # fresh frames again
        wait_until(lambda: reader.healthy, 3.0, "healthy on fresh samples")
        assert reader.lost_since_s is None
    finally:
        reader.stop()
        platform.disconnect()


def test_platform_health_does_not_wait_for_the_reader_thread(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The newest sample's age decides, whenever the reader thread last ran: with the clock
    a second ahead, every sample is too old, though the thread keeps reading."""
    import local_site.agent.platform_reader as pr

    platform = SimulatedPlatform(HoldMotion((20.0, 30.0, 100.0)))
    reader = PlatformReader(platform, poll_s=0.005, read_timeout_s=0.25)
    reader.start()
    try:
        wait_until(lambda: reader.healthy and reader.reads > 10, 3.0, "samples")
        monkeypatch.setattr(pr, "now_us", lambda: now_us() + 1_000_000)
        reads = reader.reads
        assert not reader.healthy
        lost = reader.lost_since_s
        assert lost is not None and abs(lost - (monotonic_s() - 0.75)) < scaled(0.2)
        wait_until(lambda: reader.reads > reads + 10, 3.0, "the thread reading on")
        assert not reader.healthy  # though the thread took 10 samples meanwhile
        monkeypatch.undo()
        wait_until(lambda: reader.healthy and reader.lost_since_s is None, 3.0,
                   "healthy on the true clock")
    finally:
        reader.stop()
        platform.disconnect()


def test_a_lasting_platform_silence_is_reopened() -> None:
    platform = SimulatedPlatform(HoldMotion((20.0, 30.0, 100.0)))
    reader = PlatformReader(platform, poll_s=0.005, read_timeout_s=scaled(0.1),
                            reopen_after_s=scaled(0.3), retry_min_s=0.05)
    reader.start()
    try:
        wait_until(lambda: reader.healthy and reader.reads > 10, 3.0, "samples")
        board = platform.board
        _silence(board)  # for good: only a new board (a reopen) talks again
        wait_until(lambda: reader.reconnects >= 1 and reader.healthy, 5.0,
                   "the silent platform reopened")
        assert platform.board is not board and reader.recoveries == 0
    finally:
        reader.stop()
        platform.disconnect()


def test_the_silence_hint_tells_a_silent_device_from_a_starved_reader_thread(
        monkeypatch: pytest.MonkeyPatch) -> None:
    import local_site.serial_port as sp

    reader = SerialPortReader("loop://", name="board", thread_name="rx", on_data=lambda _d: None,
                              on_error=lambda _e: None, timeout_s=0.02)
    assert reader.silence_hint() == ""  # never read: nothing to tell
    monkeypatch.setattr(sp, "monotonic_s", lambda: 100.0)
    reader.last_read_s = 100.0 - 0.03  # read 30 ms ago: the thread runs, the device is quiet
    assert "read the port 30 ms ago (the device sent nothing)" in reader.silence_hint()
    reader.last_read_s = 100.0 - 0.9  # 900 ms without coming back from a 20 ms read
    assert "has not run for 900 ms (a busy host starved it" in reader.silence_hint()


def test_platform_reader_reopen_after_must_cover_a_read_timeout() -> None:
    with pytest.raises(ConfigError, match="reopen_after_s"):
        PlatformReader(SimulatedPlatform("hold"), read_timeout_s=0.25, reopen_after_s=0.1)
    with pytest.raises(ConfigError, match="platform_reopen_after_s"):
        LocalAgentConfig(platform_read_timeout_s=0.25, platform_reopen_after_s=0.2)


@pytest.mark.parametrize("reopen_after_s", [15.0, 20.0, float("inf"), float("nan")])
def test_a_reopen_slower_than_the_platform_process_hang_timeout_is_refused_by_name(
        reopen_after_s: float) -> None:
    """Before, 20 s passed the settings and the station then refused to start with
    "hang_timeout_s must be > reopen_after_s (20.0), got 15.0": a setting no user has."""
    for where in ({"render_loop": "process"}, {"platform_process": True}):
        with pytest.raises(ConfigError, match=r"^local\.agent\.platform_reopen_after_s must be "
                                              r"(< 15 s with the platform read in a process|"
                                              r"finite)"):
            LocalAgentConfig(platform_reopen_after_s=reopen_after_s, **where)
        assert LocalAgentConfig(platform_reopen_after_s=14.9, **where)
    if reopen_after_s < float("inf"):  # a thread reader has no such limit
        assert LocalAgentConfig(platform_reopen_after_s=reopen_after_s, render_loop="thread")


def test_platform_reader_poll_must_be_shorter_than_the_read_timeout() -> None:
    with pytest.raises(ConfigError, match="poll_s"):
        PlatformReader(SimulatedPlatform("hold"), read_timeout_s=0.1, poll_s=0.1)


# ---------------------------------------------------------------- display thread priority


def test_thread_priority_applies_and_restores_or_says_it_was_refused(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    tid = threading.get_native_id()
    before = os.getpriority(os.PRIO_PROCESS, tid)
    with thread_priority(0) as applied:
        assert applied is None and os.getpriority(os.PRIO_PROCESS, tid) == before
    target = min(before + 1, 19)  # lowering the priority is always permitted
    with thread_priority(target) as applied:
        assert applied == target and os.getpriority(os.PRIO_PROCESS, tid) == target
    assert os.getpriority(os.PRIO_PROCESS, tid) == before

    def refuse(*_args: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "setpriority", refuse)
    with caplog.at_level("INFO"), thread_priority(-10) as applied:
        assert applied is None
    assert "keeps its priority (nice -10 refused" in caplog.text
    assert "RLIMIT_NICE >= 30 (systemd: LimitNICE=-10)" in caplog.text


def test_thread_realtime_applies_and_restores_or_says_it_was_refused(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    tid = threading.get_native_id()
    before = (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority)
    with thread_realtime(0) as applied:
        assert applied is None and os.sched_getscheduler(tid) == before[0]
    with caplog.at_level("INFO"), thread_realtime(1) as applied:
        # root or CAP_SYS_NICE: SCHED_FIFO 1 while inside; else refused and said so
        if applied is None:
            assert "keeps its scheduling policy (SCHED_FIFO 1 refused" in caplog.text
            assert os.sched_getscheduler(tid) == before[0]
        else:
            assert applied == 1 and os.sched_getscheduler(tid) == os.SCHED_FIFO
            assert os.sched_getparam(tid).sched_priority == 1
    assert (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority) == before

    def refuse(*_args: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    caplog.clear()
    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    with caplog.at_level("INFO"), thread_realtime(10) as applied:
        assert applied is None
    assert "keeps its scheduling policy (SCHED_FIFO 10 refused" in caplog.text
    assert "RLIMIT_RTPRIO >= 10 (systemd: LimitRTPRIO=10" in caplog.text


def _scheduling(tid: int) -> tuple[int, int, int]:
    return (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority,
            os.getpriority(os.PRIO_PROCESS, tid))


def _realtime_permitted() -> bool:
    with thread_realtime(1) as applied:
        return applied is not None


@pytest.mark.parametrize("realtime", [0, 10])
def test_the_displays_threads_do_not_inherit_the_loops_raised_priority(realtime: int) -> None:
    # the loop's thread opens the display, which starts the display's own threads (the
    # emulated board and the bus reader): they must run like the process's other threads,
    # not at the loop's priority (found: the board link's reader ran at SCHED_FIFO 10)
    if realtime and not _realtime_permitted():
        pytest.skip("SCHED_FIFO needs root, CAP_SYS_NICE or RLIMIT_RTPRIO here")
    main = _scheduling(os.getpid())
    nice = min(main[2] + 5, 19)  # lowering the priority is always permitted
    display = open_display("sim", connect=False)
    loop = DisplayLoop(display, Renderer(), TactileFrameScene(), positions=lambda: None,
                       platform_ok=lambda: True)
    stop = threading.Event()
    runner = threading.Thread(target=loop.run_in_thread, args=(stop,),
                              kwargs={"nice": nice, "realtime": realtime}, name="loop")
    known = set(threading.enumerate())
    runner.start()
    try:
        # the loop ticks once the display is open and its own priority is back
        wait_until(lambda: loop.periods.iterations > 0, 10.0, "the loop's first tick")
        started = [t for t in threading.enumerate() if t not in known and t is not runner]
        assert started, "opening the display started no thread"
        assert runner.native_id is not None
        loop_sched = _scheduling(runner.native_id)
        if realtime:
            assert loop_sched[:2] == (os.SCHED_FIFO, realtime)
        else:
            assert loop_sched[2] == nice
        for t in started:
            assert t.native_id is not None
            assert _scheduling(t.native_id) == main, t.name
        assert _scheduling(runner.native_id) == loop_sched  # the loop got its own back
    finally:
        stop.set()
        runner.join(scaled(5.0))
        display.disconnect()


_ON_MAIN_THREAD = """
import json, os, sys, threading
from local_site.agent.display_loop import DisplayLoop
from local_site.devices import open_display
from local_site.render import Renderer
from local_site.scenes import TactileFrameScene

def sched(tid):
    return [os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority,
            os.getpriority(os.PRIO_PROCESS, tid)]

nice, realtime = int(sys.argv[1]), int(sys.argv[2])
before = sched(os.getpid())
display = open_display("sim", connect=False)
loop = DisplayLoop(display, Renderer(), TactileFrameScene(), positions=lambda: None,
                   platform_ok=lambda: True)
stop, seen = threading.Event(), {}
known = {threading.get_native_id()}

def watch():
    while loop.periods.iterations == 0:
        threading.Event().wait(0.01)
    seen["loop"] = sched(os.getpid())
    seen["display"] = [sched(t.native_id) for t in threading.enumerate()
                       if t.native_id not in known and t is not threading.current_thread()]
    stop.set()

threading.Thread(target=watch, daemon=True).start()
loop.run_in_thread(stop, nice, realtime)  # on the main thread, as in the display process
display.disconnect()
print(json.dumps({"before": before, **seen}))
"""


@pytest.mark.parametrize("realtime", [0, 10])
def test_a_loop_on_the_main_thread_opens_the_display_with_its_earlier_scheduling(
        realtime: int) -> None:
    # the display process runs its loop on its main thread: the main thread's scheduling
    # is then the loop's raised one, and the board link's reader inherited SCHED_FIFO
    if realtime and not _realtime_permitted():
        pytest.skip("SCHED_FIFO needs root, CAP_SYS_NICE or RLIMIT_RTPRIO here")
    import json
    import subprocess
    import sys

    nice = min(_scheduling(os.getpid())[2] + 5, 19)
    out = subprocess.run([sys.executable, "-c", _ON_MAIN_THREAD, str(nice), str(realtime)],
                         capture_output=True, text=True, timeout=scaled(60.0), check=True)
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    if realtime:
        assert seen["loop"][:2] == [os.SCHED_FIFO, realtime]
    else:
        assert seen["loop"][2] == nice
    assert seen["display"], "opening the display started no thread"
    assert all(s == seen["before"] for s in seen["display"]), seen


def test_opening_scheduling_lowers_for_the_block_and_restores_after() -> None:
    main = _scheduling(os.getpid())
    seen: dict[str, tuple[int, int, int]] = {}

    def worker() -> None:  # a thread of its own: the helper copies the main thread's
        tid = threading.get_native_id()
        seen["before"] = _scheduling(tid)
        with thread_priority(min(main[2] + 3, 19)):
            seen["raised"] = _scheduling(tid)
            with opening_scheduling():
                seen["inside"] = _scheduling(tid)
            seen["restored"] = _scheduling(tid)
        with opening_scheduling():  # nothing to change: nothing changes
            seen["unchanged"] = _scheduling(tid)

    t = threading.Thread(target=worker)
    t.start()
    t.join(scaled(5.0))
    assert seen["before"] == main and seen["raised"][2] == min(main[2] + 3, 19)
    assert seen["inside"] == main
    assert seen["restored"] == seen["raised"]
    assert seen["unchanged"] == main


@pytest.mark.parametrize("priority", [-1, 100, 1.5, True])
def test_display_thread_realtime_is_checked(priority: object) -> None:
    with pytest.raises(ConfigError, match="display_thread_realtime"):
        LocalAgentConfig(display_thread_realtime=priority)  # type: ignore[arg-type]


@pytest.mark.parametrize("nice", [-21, 20, 1.5, True])
def test_display_thread_nice_is_checked(nice: object) -> None:
    with pytest.raises(ConfigError, match="display_thread_nice"):
        LocalAgentConfig(display_thread_nice=nice)  # type: ignore[arg-type]


def test_safe_time_counts_the_episode_a_board_reconnect_ends() -> None:
    # the pins were parked while the board was away: that episode is safe time, counted
    # when the board is back (before, the reconnect dropped it)
    display = _CaptureDisplay()
    display.connect()
    loop = DisplayLoop(display, Renderer(), TactileFrameScene(), positions=lambda: None,
                       platform_ok=lambda: True)
    loop.enter_safe_state("platform_lost", monotonic_s() - 3.0)  # parked 3 s ago
    assert loop.safe_since_s is not None and loop.counters.safe_time_s == 0.0
    display.disconnect()
    assert loop._reopen_display(lambda delay_s: False)
    assert loop.safe_since_s is None
    assert 3.0 <= loop.counters.safe_time_s < 3.0 + scaled(1.0)


def test_a_refused_priority_does_not_chain_itself_to_the_blocks_errors(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # the receiving thread of the display process runs its whole life inside such a block:
    # its own errors must not read "during handling of" a refusal long past
    def refuse(*args: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    with pytest.raises(ValueError) as info, thread_realtime(5) as applied:
        assert applied is None
        raise ValueError("the block's own error")
    assert info.value.__context__ is None
