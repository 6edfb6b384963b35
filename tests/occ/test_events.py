"""The typed-event layer (issue 39): occ/events.py's values, occ/net/decoders.py (every message a
controller takes to its event) and occ/net/packers.py (every typed output to its message), each
field checked through the wire (packed, unpacked, decoded) and what each refuses. Written for
the `events` mutation module (scripts/mutate events, docs/VERIFICATION.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

import igtl
from igtl.messages.polydata import CELL_SCALAR
from igtl.messages.sensor import Unit
from igtl.messages.transform import POSITION_ALL, POSITION_QUATERNION3
from occ.errors import OCCError
from occ.events import (
    ArrayInput,
    ForceReading,
    Mesh,
    MeshOut,
    Point,
    PointList,
    PointsOut,
    PolylineOut,
    SphereList,
    TrajectoryElement,
    TrajectoryList,
    TransformOut,
    UnknownInput,
    VectorOut,
)
from occ.net.decoders import DECODERS, decode, event_of, message_torque
from occ.net.packers import mesh_message, pack_output, transform_message
from occ.samples import PoseSample


def test_an_input_names_itself_by_its_type_and_quoted_device() -> None:
    ev = UnknownInput("ops", None, 0.0, "STRING", "Cmd's", {})
    assert ev.describe() == 'STRING "Cmd\'s"'


# ------------------------------------------------------------------------------ decoders
def _wire(msg: igtl.Message) -> Any:
    """The message as a peer's bytes read back: what the interface decodes."""
    return igtl.unpack(msg.pack())


META = {"kind": "tissue", "x": "y"}


def _common(ev: Any, kind: str, device: str, meta: dict[str, str] | None = None) -> None:
    assert (ev.interface, ev.peer, ev.t_rx) == ("master", PEER, 0.25)
    assert (ev.kind, ev.device) == (kind, device)
    assert dict(ev.meta) == (META if meta is None else meta)


PEER = ("127.0.0.1", 4000)


def test_a_point_list_keeps_every_points_name_position_radius_and_visibility() -> None:
    msg = igtl.PointMessage(
        (
            igtl.PointElement("p0", "G", (1, 2, 3, 255), (1.5, -2.0, 3.25), 2.5),
            igtl.PointElement("p1", "G", (1, 2, 3, 0), (0.0, 0.0, -1.0), 0.0),
            igtl.PointElement("p2", "G", (0, 0, 0, 1), (4.0, 5.0, 6.0), 0.5),
        ),
        device_name="Pts",
        header_version=2,
        metadata=META,
    )
    ev = decode("master", PEER, _wire(msg), 0.25)
    assert isinstance(ev, PointList)
    _common(ev, "POINT", "Pts")
    assert ev.points == (
        Point("p0", (1.5, -2.0, 3.25), 2.5, True),
        Point("p1", (0.0, 0.0, -1.0), 0.0, False),  # alpha 0: hidden
        Point("p2", (4.0, 5.0, 6.0), 0.5, True),  # the least alpha drawn
    )
    assert all(type(v) is float for p in ev.points for v in (*p.position, p.radius))


def test_a_trajectory_list_keeps_every_elements_name_type_entry_target_and_visibility() -> None:
    msg = igtl.TrajectoryMessage(
        (
            igtl.TrajectoryElement("t0", "G", 1, (9, 9, 9, 1), (1.0, 2.0, 3.0), (4.0, 5.0, 6.5)),
            igtl.TrajectoryElement("t1", "G", 2, (9, 9, 9, 0), (-1.0, 0.0, 1.0), (7.0, 8.0, 9.0)),
            igtl.TrajectoryElement("t2", "G", 3, (9, 9, 9, 255), (0.5, 0.25, 0.0), (1.0, 1.0, 1.0)),
        ),
        device_name="Plan",
        header_version=2,
        metadata=META,
    )
    ev = decode("master", PEER, _wire(msg), 0.25)
    assert isinstance(ev, TrajectoryList)
    _common(ev, "TRAJ", "Plan")
    assert ev.elements == (
        TrajectoryElement("t0", 1, (1.0, 2.0, 3.0), (4.0, 5.0, 6.5), True),
        TrajectoryElement("t1", 2, (-1.0, 0.0, 1.0), (7.0, 8.0, 9.0), False),
        TrajectoryElement("t2", 3, (0.5, 0.25, 0.0), (1.0, 1.0, 1.0), True),
    )
    assert all(type(e.type) is int for e in ev.elements)
    assert all(type(v) is float for e in ev.elements for v in (*e.entry, *e.target))


