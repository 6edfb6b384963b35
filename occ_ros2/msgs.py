"""ROS 2 message types as Cyclone DDS IDL structs, under the type names ROS 2 uses on the wire.

rmw_cyclonedds maps ``pkg/msg/Name`` to the DDS type ``pkg::msg::dds_::Name_`` with the fields
of the ``.msg`` file in order, serialised as plain (XCDR1, little-endian) CDR. Declaring the
same structs here lets a Python process without ROS 2 installed publish and subscribe to ROS 2
topics; tests/ros2/test_msgs.py checks every type byte for byte against ``rosbags`` (the
reference serialiser, ROS 2 Humble type store).

``crtk_msgs`` is not in rosbags' type store; its two messages used here (``OperatingState``,
``StringStamped``) are declared from their ``.msg`` files (collaborative-robotics/crtk_msgs,
ROS 2 branch) and tested against rosbags with those definitions registered (:data:`CRTK_MSG_DEFS`).

This module imports ``cyclonedds``: only ``occ_ros2`` may import it, never ``occ`` or ``igtl``.
"""

# No ``from __future__ import annotations``: cyclonedds resolves string annotations by name
# in this module, and builtins such as ``str`` are not found there.
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import float64, int32, sequence, uint32

if TYPE_CHECKING:  # what the fields hold, for mypy (cyclonedds' sequence is not generic to it)
    StrSeq = list[str]
    F64Seq = list[float]
else:  # what cyclonedds reads from the annotations: unbounded IDL sequences
    StrSeq = sequence[str]
    F64Seq = sequence[float64]

# Every struct below is "final" (cyclonedds' default), which serialises as plain CDR: what
# ROS 2's rmw_cyclonedds writes. Nested structs need ROS names too: types are matched by name.


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32 = 0
    nanosec: uint32 = 0

    @classmethod
    def from_seconds(cls, t: float) -> "Time":
        sec = int(t // 1)
        nanosec = min(int(round((t - sec) * 1e9)), 999_999_999)
        return cls(sec=sec, nanosec=nanosec)

    def to_seconds(self) -> float:
        return self.sec + self.nanosec * 1e-9


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class String(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    data: str = ""


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    # ROS 2's default is the identity (w = 1)
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class PoseStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
    header: Header = field(default_factory=Header)
    pose: Pose = field(default_factory=Pose)


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Transform(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3 = field(default_factory=Vector3)
    rotation: Quaternion = field(default_factory=Quaternion)


@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = field(default_factory=Transform)


@dataclass
class Wrench(IdlStruct, typename="geometry_msgs::msg::dds_::Wrench_"):
    force: Vector3 = field(default_factory=Vector3)
    torque: Vector3 = field(default_factory=Vector3)


@dataclass
class WrenchStamped(IdlStruct, typename="geometry_msgs::msg::dds_::WrenchStamped_"):
    """CRTK's ``measured_cf`` (a Cartesian force, N, and torque, N m)."""

    header: Header = field(default_factory=Header)
    wrench: Wrench = field(default_factory=Wrench)


if TYPE_CHECKING:
    TransformSeq = list[TransformStamped]
else:
    TransformSeq = sequence[TransformStamped]


@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    """tf2's message: ``/tf`` (moving frames) and ``/tf_static`` (fixed ones, latched)."""

    transforms: TransformSeq = field(default_factory=list)


@dataclass
class JointState(IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):
    header: Header = field(default_factory=Header)
    name: StrSeq = field(default_factory=list)
    position: F64Seq = field(default_factory=list)
    velocity: F64Seq = field(default_factory=list)
    effort: F64Seq = field(default_factory=list)


@dataclass
class OperatingState(IdlStruct, typename="crtk_msgs::msg::dds_::OperatingState_"):
    """CRTK's robot meta-state: ``state`` is DISABLED, ENABLED, PAUSED or FAULT."""

    header: Header = field(default_factory=Header)
    state: str = ""
    is_homed: bool = False
    is_busy: bool = False


@dataclass
class StringStamped(IdlStruct, typename="crtk_msgs::msg::dds_::StringStamped_"):
    header: Header = field(default_factory=Header)
    string: str = ""


#: the ``.msg`` definitions of the crtk_msgs types above, for registering them with rosbags
CRTK_MSG_DEFS = {
    "crtk_msgs/msg/OperatingState": "std_msgs/Header header\n"
    "string state\nbool is_homed\nbool is_busy\n",
    "crtk_msgs/msg/StringStamped": "std_msgs/Header header\nstring string\n",
}

#: every type, by its ROS 2 name
ROS_TYPES: dict[str, type[IdlStruct]] = {
    "builtin_interfaces/msg/Time": Time,
    "std_msgs/msg/Header": Header,
    "std_msgs/msg/String": String,
    "geometry_msgs/msg/Point": Point,
    "geometry_msgs/msg/Quaternion": Quaternion,
    "geometry_msgs/msg/Pose": Pose,
    "geometry_msgs/msg/PoseStamped": PoseStamped,
    "geometry_msgs/msg/Vector3": Vector3,
    "geometry_msgs/msg/Transform": Transform,
    "geometry_msgs/msg/TransformStamped": TransformStamped,
    "geometry_msgs/msg/Wrench": Wrench,
    "geometry_msgs/msg/WrenchStamped": WrenchStamped,
    "tf2_msgs/msg/TFMessage": TFMessage,
    "sensor_msgs/msg/JointState": JointState,
    "crtk_msgs/msg/OperatingState": OperatingState,
    "crtk_msgs/msg/StringStamped": StringStamped,
}

#: ROS 2's type hash (REP 2016, ``RIHS01_`` + SHA-256 of the type description) of every type
#: the bridge puts on a topic, as ROS 2 Jazzy computes it; rmw implementations since Jazzy put
#: ``typehash=<hash>;`` in every endpoint's USER_DATA and compare it on discovery. Computed with
#: rosbags (``Typestore.hash_rihs01``, ROS 2 Jazzy store, crtk_msgs from :data:`CRTK_MSG_DEFS`);
#: tests/ros2/test_msgs.py checks each against rosbags, and test_rclpy.py against rclpy's own.
TYPE_HASHES: dict[str, str] = {
    "std_msgs/msg/String":
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "geometry_msgs/msg/PoseStamped":
        "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    "sensor_msgs/msg/JointState":
        "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",
    "crtk_msgs/msg/OperatingState":
        "RIHS01_5cc57eea589b217fe5194bf2735b91d4a7f2dd5ac1245ae657f7ea7590c2c80e",
    "crtk_msgs/msg/StringStamped":
        "RIHS01_83efb802e6596e03f69ac322e3231037329946f2bd13ed48874d97f5b8f5db1d",
    "tf2_msgs/msg/TFMessage":
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    "geometry_msgs/msg/WrenchStamped":
        "RIHS01_8dc3deaf06b2ab281f9f9a742a8961c328ca7cec16e3fd6586d3a5c83fa78f77",
}  # fmt: skip

#: the ROS 2 name of each type (the inverse of :data:`ROS_TYPES`)
ROS_NAMES: dict[type[IdlStruct], str] = {cls: name for name, cls in ROS_TYPES.items()}


def user_data(cls: type[IdlStruct]) -> bytes:
    """The USER_DATA a ROS 2 Jazzy endpoint of type ``cls`` carries: ``typehash=RIHS01_...;``."""
    return f"typehash={TYPE_HASHES[ROS_NAMES[cls]]};".encode("ascii")
