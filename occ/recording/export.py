"""Recordings in formats other tools open: the sequence metafile of 3D Slicer and PLUS, ROS 2 bags.

``occ-record export REC --format seq OUT.seq.mha`` writes a *transform sequence metafile*, the
file 3D Slicer's Sequences module reads as "Linear transform sequence" and PLUS writes for tracked
data: a MetaImage header with no pixels (``DimSize = 0 0 N``, ``ElementDataFile = LOCAL``) whose
custom fields hold, per frame ``NNNN``,

- ``Seq_FrameNNNN_<From>To<To>Transform``: the 4x4 pose, 16 numbers row by row, mm;
- ``Seq_FrameNNNN_<From>To<To>TransformStatus``: ``OK``;
- ``Seq_FrameNNNN_Timestamp``: seconds since the first frame.

A transform is in a frame only when its stream has a sample in that frame's millisecond:
every pose in the file was measured at the time it is given. Slicer's reader ignores
``TransformStatus`` (any field named ``...Transform`` is a pose), so the PLUS habit of writing
every transform in every frame, a held or identity pose marked ``INVALID``, would put the tool
at the world's origin before its first sample; Slicer's browser shows a transform's last pose
until its next one, which is what it means.

The rules it follows are those of Slicer's reader (``vtkMRMLLinearTransformSequenceStorageNode``:
a frame field is ``Seq_Frame`` + number + ``_`` + name; a field whose name holds ``Transform``
and not ``Status`` is a matrix; a frame's index value is its timestamp rounded to milliseconds,
so two frames never share a millisecond here; header lines are read with ``fgets`` into 1000
bytes, so no line is longer than 998 characters and its newline) and of PLUS's transform names
(exactly one ``To`` followed by a capital: the device names are made to fit). Every TRANSFORM
and POSITION stream of the recording is one transform: the daemon's outputs (``Tip``, ``Base``:
poses in the world, as 3D Slicer shows them) as ``<Device>ToWorld``, streams it received (a
master's POSITION) as ``<Device>ToReference``.

``occ-record export REC --format mcap OUT.mcap`` writes a ROS 2 bag with rosbags' writer (the
optional extra ``record``): a single MCAP file for ``OUT.mcap``, a rosbag2 directory (the MCAP file
and ``metadata.yaml``, what ``ros2 bag record -s mcap`` makes) for a name without that suffix.
Its topics are those the ROS 2 bridge publishes (occ_ros2/bridge.py), in metres, per robot
``NAME`` (the recording's robot, ``--name`` to change it):

- ``/occ/NAME/measured_cp`` (geometry_msgs/PoseStamped): the tip in the base frame
  (Base⁻¹·Tip), frame_id ``NAME_base``;
- ``/occ/NAME/base/measured_cp``: the base in ``world``; other pose streams as
  ``/occ/NAME/<device>/measured_cp`` (an input on a name an output has, or ``base``, as
  ``/occ/NAME/input/<device>/measured_cp``; the same for forces);
- ``/occ/NAME/measured_js`` and ``/occ/NAME/setpoint_js`` (sensor_msgs/JointState): the loop
  state rows (measured and commanded joints; the commanded efforts of a haptic master);
- ``/occ/NAME/state`` (std_msgs/String): the daemon's state when it changes;
- ``/occ/NAME/measured_cf`` (geometry_msgs/WrenchStamped): the robot's own force, N (the
  torque a 6-axis sensor measured, N m, where the message has ``torque_nm``; else zero): a
  slave's contact force (the ``force_n`` of its return channel's ``SlaveTip``, or of
  its ``TipForce`` output to 3D Slicer, whichever has more samples; frame_id ``world``, the
  patient frame) or a master's displayed force (its SENSOR/NDARRAY ``Force`` output, frame_id
  ``NAME_base``, as the bridge publishes them); other force streams as
  ``/occ/NAME/<device>/measured_cf`` (a master's recording: the slave's force as it arrived on
  ``SlaveTip``, frame_id ``slavetip_reference`` like that stream's pose). The ``TipForce``
  transform (origin at the tip, z axis the force; occ/haptics/forceviz.py) is a force, not a pose:
  it is not exported as a ``measured_cp``. In the sequence metafile it is a transform like any
  other (``TipForceToWorld``), which 3D Slicer plays back as it showed it live.
- ``/tf`` (tf2_msgs/TFMessage): ``world`` -> ``NAME_base`` -> ``NAME_tip`` at each tip sample.

Header stamps are the messages' own timestamps (the daemon's wall clock); the bag's receive times
are the recording's times (``rec.t``) on the same wall clock.

``occ-record export REC OUT_DIR`` writes ``state.csv`` (the loop state rows, the state by name)
and ``messages.csv`` (one row per message) in a directory.

The output's name says its form, and a form the exporter cannot write is refused before
anything is read or written (:func:`output_format`): ``.seq.mha``/``.mha``/``.seq.mhd``/``.mhd``
(sequence), ``.mcap`` (one bag file), or a directory (CSV; a rosbag2 directory with ``--format
mcap``), whose name has no file suffix. ``.seq.nrrd`` is refused: Slicer reads a transform
sequence only from a MetaImage header (``vtkMRMLLinearTransformSequenceStorageNode``); its NRRD
sequences are image volumes.

Every output is written beside its final name and moved there when whole: an export that fails
leaves nothing behind, and an existing output (replaced only with ``force``) is kept until the
new one is complete. A damaged recording (cut mid-message: a crash, an interrupted copy) is
salvaged up to the damage (occ/recording/record.py, :class:`ReadReport`): the export is made of
what was read, and the report says where it stopped; ``occ-record`` exits 3 then.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from occ.net.decoders import message_force, message_torque
from occ.recording.record import STATE_DEVICE, STATE_NAMES, ReadReport, iter_recording
from occ.samples import quaternion_to_rotation

#: the frame of the daemon's own pose outputs (3D Slicer's RAS, the ROS frame ``world``)
WORLD = "World"
#: the frame of pose streams the daemon received (the sender's reference)
REFERENCE = "Reference"
#: Slicer's reader takes header lines with fgets into 1000 bytes: 999 characters and the
#: string's end, so a line of 999 characters is read without its newline, in two pieces
MAX_LINE = 998


class ExportError(Exception):
    """An export that cannot be made (nothing to export, a missing dependency, an existing
    output); ``code`` is the exit status ``occ-record`` returns."""

    def __init__(self, message: str, code: int = 1) -> None:
        super().__init__(message)
        self.code = code


# ---------------------------------------------------------------------- reading
@dataclass
class PoseStream:
    """One TRANSFORM or POSITION stream of a recording: its samples in recording order."""

    device: str
    direction: str  # "out": the daemon sent it; "in": it received it
    t: list[float] = field(default_factory=list)  # rec.t, the daemon's clock (s)
    stamp: list[float] = field(default_factory=list)  # the message's timestamp (s)
    pose: list[np.ndarray] = field(default_factory=list)  # 4x4, mm


@dataclass
class ForceStream:
    """One force stream of a recording (N): a slave's contact force (``force_n`` metadata of
    its ``SlaveTip`` or ``TipForce``, the patient frame) or a master's displayed force (SENSOR
    or NDARRAY ``Force``, its base frame unless its metadata says ``frame=patient``)."""

    device: str
    direction: str
    frame: str  # "patient" or "base"
    t: list[float] = field(default_factory=list)
    stamp: list[float] = field(default_factory=list)
    force: list[tuple[float, float, float]] = field(default_factory=list)
    #: the torque with each force (N m, the same frame; zero when the message has none: a
    #: 6-axis sensor's ``torque_nm`` metadata, or a 6-axis master's displayed torque)
    torque: list[tuple[float, float, float]] = field(default_factory=list)


@dataclass
class RecordingContent:
    """What the exports need of a recording, read in one pass."""

    robot: str = ""
    streams: dict[tuple[str, str], PoseStream] = field(default_factory=dict)
    #: force streams by (direction, device)
    forces: dict[tuple[str, str], ForceStream] = field(default_factory=dict)
    #: pose streams that are forces drawn as transforms (``TipForce``): not poses
    force_transforms: set[tuple[str, str]] = field(default_factory=set)
    columns: list[str] = field(default_factory=list)
    state_t: list[float] = field(default_factory=list)  # rec.t of the state rows
    state_wall: list[float] = field(default_factory=list)  # their wall-clock stamps
    state_rows: list[np.ndarray] = field(default_factory=list)
    wall_offset: float | None = None  # wall clock - daemon clock


def message_pose(msg: Any) -> np.ndarray | None:
    """The 4x4 pose (mm) of a TRANSFORM or POSITION message; None when it is not finite."""
    if msg.message_type == "TRANSFORM":
        m = np.asarray(msg.matrix, dtype=np.float64)
    else:
        m = np.eye(4)
        m[:3, 3] = msg.position
        if msg.quaternion is not None:
            m[:3, :3] = quaternion_to_rotation(msg.quaternion)
    return m if bool(np.isfinite(m).all()) else None


def read_content(path: str | Path, report: ReadReport | None = None) -> RecordingContent:
    """The pose streams, the loop state rows and the robot's name of a recording. An output
    recorded twice in one tick (sent on two interfaces) counts once; every received sample
    counts (two may arrive in one tick). ``report``: salvage a damaged recording up to the
    damage (:func:`~occ.recording.record.iter_recording`) instead of raising."""
    c = RecordingContent()
    seen: set[tuple[str, str, float]] = set()
    for m in iter_recording(path, report):
        meta = m.metadata
        mtype = m.message_type
        if mtype == "NDARRAY" and m.device_name == STATE_DEVICE:
            row = np.asarray(m.array, dtype=np.float64).ravel()  # type: ignore[attr-defined]
            if not c.columns:
                c.columns = meta.get("columns", "").split(",")
                c.robot = c.robot or meta.get("robot", "")
            if len(row) != len(c.columns) or len(row) < 2:
                continue
            c.state_t.append(float(row[0]))
            c.state_wall.append(float(m.timestamp))
            c.state_rows.append(row)
            if c.wall_offset is None and m.timestamp > 0.0:
                c.wall_offset = float(m.timestamp) - float(row[0])
            continue
        if mtype not in ("TRANSFORM", "POSITION", "SENSOR", "NDARRAY"):
            continue
        direction = meta.get("rec.dir", "")
        try:
            t = float(meta.get("rec.t", ""))
        except ValueError:
            continue  # not an occd recording's message
        key = (direction, m.device_name)
        if direction == "out":  # an output goes once a tick per interface: the same pose
            if (mtype, m.device_name, t) in seen:
                continue
            seen.add((mtype, m.device_name, t))
        force = message_force(m)
        if force is not None:
            fs = c.forces.get(key)
            if fs is None:
                fs = c.forces[key] = ForceStream(m.device_name, direction, force[0])
            fs.t.append(t)
            fs.stamp.append(float(m.timestamp))
            fs.force.append(force[1])
            fs.torque.append(message_torque(m) or (0.0, 0.0, 0.0))
            if "mm_per_n" in meta:
                c.force_transforms.add(key)
        if mtype not in ("TRANSFORM", "POSITION"):
            continue
        pose = message_pose(m)
        if pose is None:
            continue
        s = c.streams.get(key)
        if s is None:
            s = c.streams[key] = PoseStream(m.device_name, direction)
        s.t.append(t)
        s.stamp.append(float(m.timestamp))
        s.pose.append(pose)
        if c.wall_offset is None and direction == "out" and m.timestamp > 0.0:
            c.wall_offset = float(m.timestamp) - t
    return c


# ---------------------------------------------------------------------- sequence metafile
def _frame_name(text: str) -> str:
    """A coordinate frame name PLUS and Slicer accept: letters and digits, a capital first,
    no ``To`` followed by a capital or a digit (the one separator), no ``Transform`` or
    ``Status`` (which would make Slicer skip or misread the field)."""
    name = re.sub(r"[^A-Za-z0-9]", "", text) or "Stream"
    name = name.replace("Transform", "Xform").replace("Status", "State")
    if not name[0].isalpha():
        name = "S" + name
    # the capital first, then the separators out (``ToTool`` or ``toTarget`` would begin with
    # one); a name that now begins with ``to`` gets the ``S`` too
    name = re.sub(r"To(?![a-z])", "to", name[0].upper() + name[1:])
    return name if name[0].isupper() else "S" + name


def _plus_split(name: str) -> tuple[str, str] | None:
    """``(From, To)`` as PLUS splits a transform name (exactly one ``To`` followed by a
    character that is not a lower-case letter, with a name on each side), else None."""
    cuts = [m.start() for m in re.finditer("To", name) if m.end() < len(name)]
    cuts = [i for i in cuts if not name[i + 2].islower()]
    if len(cuts) != 1 or cuts[0] == 0:
        return None
    return name[: cuts[0]], name[cuts[0] + 2 :]


def transform_names(keys: Iterable[tuple[str, str]]) -> dict[tuple[str, str], str]:
    """``<From>To<To>`` for each stream: outputs ``<Device>ToWorld``, inputs
    ``<Device>ToReference``; a name taken twice gets ``In`` / a number appended to ``From``."""
    out: dict[tuple[str, str], str] = {}
    used: set[str] = set()
    for direction, device in sorted(keys, key=lambda k: (k[0] != "out", k[1])):
        plain = re.sub(r"[^A-Za-z0-9]", "", device)
        split = _plus_split(plain)
        if split is not None and all(_frame_name(p) == p for p in split):
            base, to = _frame_name(split[0]), split[1]  # already PLUS's StylusToTracker
        else:
            base, to = _frame_name(device), WORLD if direction == "out" else REFERENCE
        name, n = f"{base}To{to}", 1
        while name in used:
            n += 1
            suffix = "In" if n == 2 and direction == "in" else str(n)
            name = f"{base}{suffix}To{to}"
        used.add(name)
        out[(direction, device)] = name
    return out


def _matrix_text(m: np.ndarray) -> str:
    return " ".join(format(float(v), ".12g") for v in m.reshape(16))


def write_seq(
    content: RecordingContent,
    out: str | Path,
    *,
    devices: set[str] | None = None,
    source: str = "",
) -> dict[str, Any]:
    """Write the transform sequence metafile ``out`` (module docstring); returns a summary."""
    streams = {k: s for k, s in content.streams.items() if devices is None or s.device in devices}
    if not streams:
        have = sorted({s.device for s in content.streams.values()})
        raise ExportError(
            "no TRANSFORM or POSITION stream to export"
            + (f" (the recording has: {', '.join(have)})" if have else "")
        )
    names = transform_names(streams)
    t0 = min(s.t[0] for s in streams.values())
    # each sample into the millisecond of its recording time; the last one of a millisecond
    # stands (Slicer indexes frames by the timestamp rounded to 3 decimals)
    frames: dict[int, dict[tuple[str, str], int]] = {}
    for key, s in streams.items():
        for i, t in enumerate(s.t):
            frames.setdefault(round((t - t0) * 1000.0), {})[key] = i
    order = sorted(frames)
    keys = sorted(streams, key=lambda k: names[k])
    lines = [
        "ObjectType = Image",
        "NDims = 3",
        "AnatomicalOrientation = RAI",
        "BinaryData = True",
        "BinaryDataByteOrderMSB = False",
        "CompressedData = False",
        f"DimSize = 0 0 {len(order)}",
        "ElementSpacing = 1 1 1",
        "Offset = 0 0 0",
        "TransformMatrix = 1 0 0 0 1 0 0 0 1",
        "ElementType = MET_UCHAR",
        "Kinds = domain domain list",
    ]
    if content.robot:
        lines.append(f"OCCRobot = {content.robot}")
    if source:
        lines.append(f"OCCSource = {source}")
    ok_counts = dict.fromkeys(keys, 0)
    for n, ms in enumerate(order):
        here = frames[ms]
        prefix = f"Seq_Frame{n:04d}_"
        for key in keys:
            sample = here.get(key)
            if sample is None:  # not measured in this frame: no pose (module docstring)
                continue
            ok_counts[key] += 1
            lines.append(
                f"{prefix}{names[key]}Transform = {_matrix_text(streams[key].pose[sample])}"
            )
            lines.append(f"{prefix}{names[key]}TransformStatus = OK")
        lines.append(f"{prefix}Timestamp = {ms / 1000.0:.3f}")
    lines.append("ElementDataFile = LOCAL")
    too_long = [line[:60] for line in lines if len(line) > MAX_LINE]
    if too_long:  # cannot happen with 16 numbers of 12 digits; kept as a guard
        raise ExportError(f"header line too long for Slicer's reader: {too_long[0]}...")
    text = "\n".join(lines) + "\n"
    write_whole(Path(out), lambda tmp: tmp.write_text(text, encoding="ascii", errors="replace"))
    return {
        "frames": len(order),
        "transforms": {names[k]: ok_counts[k] for k in keys},
        "duration_s": (order[-1] - order[0]) / 1000.0 if order else 0.0,
    }


# ---------------------------------------------------------------------- ROS 2 bag
def _ros_name(text: str) -> str:
    """A ROS 2 name token: lower case letters, digits and single underscores, not starting
    with a digit."""
    name = re.sub(r"[^a-z0-9]+", "_", text.lower()).strip("_") or "stream"
    return name if not name[0].isdigit() else "s" + name


def _missing(what: str) -> ExportError:
    return ExportError(
        f"--format mcap needs {what}: pip install 'occ-igtl[record]' (or pip install rosbags)",
        code=2,
    )


class _Bag:
    """rosbags' writer with the few message types the export uses."""

    def __init__(self, out: Path) -> None:
        try:
            from rosbags.rosbag2 import StoragePlugin, Writer
            from rosbags.typesys import Stores, get_typestore
        except ImportError as err:
            raise _missing("rosbags") from err
        self.ts = get_typestore(Stores.ROS2_JAZZY)
        t = self.ts.types
        self.Time = t["builtin_interfaces/msg/Time"]
        self.Header = t["std_msgs/msg/Header"]
        self.Pose = t["geometry_msgs/msg/Pose"]
        self.Point = t["geometry_msgs/msg/Point"]
        self.Quaternion = t["geometry_msgs/msg/Quaternion"]
        self.Vector3 = t["geometry_msgs/msg/Vector3"]
        self.Transform = t["geometry_msgs/msg/Transform"]
        self.PoseStamped = t["geometry_msgs/msg/PoseStamped"]
        self.TransformStamped = t["geometry_msgs/msg/TransformStamped"]
        self.TFMessage = t["tf2_msgs/msg/TFMessage"]
        self.JointState = t["sensor_msgs/msg/JointState"]
        self.Wrench = t["geometry_msgs/msg/Wrench"]
        self.WrenchStamped = t["geometry_msgs/msg/WrenchStamped"]
        self.String = t["std_msgs/msg/String"]
        self.writer = Writer(out, version=9, storage_plugin=StoragePlugin.MCAP)
        self.conns: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    def stamp(self, seconds: float) -> Any:
        ns = max(0, round(seconds * 1e9))
        return self.Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

    def header(self, seconds: float, frame_id: str) -> Any:
        return self.Header(stamp=self.stamp(seconds), frame_id=frame_id)

    def pose(self, m_mm: np.ndarray) -> Any:
        x, y, z = (m_mm[:3, 3] * 1e-3).tolist()
        qx, qy, qz, qw = quaternion_xyzw(m_mm[:3, :3])
        return self.Pose(
            position=self.Point(x=x, y=y, z=z),
            orientation=self.Quaternion(x=qx, y=qy, z=qz, w=qw),
        )

    def transform(self, m_mm: np.ndarray, seconds: float, parent: str, child: str) -> Any:
        x, y, z = (m_mm[:3, 3] * 1e-3).tolist()
        qx, qy, qz, qw = quaternion_xyzw(m_mm[:3, :3])
        return self.TransformStamped(
            header=self.header(seconds, parent),
            child_frame_id=child,
            transform=self.Transform(
                translation=self.Vector3(x=x, y=y, z=z),
                rotation=self.Quaternion(x=qx, y=qy, z=qz, w=qw),
            ),
        )

    def write(self, topic: str, msg: Any, log_time: float) -> None:
        conn = self.conns.get(topic)
        if conn is None:
            conn = self.conns[topic] = self.writer.add_connection(
                topic, msg.__msgtype__, typestore=self.ts
            )
        data = self.ts.serialize_cdr(msg, msg.__msgtype__)
        self.writer.write(conn, max(0, round(log_time * 1e9)), data)
        self.counts[topic] = self.counts.get(topic, 0) + 1


