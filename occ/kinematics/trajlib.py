"""The trajectory library: keyframe sets saved by name in an embedded SQLite database (issue 28).

The German Heart Center system kept its trajectories in a database; here a planned and
acknowledged keyframe set is saved under a name (``KeyframeSave Set=...`` on the ``keyframe``
controller, occ/controllers/keyframe/library.py), listed, loaded after a restart, deleted.
This module is the database and nothing else: no robot, no loop, no commands. It takes and
gives :class:`SavedSet` values; the controller turns them into keyframe sets.

Which robot
    Every set is saved with the robot's name and :func:`config_hash`, a SHA-256 over what
    gives its keyframes their meaning: the joint names in order and the kinematic chain
    (joint types, axes, parents and placements, the tip and base links) as pinocchio built it.
    A set is loaded only by a robot of the same name and hash; another robot, or the same one
    with a changed URDF, is refused with the reason. Joint limits are not in the hash: a loaded
    set is planned and checked again against the limits of the day before it can run.

Schema (``PRAGMA user_version`` = :data:`SCHEMA_VERSION`, ``application_id`` =
:data:`APPLICATION_ID`, so that another program's SQLite file is never written to)::

    keyframe_sets(id, robot, name, config_hash, space, interpolation, mode, steepness, ramp,
                  duration_s, keyframe_count, joint_names (JSON), source, saved_at (UTC ISO),
                  UNIQUE(robot, name))
    keyframes(set_id -> keyframe_sets.id ON DELETE CASCADE, idx, t, pose (JSON), label,
              PRIMARY KEY(set_id, idx))

Safety of the file
    WAL journal, ``synchronous=FULL``; every write is one ``BEGIN IMMEDIATE`` transaction, so a
    daemon killed mid-write (SIGKILL, power loss) leaves the library as it was before that
    write (tests/occ/test_trajlib.py kills a writer mid-transaction). Readers never wait for a
    writer (WAL); a writer waits at most ``timeout`` seconds for another one. Every statement
    is parameterized; names are checked by :func:`check_name`. A connection is opened per
    operation (a few hundred microseconds), so the library is safe to use from any thread;
    the controller uses it only from its worker thread, never from the loop.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import re
import sqlite3
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from occ.errors import LibraryError, caused

if TYPE_CHECKING:
    from occ.kinematics.frame import Frame

#: the schema this code writes and reads (``PRAGMA user_version``)
SCHEMA_VERSION = 1
#: ``PRAGMA application_id`` of a library file: "OCCK"
APPLICATION_ID = 0x4F43434B
#: a set's name: 1-64 characters, letters, digits, ``_ - .``, starting with a letter or digit
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}")
#: the version of :func:`config_hash`'s recipe (part of what is hashed)
HASH_RECIPE = "occ-robot-config-v1"

_SCHEMA = (
    """CREATE TABLE keyframe_sets (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        robot TEXT NOT NULL,
        name TEXT NOT NULL,
        config_hash TEXT NOT NULL,
        space TEXT NOT NULL CHECK (space IN ('joint', 'cartesian')),
        interpolation TEXT NOT NULL CHECK (interpolation IN ('linear', 'spline')),
        mode TEXT NOT NULL CHECK (mode IN ('stop', 'continuous')),
        steepness REAL NOT NULL CHECK (steepness > 0),
        ramp REAL NOT NULL CHECK (ramp > 0 AND ramp <= 0.5),
        duration_s REAL NOT NULL,
        keyframe_count INTEGER NOT NULL CHECK (keyframe_count > 0),
        joint_names TEXT NOT NULL,
        source TEXT NOT NULL DEFAULT '',
        saved_at TEXT NOT NULL,
        UNIQUE (robot, name)
    )""",
    """CREATE TABLE keyframes (
        set_id INTEGER NOT NULL REFERENCES keyframe_sets(id) ON DELETE CASCADE,
        idx INTEGER NOT NULL,
        t REAL NOT NULL,
        pose TEXT NOT NULL,
        label TEXT NOT NULL DEFAULT '',
        PRIMARY KEY (set_id, idx)
    )""",
)


def check_name(name: str) -> str:
    """``name`` stripped, if it is a valid set name; LibraryError saying what is allowed."""
    text = name.strip()
    if NAME_PATTERN.fullmatch(text) is None:
        shown = text if len(text) <= 80 else text[:77] + "..."
        raise LibraryError(
            f"bad name {shown!r}: 1-64 characters, letters, digits, '_', '-' or '.', starting "
            "with a letter or digit"
        )
    return text


def config_hash(frame: Frame, joint_names: Sequence[str]) -> str:
    """The SHA-256 (hex) of what a saved keyframe means on this robot: the joint names in
    order and the kinematic chain pinocchio built (joint types, axes, parents, placements to
    1e-9, the tip and base links and their placements). Limits and drivers are left out."""

    def mat(m: Any) -> list[float]:
        # -0.0 and 0.0 hash alike; 1e-9 m or rad hides float noise of a re-parsed URDF
        return [round(float(v), 9) + 0.0 for v in m.homogeneous.reshape(-1)]

    model = frame.model
    chain = []
    for i in range(1, model.njoints):
        joint = model.joints[i]
        axis = getattr(joint.extract(), "axis", None)
        chain.append(
            {
                "name": model.names[i],
                "type": joint.shortname(),
                "axis": None if axis is None else [round(float(v), 9) + 0.0 for v in axis],
                "parent": int(model.parents[i]),
                "placement": mat(model.jointPlacements[i]),
            }
        )
    links = {}
    for link in (frame.tip_link, frame.base_link):
        if link is not None and model.existFrame(link):
            f = model.frames[model.getFrameId(link)]
            links[link] = {"joint": int(f.parentJoint), "placement": mat(f.placement)}
    doc = {
        "recipe": HASH_RECIPE,
        "joints": list(joint_names),
        "chain": chain,
        "tip": frame.tip_link,
        "base": frame.base_link,
        "links": links,
    }
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


@dataclass(frozen=True)
class SavedSet:
    """One keyframe set as the library keeps it (keyframes: ``(t, pose, label)`` or ``(t,
    pose, label, rotation)``, rotation a unit quaternion or None; poses in the set's own units:
    joint SI, or the tip in mm, world frame)."""

    name: str
    robot: str
    config_hash: str
    space: str
    interpolation: str
    mode: str
    steepness: float
    ramp: float
    duration_s: float
    keyframes: tuple[tuple[Any, ...], ...]
    joint_names: tuple[str, ...]
    source: str = ""
    saved_at: str = ""  # UTC, ISO 8601; filled in by Library.save


@dataclass(frozen=True)
class Entry:
    """A line of the library's list: a set without its keyframes."""

    name: str
    robot: str
    config_hash: str
    space: str
    interpolation: str
    mode: str
    keyframe_count: int
    duration_s: float
    saved_at: str
    source: str


