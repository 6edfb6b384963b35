"""The trajectory library's database (occ/trajlib.py, issue 28): schema, round trip, the robot's
identity, names, concurrency, and a writer killed mid-transaction.

The library through the daemon (KeyframeSave/Load/Delete/Library) is tested in
tests/occ/test_keyframe_library.py.
"""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest

from occ.errors import LibraryError
from occ.frame import Frame
from occ.trajlib import (
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
    urdf = (ROOT / "configs" / "robots" / "occ_slave.urdf").read_text()
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
    from occ.trajlib import Library, SavedSet
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
    from occ.trajlib import Library, SavedSet
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
    import dataclasses

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
