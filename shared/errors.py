"""The one error tree of Tele-Touch.

Every error the project raises on purpose derives from :class:`TeleTouchError`.
Vendor errors (``serial.SerialException``, ``can.CanError``, ``OSError``,
``msgpack`` errors, ...) are wrapped with ``raise ... from err`` so callers catch
one family and still see the cause::

    TeleTouchError
    ├── ConfigError                       bad or missing configuration value
    ├── ProtocolError                     a message broke the Tele-Touch protocol
    │   ├── LocalProtocolError            *we* tried to send something invalid (our bug)
    │   └── RemoteProtocolError           the *peer* sent something invalid (its fault)
    │       ├── MalformedMessageError     not msgpack / not a map / bad framing
    │       ├── VersionError              unsupported protocol version
    │       ├── UnknownMessageTypeError   "type" is not one we know
    │       ├── FieldError                missing field, wrong type, out of range
    │       │   └── NonFiniteError        NaN or Inf in a number or an array
    │       └── OversizeError             frame longer than the configured limit
    ├── SessionError                      session/role/auth refusals by the relay
    │   ├── AuthError                     missing or wrong token
    │   │   ├── TokenExpiredError         a v2 token expired by the relay's clock (not
    │   │   │                             final while the station's clock calls it valid)
    │   │   └── TlsCertificateError       the relay's TLS certificate is not trusted
    │   │                                 (not final: the station link retries it)
    │   ├── RoleTakenError                a second `local`/`remote` in one session
    │   ├── InvalidHelloError             our own hello breaks the rules (never sent)
    │   ├── HandshakeTimeoutError         no hello within the deadline
    │   └── LimitError                    a relay limit: connections, message rate
    ├── DeviceError                       hardware or simulated device trouble
    │   ├── DeviceInitError               could not load the backend (missing dependency),
    │   │                                 open or configure the device: connect() phase
    │   ├── DeviceOperationError          an operation failed on an open device
    │   ├── DeviceTimeoutError            the device did not answer in time
    │   └── DeviceNotConnectedError       used before connect() or after disconnect()
    ├── SafetyError                       a command refused for safety (stale, out of bounds)
    └── NumericalError                    a numerical stage got input it cannot handle
        ├── CalibrationError              missing, mismatched or degenerate calibration
        └── InputDataError                frames/labels of the wrong size, saturated, NaN

Device errors are sorted by phase in one place, :class:`shared.devices.base.Device`:
vendor errors raised while connecting become ``DeviceInitError``, while operating
``DeviceOperationError`` (``TimeoutError`` -> ``DeviceTimeoutError``); the backend loader
(:mod:`shared.devices.registry`) raises ``ConfigError`` for an unknown backend name or a
class of the wrong kind, and ``DeviceInitError`` when the backend's module cannot be
imported.

Protocol errors carry a stable machine-readable ``code`` (sent in ``error``
messages) and the WebSocket close code the relay uses when it drops the peer.
"""

from __future__ import annotations

__all__ = [
    "AuthError",
    "CalibrationError",
    "ConfigError",
    "DeviceError",
    "DeviceInitError",
    "DeviceNotConnectedError",
    "DeviceOperationError",
    "DeviceTimeoutError",
    "FieldError",
    "HandshakeTimeoutError",
    "InputDataError",
    "InvalidHelloError",
    "LimitError",
    "LocalProtocolError",
    "MalformedMessageError",
    "NonFiniteError",
    "NumericalError",
    "OversizeError",
    "ProtocolError",
    "RemoteProtocolError",
    "RoleTakenError",
    "SafetyError",
    "SessionError",
    "TeleTouchError",
    "TlsCertificateError",
    "TokenExpiredError",
    "UnknownMessageTypeError",
    "VersionError",
]


class TeleTouchError(Exception):
    """Base of every error Tele-Touch raises on purpose."""


class ConfigError(TeleTouchError):
    """A configuration value is missing, of the wrong type or out of range."""


# --------------------------------------------------------------------------- protocol


class ProtocolError(TeleTouchError):
    """A message broke the protocol.

    Attributes:
        code: stable machine-readable reason, sent in ``error`` messages.
        close_code: WebSocket close code used when the peer is dropped for it.
    """

    code: str = "protocol_error"
    close_code: int = 1002

    def __init__(self, message: str, *, code: str | None = None) -> None:
        super().__init__(message)
        if code is not None:
            self.code = code


class LocalProtocolError(ProtocolError):
    """We tried to send an invalid message: a bug on this side, never the peer's."""

    code = "local_error"
    close_code = 1011


