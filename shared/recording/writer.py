"""The MCAP writer a station feeds while it runs: a background thread behind a bounded queue.

:class:`McapRecorder` never blocks its callers (the 1 kHz display loop among them): every
``wire``/``derived`` call is one append to a bounded deque, without a lock or a wake-up of the
writer thread (a ``queue.Queue`` notified the thread on every item: hundreds of thread
switches per second per station, docs/speed.md section 9); when the deque is full the item is
dropped and counted (``dropped``). The thread drains it every ``DRAIN_INTERVAL_S`` (a
``sync`` or ``close`` wakes it at once), encodes, derives the JSON channels of
:mod:`shared.recording.schemas` from the wire messages, and writes zstd-compressed chunks. It
closes a chunk and flushes the file at least every ``flush_interval_s`` (the chunks completed
since the last flush wait in memory until then), so a station killed with SIGKILL leaves a
file readable up to its last flush (at most that much is lost).

A message counts as written (``messages_written``, ``per_topic``) only once a flush of its
chunk succeeded; when a write or flush fails (a full disk), the messages not yet flushed are
counted lost (``messages_lost``) and the failure in ``write_errors``: the recording goes on,
and a moment of full disk is never reported as a complete file with nothing missing. The
file gets a flush's bytes whole or not at all (:class:`_FlushedFile`), so what follows a
failed flush is still readable front to back; channels first written in the lost bytes are
written again. A file that lost bytes ends without the MCAP summary section (statistics,
chunk and message indexes), which would count the lost messages and point at the lost
chunks: a reader scans it front to back (``read_mcap`` always does).

The recorder lives as long as the station, not as long as a connection: reconnections and
relay restarts go into the same file. :meth:`McapRecorder.close` drains the queue, writes the
end metadata and the MCAP summary and footer.
"""

from __future__ import annotations

import base64
import collections
import contextlib
import itertools
import json
import logging
import os
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, BinaryIO, cast

import cv2
import numpy as np
from mcap.data_stream import RecordBuilder
from mcap.records import DataEnd, Footer
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

from shared import __version__
from shared.errors import ConfigError
from shared.protocol import ArmState, DataMessage, Message, PlatformState, Stats, TactileFrame
from shared.protocol.codec import encode
from shared.recording.schemas import (
    DERIVED_SCHEMAS,
    FORMAT_VERSION,
    META_END,
    META_START,
    PROFILE,
    WIRE_ENCODING,
    derived_topic,
    wire_topic,
)
from shared.report import to_jsonable

__all__ = ["McapRecorder", "hop_stages_ms"]

log = logging.getLogger(__name__)

#: the writer thread drains the items queued since its last pass this often
DRAIN_INTERVAL_S = 0.02


def hop_stages_ms(hops: Any, offsets_us: Mapping[str, int | None]) -> tuple[
        dict[str, float | None], float | None]:
    """Per-stage delays (ms) between consecutive hop stamps, and first-to-last.

    Each stamp is converted to the relay clock (``t - offset[clock]``; the relay's offset is
    0); a stage between two clocks whose offset is unknown is None (same-clock stages never
    need one). Stage names are ``<stage>_to_<stage>`` (a repeated name gets ``_2``, ...).

    Args:
        hops: the message's :class:`~shared.protocol.Hop` stamps, in order.
        offsets_us: station clock minus relay clock, per role (``stats.clock_offset_us``).
    """
    def on_relay(clock: str, t_us: int) -> int | None:
        if clock == "relay":
            return t_us
        off = offsets_us.get(clock)
        return None if off is None else t_us - off

    stages: dict[str, float | None] = {}
    for a, b in itertools.pairwise(hops):
        name = f"{a.stage}_to_{b.stage}"
        n = 2
        while name in stages:
            name, n = f"{a.stage}_to_{b.stage}_{n}", n + 1
        if a.clock == b.clock:
            stages[name] = (b.t_us - a.t_us) / 1e3
        else:
            ta, tb = on_relay(a.clock, a.t_us), on_relay(b.clock, b.t_us)
            stages[name] = None if ta is None or tb is None else (tb - ta) / 1e3
    total = None
    if len(hops) >= 2:
        first, last = hops[0], hops[-1]
        if first.clock == last.clock:
            total = (last.t_us - first.t_us) / 1e3
        else:
            ta, tb = on_relay(first.clock, first.t_us), on_relay(last.clock, last.t_us)
            total = None if ta is None or tb is None else (tb - ta) / 1e3
    return stages, total


