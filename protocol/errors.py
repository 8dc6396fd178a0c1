"""Exceptions of the protocol package; each carries the ERROR code a segment answers with."""

from protocol.constants import (
    ERR_BAD_VALUE,
    ERR_MALFORMED,
    ERR_UNKNOWN_TYPE,
    ERR_UNSUPPORTED_VERSION,
)


class ProtocolError(ValueError):
    """Base of every protocol decode/encode error; ``code`` is the wire error code to reply."""

    code = ERR_MALFORMED


class MalformedError(ProtocolError):
    """Bytes that are not a valid frame / CBOR item / message layout (ERROR code 5)."""

    code = ERR_MALFORMED


class BadValueError(ProtocolError):
    """Well-formed message with a value out of range, NaN, wrong kind (ERROR code 2)."""

    code = ERR_BAD_VALUE


class UnknownTypeError(ProtocolError):
    """Message type this implementation does not know (ERROR code 1)."""

    code = ERR_UNKNOWN_TYPE


class UnsupportedVersionError(ProtocolError):
    """Frame of a protocol version this implementation does not speak (ERROR code 3)."""

    code = ERR_UNSUPPORTED_VERSION