class RemoteProtocolError(ProtocolError):
    """The peer sent an invalid message: its fault, reported back to it."""

    code = "bad_message"
    close_code = 1002


class MalformedMessageError(RemoteProtocolError):
    """Bytes that are not a msgpack map, or a broken length prefix."""

    code = "malformed"
    close_code = 1007


class VersionError(RemoteProtocolError):
    """The peer speaks a protocol version we do not support."""

    code = "version"
    close_code = 1002


class UnknownMessageTypeError(RemoteProtocolError):
    """The ``type`` field names no known message."""

    code = "unknown_type"
    close_code = 1003


class FieldError(RemoteProtocolError):
    """A field is missing, has the wrong type, or is out of range."""

    code = "bad_field"
    close_code = 1007


class NonFiniteError(FieldError):
    """A number or an array element is NaN or infinite."""

    code = "non_finite"
    close_code = 1007


class OversizeError(RemoteProtocolError):
    """A frame is longer than the configured maximum."""

    code = "oversize"
    close_code = 1009


# --------------------------------------------------------------------------- sessions


class SessionError(TeleTouchError):
    """The relay refused a session, role or credential."""

    code: str = "session"
    close_code: int = 4000
    #: a finer cause within ``code``, sent as the ``error``'s ``reason`` (None: none)
    reason: str | None = None

    def __init__(self, message: str, *, code: str | None = None) -> None:
        super().__init__(message)
        if code is not None:
            self.code = code


class AuthError(SessionError):
    """Missing or wrong token for the session."""

    code = "auth"
    close_code = 4001


class TokenExpiredError(AuthError):
    """A version-2 token past its expiry by the relay's clock: ``auth`` with ``reason``
    ``expired`` on the wire (a station of an older release reads a plain ``auth``). Final for
    a station whose own clock agrees; one whose clock says the token is still valid retries,
    since one of the two clocks is wrong (often for a while after a boot)."""

    reason = "expired"


class TlsCertificateError(AuthError):
    """The relay's TLS certificate failed verification (unknown CA, wrong host name,
    expired): the relay could not prove who it is, so the station does not send its token."""

    code = "tls_certificate"


class RoleTakenError(SessionError):
    """The role (``local`` or ``remote``) is already held in this session."""

    code = "role_taken"
    close_code = 4002


class ReplacedError(SessionError):
    """A newer connection of the same station resumed the session (it proved the
    per-connection ``resume`` secret of this one), so the relay closed this one."""

    code = "replaced"
    close_code = 4004


class InvalidHelloError(SessionError):
    """The station's own ``hello`` breaks the protocol's rules (session id, token or name
    invalid or too long): the relay could never accept it, so the station does not send it
    and does not retry. Raised on the station's side; never sent by the relay."""

    code = "invalid_hello"


class PeerSilentError(SessionError):
    """A station sent nothing (not even a ``clock_pong``) for the relay's silence limit: its
    connection is dead or blackholed, and it would hold its role until TCP gives up."""

    code = "silent"
    close_code = 4005


class HandshakeTimeoutError(SessionError):
    """The peer sent no ``hello`` within the deadline."""

    code = "hello_timeout"
    close_code = 4003


class LimitError(SessionError):
    """A relay limit refused the connection or its traffic.

    Codes: ``too_many_connections`` (close 1013, try again later) and ``rate_limited``
    (close 1008 when sustained).
    """

    code = "limit"
    close_code = 1008

    def __init__(self, message: str, *, code: str | None = None,
                 close_code: int | None = None) -> None:
        super().__init__(message, code=code)
        if close_code is not None:
            self.close_code = close_code


# --------------------------------------------------------------------------- devices


class DeviceError(TeleTouchError):
    """Base for hardware and simulated device failures."""


class DeviceInitError(DeviceError):
    """The device could not be opened or configured (unplugged, wrong URL, busy)."""


class DeviceOperationError(DeviceError):
    """An operation failed on an open device."""


class DeviceTimeoutError(DeviceError):
    """The device did not answer within the timeout."""


class DeviceNotConnectedError(DeviceError):
    """The device was used before ``connect()`` or after ``disconnect()``."""


class SafetyError(TeleTouchError):
    """A command was refused for safety: too old, out of bounds, over the force limit."""


class CommandExpiredError(SafetyError):
    """A device was handed a command after the deadline it came with (it did not act)."""


# --------------------------------------------------------------------------- numerics


class NumericalError(TeleTouchError):
    """A numerical stage got input it cannot process safely."""


class CalibrationError(NumericalError):
    """A calibration is missing, mismatched with the data, or degenerate."""


class InputDataError(NumericalError):
    """Input data of the wrong size or type, saturated, all black, or non-finite."""