def test_a_sphere_list_keeps_its_version_hardness_and_every_sphere() -> None:
    msg = igtl.VirtualFixtureMessage(
        2.5, ((1.0, 2.0, 3.0, 4.0), (-1.0, -2.0, -3.0, 0.5)), version=2,
        device_name="VF", header_version=2, metadata=META,
    )  # fmt: skip
    ev = decode("master", PEER, _wire(msg), 0.25)
    assert isinstance(ev, SphereList)
    _common(ev, "VFIXTURE", "VF")
    assert (ev.version, ev.hardness) == (2, 2.5)
    assert ev.spheres == ((1.0, 2.0, 3.0, 4.0), (-1.0, -2.0, -3.0, 0.5))
    assert type(ev.version) is int and type(ev.hardness) is float
    empty = decode("master", PEER, _wire(igtl.VirtualFixtureMessage(device_name="VF")), 0.25)
    assert (empty.version, empty.hardness, empty.spheres) == (1, 0.0, ())
    assert dict(empty.meta) == {}


def test_a_mesh_keeps_its_points_and_every_kind_of_cell() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 2.5]])
    msg = igtl.PolyDataMessage(
        points=pts, vertices=((0,),), lines=((0, 1), (3, 2, 1)), polygons=((0, 1, 2),),
        strips=((0, 1, 2, 3),), device_name="M", header_version=2, metadata=META,
    )  # fmt: skip
    ev = decode("master", PEER, _wire(msg), 0.25)
    assert isinstance(ev, Mesh)
    _common(ev, "POLYDATA", "M")
    assert ev.points.dtype == np.float64 and ev.points.shape == (4, 3)
    assert ev.points.tolist() == pts.tolist()
    assert ev.lines == ((0, 1), (3, 2, 1)) and ev.polygons == ((0, 1, 2),)
    assert ev.strips == ((0, 1, 2, 3),)
    assert all(type(i) is int for c in (*ev.lines, *ev.polygons, *ev.strips) for i in c)
    bare = decode("master", PEER, _wire(igtl.PolyDataMessage(device_name="M")), 0.25)
    assert bare.points.shape == (0, 3) and (bare.lines, bare.polygons, bare.strips) == ((),) * 3


def test_a_reading_keeps_its_unit_as_named_and_every_value() -> None:
    msg = igtl.SensorMessage(
        data=(1.0, -2.5, 3.0, 0.125), unit=Unit(11, ((11, 1),)), device_name="Force",
        header_version=2, metadata=META,
    )  # fmt: skip
    ev = decode("master", PEER, _wire(msg), 0.25)
    assert isinstance(ev, ForceReading)
    _common(ev, "SENSOR", "Force")
    assert ev.unit == "milliN" and ev.values == (1.0, -2.5, 3.0, 0.125)
    assert all(type(v) is float for v in ev.values)


def test_an_array_is_kept_as_sent_and_cannot_be_changed() -> None:
    a = np.arange(6, dtype=np.int16).reshape(2, 3)
    msg = igtl.NDArrayMessage(array=a, device_name="Path", header_version=2, metadata=META)
    ev = decode("master", PEER, _wire(msg), 0.25)
    assert isinstance(ev, ArrayInput)
    _common(ev, "NDARRAY", "Path")
    assert ev.array.dtype == np.int16 and ev.array.tolist() == a.tolist()
    with pytest.raises(ValueError):
        ev.array[0, 0] = 9  # shared with the message's bytes: read-only
    # a message made in the process (a replay, a test): its event's array is read-only too
    held = decode("master", PEER, igtl.NDArrayMessage(array=np.zeros(3), device_name="P"), 0.25)
    with pytest.raises(ValueError):
        held.array[0] = 1.0


