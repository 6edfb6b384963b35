"""The trajectory library's database (occ/kinematics/trajlib.py, issue 28): schema, round trip, the robot's
identity, names, concurrency, and a writer killed mid-transaction.

The library through the daemon (KeyframeSave/Load/Delete/Library) is tested in
tests/occ/test_keyframe_library.py.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import threading
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest

from occ.errors import LibraryError
from occ.kinematics.frame import Frame, robots_dir
from occ.kinematics.trajlib import (
    APPLICATION_ID,
    SCHEMA_VERSION,
    Library,
    SavedSet,
    check_name,
    config_hash,
)

ROOT = Path(__file__).resolve().parents[2]
JOINTS = ("yaw", "pitch", "insertion")


def saved(name: str = "demo", robot: str = "kf", digest: str = "h" * 64, n: int = 3) -> SavedSet:
    return SavedSet(
        name=name,
        robot=robot,
        config_hash=digest,
        space="joint",
        interpolation="spline",
        mode="stop",
        steepness=6.0,
        ramp=0.25,
        duration_s=float(n),
        # values that do not survive a careless float round trip
        keyframes=tuple(
            (float(i + 1), (0.1 * (i + 1), 1 / 3, 0.05 + 1e-17 * i), f"k{i}") for i in range(n)
        ),
        joint_names=JOINTS,
        source="operator commands",
    )


def test_schema_version_application_id_and_wal(tmp_path: Path) -> None:
    path = tmp_path / "lib.db"
    Library(path)
    db = sqlite3.connect(path)
    try:
        assert db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
        assert db.execute("PRAGMA application_id").fetchone()[0] == APPLICATION_ID
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        assert tables == {"keyframe_sets", "keyframes", "sqlite_sequence"}
    finally:
        db.close()
    Library(path)  # opening it again checks, does not recreate


def test_round_trip_is_exact_and_survives_reopening(tmp_path: Path) -> None:
    lib = Library(tmp_path / "lib.db")
    s = saved()
    stored, replaced = lib.save(s)
    assert not replaced and stored.saved_at.endswith("Z")
    back = Library(tmp_path / "lib.db").load("kf", "demo", s.config_hash)
    assert back == stored  # every float bit-exact, labels, settings, joints, source
    assert back.keyframes[1][1] == (0.2, 1 / 3, 0.05 + 1e-17)
    (entry,), total = lib.entries()
    assert total == 1 and (entry.name, entry.robot, entry.keyframe_count) == ("demo", "kf", 3)
    assert entry.duration_s == 3.0 and entry.saved_at == stored.saved_at
    assert lib.integrity() == "ok"


def test_a_name_is_taken_until_replace_and_names_are_per_robot(tmp_path: Path) -> None:
    lib = Library(tmp_path / "lib.db")
    lib.save(saved(n=3))
    with pytest.raises(LibraryError, match="'demo' exists for robot 'kf'.*Replace=1"):
        lib.save(saved(n=2))
    assert len(lib.load("kf", "demo", "h" * 64).keyframes) == 3  # unchanged
    _, replaced = lib.save(saved(n=2), replace=True)
    assert replaced and len(lib.load("kf", "demo", "h" * 64).keyframes) == 2
    lib.save(saved(robot="other", n=4))  # the same name for another robot is another set
    assert lib.entries()[1] == 2
    # the replaced set's keyframes went with it (no orphans)
    db = sqlite3.connect(tmp_path / "lib.db")
    assert db.execute("SELECT count(*) FROM keyframes").fetchone()[0] == 2 + 4
    db.close()
    lib.delete("kf", "demo")
    with pytest.raises(LibraryError, match="no set named 'demo' for robot 'kf'"):
        lib.delete("kf", "demo")
    assert [e.robot for e in lib.entries()[0]] == ["other"]
    assert lib.integrity() == "ok"


def test_another_robot_or_another_configuration_is_refused_with_the_reason(
    tmp_path: Path,
) -> None:
    lib = Library(tmp_path / "lib.db")
    lib.save(saved(robot="slave", digest="a" * 64))
    with pytest.raises(LibraryError, match="saved for robot 'slave', not for this robot 'kf'"):
        lib.load("kf", "demo", "a" * 64)
    with pytest.raises(LibraryError, match="another kinematic configuration.*aaaaaaaaaaaa"):
        lib.load("slave", "demo", "b" * 64)
    with pytest.raises(LibraryError, match="no set named 'nope'"):
        lib.load("slave", "nope", "a" * 64)


def test_the_config_hash_follows_the_kinematics_not_the_file(tmp_path: Path) -> None:
    urdf = (robots_dir() / "occ_slave.urdf").read_text()
    a = Frame.builtin("occ_slave")
    (tmp_path / "same.urdf").write_text(urdf)  # the same robot from another file
    same = Frame.from_urdf(tmp_path / "same.urdf", "tool_tip")
    assert config_hash(a, JOINTS) == config_hash(same, JOINTS)
    assert len(config_hash(a, JOINTS)) == 64
    # joints renamed or reordered: keyframes would mean something else
    assert config_hash(a, ("pitch", "yaw", "insertion")) != config_hash(a, JOINTS)
    # the yaw joint 1 mm higher
    head, yaw = urdf.split('<joint name="yaw"', 1)
    assert '<origin xyz="0 0 0.30"' in yaw.split("</joint>")[0]
    longer = head + '<joint name="yaw"' + yaw.replace('xyz="0 0 0.30"', 'xyz="0 0 0.301"', 1)
    (tmp_path / "longer.urdf").write_text(longer)
    longer = Frame.from_urdf(tmp_path / "longer.urdf", "tool_tip")
    assert config_hash(longer, JOINTS) != config_hash(a, JOINTS)
    # another tool tip
    assert config_hash(Frame(a.model, "tool_link"), JOINTS) != config_hash(a, JOINTS)
    assert config_hash(Frame.builtin("master3"), JOINTS) != config_hash(a, JOINTS)


@pytest.mark.parametrize(
    "bad", ["", " ", "a b", "x" * 65, "-lead", ".hidden", "a/b", "a;DROP TABLE keyframes", "é"]
)
def test_bad_names_are_refused_before_any_sql(tmp_path: Path, bad: str) -> None:
    lib = Library(tmp_path / "lib.db")
    for call in (
        lambda: lib.save(saved(name=bad)),
        lambda: lib.load("kf", bad, "h"),
        lambda: lib.delete("kf", bad),
        lambda: check_name(bad),
    ):
        with pytest.raises(LibraryError, match="bad name"):
            call()
    assert lib.entries()[1] == 0 and lib.integrity() == "ok"


def test_good_names_and_a_quote_in_a_robot_name_or_label_are_data(tmp_path: Path) -> None:
    assert check_name(" entry-target_2.v1 ") == "entry-target_2.v1"
    assert check_name("x" * 64) == "x" * 64
    lib = Library(tmp_path / "lib.db")
    odd = saved(robot="r'); DROP TABLE keyframes; --")
    odd = SavedSet(**{**odd.__dict__, "keyframes": ((1.0, (0.0, 0.0, 0.0), 'it\'s "x"'),)})
    lib.save(odd)
    back = lib.load(odd.robot, "demo", odd.config_hash)
    assert back.robot == odd.robot and back.keyframes[0][2] == 'it\'s "x"'


def test_files_that_are_not_this_library_are_refused(tmp_path: Path) -> None:
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"not sqlite at all" * 100)
    with pytest.raises(LibraryError, match="not a trajectory library, or a damaged one"):
        Library(junk)
    other = tmp_path / "other.db"
    db = sqlite3.connect(other)
    db.execute("CREATE TABLE patients (id INTEGER)")
    db.commit()
    db.close()
    with pytest.raises(LibraryError, match="not a trajectory library"):
        Library(other)
    db = sqlite3.connect(other)
    assert [r[0] for r in db.execute("SELECT name FROM sqlite_master")] == ["patients"]
    db.close()
    newer = tmp_path / "newer.db"
    Library(newer)
    db = sqlite3.connect(newer)
    db.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    db.commit()
    db.close()
    with pytest.raises(LibraryError, match="newer than this daemon reads"):
        Library(newer)
    with pytest.raises(LibraryError, match="does not exist"):
        Library(tmp_path / "missing" / "lib.db")


def test_a_damaged_set_is_refused_not_half_loaded(tmp_path: Path) -> None:
    lib = Library(tmp_path / "lib.db")
    lib.save(saved(n=3))
    db = sqlite3.connect(tmp_path / "lib.db")
    db.execute("DELETE FROM keyframes WHERE idx = 1")
    db.commit()
    with pytest.raises(LibraryError, match="'demo' is damaged: 2 keyframes stored, 3 expected"):
        lib.load("kf", "demo", "h" * 64)
    lib.save(saved(n=1), replace=True)
    db.execute("UPDATE keyframes SET pose = ?", (json.dumps(["NaN", 0, 0]),))
    db.commit()
    db.close()
    with pytest.raises(LibraryError, match="damaged"):
        lib.load("kf", "demo", "h" * 64)


def test_a_reader_sees_the_last_commit_while_a_writer_holds_its_transaction(
    tmp_path: Path,
) -> None:
    path = tmp_path / "lib.db"
    lib = Library(path)
    lib.save(saved(n=3))
    writer = sqlite3.connect(path, isolation_level=None)
    writer.execute("BEGIN IMMEDIATE")
    writer.execute("DELETE FROM keyframes")  # uncommitted
    try:
        got: list[object] = []

        def read() -> None:
            try:
                got.append(Library(path).load("kf", "demo", "h" * 64))
            except Exception as err:  # noqa: BLE001 - reported below
                got.append(err)

        reader = threading.Thread(target=read)
        reader.start()
        reader.join(30.0)
        assert isinstance(got[0], SavedSet) and len(got[0].keyframes) == 3
        # a second writer waits for the first, then says why it gave up
        with pytest.raises(LibraryError, match="another process is writing"):
            Library(path, timeout=0.05).save(saved(name="other"))
    finally:
        writer.execute("ROLLBACK")
        writer.close()
    lib.save(saved(name="other"))
    assert lib.entries()[1] == 2


WRITER = textwrap.dedent(
    """
    import sqlite3, sys
    from occ.kinematics.trajlib import Library, SavedSet
    path, n = sys.argv[1], int(sys.argv[2])
    lib = Library(path)
    big = SavedSet("big", "kf", "h" * 64, "joint", "linear", "stop", 6.0, 0.25, float(n),
                   tuple((float(i + 1), (0.0, 0.35, 0.05), "") for i in range(n)),
                   ("yaw", "pitch", "insertion"))
    # the library's own transaction, stopped half-way: the set's row and half its keyframes
    # written, no COMMIT
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("PRAGMA synchronous = FULL")
    db.execute("PRAGMA foreign_keys = ON")
    db.execute("PRAGMA cache_size = 8")  # spill: the uncommitted pages go to the WAL file
    db.execute("BEGIN IMMEDIATE")
    db.execute("DELETE FROM keyframe_sets WHERE name = 'demo'")
    cur = db.execute(
        "INSERT INTO keyframe_sets (robot, name, config_hash, space, interpolation, mode, "
        "steepness, ramp, duration_s, keyframe_count, joint_names, source, saved_at) "
        "VALUES ('kf', 'big', ?, 'joint', 'linear', 'stop', 6, 0.25, ?, ?, '[]', '', 'now')",
        ("h" * 64, float(n), n))
    for i in range(n // 2):
        db.execute("INSERT INTO keyframes VALUES (?, ?, ?, '[0, 0.35, 0.05]', '')",
                   (cur.lastrowid, i, float(i + 1)))
    print("mid-transaction", flush=True)
    sys.stdin.readline()  # killed here
    """
)


@pytest.mark.req("SR-LIB-1")
def test_a_writer_killed_mid_transaction_leaves_the_library_intact(tmp_path: Path) -> None:
    path = tmp_path / "lib.db"
    lib = Library(path)
    before = lib.save(saved(n=3))[0]
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(path), "20000"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=ROOT,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line == b"mid-transaction\n", proc.stderr.read() if proc.stderr else line
        # the transaction's pages are in the WAL file (spilled from its small cache), not
        # committed: the hard case for a reader after the crash
        assert (tmp_path / "lib.db-wal").stat().st_size > 0
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30.0)
    assert proc.returncode == -signal.SIGKILL
    again = Library(path)
    assert again.integrity() == "ok"
    assert again.load("kf", "demo", "h" * 64) == before
    entries, total = again.entries()
    assert total == 1 and entries[0].name == "demo"
    again.save(saved(name="after"))  # and it takes writes again (no lock left behind)
    assert again.entries()[1] == 2


KILLER_LOOP = textwrap.dedent(
    """
    import sys
    from occ.kinematics.trajlib import Library, SavedSet
    lib = Library(sys.argv[1])
    print("ready", flush=True)
    i = 0
    while True:  # replaces the set over and over until it is killed
        i += 1
        n = 1 + i % 50
        lib.save(SavedSet("loop", "kf", "h" * 64, "joint", "linear", "stop", 6.0, 0.25,
                          float(n), tuple((float(k + 1), (float(i), 0.35, 0.05), "")
                                          for k in range(n)), ("yaw", "pitch", "insertion")),
                 replace=True)
    """
)


def test_a_writer_killed_at_any_moment_of_its_saves_leaves_whole_sets(tmp_path: Path) -> None:
    path = tmp_path / "lib.db"
    Library(path)
    for round_ in range(3):
        proc = subprocess.Popen(
            [sys.executable, "-c", KILLER_LOOP, str(path)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            cwd=ROOT,
        )
        try:
            assert proc.stdout is not None
            assert proc.stdout.readline() == b"ready\n"
            # let it save a while (counted in its saves, not in time): each save writes its
            # number i into the poses
            reader, want = Library(path), 40 + 17 * round_
            for _ in range(20000):
                if reader.entries()[1]:
                    if reader.load("kf", "loop", "h" * 64).keyframes[0][1][0] >= want:
                        break
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(30.0)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(30.0)
        lib = Library(path)
        assert lib.integrity() == "ok"
        (entry,), _ = lib.entries()
        back = lib.load("kf", "loop", "h" * 64)  # whole: its count matches its rows
        assert len(back.keyframes) == entry.keyframe_count == back.duration_s
        assert len({k[1][0] for k in back.keyframes}) == 1  # all from the same save


@pytest.mark.req("SR-LIB-1")
def test_orientations_are_kept_exactly(tmp_path: Path) -> None:
    """A Cartesian set with the tool's orientation (a 6-DOF arm's keyframes) comes back with
    every quaternion bit-exact; a set without keeps its plain rows."""
    rot = (0.1 / 3, -0.7071067811865476, 1 / 7, 0.6)
    s = dataclasses.replace(
        saved(name="oriented"),
        space="cartesian",
        keyframes=((1.0, (600.0, 100.0, 290.0), "a", rot), (2.0, (610.0, 1 / 3, 290.0), "b", rot)),
    )
    lib = Library(tmp_path / "lib.db")
    lib.save(s)
    lib.save(saved())
    back = Library(tmp_path / "lib.db").load("kf", "oriented", s.config_hash)
    assert [k[3] for k in back.keyframes] == [rot, rot]
    assert back.keyframes[1][1] == (610.0, 1 / 3, 290.0)
    assert all(len(k) == 3 for k in lib.load("kf", "demo", s.config_hash).keyframes)


# -------------------------------------------------------------------------------------------
# Which robot a saved plan belongs to: each part of the kinematics changed on its own (issue 29,
# mutation testing of occ/kinematics/trajlib.py). A small arm written here, each variant from its own file:
# a revolute joint about z, one about x on a 0.1 m link, a prismatic one along an unaligned axis
# (pinocchio keeps the axis as numbers), a fixed tool tip 0.02 m past it, and a fixed mount.

ARM = """<?xml version="1.0"?>
<robot name="arm">
  <link name="base_link"/>
  <joint name="mount_joint" type="fixed"><parent link="base_link"/><child link="mount"/>
    <origin xyz="{mount}" rpy="0 0 0"/></joint>
  <link name="mount"/>
  <joint name="{j1}" type="revolute"><parent link="base_link"/><child link="l1"/>
    <origin xyz="{o1}" rpy="{r1}"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="{upper}" velocity="1" effort="1"/></joint>
  <link name="l1"/>
  <joint name="j2" type="{t2}"><parent link="{p2}"/><child link="l2"/>
    <origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" velocity="1" effort="1"/></joint>
  <link name="l2"/>
  <joint name="j3" type="prismatic"><parent link="l2"/><child link="l3"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="{a3}"/>
    <limit lower="0" upper="0.1" velocity="1" effort="1"/></joint>
  <link name="l3"/>
  <joint name="tip_joint" type="fixed"><parent link="l3"/><child link="tip"/>
    <origin xyz="{tip_xyz}" rpy="0 0 0"/></joint>
  <link name="tip"/>
