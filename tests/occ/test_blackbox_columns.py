"""The black box's row, column by column: each drive's raw reading lands in its own joints'
columns whatever order the drives hold their joints in, a drive not read in a tick leaves NaN,
and a write of the wrong count keeps what fits and spills nothing (occ/recording/blackbox.py)."""

from __future__ import annotations

import math
from pathlib import Path

from occ.core.safety import RobotState
from occ.recording.blackbox import BlackBox


class _Drive:
    """A driver as the row reads it: its last reading (``raw``) and when it was taken."""

    def __init__(self, p: list[float]) -> None:
        self.raw = (p, [x + 0.5 for x in p], [x + 0.25 for x in p])
        self.raw_now = math.nan


class _Joint:
    def __init__(self, q: float) -> None:
        self.position = q


def test_each_drive_reading_lands_in_its_joints_columns_whatever_their_order() -> None:
    """Drives whose joints are consecutive (one block each), one whose joints are not (4 and
    2) and one not read in the tick (NaN): every raw column by name holds its own joint's
    reading; a write of the wrong count keeps what fits (the drives refuse it)."""
    names = ["a", "b", "c", "d", "e"]
    box = BlackBox("r", names, 1000.0, 0.01, 100)
    data = type("Data", (), {"state": RobotState.RUNNING})()
    ab, ec, d = _Drive([1.0, 2.0]), _Drive([5.0, 3.0]), _Drive([4.0])
    joints = [_Joint(10.0 + i) for i in range(5)]
    box.bind(data, joints, None, None, Path("."), [(ab, (0, 1)), (ec, (4, 2)), (d, (3,))])  # type: ignore[arg-type]
    box.on_loop()
    ab.raw_now = ec.raw_now = 0.001  # d was not read in this tick
    box.wrote([0.1, 0.2, 0.3, 0.4, 0.5], False)
    box.wrote([7.0, 8.0], True)
    box.end_tick(0.001, 1)
    row = dict(zip(box.columns, box._view[0].tolist(), strict=True))
    assert [row[f"pos.{j}"] for j in names] == [10.0, 11.0, 12.0, 13.0, 14.0]
    assert [row[f"sp.{j}"] for j in names] == [0.1, 0.2, 0.3, 0.4, 0.5]
    assert [row[f"ew.{j}"] for j in names][:2] == [7.0, 8.0]
    assert all(math.isnan(row[f"ew.{j}"]) for j in names[2:])
    for j, p in (("a", 1.0), ("b", 2.0), ("c", 3.0), ("e", 5.0)):
        assert (row[f"raw.pos.{j}"], row[f"raw.vel.{j}"], row[f"raw.eff.{j}"]) == (
            p,
            p + 0.5,
            p + 0.25,
        )
    assert all(math.isnan(row[f"raw.{k}.d"]) for k in ("pos", "vel", "eff"))
    assert (row["t"], row["k"]) == (0.001, 1.0)
    # the next tick: the drives read again but not the one of a and b
    d.raw_now = ec.raw_now = 0.002
    box.end_tick(0.002, 2)
    row = dict(zip(box.columns, box._view[1].tolist(), strict=True))
    assert all(math.isnan(row[f"raw.{k}.{j}"]) for k in ("pos", "vel", "eff") for j in "ab")
    assert (row["raw.pos.d"], row["raw.eff.e"], row["raw.vel.c"]) == (4.0, 5.25, 3.5)
    assert all(math.isnan(row[f"sp.{j}"]) for j in names)  # nothing written in it
    # a write of one value too many (the drives refuse it): the row keeps the first five
    box.wrote([0.5, 0.6, 0.7, 0.8, 0.9, 99.0], False)
    box.end_tick(0.003, 3)
    row = dict(zip(box.columns, box._view[2].tolist(), strict=True))
    assert [row[f"sp.{j}"] for j in names] == [0.5, 0.6, 0.7, 0.8, 0.9]
    assert math.isnan(row["ew.a"])  # not the sixth value