def patch_png(height: Any) -> bytes | None:
    """A height layer as a colour PNG (viridis, normalised per frame from its minimum to its
    maximum; +y up, so row 0 of the layer is the image's bottom row); None without a 2-D
    finite layer."""
    h = np.asarray(height, dtype=np.float64)
    if h.ndim != 2 or h.size == 0:
        return None
    finite = np.isfinite(h)
    if not finite.any():
        return None
    lo, hi = float(h[finite].min()), float(h[finite].max())
    q = np.where(finite, np.rint(np.clip((h - lo) / (hi - lo if hi > lo else 1.0), 0, 1)
                                 * 255), 0).astype(np.uint8)
    img = cv2.applyColorMap(q[::-1], cv2.COLORMAP_VIRIDIS)
    ok, buf = cv2.imencode(".png", img)
    return bytes(buf) if ok else None


def _layer_max(frame: TactileFrame, name: str) -> float | None:
    arr = frame.layers.get(name)
    return float(np.max(arr)) if isinstance(arr, np.ndarray) and arr.size else None


class _FlushedFile:
    """The MCAP writer's output: bytes wait in memory and reach the file at :meth:`flush`,
    whole or not at all. A failed flush (a full disk) cuts the file back to where the last
    good one ended and gives its bytes up (their messages are counted lost), so the file
    never holds a torn record that would hide everything written after it.

    Raises:
        OSError: the file cannot be created.
    """

    def __init__(self, path: Path) -> None:
        self._fh = open(path, "wb", buffering=0)  # noqa: SIM115 - closed by close()
        self._size = 0  # bytes in the file
        self._buf = bytearray()

    def write(self, data: bytes) -> int:
        self._buf += data
        return len(data)

    def tell(self) -> int:
        return self._size + len(self._buf)

    def flush(self) -> None:
        """Write what waits; on failure the file ends where it did before, and raise.

        Raises:
            OSError: the write failed (the bytes are given up).
        """
        data, self._buf = self._buf, bytearray()
        done = 0
        try:
            with memoryview(data) as view:
                while done < len(data):
                    n = self._fh.write(view[done:])
                    if not n:
                        raise OSError(f"write of {len(data) - done} bytes wrote none")
                    done += n
        except OSError:
            # a torn write (part of it reached the file): cut it off; shrinking needs no space
            self._fh.truncate(self._size)
            self._fh.seek(self._size)
            raise
        self._size += len(data)

    def close(self) -> None:
        self._fh.close()