</robot>
"""
ARM_PARTS = {
    "mount": "0 0 0.05",
    "j1": "j1",
    "o1": "0 0 0.3",
    "r1": "0 0 0",
    "upper": "1",
    "t2": "revolute",
    "p2": "l1",
    "a3": "0 0 -1",
    "tip_xyz": "0 0 -0.02",
}
ARM_JOINTS = ("j1", "j2", "j3")


def arm(folder: Path, tip: str = "tip", base: str | None = None, **parts: str) -> Frame:
    """The arm with ``parts`` changed, parsed from a file of its own."""
    text = ARM.format(**{**ARM_PARTS, **parts})
    path = folder / f"arm-{len(list(folder.glob('arm-*.urdf')))}.urdf"
    path.write_text(text)
    return Frame.from_urdf(path, tip, base)


def arm_hash(folder: Path, joints: tuple[str, ...] = ARM_JOINTS, **kw: Any) -> str:
    return config_hash(arm(folder, **kw), joints)


@pytest.mark.parametrize(
    "change",
    [
        pytest.param({"joints": ("j2", "j1", "j3")}, id="joints-reordered"),
        pytest.param({"j1": "shoulder"}, id="a-joint-renamed-in-the-urdf"),
        pytest.param({"t2": "prismatic"}, id="a-joint-type"),
        pytest.param({"a3": "0 -1 0"}, id="an-axis"),
        # turned 16 degrees: each component still rounds to the same integer
        pytest.param({"a3": "0 0.8 -0.6", "ref": {"a3": "0 0.6 -0.8"}}, id="an-axis-turned"),
        pytest.param({"p2": "base_link"}, id="a-joint-parent"),
        pytest.param({"o1": "0 0 0.301"}, id="a-joint-1-mm-higher"),
        pytest.param({"r1": "0 0 0.001"}, id="a-joint-turned-1-mrad"),
        pytest.param({"tip": "l3"}, id="another-tip-link"),
        pytest.param({"tip_xyz": "0 0 -0.021"}, id="the-tool-1-mm-longer"),
        pytest.param({"base": "mount"}, id="a-base-link-named"),
        pytest.param(
            {"base": "mount", "mount": "0 0 0.06", "ref": {"base": "mount"}},
            id="the-base-link-moved",
        ),
    ],
)
def test_each_part_of_the_kinematics_changed_alone_makes_a_plan_another_robots(
    tmp_path: Path, change: dict[str, Any]
) -> None:
    """A set saved by the arm is refused, with the reason, by the arm with one thing changed:
    its keyframes would mean another motion there."""
    change = dict(change)
    ref = change.pop("ref", {})
    saved_hash = arm_hash(tmp_path, **ref)
    changed_hash = arm_hash(tmp_path, **change)
    lib = Library(tmp_path / "lib.db")
    lib.save(saved(robot="arm", digest=saved_hash))
    with pytest.raises(LibraryError) as err:
        lib.load("arm", "demo", changed_hash)
    assert str(err.value) == (
        f"'demo' was saved for robot 'arm' with another kinematic configuration (config hash "
        f"{saved_hash[:12]}, this robot's is {changed_hash[:12]}: the joints or the URDF "
        "changed since); it is refused"
    )
    assert lib.load("arm", "demo", arm_hash(tmp_path, **ref)).config_hash == saved_hash


@pytest.mark.parametrize(
    ("a", "b"),
    [
        pytest.param({}, {"upper": "0.5"}, id="a-joint-limit"),
        pytest.param({}, {"mount": "0 0 0.2"}, id="a-link-outside-the-chain"),
        pytest.param({}, {"o1": "0 0 0.3000000004"}, id="float-noise-in-a-placement"),
        pytest.param({}, {"a3": "-3e-10 0 -1"}, id="float-noise-in-an-axis"),
        pytest.param(
            {"r1": "3.141592653589793 0 0"},
            {"r1": "-3.141592653589793 0 0"},
            id="a-half-turn-either-way",
        ),
    ],
)
def test_what_leaves_the_kinematics_alone_keeps_the_plan(
    tmp_path: Path, a: dict[str, str], b: dict[str, str]
) -> None:
    """Limits are checked again before a loaded plan runs, not hashed; a link off the chain,
    a re-exported URDF's rounding (below 1e-9) and the sign of a zero (-0.0 from a half turn's
    sine) do not move a keyframe."""
    lib = Library(tmp_path / "lib.db")
    lib.save(saved(robot="arm", digest=arm_hash(tmp_path, **a)))
    back = lib.load("arm", "demo", arm_hash(tmp_path, **b))
    assert back.config_hash == arm_hash(tmp_path, **a)


def test_the_hash_of_the_shipped_robots_stays_what_older_libraries_hold() -> None:
    """The hash is stored with every saved set: if the recipe changed, every plan saved before
    an update would be refused after it. These are the hashes the recipe (HASH_RECIPE
    "occ-robot-config-v1", unchanged since the library's first commit) gives the shipped
    robots; a deliberate change of the recipe bumps HASH_RECIPE and these values, and a change
    of a shipped URDF's kinematics changes them too (its saved plans are then refused)."""
    slave = Frame.builtin("occ_slave")
    assert config_hash(slave, slave.joint_names) == (
        "4e37a575366507cb685491156310397a52ea194e9e5912c82813e3ef6d45298c"
    )
    master = Frame.builtin("master3")
    assert config_hash(master, master.joint_names) == (
        "a092682ba33841244a21307512c1f94f0f4cd1c4340d7a711c17076d09aff5c3"
    )


# -------------------------------------------------------------------------------------------
# Names, saves and loads: every refusal with its reason, every stored field read back


@pytest.mark.parametrize(
    ("bad", "shown"),
    [
        ("-" + "x" * 79, "-" + "x" * 79),  # 80 characters: shown whole
        ("-" + "x" * 80, "-" + "x" * 76 + "..."),  # 81: cut to 77 and "..."
        ("  a b  ", "a b"),  # stripped first
    ],
)
def test_a_bad_name_is_shown_in_the_refusal_cut_when_long(bad: str, shown: str) -> None:
    with pytest.raises(LibraryError) as err:
        check_name(bad)
    assert str(err.value) == (
        f"bad name {shown!r}: 1-64 characters, letters, digits, '_', '-' or '.', starting with "
        "a letter or digit"
    )


NAN = float("nan")


@pytest.mark.parametrize(
    ("keyframe", "shown"),
    [
        ((NAN, (0.1, 0.2, 0.3), ""), "nan"),
        ((float("inf"), (0.1, 0.2, 0.3), ""), "inf"),
        ((1.0, (0.1, NAN, 0.3), ""), "1.0"),
        ((1.0, (0.1, 0.2, float("-inf")), ""), "1.0"),
        ((1.0, (), ""), "1.0"),
        ((1.0, (0.1, 0.2, 0.3), "", (0.0, 0.0, NAN, 1.0)), "1.0"),
        ((1.0, (0.1, 0.2, 0.3), "", (float("inf"), 0.0, 0.0, 1.0)), "1.0"),
    ],
)
def test_a_keyframe_that_is_not_finite_numbers_is_refused_and_nothing_is_saved(
    tmp_path: Path, keyframe: tuple[Any, ...], shown: str
) -> None:
    lib = Library(tmp_path / "lib.db")
    good = saved()
    bad = SavedSet(**{**good.__dict__, "keyframes": (*good.keyframes, keyframe)})
    with pytest.raises(LibraryError) as err:
        lib.save(bad)
    assert str(err.value) == f"keyframe at t={shown}: not finite numbers"
    with pytest.raises(LibraryError) as err:
        lib.save(SavedSet(**{**good.__dict__, "keyframes": ()}))
    assert str(err.value) == "no keyframes to save"
    assert lib.entries() == ([], 0)


def test_a_save_returns_the_stored_name_and_its_utc_time_and_a_label_may_be_none(
    tmp_path: Path,
) -> None:
    lib = Library(tmp_path / "lib.db")
    s = SavedSet(**{**saved().__dict__, "name": "  demo\t", "keyframes": ((1.0, (0.1,), None),)})
    before = datetime.now(UTC)
    stored, replaced = lib.save(s)
    after = datetime.now(UTC)
    assert not replaced
    assert stored.name == "demo" and stored.keyframes == s.keyframes
    # ISO 8601 with milliseconds, Z for UTC, the time of the save
    assert len(stored.saved_at) == len("2026-11-27T08:00:00.000Z")
    assert stored.saved_at.endswith("Z")
    at = datetime.fromisoformat(stored.saved_at.replace("Z", "+00:00"))
    assert before - timedelta(milliseconds=1) <= at <= after
    back = lib.load("kf", "demo", s.config_hash)
    assert back.keyframes == ((1.0, (0.1,), ""),)  # no label: an empty one
    assert back.saved_at == stored.saved_at and back.name == "demo"


def test_every_stored_field_comes_back_and_is_listed(tmp_path: Path) -> None:
    """Two sets that differ in every field: each comes back as it was saved, and the list
    gives each one's own header (sorted by robot, then name; limited, counted in all)."""
    lib = Library(tmp_path / "lib.db")
    a = SavedSet(
        name="b-set",
        robot="arm",
        config_hash="a" * 64,
        space="joint",
        interpolation="linear",
        mode="continuous",
        steepness=4.5,
        ramp=0.125,
        duration_s=2.5,
        keyframes=((0.5, (1.0, 2.0), "x"), (2.5, (1.5, -2.0), "y")),
        joint_names=("s", "e"),
        source="slicer",
    )
    rot = (0.0, 0.0, 0.6, 0.8)
    b = SavedSet(
        name="a-set",
        robot="kf",
        config_hash="b" * 64,
        space="cartesian",
        interpolation="spline",
        mode="stop",
        steepness=7.25,
        ramp=0.5,
        duration_s=9.0,
        keyframes=((1.0, (600.0, 1.0, 290.0), "p", rot),),
        joint_names=JOINTS,
        source="",
    )
    c = dataclasses.replace(a, name="a-set", robot="arm", duration_s=1.0)
    stored = [lib.save(s)[0] for s in (a, b, c)]
    for s in stored:
        assert lib.load(s.robot, s.name, s.config_hash) == s
    entries, total = lib.entries()
    assert total == 3
    assert [(e.robot, e.name) for e in entries] == [
        ("arm", "a-set"),
        ("arm", "b-set"),
        ("kf", "a-set"),
    ]
    for e, s in zip(entries, (stored[2], stored[0], stored[1]), strict=True):
        assert (e.name, e.robot, e.config_hash, e.space, e.interpolation, e.mode) == (
            s.name,
            s.robot,
            s.config_hash,
            s.space,
            s.interpolation,
            s.mode,
        )
        assert (e.keyframe_count, e.duration_s, e.saved_at, e.source) == (
            len(s.keyframes),
            s.duration_s,
            s.saved_at,
            s.source,
        )
    assert [(e.robot, e.name) for e in lib.entries(limit=2)[0]] == [
        ("arm", "a-set"),
        ("arm", "b-set"),
    ]
    assert lib.entries(limit=2)[1] == 3


def test_the_list_gives_a_thousand_sets_and_counts_them_all(tmp_path: Path) -> None:
    path = tmp_path / "lib.db"
    lib = Library(path)
    lib.save(saved(name="zzz"))
    db = sqlite3.connect(path)
    with db:  # 1000 more headers in one transaction (the list reads only the headers)
        db.executemany(
            "INSERT INTO keyframe_sets (robot, name, config_hash, space, interpolation, mode, "
            "steepness, ramp, duration_s, keyframe_count, joint_names, saved_at) VALUES "
            "('kf', ?, 'h', 'joint', 'linear', 'stop', 6, 0.25, 1, 1, '[]', 'now')",
            [(f"s{i:04d}",) for i in range(1000)],
        )
    db.close()
    entries, total = lib.entries()
    assert total == 1001 and len(entries) == 1000
    assert entries[0].name == "s0000" and entries[-1].name == "s0999"  # "zzz" is the 1001st


def test_a_load_refused_says_whose_set_it_is(tmp_path: Path) -> None:
    lib = Library(tmp_path / "lib.db")
    for robot in ("zeta", "alpha"):
        lib.save(saved(robot=robot))
    with pytest.raises(LibraryError) as err:
        lib.load("kf", " demo ", "h" * 64)
    assert str(err.value) == (
        "'demo' was saved for robot 'alpha', 'zeta', not for this robot 'kf'; a plan from "
        "another robot never loads"
    )
    with pytest.raises(LibraryError) as err:
        lib.load("kf", "other", "h" * 64)
    assert str(err.value) == "no set named 'other' for robot 'kf'"


def test_delete_removes_that_robots_set_and_its_keyframes_only(tmp_path: Path) -> None:
    path = tmp_path / "lib.db"
    lib = Library(path)
    lib.save(saved(robot="kf", n=3))
    lib.save(saved(robot="other", n=2))
    lib.delete("kf", " demo ")
    with pytest.raises(LibraryError) as err:
        lib.delete("kf", "demo")
    assert str(err.value) == "no set named 'demo' for robot 'kf'"
    assert len(lib.load("other", "demo", "h" * 64).keyframes) == 2
    db = sqlite3.connect(path)
    assert db.execute("SELECT count(*) FROM keyframes").fetchone()[0] == 2
    db.close()
    assert lib.integrity() == "ok"


def damage(path: Path, sql: str, *args: Any) -> None:
    """Change the file behind the library's back (another SQLite tool, no foreign keys)."""
    db = sqlite3.connect(path)
    with db:
        db.execute(sql, args)
    db.close()


@pytest.mark.parametrize(
    ("sql", "reason"),
    [
        # the last keyframe lost: the indices still run 0, 1
        ("DELETE FROM keyframes WHERE idx = 2", "2 keyframes stored, 3 expected"),
        # a gap: three rows, indices 0, 1, 5
        ("UPDATE keyframes SET idx = 5 WHERE idx = 2", "3 keyframes stored, 3 expected"),
        ("UPDATE keyframe_sets SET keyframe_count = 4", "3 keyframes stored, 4 expected"),
        (
            "UPDATE keyframes SET pose = 'not json' WHERE idx = 1",
            "Expecting value: line 1 column 1 (char 0)",
        ),
        ("UPDATE keyframes SET pose = '[]' WHERE idx = 1", "a pose is not a list of numbers: '[]'"),
        ("UPDATE keyframes SET pose = '7' WHERE idx = 1", "a pose is not a list of numbers: '7'"),
        (
            "UPDATE keyframes SET pose = '[1, \"x\"]' WHERE idx = 1",
            "could not convert string to float: 'x'",
        ),
        (
            "UPDATE keyframes SET pose = '[1, \"Infinity\"]' WHERE idx = 1",
            "a pose is not finite: '[1, \"Infinity\"]'",
        ),
        (
            "UPDATE keyframes SET pose = '{\"pose\": [1, 2, 3]}' WHERE idx = 1",
            "a rotation is not 4 numbers: '{\"pose\": [1, 2, 3]}'",
        ),
        (
            'UPDATE keyframes SET pose = \'{"pose": [1], "rotation": [0, 0, 1]}\' WHERE idx = 1',
            'a rotation is not 4 numbers: \'{"pose": [1], "rotation": [0, 0, 1]}\'',
        ),
        (
            'UPDATE keyframes SET pose = \'{"pose": [1], "rotation": "0001"}\' WHERE idx = 1',
            'a rotation is not 4 numbers: \'{"pose": [1], "rotation": "0001"}\'',
        ),
        (
            "UPDATE keyframes SET pose = "
            '\'{"pose": [1], "rotation": [0, 0, 0, 1, 0]}\' WHERE idx = 1',
            'a rotation is not 4 numbers: \'{"pose": [1], "rotation": [0, 0, 0, 1, 0\'',
        ),  # 40 of 42
        (
            'UPDATE keyframes SET pose = \'{"pose": [1], "rotation": [0, 0, "NaN", 1]}\' '
            "WHERE idx = 1",
            'a rotation is not finite: \'{"pose": [1], "rotation": [0, 0, "NaN", \'',
        ),
        (
            "UPDATE keyframes SET pose = '{\"rotation\": [0, 0, 0, 1]}' WHERE idx = 1",
            "a pose is not a list of numbers: '{\"rotation\": [0, 0, 0, 1]}'",
        ),
        (
            'UPDATE keyframes SET pose = \'{"pose": [], "rotation": [0, 0, 0, 1]}\' WHERE idx = 1',
            'a pose is not a list of numbers: \'{"pose": [], "rotation": [0, 0, 0, 1]}\'',
        ),
        # longer than 40 characters: the first 40 shown
        (
            "UPDATE keyframes SET pose = '[1, 2, 3, \"-Infinity\", 5, 6, 7, 8, 9, 10, 11]' "
            "WHERE idx = 1",
            "a pose is not finite: '[1, 2, 3, \"-Infinity\", 5, 6, 7, 8, 9, 10'",
        ),
        (
            "UPDATE keyframes SET pose = "
            '\'{"pose": {"x": 1, "y": 2}, "rotation": [0, 0, 0, 1]}\' WHERE idx = 1',
            'a pose is not a list of numbers: \'{"pose": {"x": 1, "y": 2}, "rotation": [\'',
        ),
        (
            "UPDATE keyframes SET t = 'soon' WHERE idx = 1",
            "could not convert string to float: 'soon'",
        ),
        (
            "UPDATE keyframe_sets SET joint_names = '[\"yaw\", '",
            "Expecting value: line 1 column 9 (char 8)",
        ),
    ],
)
def test_a_damaged_set_is_refused_with_what_is_wrong(tmp_path: Path, sql: str, reason: str) -> None:
    path = tmp_path / "lib.db"
    lib = Library(path)
    lib.save(saved(n=3))
    damage(path, sql)
    with pytest.raises(LibraryError) as err:
        lib.load("kf", "demo", "h" * 64)
    assert str(err.value) == f"'demo' is damaged: {reason}"
    assert isinstance(err.value.__cause__, (ValueError, TypeError))


# -------------------------------------------------------------------------------------------
# The file: what is not this library (or not whole) is refused with its reason and left as it
# was; a damaged one says so


def sqlite_file(path: Path, *statements: str) -> Path:
    db = sqlite3.connect(path, isolation_level=None)
    for statement in statements:
        db.execute(statement)
    db.close()
    return path


def tables_of(path: Path) -> list[str]:
    db = sqlite3.connect(path)
    try:
        return sorted(r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'"))
    finally:
        db.close()


def refusal(path: Path) -> str:
    with pytest.raises(LibraryError) as err:
        Library(path)
    return str(err.value)


def test_another_programs_files_are_refused_with_the_reason_and_not_written(
    tmp_path: Path,
) -> None:
    # another program's database: its own application id, no tables yet
    marked = sqlite_file(tmp_path / "marked.db", "PRAGMA application_id = 1234")
    assert refusal(marked) == (
        f"{marked} is an SQLite database but not a trajectory library (application_id 0x4d2, "
        "tables []); give another file"
    )
    # one with tables and no application id
    other = sqlite_file(tmp_path / "other.db", "CREATE TABLE patients (id INTEGER)")
    assert refusal(other) == (
        f"{other} is an SQLite database but not a trajectory library (application_id 0x0, "
        "tables ['patients']); give another file"
    )
    for path in (marked, other):
        db = sqlite3.connect(path)
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "delete"  # not made WAL
        assert db.execute("PRAGMA user_version").fetchone()[0] == 0
        db.close()
    assert tables_of(marked) == [] and tables_of(other) == ["patients"]


@pytest.mark.parametrize(
    ("statement", "shown"),
    [
        ("CREATE TABLE patients (id INTEGER)", "application_id 0x0, tables ['patients']"),
        ("PRAGMA application_id = 1234", "application_id 0x4d2, tables []"),
    ],
)
def test_another_programs_file_is_refused_at_once_while_that_program_writes(
    tmp_path: Path, statement: str, shown: str
) -> None:
    """Only an empty file is taken for a new library and locked for writing; another program's
    file is judged by reading, so its own writer (holding the write lock) makes no difference:
    refused as not a library, not "locked, retry"."""
    path = sqlite_file(tmp_path / "theirs.db", statement)
    theirs = sqlite3.connect(path, isolation_level=None)
    theirs.execute("BEGIN IMMEDIATE")
    try:
        with pytest.raises(LibraryError) as err:
            Library(path, timeout=0.01)
        assert str(err.value) == (
            f"{path} is an SQLite database but not a trajectory library ({shown}); give "
            "another file"
        )
    finally:
        theirs.execute("ROLLBACK")
        theirs.close()


def test_a_library_file_of_another_version_or_not_whole_is_refused_with_the_reason(
    tmp_path: Path,
) -> None:
    newer = tmp_path / "newer.db"
    Library(newer)
    sqlite_file(newer, f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    assert refusal(newer) == (
        f"{newer}: schema version {SCHEMA_VERSION + 1} is newer than this daemon reads "
        f"({SCHEMA_VERSION}); update occ"
    )
    # the application id set, the schema version not (a creation that stopped half-way)
    unversioned = tmp_path / "unversioned.db"
    Library(unversioned)
    sqlite_file(unversioned, "PRAGMA user_version = 0")
    assert refusal(unversioned) == f"{unversioned}: an incomplete library (schema 0)"
    # a table missing
    missing = tmp_path / "missing.db"
    Library(missing)
    sqlite_file(missing, "DROP TABLE keyframes")
    assert refusal(missing) == f"{missing}: an incomplete library (schema 1)"
    # the file's own version opens
    Library(tmp_path / "ok.db")
    Library(tmp_path / "ok.db")


def test_a_database_sqlite_keeps_no_wal_journal_for_is_refused(tmp_path: Path) -> None:
    """Without WAL a reader would wait for a writer and a crash could need the journal's
    roll-back: refused. SQLite keeps no WAL for an in-memory database, as for a file system
    without shared memory; nothing is created."""
    assert refusal(Path(":memory:")) == ":memory:: the file system refuses a WAL journal"
    assert not Path(":memory:").exists()


def test_a_library_another_tool_took_out_of_wal_is_put_back(tmp_path: Path) -> None:
    path = tmp_path / "lib.db"
    Library(path).save(saved())
    sqlite_file(path, "PRAGMA journal_mode = DELETE")
    lib = Library(path)
    db = sqlite3.connect(path)
    assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    db.close()
    assert lib.load("kf", "demo", "h" * 64).name == "demo"


@pytest.mark.parametrize(
    ("meanwhile", "outcome"),
    [
        # another daemon made the library: it is used as it is, not made twice
        ("library", None),
        # another program made its own database of the file
        (
            "CREATE TABLE patients (id INTEGER)",
            "not a trajectory library (application_id 0x0, tables ['patients'])",
        ),
        (
            "PRAGMA application_id = 1234",
            "not a trajectory library (application_id 0x4d2, tables [])",
        ),
    ],
)
def test_a_new_file_taken_by_another_process_meanwhile_is_judged_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, meanwhile: str, outcome: str | None
) -> None:
    """Between the first look at an empty file and the write transaction that creates the
    schema, another process may have written it (two daemons started at once): the look is
    taken again inside the transaction. The other process's write is made right after the first
    look here."""
    path = tmp_path / "lib.db"
    sqlite3.connect(path).close()
    real = Library._identity
    looks: list[tuple[int, int, set[str]]] = []

    def identity(db: sqlite3.Connection) -> tuple[int, int, set[str]]:
        seen = real(db)
        if not looks:
            if meanwhile == "library":
                monkeypatch.setattr(Library, "_identity", staticmethod(real))
                Library(path).save(saved())
                monkeypatch.setattr(Library, "_identity", staticmethod(identity))
            else:
                sqlite_file(path, meanwhile)
        looks.append(seen)
        return seen

    monkeypatch.setattr(Library, "_identity", staticmethod(identity))
    if outcome is None:
        lib = Library(path)
        assert lib.load("kf", "demo", "h" * 64).name == "demo"
    else:
        assert refusal(path) == (f"{path} is an SQLite database but {outcome}; give another file")
        # the other program's file as it left it: no tables added, its journal not made WAL
        assert "keyframe_sets" not in tables_of(path)
        db = sqlite3.connect(path)
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "delete"
        db.close()
    assert len(looks) == 2 and looks[0] == (0, 0, set())  # looked again inside the transaction


def test_a_damaged_file_says_what_is_wrong(tmp_path: Path) -> None:
    path = tmp_path / "lib.db"
    lib = Library(path)
    for name in ("s1", "s2"):
        lib.save(saved(name=name))
    # keyframes whose set is gone (written with foreign keys off, as another tool may)
    damage(path, "INSERT INTO keyframes VALUES (99, 0, 1.0, '[0]', ''), (98, 0, 1.0, '[0]', '')")
    assert lib.integrity() == "2 keyframes without their set"
    # a byte of the names' index changed on disk: the index no longer matches its table
    db = sqlite3.connect(path)
    db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    page = db.execute(
        "SELECT rootpage FROM sqlite_master WHERE name = 'sqlite_autoindex_keyframe_sets_1'"
    ).fetchone()[0]
    size = db.execute("PRAGMA page_size").fetchone()[0]
    db.close()
    data = bytearray(path.read_bytes())
    at = data.index(b"s2", (page - 1) * size, page * size)
    data[at : at + 2] = b"s3"
    path.write_bytes(bytes(data))
    # SQLite's own lines (their words are SQLite's), then the orphans
    *index, orphans = Library(path).integrity().split("; ")
    assert orphans == "2 keyframes without their set"
    assert index and all("sqlite_autoindex_keyframe_sets_1" in line for line in index)
    # the sets' table's page made something else: SQLite calls the file malformed
    data[(2 - 1) * size] = 0x55
    path.write_bytes(bytes(data))
    lib = Library(path)
    for call in (lambda: lib.load("kf", "s1", "h" * 64), lib.entries, lib.integrity):
        with pytest.raises(LibraryError) as err:
            call()
        assert str(err.value) == (
            f"{path}: database disk image is malformed (not a trajectory library, or a damaged one)"
        )


def test_an_sqlite_error_of_another_kind_is_given_as_it_is(tmp_path: Path) -> None:
    """A library file whose table lacks a column (made by hand, or by a broken tool): the
    error is SQLite's own, with no guess added."""
    path = tmp_path / "lib.db"
    Library(path)
    damage(path, "ALTER TABLE keyframe_sets DROP COLUMN source")
    with pytest.raises(LibraryError) as err:
        Library(path).load("kf", "demo", "h" * 64)
    assert str(err.value) == f"{path}: no such column: source"
    assert isinstance(err.value.__cause__, sqlite3.OperationalError)


def test_a_file_that_cannot_be_opened_and_a_missing_folder_are_refused(tmp_path: Path) -> None:
    (tmp_path / "a-folder").mkdir()
    assert refusal(tmp_path / "a-folder") == (
        f"{tmp_path / 'a-folder'}: cannot open: unable to open database file"
    )
    assert refusal(tmp_path / "nowhere" / "lib.db") == (
        f"{tmp_path / 'nowhere' / 'lib.db'}: the folder {tmp_path / 'nowhere'} does not exist"
    )
    assert repr(Library(tmp_path / "lib.db")) == f"Library({str(tmp_path / 'lib.db')!r})"


def test_a_writer_kept_waiting_says_why_and_a_refused_save_leaves_no_lock(tmp_path: Path) -> None:
    path = tmp_path / "lib.db"
    lib = Library(path)
    lib.save(saved())
    holder = sqlite3.connect(path, isolation_level=None)
    holder.execute("BEGIN IMMEDIATE")
    try:
        with pytest.raises(LibraryError) as err:
            Library(path, timeout=0.01).delete("kf", "demo")
        assert str(err.value) == (
            f"{path}: database is locked (another process is writing to the library; retry)"
        )
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    # a save refused inside its transaction (the name is taken) rolls it back: the next write
    # does not wait
    with pytest.raises(LibraryError) as err:
        lib.save(saved(name=" demo"))
    first = lib.load("kf", "demo", "h" * 64).saved_at
    assert (
        str(err.value) == f"'demo' exists for robot 'kf' (saved {first}); Replace=1 overwrites it"
    )
    fast = Library(path, timeout=0.0)
    fast.save(saved(name="next"))
    fast.delete("kf", "next")
    assert fast.entries()[1] == 1
