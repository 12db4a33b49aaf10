"""A simulated encoder board: the firmware's byte stream, generated from a motion source.

It samples a :class:`~local_site.platform.motion.MotionSource` at ``sample_rate_hz`` on its
own clock, turns positions into quadrature counts (quantised exactly as an encoder would,
with 32-bit wrap-around), and writes the frames of docs/platform_protocol.md to any byte
sink: a pty master (``os.write``) or a pyserial ``loop://`` port (``port.write``). Overdue
samples are emitted in one burst (timestamps stay on the board grid); when the sink is full
the frame is dropped and counted, as a board FIFO overflow would.

The motion is a pure function of time, so the board computes its frames a block at a time
(:meth:`SimulatedEncoderBoard.frames`: one vectorised motion sample for ``BLOCK_SAMPLES``
samples) and only writes each one when it is due: the bytes and their timing on the wire are
those of :meth:`SimulatedEncoderBoard.frame`, sample by sample, at a fraction of the CPU.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from types import TracebackType

import numpy as np

from local_site.platform.kinematics import PlatformGeometry
from local_site.platform.motion import MotionSource
from local_site.platform.protocol import (
    PROTOCOL_VERSION,
    BoardInfo,
    encode_info_frame,
    encode_sample_frame,
)
from shared.errors import ConfigError

__all__ = ["BLOCK_SAMPLES", "FIRMWARE_VERSION", "SimulatedEncoderBoard"]

log = logging.getLogger(__name__)

FIRMWARE_VERSION = 0x0100
#: samples computed at once (32 ms at 1 kHz: short bursts of work, never late bytes)
BLOCK_SAMPLES = 32


class SimulatedEncoderBoard:
    """Emulated encoder board streaming sample frames.

    Args:
        motion: where the platform is against time.
        write: byte sink; may raise ``BlockingIOError`` (frame dropped) or ``OSError``
            (board stops).
        geometry: must match the driver's, so counts mean the same millimetres.
        sample_rate_hz: board sample rate.
        initial_counts: counter values at power-up for position (0, 0, 0) (set near 2^31
            to exercise wrap-around).
        start_seq: first sequence number.
        start_board_t_us: board clock at the first sample (near 2^32 exercises wrap-around).
        info_period_s: how often the board repeats its info frame.
        start_sample: the sample number streaming starts at (0 for a board just powered up;
            a link reopened to a board that kept running starts where that board is now:
            its motion, sequence numbers and clock continue, they do not restart).
    """

    def __init__(self, motion: MotionSource, write: Callable[[bytes], object], *,
                 geometry: PlatformGeometry | None = None, sample_rate_hz: float = 1000.0,
                 initial_counts: tuple[int, int, int] = (0, 0, 0), start_seq: int = 0,
                 start_board_t_us: int = 0, info_period_s: float = 1.0,
                 start_sample: int = 0) -> None:
        if not 1.0 <= sample_rate_hz <= 20_000.0:
            raise ConfigError(f"sample_rate_hz must be in [1, 20000], got {sample_rate_hz}")
        if start_sample < 0:
            raise ConfigError(f"start_sample must be >= 0, got {start_sample}")
        self.motion = motion
        self.geometry = geometry or PlatformGeometry()
        self.sample_rate_hz = sample_rate_hz
        self._write = write
        self._initial_counts = initial_counts
        self._start_seq = start_seq
        self._start_board_t_us = start_board_t_us
        self._info_every = max(1, round(info_period_s * sample_rate_hz))
        self._start_sample = start_sample
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._inject: list[bytes] = []
        self._lock = threading.Lock()
        self._block_start = 0
        self._block: list[bytes] = []
        self.frames_sent = 0
        self.frames_dropped = 0
        self.error: BaseException | None = None

    @property
    def info(self) -> BoardInfo:
        """The self-description this board sends."""
        return BoardInfo(protocol_version=PROTOCOL_VERSION, axes=3,
                         pulses_per_rev=self.geometry.pulses_per_rev,
                         decoding=self.geometry.decoding,
                         sample_rate_hz=round(self.sample_rate_hz),
                         firmware_version=FIRMWARE_VERSION)

    def frame(self, n: int) -> bytes:
        """The sample frame of sample number ``n`` (pure: same n, same bytes)."""
        t_s = n / self.sample_rate_hz
        counts = self.geometry.mm_to_counts(self.motion.position_mm(t_s))
        counts = tuple(c + i for c, i in zip(counts, self._initial_counts, strict=True))  # type: ignore[assignment]
        board_t_us = self._start_board_t_us + round(t_s * 1e6)
        return encode_sample_frame(self._start_seq + n, board_t_us, counts)

    def frames(self, first: int, count: int) -> list[bytes]:
        """The sample frames ``first`` .. ``first + count - 1``, each equal to :meth:`frame`.

        One vectorised motion sample and quantisation for the block (the same float
        arithmetic element by element: ``n / rate``, ``p / mm_per_count`` rounded half to
        even as ``round`` does), then the frames' bytes.
        """
        n = np.arange(first, first + count)
        t_s = n / self.sample_rate_hz
        position = self.motion.sample(t_s)
        counts = np.rint(position / np.asarray(self.geometry.mm_per_count)).astype(np.int64) \
            + np.asarray(self._initial_counts, dtype=np.int64)
        board_t_us = self._start_board_t_us + np.rint(t_s * 1e6).astype(np.int64)
        seq0 = self._start_seq + first
        return [encode_sample_frame(seq0 + i, t, (cx, cy, cz))
                for i, (t, (cx, cy, cz)) in enumerate(zip(board_t_us.tolist(), counts.tolist(),
                                                         strict=True))]

    def _due_frame(self, n: int) -> bytes:
        """Frame ``n`` from the current block (computing the next block when needed)."""
        i = n - self._block_start
        if not 0 <= i < len(self._block):
            self._block_start, self._block, i = n, self.frames(n, BLOCK_SAMPLES), 0
        return self._block[i]

    def inject(self, data: bytes) -> None:
        """Queue raw bytes (line noise, a corrupted frame) to go out before the next frame."""
        with self._lock:
            self._inject.append(bytes(data))

    def start(self) -> None:
        """Start streaming from sample ``start_sample``, in real time."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="sim-encoder-board", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop streaming (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def __enter__(self) -> SimulatedEncoderBoard:
        self.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    def _send(self, data: bytes) -> bool:
        try:
            self._write(data)
        except BlockingIOError:
            self.frames_dropped += 1
            return True
        except Exception as err:  # the sink is gone (pty closed, port closed): board stops
            self.error = err
            log.debug("simulated encoder board stops: %s", err)
            return False
        return True

    def _run(self) -> None:
        period_s = 1.0 / self.sample_rate_hz
        n = first = self._start_sample
        t0 = time.perf_counter() - n * period_s  # sample n is due now
        while not self._stop.is_set():
            due = int((time.perf_counter() - t0) / period_s) + 1
            chunks: list[bytes] = []
            with self._lock:
                chunks.extend(self._inject)
                self._inject.clear()
            for k in range(n, due):
                if k % self._info_every == 0 or k == first:  # the link opens with its info
                    chunks.append(encode_info_frame(self.info))
                chunks.append(self._due_frame(k))
            if chunks:
                if not self._send(b"".join(chunks)):
                    return
                self.frames_sent += due - n
                n = due
            sleep_s = t0 + n * period_s - time.perf_counter()
            if sleep_s > 0:
                self._stop.wait(sleep_s)