def test_a_message_no_decoder_takes_is_unknown_with_its_type_device_and_sender() -> None:
    msg = igtl.StringMessage("go", device_name="CMD_1", header_version=2, metadata=META)
    ev = decode("master", PEER, _wire(msg), 0.25)
    assert type(ev) is UnknownInput
    _common(ev, "STRING", "CMD_1")
    assert ev.describe() == "STRING 'CMD_1'"


@pytest.mark.parametrize("mtype", ["VFIXTURE", "POINT", "TRAJ", "POLYDATA", "SENSOR", "NDARRAY"])
def test_a_message_whose_content_was_never_decoded_is_unknown_never_an_empty_definition(
    mtype: str,
) -> None:
    """A RawMessage naming a type a decoder takes (made in the process: a replay's, a test's)
    has no fields to read: it is refused as unknown. Before, a VFIXTURE one became a sphere list
    of version 1, hardness 0 and no spheres, a definition that clears the device's spheres."""
    raw = igtl.RawMessage(type_name=mtype, content=b"\x01\x00", device_name="VF", metadata=META)
    ev = decode("master", PEER, raw, 0.25)
    assert type(ev) is UnknownInput
    _common(ev, mtype, "VF")


def test_a_pose_decodes_to_its_sample() -> None:
    msg = igtl.PositionMessage(
        (1.0, 2.0, 3.0), device_name="Handle", header_version=2, message_id=9, metadata={"a": "b"}
    )
    for m in (msg, igtl.TransformMessage.from_matrix(np.eye(4), device_name="Handle")):
        ev = decode("master", PEER, _wire(m), 0.25)
        assert isinstance(ev, PoseSample)
        assert (ev.interface, ev.peer, ev.t_rx, ev.device) == ("master", PEER, 0.25, "Handle")
        assert ev.kind == m.message_type


def test_every_type_a_controller_takes_has_its_decoder() -> None:
    assert sorted(DECODERS) == sorted(
        ["POSITION", "TRANSFORM", "POINT", "TRAJ", "VFIXTURE", "POLYDATA", "SENSOR", "NDARRAY"]
    )


def test_event_of_decodes_as_if_from_nobody_at_time_zero() -> None:
    ev = event_of(igtl.StringMessage("go", device_name="C"))
    assert (ev.interface, ev.peer, ev.t_rx) == ("", None, 0.0)
    ev = event_of(igtl.StringMessage("go", device_name="C"), "ops", PEER, 2.0)
    assert (ev.interface, ev.peer, ev.t_rx) == ("ops", PEER, 2.0)


def test_a_recorded_torque_is_read_from_its_metadata() -> None:
    def sensor(meta: dict[str, str]) -> Any:
        return igtl.SensorMessage(data=(1.0, 2.0, 3.0), device_name="Force", header_version=2,
                                  metadata=meta)  # fmt: skip

    assert message_torque(sensor({"torque_nm": "0.5,-1,2"})) == (0.5, -1.0, 2.0)
    assert message_torque(sensor({})) is None
    assert message_torque(sensor({"torque_nm": "1,2"})) is None
    assert message_torque(sensor({"force_n": "1,2,3"})) is None


# ------------------------------------------------------------------------------ packers
@dataclass(frozen=True)
class Out:
    """An output as configured (occ/net/packers.py's Target)."""

    type: str
    device: str = "Dev"
    header_version: int = 2


def _packed(value: Any, out: Out) -> Any:
    """The value as packed for ``out``, read back from its bytes as a peer would."""
    back = igtl.unpack(pack_output(value, out).pack())
    assert (back.message_type, back.device_name) == (out.type, out.device)
    assert back.header_version == out.header_version
    return back


def _pose(q: tuple[float, float, float, float] = (0.0, 0.0, 0.6, 0.8), seq: int | None = 41) -> Any:
    return PoseSample(
        "i", None, "Tip", (1.5, -2.0, 3.25), q, seq=seq, t_sample=1234.5, meta={"state": "run"}
    )


def test_a_pose_goes_as_a_version_2_position_with_its_sequence_number_and_metadata() -> None:
    back = _packed(_pose(), Out("POSITION"))
    assert back.position == (1.5, -2.0, 3.25) and back.layout == POSITION_ALL
    assert back.quaternion == pytest.approx((0.0, 0.0, 0.6, 0.8))
    assert back.message_id == 41 and back.timestamp == pytest.approx(1234.5)
    assert dict(back.metadata) == {"state": "run"}
    assert _packed(_pose(seq=None), Out("POSITION")).message_id == 0  # none: 0


