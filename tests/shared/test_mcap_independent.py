"""The recordings read by other tools: Foxglove's TypeScript MCAP reader and schemas.

``tests/mcap_reader/check_mcap.mjs`` reads a file with ``@mcap/core`` (the MCAP library
inside Foxglove Studio and Lichtblick; npm, pinned in ``tests/mcap_reader/package-lock.json``),
independently of the Python ``mcap`` package that wrote it: front to back with chunk CRCs
validated, and through the summary and indexes (summary CRC, every message with its CRC),
as Studio opens a complete file. The test checks that it agrees with the recorder on every
channel and count, that the derived channels are JSON with the ``jsonschema`` schemas
Foxglove decodes, and that the tactile image channel uses Foxglove's own
``foxglove.CompressedImage`` JSON schema (compared with the one ``@foxglove/schemas``
publishes) with PNGs that decode. A file cut short reads, in that reader too, as the
prefix up to its last complete chunk.

Needs ``node`` and ``npm ci --prefix tests/mcap_reader`` (``.ci/run`` does both): skipped
on a developer's machine without them, FAILS under ``CI=true``.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
from pathlib import Path
from typing import Any

import cv2
import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader

from shared.recording import RecordingFormatError, read_mcap
from shared.recording.schemas import DERIVED_SCHEMAS
from shared.recording.writer import patch_png
from tests.recordings import write_local_recording
from tests.support import REPO_ROOT, scaled

CHECKER = REPO_ROOT / "tests" / "mcap_reader"


def node_for_check() -> str | None:
    """``node`` when it and the checker's npm packages are installed, else None."""
    node = shutil.which("node") or shutil.which("nodejs")
    return node if node and (CHECKER / "node_modules" / "@mcap" / "core").is_dir() else None


def _node() -> str:
    node = node_for_check()
    if node:
        return node
    installed = (CHECKER / "node_modules" / "@mcap" / "core").is_dir()
    message = ("the independent MCAP check needs node and `npm ci --prefix tests/mcap_reader` "
               f"(node: {node}, packages installed: {installed}); .ci/run installs both")
    if os.environ.get("CI", "").strip().lower() in ("true", "1", "yes"):
        pytest.fail(message)
    pytest.skip(message)


def check_mcap(path: Path) -> dict[str, Any]:
    """What Foxglove's reader makes of ``path`` (see ``tests/mcap_reader/check_mcap.mjs``)."""
    out = subprocess.run([_node(), str(CHECKER / "check_mcap.mjs"), str(path)],
                         capture_output=True, timeout=scaled(120), check=False)
    assert out.returncode == 0, out.stderr.decode()[-2000:]
    return dict(json.loads(out.stdout))


def _foxglove_schema(name: str) -> dict[str, Any]:
    out = subprocess.run([_node(), str(CHECKER / "check_mcap.mjs"), "--foxglove-schema", name],
                         capture_output=True, timeout=scaled(60), check=True)
    return dict(json.loads(out.stdout))


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("indep") / "local.mcap"
    # small chunks: the file has many, as a station's (flushed every second) has
    write_local_recording(path, seconds=3.0, image_hz=10.0, chunk_bytes=64 << 10)
    return path