def quaternion_xyzw(r: np.ndarray) -> tuple[float, float, float, float]:
    """The unit quaternion (x, y, z, w), w >= 0, of a rotation matrix (Shepperd's method,
    with the rows re-orthonormalised: float32 wire matrices are not exactly orthonormal)."""
    u, _, vt = np.linalg.svd(np.asarray(r, dtype=np.float64))
    r = u @ vt
    tr = float(r[0, 0] + r[1, 1] + r[2, 2])
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        w, x = 0.25 * s, (r[2, 1] - r[1, 2]) / s
        y, z = (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2.0
        w, x = (r[2, 1] - r[1, 2]) / s, 0.25 * s
        y, z = (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2.0
        w, x = (r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s
        y, z = 0.25 * s, (r[1, 2] + r[2, 1]) / s
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2.0
        w, x = (r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s
        y, z = (r[1, 2] + r[2, 1]) / s, 0.25 * s
    q = (float(x), float(y), float(z), float(w))
    if q[3] < 0.0:
        q = (-q[0], -q[1], -q[2], -q[3])
    return q


def write_mcap(
    content: RecordingContent,
    out: str | Path,
    *,
    name: str | None = None,
    replace: bool = False,
) -> dict[str, Any]:
    """Write the ROS 2 bag ``out`` (module docstring); returns the message count per topic.
    The bag is made in a directory of its own, removed if the export fails; ``replace``: an
    existing single file ``out`` is replaced once the new one is whole."""
    out = Path(out)
    robot = _ros_name(name or content.robot or "robot")
    single_file = out.suffix.lower() == ".mcap"  # as guess_format reads the name
    bag_dir = _mcap_bag_dir(content, out, single_file, replace and single_file)
    bag = _Bag(bag_dir)
    try:
        counts = _fill_bag(bag, content, robot)
        if single_file:
            produced = bag_dir / f"{bag_dir.name}.mcap"
            os.replace(produced, out)
            (bag_dir / "metadata.yaml").unlink(missing_ok=True)
            bag_dir.rmdir()
    except BaseException:
        shutil.rmtree(bag_dir, ignore_errors=True)  # made here (refused when it existed)
        raise
    return counts


def _fill_bag(bag: _Bag, content: RecordingContent, robot: str) -> dict[str, Any]:
    """Every record of the recording into ``bag``, in time order; the count per topic."""
    ns = f"/occ/{robot}"
    base_frame = f"{robot}_base"
    offset = content.wall_offset or 0.0
    # every record with its receive time (the recording's time on the wall clock), written in
    # time order; at equal times Base before Tip, so a tip is expressed in its own tick's base
    events = _tip_base_events(bag, content, ns, robot, offset)
    taken = {f"{ns}/measured_cp", f"{ns}/base/measured_cp"}
    events.extend(_other_pose_events(bag, content, ns, offset, taken))
    events.extend(_force_events(bag, content, ns, base_frame, offset, taken))
    events.extend(_state_events(bag, content, ns, base_frame, offset))
    events.sort(key=lambda e: (e[0], e[1]))
    bag.writer.set_custom_data("occ.core.robot", content.robot or robot)
    bag.writer.open()
    try:
        for _, _, emit in events:
            emit()
    finally:
        bag.writer.close()
    return dict(sorted(bag.counts.items()))


def _mcap_bag_dir(content: RecordingContent, out: Path, single_file: bool, replace: bool) -> Path:
    """The rosbag2 directory to write (beside ``out`` for a single file); ExportError when
    ``out`` (unless ``replace``) or it exists, or when there is nothing to export."""
    if out.exists() and not replace:
        raise ExportError(f"{out} exists; not overwriting (--force replaces it)")
    bag_dir = out.with_name(out.name + ".bagdir") if single_file else out
    if bag_dir.exists():
        raise ExportError(f"{bag_dir} exists (a leftover of an export?); remove it first")
    if not content.streams and not content.state_rows:
        raise ExportError("nothing to export: no pose stream and no state rows")
    return bag_dir


def _tip_base_events(
    bag: _Bag, content: RecordingContent, ns: str, robot: str, offset: float
) -> list[tuple[float, int, Callable[[], None]]]:
    """The robot's Base (world frame) and Tip (in its base: measured_cp, and /tf) streams."""
    base_frame, tip_frame, world = f"{robot}_base", f"{robot}_tip", "world"
    events: list[tuple[float, int, Callable[[], None]]] = []
    tip = content.streams.get(("out", "Tip"))
    base = content.streams.get(("out", "Base"))
    current_base: list[np.ndarray] = [np.eye(4)]

    def on_base(i: int) -> Callable[[], None]:
        assert base is not None
        s = base

        def emit() -> None:
            current_base[0] = s.pose[i]
            bag.write(
                f"{ns}/base/measured_cp",
                bag.PoseStamped(header=bag.header(s.stamp[i], world), pose=bag.pose(s.pose[i])),
                s.t[i] + offset,
            )

        return emit

    def on_tip(i: int) -> Callable[[], None]:
        assert tip is not None
        s = tip

        def emit() -> None:
            b = current_base[0]
            local = np.linalg.solve(b, s.pose[i])  # Base^-1 . Tip
            stamp, when = s.stamp[i], s.t[i] + offset
            bag.write(
                f"{ns}/measured_cp",
                bag.PoseStamped(header=bag.header(stamp, base_frame), pose=bag.pose(local)),
                when,
            )
            bag.write(
                "/tf",
                bag.TFMessage(
                    transforms=[
                        bag.transform(b, stamp, world, base_frame),
                        bag.transform(local, stamp, base_frame, tip_frame),
                    ]
                ),
                when,
            )

        return emit

    if base is not None:
        events.extend((t, 0, on_base(i)) for i, t in enumerate(base.t))
    if tip is not None:
        events.extend((t, 1, on_tip(i)) for i, t in enumerate(tip.t))
    return events


def _other_pose_events(
    bag: _Bag, content: RecordingContent, ns: str, offset: float, taken: set[str]
) -> list[tuple[float, int, Callable[[], None]]]:
    """Every other pose stream on a topic of its own (added to ``taken``)."""
    world = "world"
    tip = content.streams.get(("out", "Tip"))
    base = content.streams.get(("out", "Base"))
    events: list[tuple[float, int, Callable[[], None]]] = []

    def on_other(s: PoseStream, topic: str, frame: str, i: int) -> Callable[[], None]:
        def emit() -> None:
            bag.write(
                topic,
                bag.PoseStamped(header=bag.header(s.stamp[i], frame), pose=bag.pose(s.pose[i])),
                s.t[i] + offset,
            )

        return emit

    # outputs first: a name both an output and an input have is the output's; the input's
    # goes under input/
    for _key, s in sorted(content.streams.items(), key=_outputs_first):
        if s is tip or s is base or _key in content.force_transforms:
            continue
        leaf = _ros_name(s.device)
        topic = f"{ns}/{leaf}/measured_cp"
        if topic in taken:
            topic = f"{ns}/input/{leaf}/measured_cp"
        taken.add(topic)
        frame = world if s.direction == "out" else f"{leaf}_reference"
        events.extend((t, 2, on_other(s, topic, frame, i)) for i, t in enumerate(s.t))
    return events


def _outputs_first(item: tuple[tuple[str, str], Any]) -> tuple[bool, str]:
    """The order streams take their topics in: outputs, then inputs, each by device."""
    (direction, device), _ = item
    return direction != "out", device


def _force_events(
    bag: _Bag, content: RecordingContent, ns: str, base_frame: str, offset: float,
    taken: set[str],
) -> list[tuple[float, int, Callable[[], None]]]:  # fmt: skip
    """measured_cf (module docstring): the robot's own force stream with the most samples,
    the others on topics of their own."""
    own = [k for k in content.forces if k[0] == "out"]
    main = max(own, key=lambda k: len(content.forces[k].t), default=None)
    events: list[tuple[float, int, Callable[[], None]]] = []

    def on_force(s: ForceStream, topic: str, frame: str, i: int) -> Callable[[], None]:
        def emit() -> None:
            fx, fy, fz = s.force[i]
            tx, ty, tz = s.torque[i]
            bag.write(
                topic,
                bag.WrenchStamped(
                    header=bag.header(s.stamp[i], frame),
                    wrench=bag.Wrench(
                        force=bag.Vector3(x=fx, y=fy, z=fz),
                        torque=bag.Vector3(x=tx, y=ty, z=tz),
                    ),
                ),
                s.t[i] + offset,
            )

        return emit

    for key, s in sorted(content.forces.items(), key=_outputs_first):
        leaf = _ros_name(s.device)
        if key == main:
            topic = f"{ns}/measured_cf"
        else:
            topic = f"{ns}/{leaf}/measured_cf"
            if topic in taken:
                topic = f"{ns}/input/{leaf}/measured_cf"
        taken.add(topic)
        if s.direction == "in":
            frame = f"{leaf}_reference"
        else:
            frame = "world" if s.frame == "patient" else base_frame
        events.extend((t, 2, on_force(s, topic, frame, i)) for i, t in enumerate(s.t))
    return events


def _state_events(
    bag: _Bag, content: RecordingContent, ns: str, frame: str, offset: float
) -> list[tuple[float, int, Callable[[], None]]]:
    """measured_js, setpoint_js and state from the loop state rows."""
    cols = content.columns
    q_idx = [i for i, c in enumerate(cols) if c.startswith("q.")]
    names = [cols[i][2:] for i in q_idx]
    sp_idx = [cols.index("sp." + n) for n in names if "sp." + n in cols]
    eff_idx = [cols.index("eff." + n) for n in names if "eff." + n in cols]
    events: list[tuple[float, int, Callable[[], None]]] = []
    last_state: list[str] = [""]

    def emit_row(k: int) -> Callable[[], None]:
        def emit() -> None:
            row = content.state_rows[k]
            stamp, when = content.state_wall[k], content.state_t[k] + offset
            if q_idx:
                bag.write(
                    f"{ns}/measured_js",
                    bag.JointState(
                        header=bag.header(stamp, frame),
                        name=names,
                        position=np.asarray(row[q_idx], dtype=np.float64),
                        velocity=np.zeros(0),
                        effort=np.zeros(0),
                    ),
                    when,
                )
            if len(sp_idx) == len(names) and names:
                bag.write(
                    f"{ns}/setpoint_js",
                    bag.JointState(
                        header=bag.header(stamp, frame),
                        name=names,
                        position=np.asarray(row[sp_idx], dtype=np.float64),
                        velocity=np.zeros(0),
                        effort=np.asarray(row[eff_idx], dtype=np.float64)
                        if len(eff_idx) == len(names)
                        else np.zeros(0),
                    ),
                    when,
                )
            state = STATE_NAMES.get(int(row[1]), "")
            if state and state != last_state[0]:
                last_state[0] = state
                bag.write(f"{ns}/state", bag.String(data=state), when)

        return emit

    for k, t in enumerate(content.state_t):
        events.append((t, 3, emit_row(k)))
    return events


# ---------------------------------------------------------------------- CSV
def export_csv(
    path: str | Path,
    out_dir: str | Path,
    *,
    report: ReadReport | None = None,
    force: bool = False,
) -> tuple[Path, Path]:
    """Write ``state.csv`` (the loop state rows) and ``messages.csv`` (one row per message) in
    the directory ``out_dir``, made when missing. Both are written aside and moved into place
    when whole: a failure leaves nothing (not even the directory); an existing file of those
    names is replaced only with ``force``. ``report``: salvage a damaged recording."""
    out = Path(out_dir)
    names = ("state.csv", "messages.csv")
    if out.is_dir():
        there = [n for n in names if (out / n).exists()]
        if there and not force:
            raise ExportError(f"{out / there[0]} exists; not overwriting (--force replaces it)")
        state_path, msg_path = out / names[0], out / names[1]

        def both(tmp_state: Path) -> None:  # messages.csv moved in first, state.csv last
            write_whole(msg_path, lambda tmp_msgs: _write_csv(path, tmp_state, tmp_msgs, report))

        write_whole(state_path, both)
        return state_path, msg_path
    if out.exists():
        raise ExportError(f"{out} exists and is not a directory")

    def fill(tmp_dir: Path) -> None:
        _write_csv(path, tmp_dir / names[0], tmp_dir / names[1], report)

    write_whole(out, fill, directory=True)
    return out / names[0], out / names[1]


def _write_csv(
    path: str | Path, state_path: Path, msg_path: Path, report: ReadReport | None
) -> None:
    with open(state_path, "w", newline="") as fs, open(msg_path, "w", newline="") as fm:
        ws, wm = csv.writer(fs), csv.writer(fm)
        header_written = False
        wm.writerow(
            ["t", "dir", "interface", "type", "device", "message_id", "timestamp", "content"]
        )
        n = 0
        for m in iter_recording(path, report):
            n += 1
            if m.message_type == "NDARRAY" and m.device_name == STATE_DEVICE:
                if not header_written:
                    ws.writerow(m.metadata.get("columns", "").split(","))
                    header_written = True
                row = [f"{v:.9g}" for v in np.asarray(m.array).ravel().tolist()]  # type: ignore[attr-defined]
                if len(row) > 1:  # the state column by its name, not its code (READY, RUNNING)
                    row[1] = STATE_NAMES.get(int(float(row[1])), row[1])
                ws.writerow(row)
                continue
            meta = m.metadata
            wm.writerow(
                [
                    meta.get("rec.t", ""),
                    meta.get("rec.dir", ""),
                    meta.get("rec.if", ""),
                    m.message_type,
                    m.device_name,
                    m.message_id,
                    f"{m.timestamp:.6f}",
                    _short(m),
                ]
            )
    if n == 0:
        raise ExportError("nothing to export: no message could be read")


def _short(m: Any) -> str:
    text = json.dumps(m.content_summary(), separators=(",", ":"), default=str)
    return text if len(text) <= 200 else text[:197] + "..."


# ---------------------------------------------------------------------- outputs
def write_whole(out: Path, write: Callable[[Path], object], *, directory: bool = False) -> None:
    """``write(tmp)`` to a file (or a ``directory``) beside ``out``, then ``tmp`` renamed to
    ``out``: ``out`` is whole or untouched (an existing file is replaced only at the end), and
    a failure leaves nothing behind, the directories made for ``out`` included."""
    made = _make_parents(out.parent)
    try:
        if directory:
            tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".part", dir=out.parent))
        else:
            fd, name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".part", dir=out.parent)
            os.close(fd)
            tmp = Path(name)
    except BaseException:
        _remove_dirs(made)
        raise
    try:
        write(tmp)
        if directory:
            os.rename(tmp, out)  # never over something that appeared meanwhile
        else:
            os.replace(tmp, out)
    except BaseException:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            tmp.unlink(missing_ok=True)
        _remove_dirs(made)
        raise


def _make_parents(directory: Path) -> list[Path]:
    """Make ``directory`` and the parents it lacks; the ones made, outermost first."""
    missing: list[Path] = []
    d = directory
    while not d.exists() and d != d.parent:
        missing.append(d)
        d = d.parent
    directory.mkdir(parents=True, exist_ok=True)
    return missing[::-1]


def _remove_dirs(made: list[Path]) -> None:
    for d in reversed(made):  # innermost first; one that is not empty stays with its parents
        try:
            d.rmdir()
        except OSError:
            return


#: the output names the exporter writes, for its refusals
SUPPORTED = (
    "occ-record export writes OUT.seq.mha (or .mha, .seq.mhd, .mhd: the transform sequence "
    "of 3D Slicer and PLUS), OUT.mcap (a ROS 2 bag, one file) or a directory whose name has "
    "no file suffix (CSV: state.csv and messages.csv; a rosbag2 directory with --format mcap)"
)
#: a name's last suffix that says "a file of this kind" (``.nrrd``, ``.csv``), unlike a
#: dated directory's (``run.2025-01-31``)
_FILE_SUFFIX = re.compile(r"\.[a-z][a-z0-9]{0,7}")
FORMATS = ("csv", "seq", "mcap")


def output_format(out: str | Path, fmt: str | None = None) -> str:
    """The format ``out`` is written in (``fmt``, or what its name asks for), or ExportError
    (code 2: the command was wrong, nothing read or written) for a name whose form the
    exporter cannot write, or that another format than ``fmt`` would need."""
    if fmt is not None and fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r} (one of {', '.join(FORMATS)})", code=2)
    out = Path(out)
    lower = out.name.lower()
    suffix = Path(lower).suffix
    if lower.endswith((".mha", ".mhd")):
        form = "seq"
    elif suffix == ".mcap":
        form = "mcap"
    elif out.is_dir() or not _FILE_SUFFIX.fullmatch(suffix):
        form = "dir"
    else:
        why = ""
        if suffix in (".nrrd", ".nhdr"):
            why = (
                "3D Slicer reads a transform sequence only from a MetaImage header (.seq.mha); "
                "its NRRD sequences are image volumes. "
            )
        raise ExportError(f"cannot write {out.name!r}: {why}{SUPPORTED}", code=2)
    guessed = {"seq": "seq", "mcap": "mcap", "dir": "csv"}[form]
    if fmt is None or fmt == guessed or (fmt == "mcap" and form == "dir"):
        return fmt or guessed
    raise ExportError(
        f"--format {fmt} cannot write {out.name!r} (that name is a {guessed} output): {SUPPORTED}",
        code=2,
    )