def test_a_pose_goes_as_a_version_1_position_without_metadata() -> None:
    back = _packed(_pose(), Out("POSITION", header_version=1))
    assert back.position == (1.5, -2.0, 3.25) and back.layout == POSITION_ALL
    assert back.quaternion == pytest.approx((0.0, 0.0, 0.6, 0.8))
    assert back.timestamp == pytest.approx(1234.5) and dict(back.metadata) == {}


@pytest.mark.parametrize("version", [1, 2])
def test_a_pose_without_rotation_goes_in_the_24_byte_form(version: int) -> None:
    back = _packed(_pose((0.0, 0.0, 0.0, 1.0)), Out("POSITION", header_version=version))
    assert back.layout == POSITION_QUATERNION3 and back.quaternion == (0.0, 0.0, 0.0, 1.0)
    # the same rotation with w < 0 is turned to w >= 0 before the form is chosen
    back = _packed(_pose((-0.0, -0.0, -0.0, -1.0)), Out("POSITION", header_version=version))
    assert back.layout == POSITION_QUATERNION3 and back.quaternion == (0.0, 0.0, 0.0, 1.0)


@pytest.mark.parametrize("version", [1, 2])
def test_a_pose_with_w_negative_goes_as_the_same_rotation_with_w_positive(version: int) -> None:
    back = _packed(_pose((0.1, -0.2, 0.6, -0.7)), Out("POSITION", header_version=version))
    assert back.layout == POSITION_ALL
    assert back.quaternion == pytest.approx((-0.1, 0.2, -0.6, 0.7))
    # w = 0 exactly (a half turn) is left as it is
    back = _packed(_pose((0.0, -1.0, 0.0, 0.0)), Out("POSITION", header_version=version))
    assert back.quaternion == (0.0, -1.0, 0.0, 0.0)


def test_a_pose_goes_as_a_transform_with_its_matrix_and_in_version_2_its_metadata() -> None:
    pose = _pose()
    back = _packed(pose, Out("TRANSFORM"))
    assert back.matrix == pytest.approx(pose.matrix_mm(), abs=1e-6)
    assert back.message_id == 41 and back.timestamp == pytest.approx(1234.5)
    assert dict(back.metadata) == {"state": "run"}
    assert _packed(_pose(seq=None), Out("TRANSFORM")).message_id == 0
    v1 = _packed(pose, Out("TRANSFORM", header_version=1))
    assert v1.matrix == pytest.approx(pose.matrix_mm(), abs=1e-6)
    assert v1.message_id == 0 and dict(v1.metadata) == {}
    assert v1.timestamp == pytest.approx(1234.5)


def test_a_pose_on_any_other_type_is_refused() -> None:
    with pytest.raises(OCCError, match="^output type POINT cannot carry a pose$"):
        pack_output(_pose(), Out("POINT"))


@pytest.mark.parametrize("version", [1, 2])
def test_readings_go_as_sensor_with_their_unit_code(version: int) -> None:
    value = VectorOut((1, -2.5, 3), 99.5, "N", {"frame": "patient"})
    back = _packed(value, Out("SENSOR", header_version=version))
    assert back.data == (1.0, -2.5, 3.0) and str(back.unit) == "N"
    assert back.unit == Unit(0, ((11, 1),)) and back.timestamp == pytest.approx(99.5)
    assert dict(back.metadata) == ({"frame": "patient"} if version == 2 else {})
    plain = _packed(VectorOut((0.5,), 1.0), Out("SENSOR", header_version=version))
    assert plain.unit == Unit() and plain.data == (0.5,)
    assert dict(plain.metadata) == {}  # none given
    rad = _packed(VectorOut((0.5,), 1.0, "rad"), Out("SENSOR", header_version=version))
    assert rad.unit == Unit(0, ((8, 1),))


def test_readings_in_a_unit_sensor_has_no_code_for_are_refused() -> None:
    with pytest.raises(OCCError, match="^SENSOR: no unit code for 'mm'$"):
        pack_output(VectorOut((1.0,), 0.0, "mm"), Out("SENSOR"))