class Library:
    """A trajectory library file (see the module docstring). Opening it creates the file and
    its schema if it is new and checks them if not: LibraryError when it is not a library of
    this version (another program's database, a newer schema, a damaged file)."""

    def __init__(self, path: str | Path, *, timeout: float = 2.0) -> None:
        self.path = Path(path)
        self.timeout = float(timeout)
        if not self.path.parent.is_dir():
            raise LibraryError(f"{self.path}: the folder {self.path.parent} does not exist")
        with self._connect() as db:
            self._prepare(db)

    def __repr__(self) -> str:
        return f"Library({str(self.path)!r})"

    # ------------------------------------------------------------------ the file
    @contextlib.contextmanager
    def _connect(self) -> Iterator[sqlite3.Connection]:
        try:
            db = sqlite3.connect(self.path, timeout=self.timeout, isolation_level=None)
        except sqlite3.Error as err:
            raise caused(LibraryError(f"{self.path}: cannot open: {err}"), err) from err
        try:
            db.execute("PRAGMA foreign_keys = ON")
            db.execute("PRAGMA synchronous = FULL")
            yield db
        except sqlite3.Error as err:
            raise caused(LibraryError(f"{self.path}: {_sqlite_reason(err)}"), err) from err
        finally:
            db.close()

    @staticmethod
    @contextlib.contextmanager
    def _write(db: sqlite3.Connection) -> Iterator[None]:
        """One write transaction: all of it is committed, or none of it."""
        db.execute("BEGIN IMMEDIATE")
        try:
            yield
        except BaseException:
            db.execute("ROLLBACK")
            raise
        db.execute("COMMIT")

    @staticmethod
    @contextlib.contextmanager
    def _read(db: sqlite3.Connection) -> Iterator[None]:
        """One read transaction: its statements see one snapshot (a set and its keyframes
        from the same save, even while another process replaces it)."""
        db.execute("BEGIN")
        try:
            yield
        finally:
            db.execute("COMMIT")

    def _prepare(self, db: sqlite3.Connection) -> None:
        app, version, tables = self._identity(db)
        if app == 0 and version == 0 and not tables:
            # a new file (or one a second daemon, or another program, is writing at this
            # moment: decided again inside the transaction)
            with self._write(db):
                app, version, tables = self._identity(db)
                if app == 0 and version == 0 and not tables:
                    for statement in _SCHEMA:
                        db.execute(statement)
                    db.execute(f"PRAGMA application_id = {APPLICATION_ID}")
                    db.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")
                    app, version, tables = self._identity(db)
        if app != APPLICATION_ID:
            raise LibraryError(
                f"{self.path} is an SQLite database but not a trajectory library "
                f"(application_id {app:#x}, tables {sorted(tables)}); give another file"
            )
        if version > SCHEMA_VERSION:
            raise LibraryError(
                f"{self.path}: schema version {version} is newer than this daemon reads "
                f"({SCHEMA_VERSION}); update occ"
            )
        if version < 1 or not {"keyframe_sets", "keyframes"} <= tables:
            raise LibraryError(f"{self.path}: an incomplete library (schema {version})")
        # WAL only once the file is known to be a library (switching the journal writes the
        # file's header), outside a transaction (SQLite's rule); a no-op when it already is
        if db.execute("PRAGMA journal_mode = WAL").fetchone()[0].lower() != "wal":
            raise LibraryError(f"{self.path}: the file system refuses a WAL journal")

    @staticmethod
    def _identity(db: sqlite3.Connection) -> tuple[int, int, set[str]]:
        app = int(db.execute("PRAGMA application_id").fetchone()[0])
        version = int(db.execute("PRAGMA user_version").fetchone()[0])
        tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        return app, version, tables

    def integrity(self) -> str:
        """SQLite's ``integrity_check`` and ``foreign_key_check``: ``"ok"`` or the problems."""
        with self._connect() as db:
            rows = [r[0] for r in db.execute("PRAGMA integrity_check")]
            orphans = db.execute("PRAGMA foreign_key_check").fetchall()
        problems = [r for r in rows if r != "ok"]
        if orphans:
            problems.append(f"{len(orphans)} keyframes without their set")
        return "; ".join(problems) or "ok"

    # ------------------------------------------------------------------ operations
    def save(self, saved: SavedSet, *, replace: bool = False) -> tuple[SavedSet, bool]:
        """Store ``saved`` under its name for its robot, in one transaction. A name taken for
        that robot is refused unless ``replace``. Returns (the set with its ``saved_at``,
        whether it replaced one)."""
        name = check_name(saved.name)
        if not saved.keyframes:
            raise LibraryError("no keyframes to save")
        for k in saved.keyframes:
            t, pose = k[0], k[1]
            rot = k[3] if len(k) > 3 else None
            values = (*pose, *(rot or ()))
            if not (math.isfinite(t) and pose and all(math.isfinite(v) for v in values)):
                raise LibraryError(f"keyframe at t={t!r}: not finite numbers")
        stamp = datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
        row = (
            saved.robot,
            name,
            saved.config_hash,
            saved.space,
            saved.interpolation,
            saved.mode,
            float(saved.steepness),
            float(saved.ramp),
            float(saved.duration_s),
            len(saved.keyframes),
            json.dumps(list(saved.joint_names)),
            saved.source,
            stamp,
        )
        with self._connect() as db, self._write(db):
            old = db.execute(
                "SELECT id, saved_at FROM keyframe_sets WHERE robot = ? AND name = ?",
                (saved.robot, name),
            ).fetchone()
            if old is not None:
                if not replace:
                    raise LibraryError(
                        f"{name!r} exists for robot {saved.robot!r} (saved {old[1]}); "
                        "Replace=1 overwrites it"
                    )
                db.execute("DELETE FROM keyframe_sets WHERE id = ?", (old[0],))
            cur = db.execute(
                "INSERT INTO keyframe_sets (robot, name, config_hash, space, interpolation, "
                "mode, steepness, ramp, duration_s, keyframe_count, joint_names, source, "
                "saved_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                row,
            )
            set_id = cur.lastrowid
            db.executemany(
                "INSERT INTO keyframes (set_id, idx, t, pose, label) VALUES (?, ?, ?, ?, ?)",
                [
                    (set_id, i, float(k[0]), _pose_text(k), k[2] or "")
                    for i, k in enumerate(saved.keyframes)
                ],
            )
        return dataclasses.replace(saved, name=name, saved_at=stamp), old is not None

    def load(self, robot: str, name: str, config_hash: str) -> SavedSet:
        """The set ``name`` of ``robot``; LibraryError when there is none, when it was saved
        for another robot (the name is only another robot's), or with another kinematic
        configuration (``config_hash`` differs), or when it is damaged."""
        name = check_name(name)
        with self._connect() as db, self._read(db):
            head = db.execute(
                "SELECT id, robot, name, config_hash, space, interpolation, mode, steepness, "
                "ramp, duration_s, keyframe_count, joint_names, source, saved_at "
                "FROM keyframe_sets WHERE robot = ? AND name = ?",
                (robot, name),
            ).fetchone()
            if head is None:
                others = [
                    r[0]
                    for r in db.execute(
                        "SELECT robot FROM keyframe_sets WHERE name = ? ORDER BY robot", (name,)
                    )
                ]
                if others:
                    raise LibraryError(
                        f"{name!r} was saved for robot {', '.join(map(repr, others))}, not for "
                        f"this robot {robot!r}; a plan from another robot never loads"
                    )
                raise LibraryError(f"no set named {name!r} for robot {robot!r}")
            rows = db.execute(
                "SELECT idx, t, pose, label FROM keyframes WHERE set_id = ? ORDER BY idx",
                (head[0],),
            ).fetchall()
        if head[3] != config_hash:
            raise LibraryError(
                f"{name!r} was saved for robot {robot!r} with another kinematic configuration "
                f"(config hash {head[3][:12]}, this robot's is {config_hash[:12]}: the joints "
                "or the URDF changed since); it is refused"
            )
        try:
            if len(rows) != head[10] or [r[0] for r in rows] != list(range(len(rows))):
                raise ValueError(f"{len(rows)} keyframes stored, {head[10]} expected")
            parsed = [(float(r[1]), _pose(r[2]), str(r[3])) for r in rows]
            keyframes = tuple(
                (t, pr[0], label) if pr[1] is None else (t, pr[0], label, pr[1])
                for t, pr, label in parsed
            )
            joints = tuple(str(j) for j in json.loads(head[11]))
        except (ValueError, TypeError) as err:
            raise caused(LibraryError(f"{name!r} is damaged: {err}"), err) from err
        return SavedSet(
            name=head[2],
            robot=head[1],
            config_hash=head[3],
            space=head[4],
            interpolation=head[5],
            mode=head[6],
            steepness=float(head[7]),
            ramp=float(head[8]),
            duration_s=float(head[9]),
            keyframes=keyframes,
            joint_names=joints,
            source=head[12],
            saved_at=head[13],
        )

    def delete(self, robot: str, name: str) -> None:
        """Delete ``robot``'s set ``name`` (its keyframes with it); LibraryError if none."""
        name = check_name(name)
        with self._connect() as db, self._write(db):
            cur = db.execute(
                "DELETE FROM keyframe_sets WHERE robot = ? AND name = ?", (robot, name)
            )
            if cur.rowcount == 0:
                raise LibraryError(f"no set named {name!r} for robot {robot!r}")

    def entries(self, limit: int = 1000) -> tuple[list[Entry], int]:
        """Up to ``limit`` sets, by robot then name, and how many there are in all."""
        with self._connect() as db, self._read(db):
            total = db.execute("SELECT count(*) FROM keyframe_sets").fetchone()[0]
            rows = db.execute(
                "SELECT name, robot, config_hash, space, interpolation, mode, keyframe_count, "
                "duration_s, saved_at, source FROM keyframe_sets ORDER BY robot, name LIMIT ?",
                (int(limit),),
            ).fetchall()
        return [Entry(*r) for r in rows], int(total)


