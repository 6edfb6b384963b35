"""Every ROS 2 type of occ_ros2.msgs serialises to the bytes rosbags (the reference) produces.

rosbags' ROS 2 Humble type store is the reference for the standard types; the crtk_msgs types
are registered in a copy of it from their ``.msg`` definitions. Both serialisers emit the 4-byte
encapsulation header (CDR, little-endian) then the body; the whole buffers are compared.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import pytest

from .conftest import require_extra

require_extra()

from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

from occ_ros2 import msgs as m  # noqa: E402

ROS_NAME = {cls: name for name, cls in m.ROS_TYPES.items()}


@pytest.fixture(scope="module")
def typestore() -> Any:
    store = get_typestore(Stores.ROS2_HUMBLE)
    for name, text in m.CRTK_MSG_DEFS.items():
        store.register(get_types_from_msg(text, name))
    return store


def to_rosbags(obj: Any, store: Any) -> Any:
    """The rosbags message with the same field values as a cyclonedds struct."""
    if isinstance(obj, list):
        return [to_rosbags(v, store) for v in obj]
    if type(obj) not in ROS_NAME:
        return obj
    cls = store.types[ROS_NAME[type(obj)]]
    values = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
    kwargs = {k: to_rosbags(v, store) for k, v in values.items()}
    if ROS_NAME[type(obj)] == "sensor_msgs/msg/JointState":
        import numpy as np  # rosbags holds float64 sequences as numpy arrays

        for k in ("position", "velocity", "effort"):
            kwargs[k] = np.array(kwargs[k], dtype=np.float64)
    return cls(**kwargs)


def stamp(frame: str) -> m.Header:
    return m.Header(stamp=m.Time(sec=1_790_000_000, nanosec=123_456_789), frame_id=frame)


SAMPLES: list[Any] = [
    m.Time(sec=-3, nanosec=999_999_999),
    stamp("slave_base"),
    m.String(data="RUNNING"),
    m.String(data=""),
    m.Point(x=0.1, y=-2.5, z=1e-9),
    m.Quaternion(x=0.0, y=math.sqrt(0.5), z=0.0, w=math.sqrt(0.5)),
    m.Pose(),
    m.PoseStamped(
        header=stamp("base"),
        pose=m.Pose(m.Point(0.01, 0.02, -0.12), m.Quaternion(0.1, 0.2, 0.3, math.sqrt(0.86))),
    ),
    m.PoseStamped(header=stamp("a_frame_id_of_odd_length"), pose=m.Pose()),
    m.JointState(
        header=stamp("slave"),
        name=["yaw", "pitch", "insertion"],
        position=[0.0, 0.35, 0.05],
        velocity=[],
        effort=[1.0, -2.0, 3.5],
    ),
    m.OperatingState(header=stamp("slave"), state="ENABLED", is_homed=True, is_busy=False),
    m.OperatingState(header=stamp(""), state="FAULT", is_homed=False, is_busy=True),
    m.StringStamped(header=stamp("slave"), string="enable"),
    m.Vector3(x=1.5, y=-0.25, z=3e-7),
    m.Transform(m.Vector3(0.01, 0.0, -0.2), m.Quaternion(0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5))),
    m.TransformStamped(header=stamp("slave_base"), child_frame_id="slave_tip"),
    m.TFMessage(transforms=[]),
    m.Wrench(force=m.Vector3(1.5, -0.25, 9.75)),
    m.WrenchStamped(
        header=stamp("master_base"),
        wrench=m.Wrench(m.Vector3(-10.0, 0.0, 1e-3), m.Vector3(0.0, 0.5, 0.0)),
    ),
    m.TFMessage(
        transforms=[
            m.TransformStamped(
                header=stamp("world"),
                child_frame_id="slave_base",
                transform=m.Transform(m.Vector3(0.1, 0.2, 0.3), m.Quaternion(0.5, 0.5, 0.5, 0.5)),
            ),
            m.TransformStamped(header=stamp("slave_base"), child_frame_id="slave_tip_odd"),
        ]
    ),
]


@pytest.mark.parametrize("sample", SAMPLES, ids=lambda s: type(s).__name__)
def test_bytes_equal_rosbags(sample: Any, typestore: Any) -> None:
    ours = sample.serialize()
    ref = bytes(typestore.serialize_cdr(to_rosbags(sample, typestore), ROS_NAME[type(sample)]))
    assert ours[:4] == b"\x00\x01\x00\x00"  # CDR little-endian, as rmw_cyclonedds writes
    assert ours == ref, f"{type(sample).__name__}: {len(ours)} vs {len(ref)} bytes"
    # and each side reads the other's bytes back to the same values
    assert type(sample).deserialize(ref) == sample


def test_posestamped_is_84_bytes_with_a_short_frame_id(typestore: Any) -> None:
    """The size the issue quotes (4 encapsulation + 80 body bytes with frame_id "base")."""
    msg = SAMPLES[7]
    assert len(msg.serialize()) == 84


def test_type_hashes_are_rosbags_jazzy_ones() -> None:
    """The RIHS01 hashes the bridge puts in USER_DATA (msgs.TYPE_HASHES) are the ones rosbags
    computes from the type definitions in its ROS 2 Jazzy store (crtk_msgs registered); one
    per type the bridge puts on a topic, and no other (test_rclpy.py checks one against rclpy)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    for name, text in m.CRTK_MSG_DEFS.items():
        store.register(get_types_from_msg(text, name))
    for name, value in m.TYPE_HASHES.items():
        assert value == store.hash_rihs01(name), name
    topic_types = {"std_msgs/msg/String", "geometry_msgs/msg/PoseStamped",
                   "sensor_msgs/msg/JointState", "crtk_msgs/msg/OperatingState",
                   "crtk_msgs/msg/StringStamped", "tf2_msgs/msg/TFMessage",
                   "geometry_msgs/msg/WrenchStamped"}  # fmt: skip
    assert set(m.TYPE_HASHES) == topic_types
    assert m.user_data(m.PoseStamped) == (b"typehash=" + m.TYPE_HASHES[
        "geometry_msgs/msg/PoseStamped"].encode() + b";")  # fmt: skip


def test_every_type_is_sampled() -> None:
    assert {type(s) for s in SAMPLES} == set(m.ROS_TYPES.values())


def test_type_names_follow_rmw_cyclonedds() -> None:
    for ros_name, cls in m.ROS_TYPES.items():
        pkg, kind, name = ros_name.split("/")
        assert cls.__idl_typename__ == f"{pkg}::{kind}::dds_::{name}_"
