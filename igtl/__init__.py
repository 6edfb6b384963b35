"""A complete, hardened OpenIGTLink implementation: codec (sans-IO) and transports.

Quick use::

    import igtl
    msg = igtl.TransformMessage.from_matrix(m, device_name="Tip")
    data = msg.pack()
    same = igtl.unpack(data)           # CRC verified
    dec = igtl.StreamDecoder()
    dec.feed(data[:10]); dec.feed(data[10:])
    for m in dec: ...
"""

from . import wire
from .codec import StreamDecoder, decode_body, unpack
from .errors import (
    BodyTooLargeError,
    ConnectionClosedError,
    ContentError,
    CRCError,
    DecodeError,
    DecoderFailedError,
    ExtendedHeaderError,
    FragmentError,
    HeaderError,
    IGTLError,
    InvalidTextError,
    MetadataError,
    TransportError,
    TruncatedMessageError,
    UnknownHeaderVersionError,
)
from .messages import *  # noqa: F403
from .messages import __all__ as _messages_all

__version__ = "0.1.0"

__all__ = [
    "BodyTooLargeError",
    "CRCError",
    "ConnectionClosedError",
    "ContentError",
    "DecodeError",
    "DecoderFailedError",
    "ExtendedHeaderError",
    "FragmentError",
    "HeaderError",
    "IGTLError",
    "InvalidTextError",
    "MetadataError",
    "StreamDecoder",
    "TransportError",
    "TruncatedMessageError",
    "UnknownHeaderVersionError",
    "decode_body",
    "unpack",
    "wire",
    *_messages_all,
]