def test_foxglove_reader_reads_every_message_with_crcs_and_json_schemas(recorded: Path) -> None:
    rec = read_mcap(recorded)
    ours = rec.topics()
    got = check_mcap(recorded)
    stream, indexed = got["stream"], got["indexed"]
    # front to back: every chunk's CRC checked, the footer reached
    assert stream["error"] is None and stream["done"], stream
    assert stream["profile"] == "teletouch" and stream["chunks"] > 3
    assert stream["messages"] == len(rec.messages)
    assert stream["metadata"][0] == "teletouch" and "teletouch.end" in stream["metadata"]
    # through the summary and indexes, as Studio opens a complete file
    assert indexed["error"] is None, indexed["error"]
    assert indexed["messages"] == indexed["statisticsMessageCount"] == len(rec.messages)
    channels = {c["topic"]: c for c in indexed["channels"]}
    assert {t: c["count"] for t, c in channels.items()} == ours
    if indexed["dataSectionCrc"] is not None:  # 0 (not written) comes back as None
        assert indexed["dataSectionCrc"]["stored"] == indexed["dataSectionCrc"]["computed"]
    # the Python library's own indexed reader with CRC validation agrees too
    with open(recorded, "rb") as fh:
        assert sum(1 for _ in make_reader(fh, validate_crcs=True).iter_messages()) == len(
            rec.messages)
    for topic, c in channels.items():
        if c["messageEncoding"] == "json":  # what Foxglove decodes and plots
            name = topic.rsplit("/", 1)[1]
            assert c["schemaEncoding"] == "jsonschema" and c["jsonErrors"] == 0, c
            assert c["schemaData"] == DERIVED_SCHEMAS[name]
            assert c["schemaName"] == DERIVED_SCHEMAS[name]["title"]
            jsonschema.validate(c["firstJson"], c["schemaData"])
        else:  # the wire channels: msgpack, schemaless (Foxglove shows them, cannot plot them)
            assert c["messageEncoding"] == "msgpack" and c["schemaName"] is None, c


def test_the_tactile_image_is_foxglove_compressed_image_with_pngs(recorded: Path) -> None:
    official = _foxglove_schema("CompressedImage")
    assert DERIVED_SCHEMAS["tactile_image"] == official  # ours is Foxglove's, unchanged
    images = list(read_mcap(recorded).on("/local/tactile_image"))
    frames = list(read_mcap(recorded).on("/local/rx/tactile_frame"))
    # decimated to 10 Hz of recorded time from 30 Hz frames
    assert 0 < len(images) < len(frames)
    span_s = (images[-1].t_us - images[0].t_us) / 1e6
    assert (len(images) - 1) / span_s <= 10.0 + 1e-6
    for m in images:
        doc = m.json()
        jsonschema.validate(doc, official)
        assert doc["format"] == "png" and doc["frame_id"] == "tactile_patch"
        assert doc["timestamp"]["sec"] * 1_000_000 + doc["timestamp"]["nsec"] // 1000 == m.t_us
        img = cv2.imdecode(np.frombuffer(base64.b64decode(doc["data"]), np.uint8),
                           cv2.IMREAD_UNCHANGED)
        assert img is not None and img.shape == (24, 24, 3)


def test_the_image_channel_is_off_by_default_and_png_keeps_the_layer_order(
        tmp_path: Path) -> None:
    write_local_recording(tmp_path / "plain.mcap", seconds=0.5)
    assert "/local/tactile_image" not in read_mcap(tmp_path / "plain.mcap").topics()
    # row 0 of a layer is its lowest y: the image's bottom row; colour rises with height
    h = np.zeros((4, 3), np.float32)
    h[0, :] = 1.0
    png = patch_png(h)
    assert png is not None
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.shape == (4, 3, 3)
    bottom, top = img[-1].astype(int).sum(), img[0].astype(int).sum()
    assert bottom > top  # viridis: yellow (high) is brighter than dark purple (low)
    assert patch_png(np.full((3, 3), np.nan)) is None and patch_png(np.zeros(5)) is None


def test_a_cut_file_reads_as_the_same_prefix_in_both_libraries(recorded: Path,
                                                               tmp_path: Path) -> None:
    data = recorded.read_bytes()
    for frac in (0.3, 0.55, 0.8):
        cut = tmp_path / f"cut{int(frac * 100)}.mcap"
        cut.write_bytes(data[:int(len(data) * frac)])
        try:
            ours = len(read_mcap(cut).messages)
        except RecordingFormatError:
            ours = 0
        got = check_mcap(cut)
        assert not got["stream"]["done"]  # no footer: the reader says it is not complete
        assert got["stream"]["messages"] == ours > 0
        assert got["indexed"]["error"] is not None  # no summary: Studio reads it unindexed