@pytest.mark.parametrize("version", [1, 2])
def test_readings_go_as_a_float64_array_with_the_unit_in_version_2_metadata(version: int) -> None:
    value = VectorOut((1, -2.5, 3), 99.5, "N", {"frame": "patient"})
    back = _packed(value, Out("NDARRAY", header_version=version))
    assert back.array.dtype == np.float64 and back.array.tolist() == [1.0, -2.5, 3.0]
    assert back.timestamp == pytest.approx(99.5)
    meta = {"frame": "patient", "unit": "N"} if version == 2 else {}
    assert dict(back.metadata) == meta
    plain = _packed(VectorOut((0.5,), 1.0), Out("NDARRAY", header_version=version))
    assert dict(plain.metadata) == {}  # no unit, no metadata: none said


@pytest.mark.parametrize("type_", ["SENSOR", "NDARRAY"])
def test_readings_given_as_integers_go_as_float64(type_: str) -> None:
    """A source's whole numbers (a count, a force rounded to newtons) go as the float64
    readings both types promise, never as an NDARRAY of integers."""
    back = _packed(VectorOut((1, 2, -3), 0.0, "N"), Out(type_))
    values = back.data if type_ == "SENSOR" else back.array
    assert np.asarray(values).dtype == np.float64 and list(values) == [1.0, 2.0, -3.0]


def test_readings_on_any_other_type_are_refused() -> None:
    with pytest.raises(OCCError, match="^readings go as SENSOR or NDARRAY, not POINT$"):
        pack_output(VectorOut((1.0,), 0.0, "N"), Out("POINT"))


@pytest.mark.parametrize("version", [1, 2])
def test_a_point_list_goes_as_point_with_every_name_position_group_and_colour(version: int) -> None:
    value = PointsOut(["a", "b"], [(1, 2, 3), (4.5, -5.0, 6.0)], 7.5, meta={"k": "v"})
    back = _packed(value, Out("POINT", header_version=version))
    assert [(p.name, p.group, p.rgba, p.position) for p in back.points] == [
        ("a", "Point", (255, 200, 0, 255), (1.0, 2.0, 3.0)),
        ("b", "Point", (255, 200, 0, 255), (4.5, -5.0, 6.0)),
    ]
    assert back.timestamp == pytest.approx(7.5)
    assert dict(back.metadata) == ({"k": "v"} if version == 2 else {})
    mine = PointsOut(["c"], [(0, 0, 0)], 0.0, group="Landmark", rgba=(1, 2, 3, 4))
    (p,) = _packed(mine, Out("POINT", header_version=version)).points
    assert (p.group, p.rgba) == ("Landmark", (1, 2, 3, 4))


def test_a_point_name_longer_than_the_field_is_cut_at_a_whole_character() -> None:
    # 63 bytes then a 2-byte letter: the field's 64 bytes would split it; it is left out
    name = "x" * 63 + "é" + "tail"
    (p,) = _packed(PointsOut([name], [(0, 0, 0)], 0.0), Out("POINT")).points
    assert p.name == "x" * 63
    (q,) = _packed(PointsOut(["é" * 32 + "z"], [(0, 0, 0)], 0.0), Out("POINT")).points
    assert q.name == "é" * 32  # exactly 64 bytes


def test_a_point_list_whose_names_and_positions_differ_in_number_is_refused() -> None:
    with pytest.raises(ValueError):
        pack_output(PointsOut(["a", "b"], [(0, 0, 0)], 0.0), Out("POINT"))


def test_a_point_list_on_any_other_type_is_refused() -> None:
    with pytest.raises(OCCError, match="^a point list goes as POINT, not POLYDATA$"):
        pack_output(PointsOut(["a"], [(0, 0, 0)], 0.0), Out("POLYDATA"))


@pytest.mark.parametrize("version", [1, 2])
def test_a_polyline_goes_as_polydata_with_one_line_through_its_points(version: int) -> None:
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [4.0, 5.0, 6.5]])
    back = _packed(PolylineOut(pts, 3.0, {"k": "v"}), Out("POLYDATA", header_version=version))
    assert back.points.tolist() == pts.tolist() and back.lines == ((0, 1, 2),)
    assert back.polygons == () and back.timestamp == pytest.approx(3.0)
    assert dict(back.metadata) == ({"k": "v"} if version == 2 else {})
    two = _packed(PolylineOut(pts[:2], 3.0), Out("POLYDATA", header_version=version))
    assert two.lines == ((0, 1),) and dict(two.metadata) == {}
    one = _packed(PolylineOut(pts[:1], 3.0), Out("POLYDATA", header_version=version))
    assert one.lines == () and one.points.tolist() == [[0.0, 0.0, 0.0]]  # no line of one point


