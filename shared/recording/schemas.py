"""Channels of a Tele-Touch MCAP recording: topics, encodings and JSON Schemas.

Two kinds of channel (``docs/recording.md`` has the full table):

* **wire** channels, ``/<station>/<tx|rx>/<message type>``: every message the station sent to
  or received from the relay, encoded exactly as on the wire (msgpack, ``message_encoding``
  ``msgpack``, no schema), with all its hop stamps (a received message carries the
  station's ``station_rx`` stamp);
* **derived** channels, ``/<station>/<name>``: JSON with a JSON Schema (``jsonschema``), so
  Foxglove or Lichtblick plot them without Tele-Touch code.

The file's header profile is :data:`PROFILE`; a metadata record named :data:`META_START`
(written first) says which station wrote it and its settings, one named :data:`META_END`
(written on a clean stop) its counts.
"""

from __future__ import annotations

from typing import Any

__all__ = ["DERIVED_SCHEMAS", "META_END", "META_START", "PROFILE", "WIRE_ENCODING",
           "derived_topic", "parse_wire_topic", "wire_topic"]

#: the MCAP header profile of a Tele-Touch recording
PROFILE = "teletouch"
#: format version written into :data:`META_START`
FORMAT_VERSION = "1"
#: metadata record written when recording starts
META_START = "teletouch"
#: metadata record written on a clean stop
META_END = "teletouch.end"
#: message encoding of the wire channels
WIRE_ENCODING = "msgpack"
DIRECTIONS = ("tx", "rx")

_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}
_INT = {"type": "integer"}
_PINS = {"type": "array", "items": _NUM, "minItems": 16, "maxItems": 16}
_PINS_OR_NULL = {"oneOf": [_PINS, {"type": "null"}]}


def _obj(title: str, description: str, props: dict[str, Any],
         required: list[str] | None = None) -> dict[str, Any]:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title,
            "description": description, "type": "object", "properties": props,
            "required": sorted(props) if required is None else required}


#: derived channel name -> JSON Schema (the schema's ``title`` is its MCAP schema name)
DERIVED_SCHEMAS: dict[str, dict[str, Any]] = {
    "latency": _obj(
        "teletouch.Latency",
        "Per-stage delays of one received data message, from its hop stamps, in ms. Stamps "
        "on different clocks are converted to the relay clock with the offsets of the "
        "latest relay stats; a stage whose offset is unknown is null.",
        {"type": {"type": "string"}, "seq": _INT, "end_to_end_ms": _NUM_OR_NULL,
         "stages_ms": {"type": "object", "additionalProperties": _NUM_OR_NULL}}),
    "trajectory": _obj(
        "teletouch.Trajectory",
        "The probe position the local station sent (platform_state, platform frame, mm).",
        {"seq": _INT, "x_mm": _NUM, "y_mm": _NUM, "z_mm": _NUM}),
    "arm": _obj(
        "teletouch.ArmState",
        "The arm tool position (phantom frame, mm) and measured force (N) the remote "
        "station sent.",
        {"seq": _INT, "x_mm": _NUM, "y_mm": _NUM, "z_mm": _NUM, "force_n": _NUM,
         "status": {"type": "string"}}),
    "tactile": _obj(
        "teletouch.Tactile",
        "One tactile frame without its layers: patch centre (platform frame), contact, "
        "force, indentation and the layers' maxima.",
        {"seq": _INT, "center_x_mm": _NUM, "center_y_mm": _NUM, "pitch_mm": _NUM,
         "contact": {"type": "boolean"}, "force_n": _NUM, "indentation_mm": _NUM,
         "height_max_mm": _NUM, "stiffness_n_per_mm_max": _NUM_OR_NULL}),
    "pins": _obj(
        "teletouch.Pins",
        "The 16 pins of the ArrayTac display: commanded height (mm), stiffness k and "
        "friction f, and the heights the board measured (null before its first report, and when "
        "its latest feedback is older than 20 ms). "
        "safe_reason is set while the pins are held in their safe state; no command "
        "exists then: the commanded values are null. Sampled at a fixed rate and at once "
        "on every change between rendering and the safe state.",
        {"commanded_mm": _PINS_OR_NULL, "stiffness_k": _PINS_OR_NULL,
         "friction": _PINS_OR_NULL, "measured_mm": _PINS_OR_NULL,
         "safe_reason": {"type": ["string", "null"]}}),
    "frame_accepted": _obj(
        "teletouch.FrameAccepted",
        "A received tactile frame the local station accepted into its scene (its seq and "
        "station_rx time); the palpation analysis reads these frames.",
        {"seq": _INT, "rx_us": _INT}),
    "findings": _obj(
        "teletouch.Findings",
        "Tumors found by the palpation analysis: centre (phantom frame, mm), type, size "
        "and confidence in [0, 1] when the analysis gives one.",
        {"findings": {"type": "array", "items": {
            "type": "object",
            "properties": {"x_mm": _NUM, "y_mm": _NUM, "kind": {"type": "string"},
                           "radius_mm": _NUM, "confidence": _NUM_OR_NULL,
                           "severity_rank": _INT},
            "required": ["x_mm", "y_mm", "kind"]}}}),
    # the tactile patch as a picture (off by default; ``image_rate_hz``): Foxglove's own
    # schema, so its Image panel shows it. Copied from Foxglove's published JSON schema
    # (npm @foxglove/schemas 2.1.0, jsonschema/CompressedImage); tests compare the two.
    "tactile_image": {
        "title": "foxglove.CompressedImage",
        "description": "A compressed image",
        "$comment": "Generated by https://github.com/foxglove/foxglove-sdk",
        "type": "object",
        "properties": {
            "timestamp": {
                "type": "object", "title": "time",
                "properties": {"sec": {"type": "integer", "minimum": 0},
                               "nsec": {"type": "integer", "minimum": 0,
                                        "maximum": 999999999}},
                "description": "Timestamp of image"},
            "frame_id": {
                "type": "string",
                "description": "Frame of reference for the image. The origin of the frame is "
                "the optical center of the camera. +x points to the right in the image, +y "
                "points down, and +z points into the plane of the image."},
            "data": {"type": "string", "contentEncoding": "base64",
                     "description": "Compressed image data"},
            "format": {"type": "string",
                       "description": "Image format\n\nSupported values: `jpeg`, `png`, "
                       "`webp`, `avif`"}},
        "required": ["timestamp", "frame_id", "data", "format"]},
}


def wire_topic(station: str, direction: str, msg_type: str) -> str:
    """``/<station>/<tx|rx>/<type>``."""
    return f"/{station}/{direction}/{msg_type}"


def parse_wire_topic(topic: str) -> tuple[str, str, str] | None:
    """(station, direction, type) of a wire topic, None for any other topic."""
    parts = topic.split("/")
    if len(parts) == 4 and parts[0] == "" and parts[2] in DIRECTIONS:
        return parts[1], parts[2], parts[3]
    return None


def derived_topic(station: str, name: str) -> str:
    """``/<station>/<name>`` of a derived channel (``name`` in :data:`DERIVED_SCHEMAS`)."""
    if name not in DERIVED_SCHEMAS:
        raise KeyError(f"unknown derived channel {name!r}; known: {sorted(DERIVED_SCHEMAS)}")
    return f"/{station}/{name}"
