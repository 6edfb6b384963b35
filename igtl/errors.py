"""The exception tree of the ``igtl`` package.

::

    IGTLError                          anything igtl raises on purpose
     +-- DecodeError                   the peer's bytes are not a valid OpenIGTLink message
     |    +-- HeaderError              the 58-byte header itself is unusable (stream desynchronised)
     |    |    +-- UnknownHeaderVersionError   VERSION is not 1 or 2
     |    |    +-- BodyTooLargeError           BODY_SIZE > configured limit (nothing allocated)
     |    +-- TruncatedMessageError    fewer bytes than the header announces
     |    +-- CRCError                 CRC-64 of the body does not match the header
     |    +-- ExtendedHeaderError      v2 extended-header sizes do not add up
     |    +-- MetadataError            v2 metadata index/sizes inconsistent or text undecodable
     |    +-- ContentError             the content does not fit its type (sizes, counts, values)
     |    |    +-- InvalidTextError    text bytes not valid in their declared encoding, or a
     |    |         |                      NUL-padded field with bytes after its NUL
     |    |         +-- HeaderTextError    the header's TYPE or DEVICE_NAME is such a field
     |    +-- FragmentError            an RTP datagram that is not a valid fragment (UDP)
     +-- DecoderFailedError            a StreamDecoder was used after an unrecoverable error
     +-- TransportError                a socket-level problem (transports only)
          +-- ConnectionClosedError    the peer went away

Errors raised while decoding carry ``offset`` (byte offset in the message or stream where the
problem was found, when known), ``message_type`` and ``device_name`` (when the header was read).
A :class:`DecodeError` whose ``recoverable`` is true means the header was sound and the stream is
still in sync (the bad message was skipped); otherwise the stream cannot be trusted any more.

Programming mistakes on our side (bad arguments to a constructor) raise ``ValueError`` or
``TypeError``, as usual in Python.
"""

from __future__ import annotations


class IGTLError(Exception):
    """Base class of every error raised on purpose by :mod:`igtl`."""


class DecodeError(IGTLError):
    """Bytes received from a peer do not form a valid OpenIGTLink message."""

    #: True when the header was sound, so the stream is still framed correctly.
    recoverable: bool = True

    def __init__(
        self,
        message: str,
        *,
        offset: int | None = None,
        message_type: str | None = None,
        device_name: str | None = None,
    ) -> None:
        super().__init__(message)
        self.offset = offset
        self.message_type = message_type
        self.device_name = device_name

    def __str__(self) -> str:
        text = super().__str__()
        where = []
        if self.message_type is not None:
            where.append(f"type {self.message_type!r}")
        if self.device_name is not None:
            where.append(f"device {self.device_name!r}")
        if self.offset is not None:
            where.append(f"offset {self.offset}")
        return f"{text} ({', '.join(where)})" if where else text


class HeaderError(DecodeError):
    """The 58-byte header cannot be trusted; the stream is desynchronised."""

    recoverable = False


class UnknownHeaderVersionError(HeaderError):
    """The header VERSION field is neither 1 nor 2."""


class BodyTooLargeError(HeaderError):
    """BODY_SIZE exceeds the configured limit; rejected before any allocation."""


class TruncatedMessageError(DecodeError):
    """The data ends before the message the header announced."""


class CRCError(DecodeError):
    """The CRC-64 over the body does not match the header's CRC field."""


class ExtendedHeaderError(DecodeError):
    """A header-version-2 extended header whose sizes do not add up."""


class MetadataError(DecodeError):
    """Header-version-2 metadata whose index or sizes are inconsistent."""


class ContentError(DecodeError):
    """Message content that does not fit its type (size, element count, field value)."""


class InvalidTextError(ContentError):
    """Text bytes that are not valid in their declared encoding."""


class HeaderTextError(InvalidTextError):
    """The header's TYPE or DEVICE_NAME has bytes after its NUL. Recoverable: the header's
    sizes are sound, so the decoder skips the message's ``body_size`` body bytes."""

    def __init__(self, message: str, *, body_size: int, **kwargs: object) -> None:
        super().__init__(message, **kwargs)  # type: ignore[arg-type]
        self.body_size = body_size


class FragmentError(DecodeError):
    """A datagram that is not a valid RTP-wrapped OpenIGTLink fragment, or fragments that do
    not fit together. Recoverable: only that datagram (or that message) is lost."""


class DecoderFailedError(IGTLError):
    """A StreamDecoder hit an unrecoverable error earlier and refuses further input."""


class TransportError(IGTLError):
    """A socket-level failure in one of the transports."""


class ConnectionClosedError(TransportError):
    """The peer closed the connection."""