def test_a_polyline_on_any_other_type_is_refused() -> None:
    with pytest.raises(OCCError, match="^a polyline goes as POLYDATA, not POINT$"):
        pack_output(PolylineOut(np.zeros((2, 3)), 0.0), Out("POINT"))


def _model(v2: bool = False, meta: dict[str, str] | None = None) -> MeshOut:
    return MeshOut(
        np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 2.5]), 4.5, lines=((0, 1),),
        polygons=((0, 1, 2),), cell_scalars=(("hard", np.array([1.0, 0.5])),), meta=meta, v2=v2,
    )  # fmt: skip


@pytest.mark.parametrize("version", [1, 2])
def test_a_model_goes_as_polydata_with_its_cells_and_cell_scalars(version: int) -> None:
    back = _packed(_model(meta={"k": "v"}), Out("POLYDATA", header_version=version))
    assert back.points.tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 2.5]]
    assert back.lines == ((0, 1),) and back.polygons == ((0, 1, 2),)
    (attr,) = back.attributes
    assert (attr.type, attr.name) == (CELL_SCALAR, "hard")
    assert np.asarray(attr.data).ravel().tolist() == [1.0, 0.5]
    assert back.timestamp == pytest.approx(4.5)
    assert dict(back.metadata) == ({"k": "v"} if version == 2 else {})
    assert dict(_packed(_model(), Out("POLYDATA", header_version=version)).metadata) == {}


def test_a_model_that_says_v2_goes_in_version_2_with_its_metadata_whatever_the_output() -> None:
    msg = igtl.unpack(mesh_message(_model(True, {"k": "v"}), "M", 1).pack())
    assert msg.header_version == 2 and dict(msg.metadata) == {"k": "v"}
    assert msg.device_name == "M"
    default = igtl.unpack(mesh_message(_model(meta={"k": "v"}), "M").pack())
    assert default.header_version == 1 and dict(default.metadata) == {}


def test_a_model_on_any_other_type_is_refused() -> None:
    with pytest.raises(OCCError, match="^a model goes as POLYDATA, not TRANSFORM$"):
        pack_output(_model(), Out("TRANSFORM"))


def _matrix() -> np.ndarray:
    m = np.diag([2.0, 1.0, 0.5, 1.0])  # a scale: no rotation
    m[:3, 3] = (10.0, -20.0, 30.5)
    return m


@pytest.mark.parametrize("version", [1, 2])
def test_a_matrix_goes_as_transform_as_it_is(version: int) -> None:
    value = TransformOut(_matrix(), 8.5, {"k": "v"})
    back = _packed(value, Out("TRANSFORM", header_version=version))
    assert back.matrix == pytest.approx(_matrix())
    assert back.timestamp == pytest.approx(8.5)
    assert dict(back.metadata) == ({"k": "v"} if version == 2 else {})
    plain = _packed(TransformOut(_matrix(), 8.5), Out("TRANSFORM", header_version=version))
    assert dict(plain.metadata) == {}


def test_a_matrix_that_says_v2_goes_in_version_2_with_its_metadata_whatever_the_output() -> None:
    msg = igtl.unpack(transform_message(TransformOut(_matrix(), 1.0, {"k": "v"}, True), "T").pack())
    assert msg.header_version == 2 and dict(msg.metadata) == {"k": "v"} and msg.device_name == "T"
    default = igtl.unpack(transform_message(TransformOut(_matrix(), 1.0, {"k": "v"}), "T").pack())
    assert default.header_version == 1 and dict(default.metadata) == {}


def test_a_matrix_on_any_other_type_is_refused() -> None:
    with pytest.raises(OCCError, match="^a matrix goes as TRANSFORM, not POSITION$"):
        pack_output(TransformOut(_matrix(), 0.0), Out("POSITION"))
