"""Session recordings in MCAP: one file per station, written while it runs, read afterwards.

* :mod:`shared.recording.schemas`: the channels (topics), their encodings and JSON Schemas;
* :mod:`shared.recording.writer`: :class:`McapRecorder`, the background-thread writer a
  station feeds (every wire message it sends and receives, plus derived JSON channels);
* :mod:`shared.recording.reader`: :func:`read_mcap`, which reads a recording (also one cut
  short by a killed station, up to its last complete chunk) and rejects other files with a
  clear :class:`RecordingFormatError`.

``docs/recording.md`` documents the channels.
"""

from shared.recording.reader import McapRecording, RecordedMessage, RecordingFormatError, read_mcap
from shared.recording.schemas import PROFILE, wire_topic
from shared.recording.writer import McapRecorder

__all__ = ["PROFILE", "McapRecorder", "McapRecording", "RecordedMessage", "RecordingFormatError",
           "read_mcap", "wire_topic"]