class McapRecorder:
    """Writes one station's recording (see the module docstring).

    Args:
        path: the ``.mcap`` file (created or replaced; another suffix is refused).
        station: ``local`` or ``remote`` (the topics' first part).
        meta: settings written into the start metadata (JSON-able).
        queue_size: items waiting for the thread before new ones are dropped.
        chunk_bytes: uncompressed size at which a chunk is closed.
        flush_interval_s: a chunk is closed and the file flushed at least this often.
        image_rate_hz: also write the tactile patch as a ``foxglove.CompressedImage`` PNG
            (``/<station>/tactile_image``) at most this often (recorded time, on the writer
            thread); None: no image channel.

    Raises:
        ConfigError: the file cannot be created, is not named ``*.mcap``, or bad settings.
    """

    def __init__(self, path: str | os.PathLike[str], station: str, *,
                 meta: Mapping[str, Any] | None = None, queue_size: int = 8192,
                 chunk_bytes: int = 1 << 20, flush_interval_s: float = 1.0,
                 image_rate_hz: float | None = None) -> None:
        if queue_size < 1 or chunk_bytes < 1 or not flush_interval_s > 0:
            raise ConfigError("recorder queue_size, chunk_bytes and flush_interval_s must be > 0")
        if image_rate_hz is not None and not 0 < image_rate_hz <= 1000:
            raise ConfigError(f"recorder image_rate_hz must lie in (0, 1000], got {image_rate_hz}")
        self._image_period_us = None if image_rate_hz is None else int(1e6 / image_rate_hz)
        self._last_image_us: int | None = None
        #: CPU seconds the writer thread spent encoding images (the image channel's cost)
        self.image_cpu_s = 0.0
        if not station.isidentifier():
            raise ConfigError(f"station name {station!r} is not a valid topic part")
        self.path = Path(path)
        if self.path.suffix != ".mcap":
            raise ConfigError(f"a recording is an MCAP file: name it *.mcap (got {self.path}; "
                              "the .npz recording format is gone)")
        self.station = station
        self.flush_interval_s = flush_interval_s
        try:
            self._file = _FlushedFile(self.path)
        except OSError as err:
            raise ConfigError(f"cannot write the recording {self.path}: {err}") from err
        self._writer = Writer(cast(BinaryIO, self._file), chunk_size=chunk_bytes,
                              compression=CompressionType.ZSTD)
        try:
            self._writer.start(profile=PROFILE, library=f"teletouch {__version__}")
            self._writer.add_metadata(META_START, {
                "format_version": FORMAT_VERSION, "station": station,
                "started_us": str(time.time_ns() // 1000),
                "meta_json": json.dumps(to_jsonable(dict(meta or {})), sort_keys=True,
                                        allow_nan=False)})
            self._writer.flush()
        except OSError as err:  # a full disk
            self._file.close()
            raise ConfigError(f"cannot write the recording {self.path}: {err}") from err
        #: items for the writer thread: appended by any thread, popped by the writer only
        #: (deque append/popleft are atomic); at most ``queue_size`` wait
        self._items: collections.deque[tuple[Any, ...]] = collections.deque()
        self._queue_size = queue_size
        self._wake = threading.Event()  # a sync or close: drain now
        self._stopping = False
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        #: channels and schemas registered since the last flush (their records are in the
        #: chunk it writes: registered again when that flush fails)
        self._unflushed: list[tuple[dict[str, int], str]] = []
        self._offsets_us: dict[str, int | None] = {}
        self._seq = 0
        self.dropped = 0
        #: messages on disk (their chunk flushed)
        self.written = 0
        #: messages handed to the MCAP writer whose write or flush failed
        self.lost = 0
        self.write_errors = 0
        #: bytes were given up (the file ends without the MCAP summary)
        self._bytes_lost = False
        #: messages in the chunk not flushed yet, per topic (written or lost at the next flush)
        self._pending: dict[str, int] = {}
        #: CPU time the writer thread used (seconds, updated as it runs)
        self.writer_cpu_s = 0.0
        self.message_counts: dict[str, int] = {}
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=f"mcap-{station}", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ producers (any thread)

    def _put(self, item: tuple[Any, ...]) -> bool:
        if self._closed:
            return False
        if len(self._items) >= self._queue_size:
            self.dropped += 1
            return False
        self._items.append(item)
        return True

    def wire(self, direction: str, msg: Message, t_us: int) -> bool:
        """Record a message sent (``tx``) or received (``rx``) at ``t_us`` (wall clock).

        Returns:
            False when it was dropped (queue full or recorder closed).
        """
        return self._put(("wire", direction, msg, int(t_us)))

    def tap(self, direction: str, msg: Message, t_us: int) -> None:
        """:meth:`wire` as a :class:`shared.client.StationLink` tap (result ignored)."""
        self._put(("wire", direction, msg, int(t_us)))

    def derived(self, name: str, t_us: int,
                payload: Mapping[str, Any] | Callable[[], Mapping[str, Any]]) -> bool:
        """Record one message of the derived channel ``name`` (JSON).

        ``payload`` may be a callable, run on the writer thread (so the caller does not pay
        for building it).

        Returns:
            False when it was dropped.

        Raises:
            KeyError: ``name`` is not a derived channel of the schema table.
        """
        derived_topic(self.station, name)
        return self._put(("derived", name, payload, int(t_us)))

    def sync(self, timeout_s: float = 10.0) -> bool:
        """Wait until everything queued so far is on disk (its chunk completed, file flushed).

        For a reader of the file while the station still runs (the findings at shutdown).
        Blocks the caller, so never call it from a loop that must not wait.

        Returns:
            False when the recorder is closed, the writer did not get there in time, or the
            flush failed (at once, not after ``timeout_s``).
        """
        done = threading.Event()
        flushed: list[bool] = []
        if self._closed:
            return False
        self._items.append(("sync", done, flushed, 0))  # beyond the bound: it is not data
        self._wake.set()
        return done.wait(timeout_s) and flushed == [True]

    # ------------------------------------------------------------------ writer thread

    def _channel(self, topic: str, encoding: str, schema: dict[str, Any] | None,
                 metadata: dict[str, str]) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            sid = 0
            if schema is not None:
                name = str(schema["title"])
                sid = self._schemas.get(name, 0)
                if not sid:
                    sid = self._writer.register_schema(
                        name=name, encoding="jsonschema",
                        data=json.dumps(schema, sort_keys=True).encode())
                    self._schemas[name] = sid
                    self._unflushed.append((self._schemas, name))
            cid = self._writer.register_channel(topic=topic, message_encoding=encoding,
                                                schema_id=sid, metadata=metadata)
            self._channels[topic] = cid
            self._unflushed.append((self._channels, topic))
        return cid

    def _add(self, topic: str, cid: int, data: bytes, t_us: int) -> None:
        self._seq += 1
        t_ns = t_us * 1000
        self._pending[topic] = self._pending.get(topic, 0) + 1
        try:  # a full chunk is written here: a failure loses the chunk
            self._writer.add_message(channel_id=cid, log_time=t_ns, data=data,
                                     publish_time=t_ns, sequence=self._seq & 0xFFFFFFFF)
        except Exception:
            self._lose_pending()
            raise

    def _lose_pending(self) -> None:
        self._bytes_lost = True
        self.lost += sum(self._pending.values())
        self._pending.clear()
        for registry, key in self._unflushed:  # their records were lost with the chunk
            registry.pop(key, None)
        self._unflushed.clear()

    def _flush(self) -> bool:
        """Complete the chunk and flush the file; its messages count as written, or as lost
        when that fails (the failure is logged and counted; never raised)."""
        try:
            self._writer.flush()
        except Exception as err:  # a full disk: the recording goes on
            self.write_errors += 1
            pending = sum(self._pending.values())
            self._lose_pending()
            log.error("recording %s: flush failed, %d messages lost: %s", self.path, pending,
                      err)
            return False
        for topic, n in self._pending.items():
            self.message_counts[topic] = self.message_counts.get(topic, 0) + n
            self.written += n
        self._pending.clear()
        self._unflushed.clear()
        return True

    def _write_json(self, name: str, payload: Mapping[str, Any], t_us: int) -> None:
        topic = derived_topic(self.station, name)
        cid = self._channel(topic, "json", DERIVED_SCHEMAS[name], {"kind": "derived"})
        self._add(topic, cid, json.dumps(to_jsonable(dict(payload)), allow_nan=False,
                                         separators=(",", ":")).encode(), t_us)

    def _write_wire(self, direction: str, msg: Message, t_us: int) -> None:
        topic = wire_topic(self.station, direction, msg.TYPE)
        cid = self._channel(topic, WIRE_ENCODING, None,
                            {"kind": "wire", "station": self.station, "direction": direction})
        self._add(topic, cid, encode(msg, validate=False, max_message_bytes=1 << 30), t_us)
        for name, payload in self._derive(direction, msg):
            self._write_json(name, payload, t_us)
        if self._image_period_us is not None and isinstance(msg, TactileFrame) and (
                self._last_image_us is None
                or t_us - self._last_image_us >= self._image_period_us):
            self._write_image(msg, t_us)

    def _write_image(self, frame: TactileFrame, t_us: int) -> None:
        t0 = time.thread_time()
        png = patch_png(frame.layers.get("height_mm"))
        self.image_cpu_s += time.thread_time() - t0
        if png is None:
            return
        self._last_image_us = t_us
        self._write_json("tactile_image", {
            "timestamp": {"sec": t_us // 1_000_000, "nsec": (t_us % 1_000_000) * 1000},
            "frame_id": "tactile_patch", "format": "png",
            "data": base64.b64encode(png).decode("ascii")}, t_us)

    def _derive(self, direction: str, msg: Message) -> list[tuple[str, dict[str, Any]]]:
        out: list[tuple[str, dict[str, Any]]] = []
        if isinstance(msg, Stats):
            raw = msg.metrics.get("clock_offset_us")
            if isinstance(raw, dict):
                self._offsets_us = {str(k): int(v) if isinstance(v, int | float)
                                    and not isinstance(v, bool) else None
                                    for k, v in raw.items()}
            return out
        if not isinstance(msg, DataMessage):
            return out
        if direction == "rx" and len(msg.hops) >= 2:
            stages, total = hop_stages_ms(msg.hops, self._offsets_us)
            out.append(("latency", {"type": msg.TYPE, "seq": msg.seq, "end_to_end_ms": total,
                                    "stages_ms": stages}))
        if isinstance(msg, PlatformState) and direction == "tx":
            x, y, z = msg.position_mm
            out.append(("trajectory", {"seq": msg.seq, "x_mm": x, "y_mm": y, "z_mm": z}))
        elif isinstance(msg, ArmState) and direction == "tx":
            x, y, z = msg.position_mm
            out.append(("arm", {"seq": msg.seq, "x_mm": x, "y_mm": y, "z_mm": z,
                                "force_n": msg.force_n, "status": msg.status}))
        elif isinstance(msg, TactileFrame):
            out.append(("tactile", {
                "seq": msg.seq, "center_x_mm": msg.center_mm[0],
                "center_y_mm": msg.center_mm[1], "pitch_mm": msg.pitch_mm,
                "contact": msg.contact, "force_n": msg.force_n,
                "indentation_mm": msg.indentation_mm,
                "height_max_mm": _layer_max(msg, "height_mm") or 0.0,
                "stiffness_n_per_mm_max": _layer_max(msg, "stiffness_n_per_mm")}))
        return out

    def _handle(self, item: tuple[Any, ...]) -> None:
        kind, a, b, t_us = item
        if kind == "wire":
            self._write_wire(a, b, t_us)
        elif kind == "sync":
            try:
                b.append(self._flush())
            finally:  # the caller never waits out its timeout on a failed flush
                a.set()
        else:
            self._write_json(a, b() if callable(b) else b, t_us)

    def _run(self) -> None:
        last_flush = time.monotonic()
        items = self._items
        while True:
            timeout = max(0.0, self.flush_interval_s - (time.monotonic() - last_flush))
            self._wake.wait(min(DRAIN_INTERVAL_S, timeout))
            self._wake.clear()  # before draining: a later sync's item is drained next pass
            stopping = self._stopping  # read before the last drain: nothing is left behind
            # the items present now (not "until empty": producers faster than the writer
            # must not starve the periodic flush below)
            for _ in range(len(items)):
                try:
                    self._handle(items.popleft())
                except Exception as err:  # a bad item must not end the recording
                    self.write_errors += 1
                    if self.write_errors == 1:
                        log.error("recording %s: an item was not written: %s", self.path, err)
            self.writer_cpu_s = time.thread_time()
            if stopping and not items:
                return
            if time.monotonic() - last_flush >= self.flush_interval_s:
                last_flush = time.monotonic()
                self._flush()  # a failure keeps the thread: close() still needs it

    # ------------------------------------------------------------------ closing

    def counts(self) -> dict[str, Any]:
        """What was written (flushed to the file), dropped and lost so far."""
        return {"path": str(self.path), "messages_written": self.written,
                "dropped_queue_full": self.dropped, "write_errors": self.write_errors,
                "messages_lost": self.lost,
                "writer_cpu_s": round(self.writer_cpu_s, 4),
                "image_cpu_s": round(self.image_cpu_s, 4),
                "per_topic": dict(sorted(self.message_counts.items()))}

    def loss_error(self) -> ConfigError | None:
        """The error a station ends with when the file is finished but lost messages (a
        write or flush failed: a full disk); None when nothing was lost. A session whose
        record is incomplete must not end as a success (exit 0) with only a count saying
        so."""
        if not self.lost:
            return None
        return ConfigError(f"the recording {self.path} lost {self.lost} messages ("
                           f"{self.write_errors} write errors, e.g. a full disk): the file "
                           "reads, but incomplete")

    def _finish_without_summary(self) -> None:
        """End the file as ``Writer.finish`` does, but without the summary section: the
        library's would count lost messages and index lost chunks (the data section's CRC
        is not computed either way: 0)."""
        records = RecordBuilder()
        DataEnd(data_section_crc=0).write(records)
        Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(records)
        self._file.write(records.end())
        self._file.write(MCAP0_MAGIC)

    def close(self, end_meta: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """Drain the queue, write the end metadata, summary and footer; close the file.

        Idempotent. Returns :meth:`counts`.

        Raises:
            ConfigError: the file could not be finished.
        """
        if self._closed:
            return self.counts()
        self._closed = True
        self._stopping = True
        self._wake.set()
        self._thread.join(30.0)
        if self._thread.is_alive():
            raise ConfigError(f"cannot finish the recording {self.path}: its writer thread "
                              "did not drain the queue within 30 s")
        self._flush()  # the last chunk, so the end metadata counts it written or lost
        try:
            self._writer.add_metadata(META_END, {
                "ended_us": str(time.time_ns() // 1000),
                "counts_json": json.dumps(self.counts(), sort_keys=True),
                "meta_json": json.dumps(to_jsonable(dict(end_meta or {})), sort_keys=True,
                                        allow_nan=False)})
            if self._bytes_lost:
                self._finish_without_summary()
            else:
                self._writer.finish()
            self._file.flush()
        except (OSError, ValueError) as err:
            raise ConfigError(f"cannot finish the recording {self.path}: {err}") from err
        finally:
            with contextlib.suppress(OSError):
                self._file.close()
        log.info("recording written to %s (%d messages, %d dropped, %d lost)", self.path,
                 self.written, self.dropped, self.lost)
        return self.counts()
