"""Typed errors of the message protocol.

Every decoder of `ddvs_service.protocol` raises only `ProtocolError` subclasses on bad input, never another
exception type. Messages name the field, the value found and what was expected.
"""

from __future__ import annotations


class ProtocolError(ValueError):
    """A message could not be decoded or validated."""


class TruncatedMessage(ProtocolError):
    """The buffer ended before the message did."""


class InconsistentMessage(ProtocolError):
    """The fields contradict each other (e.g. `height*step != len(data)`) or a value is out of its domain."""


class UnsupportedEncoding(ProtocolError):
    """An image encoding or a CDR representation this implementation does not handle."""


class MessageTooLarge(ProtocolError):
    """A message, or a size/length field in it, exceeds the configured maximum (checked before allocating)."""


class InvalidMessage(ProtocolError):
    """A JSON control-plane message is malformed, of the wrong version, or fails its schema."""