def _pose_text(k: tuple[Any, ...]) -> str:
    """A keyframe's pose as stored: a JSON list, or ``{"pose": [...], "rotation": [x, y, z,
    w]}`` for a Cartesian keyframe with the tool's orientation (an older reader refuses such a
    set as damaged, never drops its orientation)."""
    pose = [float(v) for v in k[1]]
    rot = k[3] if len(k) > 3 else None
    if rot is None:
        return json.dumps(pose)
    return json.dumps({"pose": pose, "rotation": [float(v) for v in rot]})


def _pose(text: str) -> tuple[tuple[float, ...], tuple[float, ...] | None]:
    """(pose, rotation or None) from the stored text (:func:`_pose_text`)."""
    data = json.loads(text)
    rotation: tuple[float, ...] | None = None
    values = data
    if isinstance(data, dict):
        values = data.get("pose")
        rot = data.get("rotation")
        if not isinstance(rot, list) or len(rot) != 4:
            raise ValueError(f"a rotation is not 4 numbers: {text[:40]!r}")
        rotation = tuple(float(v) for v in rot)
        if not all(math.isfinite(v) for v in rotation):
            raise ValueError(f"a rotation is not finite: {text[:40]!r}")
    if not isinstance(values, list) or not values:
        raise ValueError(f"a pose is not a list of numbers: {text[:40]!r}")
    pose = tuple(float(v) for v in values)
    if not all(math.isfinite(v) for v in pose):
        raise ValueError(f"a pose is not finite: {text[:40]!r}")
    return pose, rotation


def _sqlite_reason(err: sqlite3.Error) -> str:
    text = str(err)
    if "locked" in text or "busy" in text:
        return f"{text} (another process is writing to the library; retry)"
    if "not a database" in text or "malformed" in text:
        return f"{text} (not a trajectory library, or a damaged one)"
    return text
