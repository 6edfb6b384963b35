"""All message types. Importing this package registers every type with the codec."""

from .base import REGISTRY, Message, RawMessage, register
from .status import StatusCode, StatusMessage, StringMessage
from .transform import PositionMessage, TransformMessage

__all__ = [
    "REGISTRY",
    "Message",
    "PositionMessage",
    "RawMessage",
    "StatusCode",
    "StatusMessage",
    "StringMessage",
    "TransformMessage",
    "register",
]