# ---------------------------------------------------------------------- entry point
def export(
    path: str | Path,
    out: str | Path,
    fmt: str | None = None,
    *,
    devices: set[str] | None = None,
    name: str | None = None,
    force: bool = False,
    report: ReadReport | None = None,
) -> dict[str, Any]:
    """``occ-record export``: check the output's name (:func:`output_format`), read ``path``
    (salvaged into ``report`` when given), write ``out`` whole or not at all."""
    out = Path(out)
    fmt = output_format(out, fmt)
    if fmt == "mcap":
        try:
            import rosbags  # noqa: F401
        except ImportError as err:
            raise _missing("rosbags") from err
    if fmt == "csv":
        state, messages = export_csv(path, out, report=report, force=force)
        return {"state": str(state), "messages": str(messages)}
    if out.exists():
        if out.is_dir():
            raise ExportError(f"{out} is a directory; remove it yourself")
        if not force:
            raise ExportError(f"{out} exists; not overwriting (--force replaces it)")
    content = read_content(path, report)
    if fmt == "seq":
        return write_seq(content, out, devices=devices, source=Path(path).name)
    if devices is not None:
        content.streams = {k: s for k, s in content.streams.items() if s.device in devices}
    return write_mcap(content, out, name=name, replace=force)


def guess_format(out: str | Path) -> str:
    """The export format an output name asks for: ``.mha``/``.mhd`` -> seq, ``.mcap`` -> mcap,
    anything else (a directory) -> csv."""
    lower = str(out).lower()
    if lower.endswith((".mha", ".mhd")):
        return "seq"
    if lower.endswith(".mcap"):
        return "mcap"
    return "csv"
