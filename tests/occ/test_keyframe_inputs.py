"""Keyframes from 3D Slicer's messages (occ/kinematics/keyframe_inputs.py): a Markups point list (POINT)
or a TRAJ made into Cartesian keyframes as the keyframe controller takes them, with the
`times` metadata, Slicer's hidden points left out, and every refusal saying why.

Real igtl messages, packed and decoded as they arrive from Slicer."""

from __future__ import annotations

import pytest

import igtl
from occ.net.decoders import event_of
from occ.kinematics.keyframe_inputs import items_from_event, parse_times


def wire(msg: igtl.Message) -> igtl.Message:
    """The message as the daemon receives it: packed, then decoded."""
    return igtl.unpack(msg.pack())


def points(alphas: list[int], times: str | None = None, header_version: int = 2) -> igtl.Message:
    return wire(
        igtl.PointMessage(
            points=tuple(
                igtl.PointElement(
                    name=f"F-{i + 1}", rgba=(255, 0, 0, a), position=(i, 2.0 * i, 3.0)
                )
                for i, a in enumerate(alphas)
            ),
            device_name="F",
            header_version=header_version,
            metadata={"times": times} if times is not None else {},
        )
    )


def traj(*elements: igtl.TrajectoryElement) -> igtl.Message:
    return wire(igtl.TrajectoryMessage(trajectories=elements, device_name="T"))


def test_points_every_interval_without_times_and_a_faint_point_is_visible() -> None:
    """Alpha 1 of 255 is faint, not hidden (Slicer hides a point with alpha 0)."""
    items = items_from_event(event_of(points([255, 1])), 2.0)
    assert items == [(2.0, (0.0, 0.0, 3.0), "F-1"), (4.0, (1.0, 2.0, 3.0), "F-2")]


def test_points_with_times_and_a_hidden_point_left_out_with_its_time() -> None:
    items = items_from_event(event_of(points([255, 0, 255], times="1, 2.5 4")), 2.0)
    assert items == [(1.0, (0.0, 0.0, 3.0), "F-1"), (4.0, (2.0, 4.0, 3.0), "F-3")]


def test_a_header_v1_point_list_has_no_times_and_is_spaced() -> None:
    items = items_from_event(event_of(points([255, 255], header_version=1)), 0.5)
    assert [t for t, _, _ in items] == [0.5, 1.0]


@pytest.mark.parametrize(
    ("kind", "expected"),
    [
        (1, [(2.0, (1.0, 2.0, 3.0), "needle entry")]),
        (2, [(2.0, (4.0, 5.0, 6.0), "needle target")]),
        (3, [(2.0, (1.0, 2.0, 3.0), "needle entry"), (4.0, (4.0, 5.0, 6.0), "needle target")]),
    ],
)
def test_a_traj_element_gives_its_entry_its_target_or_both_as_its_type_says(
    kind: int, expected: list[tuple[float, tuple[float, float, float], str]]
) -> None:
    el = igtl.TrajectoryElement(name="needle", type=kind, entry=(1, 2, 3), target=(4, 5, 6))
    assert items_from_event(event_of(traj(el)), 2.0) == expected


def test_unnamed_traj_elements_and_hidden_ones() -> None:
    shown = igtl.TrajectoryElement(type=3, rgba=(0, 0, 255, 1), entry=(1, 2, 3), target=(4, 5, 6))
    hidden = igtl.TrajectoryElement(name="h", type=3, rgba=(0, 0, 255, 0), target=(7, 8, 9))
    items = items_from_event(event_of(traj(hidden, shown)), 1.0)
    assert items == [(3.0, (1.0, 2.0, 3.0), "entry"), (4.0, (4.0, 5.0, 6.0), "target")]


def test_every_refusal_says_why() -> None:
    with pytest.raises(ValueError, match=r"^TRAJ element 'odd': unknown type 4$"):
        items_from_event(event_of(traj(igtl.TrajectoryElement(name="odd", type=4))), 1.0)
    with pytest.raises(ValueError, match=r"^TRANSFORM carries no keyframes$"):
        items_from_event(event_of(wire(igtl.TransformMessage(device_name="X"))), 1.0)
    with pytest.raises(ValueError, match=r"^POINT 'F' has no visible points$"):
        items_from_event(event_of(points([0, 0])), 1.0)
    with pytest.raises(ValueError, match=r"^metadata 'times' has 1 values for 2 points$"):
        items_from_event(event_of(points([255, 255], times="1")), 1.0)


def test_times_are_counted_parsed_and_finite() -> None:
    assert parse_times(" 1,2  3.5 ,", 3) == [1.0, 2.0, 3.5]
    with pytest.raises(ValueError, match=r"^metadata 'times' has 3 values for 2 points$"):
        parse_times("1 2 3", 2)
    with pytest.raises(
        ValueError, match=r"^metadata 'times': could not convert string to float: 'x'$"
    ):
        parse_times("1 x", 2)
    for bad in ("1 inf", "nan 2"):
        with pytest.raises(ValueError, match=r"^metadata 'times' must be finite$"):
            parse_times(bad, 2)
