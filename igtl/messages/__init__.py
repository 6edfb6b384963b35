"""All message types. Importing this package registers every type with the codec."""

from .base import REGISTRY, Message, RawMessage, register
from .bind import BindChild, BindMessage, GetBindMessage, StartBindMessage
from .capability import CapabilityMessage
from .colortable import ColorTableMessage
from .command import CommandMessage, RTSCommandMessage
from .image import (
    ImageMessage,
    ImageMetaElement,
    ImageMetaMessage,
    LabelMetaElement,
    LabelMetaMessage,
)
from .ndarray import NDArrayMessage
from .point import PointElement, PointMessage, TrajectoryElement, TrajectoryMessage
from .polydata import PolyDataAttribute, PolyDataMessage
from .query import (
    QueryMessage,
    RTSMessage,
    StartPolyDataMessage,
    StartTrackingMessage,
    StartVideoMessage,
)
from .sensor import SensorMessage, Unit
from .status import StatusCode, StatusMessage, StringMessage
from .tracking import (
    QuaternionTrackingDataMessage,
    QuaternionTrackingElement,
    TrackingDataMessage,
    TrackingElement,
)
from .transform import PositionMessage, TransformMessage
from .vfixture import VirtualFixtureMessage
from .video import VideoMessage, VideoMetaElement, VideoMetaMessage

__all__ = [
    "REGISTRY",
    "BindChild",
    "BindMessage",
    "CapabilityMessage",
    "ColorTableMessage",
    "CommandMessage",
    "GetBindMessage",
    "ImageMessage",
    "ImageMetaElement",
    "ImageMetaMessage",
    "LabelMetaElement",
    "LabelMetaMessage",
    "Message",
    "NDArrayMessage",
    "PointElement",
    "PointMessage",
    "PolyDataAttribute",
    "PolyDataMessage",
    "PositionMessage",
    "QuaternionTrackingDataMessage",
    "QuaternionTrackingElement",
    "QueryMessage",
    "RTSCommandMessage",
    "RTSMessage",
    "RawMessage",
    "SensorMessage",
    "StartBindMessage",
    "StartPolyDataMessage",
    "StartTrackingMessage",
    "StartVideoMessage",
    "StatusCode",
    "StatusMessage",
    "StringMessage",
    "TrackingDataMessage",
    "TrackingElement",
    "TrajectoryElement",
    "TrajectoryMessage",
    "TransformMessage",
    "Unit",
    "VideoMessage",
    "VideoMetaElement",
    "VideoMetaMessage",
    "VirtualFixtureMessage",
    "register",
]
