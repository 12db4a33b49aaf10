"""The Tele-Touch wire protocol, sans-I/O: messages, msgpack codec, TCP framing, and the
session state machines of both ends (:mod:`~shared.protocol.station_session` for stations,
:mod:`~shared.protocol.peer_session` for the relay's side of each connection).

See ``docs/protocol.md`` for the byte-level specification.
"""

from shared.protocol.codec import (
    DEFAULT_MAX_MESSAGE_BYTES,
    PROTOCOL_VERSION,
    SUPPORTED_VERSIONS,
    decode,
    decode_map,
    encode,
    message_from_map,
)
from shared.protocol.connection import (
    ConnectionFailed,
    Event,
    MessageReceived,
    MessageRejected,
    ProtocolConnection,
)
from shared.protocol.framing import LengthPrefixDecoder, frame
from shared.protocol.messages import (
    CLOCKS,
    LATEST_WINS_TYPES,
    LAYER_RANGES,
    MESSAGE_TYPES,
    ROLES,
    ArmCommand,
    ArmState,
    Bye,
    ClockPing,
    ClockPong,
    DataMessage,
    Error,
    Hello,
    Hop,
    Message,
    PlatformState,
    Stats,
    StreamPolicy,
    TactileCompact,
    TactileFrame,
    Welcome,
    carry_motion,
)
from shared.protocol.queues import StreamQueue

__all__ = [
    "CLOCKS",
    "DEFAULT_MAX_MESSAGE_BYTES",
    "LATEST_WINS_TYPES",
    "LAYER_RANGES",
    "MESSAGE_TYPES",
    "PROTOCOL_VERSION",
    "ROLES",
    "SUPPORTED_VERSIONS",
    "ArmCommand",
    "ArmState",
    "Bye",
    "ClockPing",
    "ClockPong",
    "ConnectionFailed",
    "DataMessage",
    "Error",
    "Event",
    "Hello",
    "Hop",
    "LengthPrefixDecoder",
    "Message",
    "MessageReceived",
    "MessageRejected",
    "PlatformState",
    "ProtocolConnection",
    "Stats",
    "StreamPolicy",
    "StreamQueue",
    "TactileCompact",
    "TactileFrame",
    "Welcome",
    "carry_motion",
    "decode",
    "decode_map",
    "encode",
    "frame",
    "message_from_map",
]
