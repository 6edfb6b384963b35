"""Recordings the ecosystem opens: the sequence metafile 3D Slicer and PLUS read, a ROS 2 bag.

Each export is checked by someone else's reader: the rules of Slicer's
``vtkMRMLLinearTransformSequenceStorageNode`` (re-implemented below from its reading code, with
PLUS's transform-name rule), SimpleITK's MetaImage reader, and mcap-ros2-support's decoder. The
expected poses are taken from the recording itself, message by message, not from the exporter.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import igtl
from occ.recording.cli import main
from occ.recording.record import STATE_DEVICE, Recorder, read_recording
from occ_testkit.testing import SimRobot

ROOT = Path(__file__).resolve().parents[2]
TOL_MM = 1e-4


def require(module: str, why: str) -> Any:
    """Import a real peer; skip without it, fail under OCC_REQUIRE_INTEROP=1 (CI)."""
    try:
        return __import__(module, fromlist=["_"])
    except ImportError:
        if os.environ.get("OCC_REQUIRE_INTEROP") == "1":
            pytest.fail(f"{module} missing: {why}")
        pytest.skip(f"{module} missing: {why}")


def rot(axis: str, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    m = np.eye(4)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


#: a base turned and moved, so Base^-1 . Tip is not the tip itself
BASE = rot("z", 30.0) @ rot("x", -20.0)
BASE[:3, 3] = (0.0125, -0.040, 0.007)  # metres


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "slave.igtl"
    rec = Recorder(path, rate_hz=100).start()
    sim = SimRobot(ROOT / "configs" / "slave.yaml", recorder=rec)
    sim.robot.data.base = BASE.copy()
    master = sim.peer("master", address=("127.0.0.1", 5000))
    sim.peer("slicer")  # Tip, Base and Joints outputs at 10 Hz
    sim.robot.state_machine.request("enable")
    sim.robot.state_machine.request("run")
    for k in range(1200):
        if k % 2 == 0:  # the master's POSITION stream at 500 Hz, moving in x and y
            pos = (20.0 * math.sin(k / 150.0), 50.0 + 10.0 * math.cos(k / 200.0), 270.0)
            assert master.send_position(pos, seq=k // 2 + 1) == 1
        sim.tick()
    sim.close()
    rec.close()
    return path


def recorded_poses(path: Path) -> dict[tuple[str, str], list[tuple[float, np.ndarray, float]]]:
    """(direction, device) -> [(rec.t, 4x4 mm, header timestamp)] straight from the messages."""
    out: dict[tuple[str, str], list[tuple[float, np.ndarray, float]]] = {}
    for m in read_recording(path):
        if m.message_type not in ("TRANSFORM", "POSITION"):
            continue
        if m.message_type == "TRANSFORM":
            mat = np.asarray(m.matrix, dtype=float)  # type: ignore[attr-defined]
        else:
            x, y, z, w = m.quaternion  # type: ignore[attr-defined]
            mat = np.eye(4)
            mat[:3, :3] = [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
            mat[:3, 3] = m.position  # type: ignore[attr-defined]
        key = (m.metadata["rec.dir"], m.device_name)
        out.setdefault(key, []).append((float(m.metadata["rec.t"]), mat, m.timestamp))
    return out


# ---------------------------------------------------------------------- Slicer's reading rules
def fgets_lines(data: bytes, size: int = 1000) -> list[str]:
    """What ``fgets(line, MAX_LINE_LENGTH, stream)`` with MAX_LINE_LENGTH 1000 hands Slicer's
    reader: at most 999 bytes at a time, up to and including a newline."""
    out, i = [], 0
    while i < len(data):
        end = data.find(b"\n", i, i + size - 1)
        j = end + 1 if end >= 0 else min(len(data), i + size - 1)
        out.append(data[i:j].decode("latin-1"))
        i = j
    return out


def slicer_parse(path: Path) -> tuple[dict[str, str], dict[str, dict[str, np.ndarray]], int]:
    """The reading rules of vtkMRMLLinearTransformSequenceStorageNode::ReadSequenceFileTransforms
    for a .seq.mha: header fields (name = value, split at the first '=', trimmed) up to
    ElementDataFile; a frame field is Seq_Frame<number>_<name>, split at the first '_'; a name
    holding 'Transform' and not 'Status' is a matrix (1, 4, 9 or 16 numbers between space, ',',
    ':', ';', tab, newline or brackets, all of them numbers); Timestamp gives the frame's index
    value, rounded to 3 decimals; a transform's sequence is named by its field name without the
    trailing 'Transform' (Sequences.Source). Returns (header, source -> index value -> matrix,
    last frame number)."""
    header: dict[str, str] = {}
    transforms: dict[int, list[tuple[str, np.ndarray]]] = {}
    index: dict[int, str] = {}
    last = -1
    for line in fgets_lines(path.read_bytes()):
        assert line.endswith("\n"), f"a line Slicer would read in two pieces: {line[:60]}"
        sep = line.find("=")
        assert sep >= 0, f"no '=' in {line!r}"
        name, value = line[:sep].strip(" \t\r\n"), line[sep + 1 :].strip(" \t\r\n")
        if name == "ElementDataFile":
            header[name] = value
            break
        if not name.startswith("Seq_Frame"):
            header[name] = value
            continue
        rest = name[len("Seq_Frame") :]
        us = rest.find("_")
        assert us > 0, name
        number, field = rest[:us], rest[us + 1 :]
        assert number.isdigit(), name  # strtol must take all of it
        frame = int(number)
        last = max(last, frame)
        if "Transform" in field and "Status" not in field:
            tokens = [t for t in re.split(r"[ ,:;\t\n\[\]]", value) if t]
            numbers = [float(t) for t in tokens]  # strtod must take each token whole
            assert len(numbers) in (1, 4, 9, 16)
            assert len(numbers) == 16, "a 4x4 matrix, row by row"
            transforms.setdefault(frame, []).append((field, np.array(numbers).reshape(4, 4)))
        if field == "Timestamp":
            index[frame] = f"{float(value):.3f}"
    sequences: dict[str, dict[str, np.ndarray]] = {}
    for frame in range(last + 1):
        for field, matrix in transforms.get(frame, []):
            source = field[: -len("Transform")] if field.endswith("Transform") else field
            seq = sequences.setdefault(source, {})
            # Slicer's SetDataNodeAtValue: a second frame at the same index value would replace
            # the first one
            assert index[frame] not in seq, f"two frames at index value {index[frame]}"
            seq[index[frame]] = matrix
    return header, sequences, last


def plus_split(name: str) -> tuple[str, str]:
    """PLUS's igsioTransformName: exactly one 'To' followed by a capital (or any non-lowercase
    character) splits From and To."""
    cuts = [m.start() for m in re.finditer("To", name) if m.end() < len(name)]
    cuts = [i for i in cuts if name[i + 2].upper() == name[i + 2]]
    assert len(cuts) == 1, f"{name}: {len(cuts)} 'To' separators"
    i = cuts[0]
    assert 0 < i < len(name) - 2
    return name[:i], name[i + 2 :]


def expected_frames(
    poses: dict[tuple[str, str], list[tuple[float, np.ndarray, float]]],
) -> tuple[list[int], dict[tuple[str, str], dict[int, np.ndarray]]]:
    """Frames by the millisecond of the recording time; per stream the pose it holds in each
    frame (its last sample at or before it; None before the first)."""
    t0 = min(v[0][0] for v in poses.values())
    per: dict[tuple[str, str], dict[int, np.ndarray]] = {}
    for key, samples in poses.items():
        per[key] = {round((t - t0) * 1000.0): m for t, m, _ in samples}
    return sorted({ms for d in per.values() for ms in d}), per


def test_seq_follows_slicers_reading_rules(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "slave.seq.mha"
    assert main(["export", str(recording), str(out)]) == 0  # the format from the name
    header, sequences, last = slicer_parse(out)
    poses = recorded_poses(recording)
    frames, per = expected_frames(poses)
    # the header Slicer's own writer and PLUS write; no pixels: DimSize 0 0 <frames>
    first = out.read_text().splitlines()[0]
    assert first == "ObjectType = Image"
    assert header["NDims"] == "3"
    assert header["DimSize"] == f"0 0 {len(frames)}"
    assert header["ElementType"] == "MET_UCHAR"
    assert header["Kinds"] == "domain domain list"
    assert header["ElementDataFile"] == "LOCAL"
    assert (header["OCCRobot"], header["OCCSource"]) == ("slave", "slave.igtl")
    assert out.read_text().rstrip("\n").splitlines()[-1] == "ElementDataFile = LOCAL"
    assert last + 1 == len(frames)
    # one sequence per stream, named <From>To<To> as PLUS splits it
    # (and any other pose stream the slave sends, e.g. its tip back to the master: SlaveTip)
    assert set(sequences) == {
        f"{dev}To{'World' if d == 'out' else 'Reference'}" for d, dev in poses
    }
    assert {"TipToWorld", "BaseToWorld", "MasterToReference"} <= set(sequences)
    assert {("Tip", "World"), ("Base", "World"), ("Master", "Reference")} <= {
        plus_split(n) for n in sequences
    }
    assert len(poses[("out", "Tip")]) >= 10 and len(poses[("in", "Master")]) == 600
    names = {("out", "Tip"): "TipToWorld", ("out", "Base"): "BaseToWorld"}
    names[("in", "Master")] = "MasterToReference"
    t0 = frames[0]
    for key, source in names.items():
        seq = sequences[source]
        # a transform only where it was measured: Slicer takes every pose it reads as real
        assert sorted(seq) == [f"{(ms - t0) / 1000.0:.3f}" for ms in sorted(per[key])]
        for ms, pose in per[key].items():
            got = seq[f"{(ms - t0) / 1000.0:.3f}"]
            assert np.abs(got - pose).max() < TOL_MM, (source, ms)


def test_seq_status_and_timestamps(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "r.seq.mha"
    assert main(["export", str(recording), str(out), "--format", "seq"]) == 0
    fields = dict(
        line.split(" = ", 1) for line in out.read_text().splitlines() if line.startswith("Seq_")
    )
    poses = recorded_poses(recording)
    frames, per = expected_frames(poses)
    for n, ms in enumerate(frames):
        assert fields[f"Seq_Frame{n:04d}_Timestamp"] == f"{(ms - frames[0]) / 1000.0:.3f}"
        for key, source in (
            (("out", "Tip"), "TipToWorld"),
            (("in", "Master"), "MasterToReference"),
        ):
            # a frame without a sample of the stream has no field: no pose that was not
            # measured, whatever a reader makes of TransformStatus
            status = fields.get(f"Seq_Frame{n:04d}_{source}TransformStatus")
            assert status == ("OK" if ms in per[key] else None)
            assert (f"Seq_Frame{n:04d}_{source}Transform" in fields) == (ms in per[key])
    # OK exactly once per recorded sample
    oks = sum(
        1 for k, v in fields.items() if k.endswith("_TipToWorldTransformStatus") and v == "OK"
    )
    assert oks == len(poses[("out", "Tip")])


def test_seq_opens_with_simpleitk(recording: Path, tmp_path: Path) -> None:
    sitk = require("SimpleITK", "pip install -e .[test] (SimpleITK reads MetaImage files)")
    out = tmp_path / "slave.seq.mha"
    assert main(["export", str(recording), str(out)]) == 0
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(out))
    reader.ReadImageInformation()
    poses = recorded_poses(recording)
    frames, per = expected_frames(poses)
    assert reader.GetSize() == (0, 0, len(frames))
    assert reader.GetDimension() == 3
    keys = set(reader.GetMetaDataKeys())
    assert reader.GetMetaData("Kinds") == "domain domain list"
    names = {("out", "Tip"): "TipToWorld", ("out", "Base"): "BaseToWorld"}
    names[("in", "Master")] = "MasterToReference"
    for key, source in names.items():
        for n, ms in enumerate(frames):
            field = f"Seq_Frame{n:04d}_{source}Transform"
            stamp = float(reader.GetMetaData(f"Seq_Frame{n:04d}_Timestamp"))
            assert stamp == pytest.approx((ms - frames[0]) / 1000.0, abs=1e-9)
            if ms not in per[key]:  # not measured here: no pose at all (no held, no identity)
                assert field not in keys and f"{field}Status" not in keys, (source, n)
                continue
            got = np.array([float(v) for v in reader.GetMetaData(field).split()]).reshape(4, 4)
            assert np.abs(got - per[key][ms]).max() < TOL_MM, (source, n)
            assert reader.GetMetaData(f"{field}Status") == "OK"
    # the whole image reads too (no pixels)
    assert reader.Execute().GetSize() == (0, 0, len(frames))


def test_seq_device_filter_and_errors(recording: Path, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "tip.seq.mha"
    assert main(["export", str(recording), str(out), "--device", "Tip"]) == 0
    _, sequences, _ = slicer_parse(out)
    assert set(sequences) == {"TipToWorld"}
    # an existing output is kept unless --force
    assert main(["export", str(recording), str(out)]) == 1
    assert "exists" in capsys.readouterr().err
    assert main(["export", str(recording), str(out), "--device", "Base", "--force"]) == 0
    assert set(slicer_parse(out)[1]) == {"BaseToWorld"}
    # nothing to export: a clear error, exit 1
    assert main(["export", str(recording), str(tmp_path / "x.seq.mha"), "--device", "Nope"]) == 1
    assert "no TRANSFORM or POSITION stream" in capsys.readouterr().err


def test_transform_names_fit_plus_and_slicer() -> None:
    from occ.recording.export import transform_names

    devices = ["Tip", "ToolTip", "StylusToTracker", "Transform1", "Status", "3d", "a_b", "AToBToC"]
    names = transform_names([("out", d) for d in devices] + [("in", "Tip"), ("in", "Master")])
    assert names[("out", "Tip")] == "TipToWorld"
    assert names[("in", "Tip")] == "TipToReference"
    assert names[("out", "StylusToTracker")] == "StylusToTracker"  # a PLUS name stays
    assert len(set(names.values())) == len(names)
    for name in names.values():
        # Slicer: a 'Transform' field that is not a 'Status' one; PLUS: one From/To split
        assert "Status" not in name and "Transform" not in name
        frm, to = plus_split(name)
        assert frm[0].isupper() and to in ("World", "Reference", "Tracker")


# ---------------------------------------------------------------------- ROS 2 bag
def quat_matrix(q: Any) -> np.ndarray:
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def pose_mm(position: Any, orientation: Any) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quat_matrix(orientation)
    m[:3, 3] = np.array([position.x, position.y, position.z]) * 1000.0
    return m


def decode_mcap(path: Path) -> dict[str, list[tuple[Any, int]]]:
    """Every message of an MCAP file as mcap-ros2-support decodes it (from the schemas the
    file carries): topic -> [(message, log time ns)]."""
    decoder = require("mcap_ros2.decoder", "pip install -e .[test] (mcap-ros2-support)")
    from mcap.reader import make_reader

    out: dict[str, list[tuple[Any, int]]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[decoder.DecoderFactory()])
        for _schema, channel, message, ros_msg in reader.iter_decoded_messages():
            out.setdefault(channel.topic, []).append((ros_msg, message.log_time))
    return out


def test_mcap_decodes_to_the_recorded_poses(recording: Path, tmp_path: Path) -> None:
    require("rosbags", "pip install -e .[record]")
    out = tmp_path / "slave.mcap"
    assert main(["export", str(recording), str(out)]) == 0
    assert out.is_file()
    topics = decode_mcap(out)
    poses = recorded_poses(recording)
    tips, bases = poses[("out", "Tip")], poses[("out", "Base")]
    assert len(tips) == len(bases)
    # measured_cp: Base^-1 . Tip in metres, frame <robot>_base, stamped as the Tip was
    cps = topics["/occ/slave/measured_cp"]
    assert len(cps) == len(tips)
    for (msg, _), (_, tip, stamp), (_, base, _) in zip(cps, tips, bases, strict=True):
        assert msg.header.frame_id == "slave_base"
        assert msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9 == pytest.approx(
            stamp, abs=2e-9
        )
        local = np.linalg.solve(base, tip)
        got = pose_mm(msg.pose.position, msg.pose.orientation)
        assert np.abs(got[:3, 3] - local[:3, 3]).max() < TOL_MM
        assert np.abs(got[:3, :3] - local[:3, :3]).max() < 1e-6
    # base/measured_cp in world
    for (msg, _), (_, base, _) in zip(topics["/occ/slave/base/measured_cp"], bases, strict=True):
        assert msg.header.frame_id == "world"
        assert np.abs(pose_mm(msg.pose.position, msg.pose.orientation) - base).max() < TOL_MM
    # /tf: world -> slave_base -> slave_tip composes to the Tip the daemon sent
    tfs = topics["/tf"]
    assert len(tfs) == len(tips)
    for (msg, _), (_, tip, _) in zip(tfs, tips, strict=True):
        a, b = msg.transforms
        assert (a.header.frame_id, a.child_frame_id) == ("world", "slave_base")
        assert (b.header.frame_id, b.child_frame_id) == ("slave_base", "slave_tip")
        chain = pose_mm(a.transform.translation, a.transform.rotation) @ pose_mm(
            b.transform.translation, b.transform.rotation
        )
        assert np.abs(chain[:3, 3] - tip[:3, 3]).max() < TOL_MM
        assert np.abs(chain[:3, :3] - tip[:3, :3]).max() < 1e-6
    # the master's stream the slave received
    masters = topics["/occ/slave/master/measured_cp"]
    assert len(masters) == len(poses[("in", "Master")]) == 600
    for (msg, _), (_, m, _) in zip(masters, poses[("in", "Master")], strict=True):
        assert (
            np.abs(pose_mm(msg.pose.position, msg.pose.orientation)[:3, 3] - m[:3, 3]).max()
            < TOL_MM
        )


def test_mcap_joints_and_state(recording: Path, tmp_path: Path) -> None:
    require("rosbags", "pip install -e .[record]")
    out = tmp_path / "bag"  # no .mcap suffix: a rosbag2 directory
    assert main(["export", str(recording), str(out), "--format", "mcap"]) == 0
    assert (out / "metadata.yaml").is_file() and (out / "bag.mcap").is_file()
    topics = decode_mcap(out / "bag.mcap")
    rows = [m for m in read_recording(recording) if m.device_name == STATE_DEVICE]
    cols = rows[0].metadata["columns"].split(",")
    q_cols = [c for c in cols if c.startswith("q.")]
    js = topics["/occ/slave/measured_js"]
    sp = topics["/occ/slave/setpoint_js"]
    assert len(js) == len(sp) == len(rows) > 110  # 100 Hz over 1.2 s
    for (msg, _), (spm, _), row in zip(js, sp, rows, strict=True):
        values = np.asarray(row.array).ravel()  # type: ignore[attr-defined]
        assert list(msg.name) == [c[2:] for c in q_cols] == ["yaw", "pitch", "insertion"]
        assert list(msg.position) == pytest.approx(
            [values[cols.index(c)] for c in q_cols], abs=1e-12
        )
        assert list(spm.position) == pytest.approx(
            [values[cols.index("sp." + c[2:])] for c in q_cols], abs=1e-12
        )
    states = [m.data for m, _ in topics["/occ/slave/state"]]
    assert states == ["RUNNING"]
    # log times in order (a player replays them in this order)
    for msgs in topics.values():
        times = [t for _, t in msgs]
        assert times == sorted(times)


def test_mcap_without_rosbags_says_so(recording: Path, tmp_path: Path, monkeypatch, capsys) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setitem(sys.modules, "rosbags", None)  # import rosbags -> ImportError
    assert main(["export", str(recording), str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err
    assert err == (
        "occ-record: --format mcap needs rosbags: pip install 'occ-igtl[record]'"
        " (or pip install rosbags)\n"
    )
    assert not (tmp_path / "x.mcap").exists()


@pytest.mark.slow
def test_occ_record_command_line(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "cli.seq.mha"
    res = subprocess.run(
        [sys.executable, "-m", "occ.recording.cli", "export", str(recording), str(out)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert res.returncode == 0, res.stderr
    assert "TipToWorld" in res.stdout and out.is_file()


def test_outputs_count_once_received_samples_all(tmp_path: Path) -> None:
    """An output sent on two interfaces in one tick is one sample; two datagrams drained in
    one tick are two (they share the tick's time)."""
    import igtl
    from occ.recording.export import read_content

    path = tmp_path / "r.igtl"
    rec = Recorder(path).start()
    tip = igtl.TransformMessage.from_matrix(np.eye(4), device_name="Tip", header_version=2)
    for now in (0.001, 0.002):
        rec.record_message(tip, "out", "slicer", now)
        rec.record_message(tip, "out", "viewer2", now)
        for seq in (1, 2):
            pos = igtl.PositionMessage((seq, 0.0, 0.0), device_name="Master", message_id=seq)
            rec.record_message(pos, "in", "master", now)
    rec.close()
    c = read_content(path)
    assert len(c.streams[("out", "Tip")].t) == 2
    assert [p[0, 3] for p in c.streams[("in", "Master")].pose] == [1.0, 2.0, 1.0, 2.0]


# ---------------------------------------------------------------------- a recording made by hand
#: the daemon's clock at the first record (a daemon's recording does not start at 0)
T0 = 1000.25
#: its wall clock minus its own
WALL = 1.7e9
COLUMNS = "t,state,q.a,q.b,sp.a,sp.b,tip.x_mm,tip.y_mm,tip.z_mm,eff.a,eff.b"
#: the state per row: READY, READY, ENABLED, ENABLED, RUNNING ... (STATE_CODES)
STATES = [1, 1, 2, 2, 3, 3, 3, 4, 4, 3]


def turned(k: int) -> np.ndarray:
    """The base of tick ``k``: turned a further 7 degrees about z and 3 about x each tick."""
    m = rot("z", 7.0 * k) @ rot("x", -3.0 * k)
    m[:3, 3] = (10.0 * k, -4.0, 2.5 * k)
    return m


def tip_pose(k: int) -> np.ndarray:
    m = rot("y", 11.0 * k) @ rot("z", 5.0)
    m[:3, 3] = (30.0 + k, 12.0 - 2.0 * k, 250.0 + 0.5 * k)
    return m


@pytest.fixture(scope="module")
def handmade(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Ten ticks of a robot ``Rig 7`` (a haptic master's state columns, with efforts) through
    the daemon's Recorder: its Tip and a moving Base sent on two interfaces each tick, a
    master's POSITION twice a tick, its return channel (SlaveTip with force_n) every tick,
    a TipForce to Slicer every other one and a displayed Force every fourth, a force and poses
    received on names it sends or the exports take themselves (Force, SlaveTip, TipForce,
    Base), a STRING; then what must not be read as a sample: a row of the wrong length, a pose
    that is not finite, and a message no daemon recorded."""
    path = tmp_path_factory.mktemp("hand") / "rig.igtl"
    rec = Recorder(path).start()

    def tf(m: np.ndarray, device: str, meta: dict[str, str] | None = None) -> Any:
        return igtl.TransformMessage.from_matrix(
            m, device_name=device, header_version=2, timestamp=WALL + t, metadata=meta or {}
        )

    for k in range(10):
        t = T0 + 0.01 * k
        row = [t, STATES[k], 0.1 * k, -0.2 * k, 0.1 * k + 0.01, -0.2 * k - 0.01]
        row += [1.0, 2.0, 3.0, 0.5 * k, -0.25 * k]
        state = igtl.NDArrayMessage(
            array=np.asarray(row if k != 6 else row[:-1], dtype=np.float64),
            device_name=STATE_DEVICE,
            header_version=2,
            metadata={"columns": COLUMNS, "robot": "Rig 7"} if k == 0 else {},
            timestamp=0.0 if k == 0 else WALL + t - 0.0001,
        )
        rec.record_message(state, "out", "*", t)
        f = (0.5 * k, -0.1 * k, 1.5)
        force_n = f"{f[0]:.4f},{f[1]:.4f},{f[2]:.4f}"
        slavetip = igtl.PositionMessage(
            (5.0, 6.0, 7.0 + k), device_name="SlaveTip", header_version=2, timestamp=WALL + t,
            metadata={"force_n": force_n, "map": "m1"},
        )  # fmt: skip
        # a slave's return channel and force arrow as received (before this tick's outputs,
        # as a daemon reads before it sends): both on names outputs have
        if k % 5 == 0:
            rec.record_message(slavetip, "in", "slave", t + 0.0001)
            arrow_in = tf(
                np.eye(4), "TipForce", {"force_n": "0.0000,0.0000,2.0000", "mm_per_n": "5"}
            )
            rec.record_message(arrow_in, "in", "slave", t + 0.0001)
        for itf in ("slicer", "viewer"):
            rec.record_message(tf(turned(k), "Base"), "out", itf, t + 0.0004)
            rec.record_message(tf(tip_pose(k), "Tip"), "out", itf, t + 0.0004)
        for j in (1, 2):  # two datagrams drained in one tick: both count, the last stands
            q = (0.0, math.sin(0.05 * (2 * k + j)), 0.0, math.cos(0.05 * (2 * k + j)))
            pos = igtl.PositionMessage(
                (1.0 * k, 2.0 * j, 3.0), q, device_name="Master", header_version=2,
                timestamp=WALL + t, message_id=2 * k + j,
            )  # fmt: skip
            rec.record_message(pos, "in", "master", t + 0.0002)
        rec.record_message(slavetip, "out", "master", t + 0.0004)
        if k % 2 == 0:
            arrow = np.eye(4)
            arrow[:3, 3] = (30.0 + k, 12.0, 250.0)
            meta = {"force_n": force_n, "mm_per_n": "10", "frame": "patient"}
            rec.record_message(tf(arrow, "TipForce", meta), "out", "slicer", t + 0.0004)
        hand = igtl.SensorMessage(
            device_name="Force", data=(0.1 * k, 0.2, -0.3), header_version=2, timestamp=WALL + t
        )
        rec.record_message(hand, "in", "slave", t + 0.0003)
        other = igtl.PositionMessage(
            (9.0, 8.0, 7.0 * k), device_name="Base", header_version=2, timestamp=WALL + t
        )
        rec.record_message(other, "in", "tracker", t + 0.0003)
        if k % 4 == 0:  # a force it displays itself (a master's, in its base frame)
            shown = igtl.SensorMessage(
                device_name="Force", data=(0.0, -1.0 * k, 0.5), header_version=2,
                timestamp=WALL + t,
            )  # fmt: skip
            rec.record_message(shown, "out", "operator", t + 0.0004)
        rec.record_message(igtl.StringMessage("x", device_name="Tip"), "out", "slicer", t)
        bad = np.eye(4)
        bad[0, 3] = math.nan
        rec.record_message(tf(bad, "Tip"), "out", "slicer", t + 0.0005)
    rec.close()
    # a message no daemon recorded (no rec.t), first in the file: not a sample of any stream,
    # and the rest is read
    data = path.read_bytes()
    path.write_bytes(bytes(tf(np.eye(4), "Tip").pack(2)) + data)
    return path


def handmade_messages(path: Path, mtype: str, device: str, direction: str) -> list[Any]:
    """The recorded messages of one stream, an output once per tick (as the daemon sent it)."""
    out: list[Any] = []
    seen: set[str] = set()
    for m in read_recording(path):
        meta = m.metadata
        if m.message_type != mtype or m.device_name != device or "rec.t" not in meta:
            continue
        if meta["rec.dir"] != direction:
            continue
        if direction == "out" and meta["rec.t"] in seen:
            continue
        seen.add(meta["rec.t"])
        out.append(m)
    return out


def test_read_content_of_a_handmade_recording(handmade: Path, tmp_path: Path) -> None:
    from occ.recording.export import read_content

    # the wall clock's offset from the first state row when it comes first (the pose after it
    # has another offset)
    small = tmp_path / "small.igtl"
    rec = Recorder(small).start()
    row = igtl.NDArrayMessage(
        array=np.array([5.0, 1.0]), device_name=STATE_DEVICE, header_version=2,
        metadata={"columns": "t,state", "robot": "r"}, timestamp=WALL + 5.0,
    )  # fmt: skip
    rec.record_message(row, "out", "*", 5.0)
    tip = igtl.TransformMessage.from_matrix(
        np.eye(4), device_name="Tip", header_version=2, timestamp=WALL + 9.0
    )
    rec.record_message(tip, "out", "slicer", 5.0)
    rec.close()
    assert read_content(small).wall_offset == WALL
    # a state row with no columns or robot (not the daemon's): no rows, no name, no crash; an
    # output stamped 0 gives no offset, the next one does; a force as an NDARRAY
    other = tmp_path / "other.igtl"
    rec = Recorder(other).start()
    row = igtl.NDArrayMessage(array=np.array([5.0, 1.0]), device_name=STATE_DEVICE)
    rec.record_message(row, "out", "*", 5.0)
    for stamp, t in ((0.0, 5.0), (WALL + 7.0, 6.0)):
        tip = igtl.TransformMessage.from_matrix(np.eye(4), device_name="Tip", timestamp=stamp)
        rec.record_message(tip, "out", "slicer", t)
    shown = igtl.NDArrayMessage(array=np.array([1.0, 2.0, 3.0]), device_name="Force")
    rec.record_message(shown, "out", "operator", 6.0)
    rec.close()
    c = read_content(other)
    assert (c.robot, c.columns, c.state_rows) == ("", [""], [])
    assert len(c.streams[("out", "Tip")].t) == 2
    assert c.wall_offset == WALL + 1.0
    assert c.forces[("out", "Force")].force == [(1.0, 2.0, 3.0)]
    assert c.forces[("out", "Force")].frame == "base"

    c = read_content(handmade)
    assert c.robot == "Rig 7" and c.columns == COLUMNS.split(",")
    # the short row is left out; the first row's wall stamp (0) gives no offset: the first
    # output's does (Base, 0.4 ms after the row)
    assert c.state_t == pytest.approx([T0 + 0.01 * k for k in range(10) if k != 6], abs=1e-9)
    assert c.state_wall[0] == 0.0
    assert c.wall_offset == pytest.approx(WALL - 0.0004, abs=2e-6)
    assert [int(r[1]) for r in c.state_rows] == [s for k, s in enumerate(STATES) if k != 6]
    assert set(c.streams) == {
        ("out", "Tip"), ("out", "Base"), ("out", "SlaveTip"), ("out", "TipForce"),
        ("in", "Master"), ("in", "Base"), ("in", "SlaveTip"), ("in", "TipForce"),
    }  # fmt: skip
    tip = c.streams[("out", "Tip")]
    assert tip.device == "Tip" and tip.direction == "out"
    assert tip.t == pytest.approx([T0 + 0.01 * k + 0.0004 for k in range(10)], abs=1e-9)
    for k, m in enumerate(tip.pose):
        assert np.abs(m - tip_pose(k)).max() < TOL_MM
    assert tip.stamp == pytest.approx([WALL + T0 + 0.01 * k for k in range(10)], abs=1e-5)
    master = c.streams[("in", "Master")]
    assert len(master.t) == 20
    for m, msg in zip(master.pose, handmade_messages(handmade, "POSITION", "Master", "in"),
                      strict=True):  # fmt: skip
        x, y, z, w = msg.quaternion
        assert np.abs(m[:3, 3] - msg.position).max() < 1e-9
        # a turn about y: its cosine on the diagonal, its sine in (0, 2)
        assert m[0, 0] == pytest.approx(1 - 2 * y * y, abs=1e-6)
        assert m[0, 2] == pytest.approx(2 * y * w, abs=1e-6)
    base_in = c.streams[("in", "Base")]
    assert [m[:3, :3].tolist() for m in base_in.pose] == [np.eye(3).tolist()] * 10
    # forces: the return channel and the Slicer arrow in the patient frame, the received
    # SENSOR Force in its sender's base frame
    assert set(c.forces) == {
        ("out", "SlaveTip"), ("out", "TipForce"), ("out", "Force"), ("in", "Force"),
        ("in", "SlaveTip"), ("in", "TipForce"),
    }  # fmt: skip
    shown = c.forces[("out", "Force")]
    assert shown.frame == "base" and shown.force == [(0.0, -4.0 * k, 0.5) for k in (0, 1, 2)]
    st = c.forces[("out", "SlaveTip")]
    assert (st.device, st.direction, st.frame) == ("SlaveTip", "out", "patient")
    assert st.force == [(round(0.5 * k, 4), round(-0.1 * k, 4), 1.5) for k in range(10)]
    assert st.t == pytest.approx(tip.t, abs=1e-9) and st.stamp == pytest.approx(
        [WALL + T0 + 0.01 * k for k in range(10)], abs=1e-5
    )
    assert len(c.forces[("out", "TipForce")].t) == 5
    hand = c.forces[("in", "Force")]
    assert hand.frame == "base"
    assert np.abs(np.array(hand.force) - [(0.1 * k, 0.2, -0.3) for k in range(10)]).max() < 1e-6
    assert c.forces[("in", "TipForce")].force == [(0.0, 0.0, 2.0)] * 2
    assert c.force_transforms == {("out", "TipForce"), ("in", "TipForce")}


def test_seq_of_a_handmade_recording(handmade: Path, tmp_path: Path) -> None:
    from occ.recording.export import read_content, write_seq

    out = tmp_path / "deeper" / "still" / "rig.seq.mha"  # directories not there yet
    summary = write_seq(read_content(handmade), out, source="rig.igtl")
    text = out.read_text()
    lines = text.splitlines()
    # the header PLUS writes for a tracked sequence (no pixels), then the daemon's own fields
    assert lines[:14] == [
        "ObjectType = Image",
        "NDims = 3",
        "AnatomicalOrientation = RAI",
        "BinaryData = True",
        "BinaryDataByteOrderMSB = False",
        "CompressedData = False",
        "DimSize = 0 0 10",
        "ElementSpacing = 1 1 1",
        "Offset = 0 0 0",
        "TransformMatrix = 1 0 0 0 1 0 0 0 1",
        "ElementType = MET_UCHAR",
        "Kinds = domain domain list",
        "OCCRobot = Rig 7",
        "OCCSource = rig.igtl",
    ]
    assert lines[-1] == "ElementDataFile = LOCAL" and text.endswith("\n")
    header, sequences, last = slicer_parse(out)
    assert last == 9  # a frame a tick: its samples 0.2 to 0.4 ms after its start, one ms
    assert set(sequences) == {
        "TipToWorld", "BaseToWorld", "SlaveTipToWorld", "TipForceToWorld",
        "MasterToReference", "BaseToReference", "SlaveTipToReference", "TipForceToReference",
    }  # fmt: skip
    # timestamps from the first frame (the daemon's clock started long before)
    stamps = sorted(float(v) for v in sequences["TipToWorld"])
    assert stamps == [0.01 * k for k in range(10)]
    # the master's two samples of a tick share its millisecond: the second one stands
    masters = handmade_messages(handmade, "POSITION", "Master", "in")
    seq = sequences["MasterToReference"]
    for k in range(10):
        got = seq[f"{0.01 * k:.3f}"]
        assert got[:3, 3].tolist() == pytest.approx(masters[2 * k + 1].position, abs=1e-6)
    assert summary == {
        "frames": 10,
        "transforms": {
            "BaseToReference": 10, "BaseToWorld": 10, "MasterToReference": 10,
            "SlaveTipToReference": 2, "SlaveTipToWorld": 10, "TipForceToReference": 2,
            "TipForceToWorld": 5, "TipToWorld": 10,
        },
        "duration_s": 0.09,
    }  # fmt: skip
    # every frame lists the transforms in the same order (by name)
    first = [ln.split(" = ")[0] for ln in lines if ln.startswith("Seq_Frame0000_")]
    assert first == [
        f"Seq_Frame0000_{n}{f}"
        for n in ("BaseToReference", "BaseToWorld", "MasterToReference", "SlaveTipToReference",
                  "SlaveTipToWorld", "TipForceToReference", "TipForceToWorld", "TipToWorld")
        for f in ("Transform", "TransformStatus")
    ] + ["Seq_Frame0000_Timestamp"]  # fmt: skip


def test_seq_refuses_what_slicer_would_misread(tmp_path: Path) -> None:
    from occ.recording.export import ExportError, PoseStream, RecordingContent, write_seq

    c = RecordingContent(robot="Zürich")  # written as ASCII, the rest replaced
    c.streams[("out", "Tip")] = PoseStream("Tip", "out", [0.0], [0.0], [np.eye(4)])
    out = tmp_path / "a.seq.mha"
    write_seq(c, out)
    assert "OCCRobot = Z?rich\n" in out.read_text(encoding="ascii")
    assert "OCCSource" not in out.read_text()
    # a line Slicer would read in two pieces (fgets with 1000 bytes: 999 with the newline):
    # refused, nothing written; the longest line is a frame's Transform (65 + the device name)
    long = "T" + "x" * 934  # 999 characters and the newline
    c.streams = {("out", long): PoseStream(long, "out", [0.0], [0.0], [np.eye(4)])}
    with pytest.raises(ExportError) as err:
        write_seq(c, tmp_path / "b.seq.mha")
    assert str(err.value) == (
        f"header line too long for Slicer's reader: Seq_Frame0000_{long[:46]}..."
    )
    assert not (tmp_path / "b.seq.mha").exists()
    just = "T" + "x" * 933  # 998 and the newline: read whole
    c.streams = {("out", just): PoseStream(just, "out", [0.0], [0.0], [np.eye(4)])}
    write_seq(c, tmp_path / "c.seq.mha")
    assert max(len(b) for b in (tmp_path / "c.seq.mha").read_bytes().splitlines(True)) == 999
    slicer_parse(tmp_path / "c.seq.mha")
    # nothing to export: the error names what there is
    c.streams[("in", "Master")] = PoseStream("Master", "in", [0.0], [0.0], [np.eye(4)])
    with pytest.raises(ExportError) as err:
        write_seq(c, tmp_path / "d.seq.mha", devices={"Nope"})
    assert str(err.value) == (
        f"no TRANSFORM or POSITION stream to export (the recording has: Master, {just})"
    )
    assert err.value.code == 1
    with pytest.raises(ExportError) as err:
        write_seq(RecordingContent(), tmp_path / "d.seq.mha")
    assert str(err.value) == "no TRANSFORM or POSITION stream to export"


def log_ns(t: float, offset: float) -> int:
    return round((t + offset) * 1e9)


def stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def test_mcap_of_a_handmade_recording(handmade: Path, tmp_path: Path) -> None:
    require("rosbags", "pip install -e .[record]")
    from occ.recording.export import export, read_content

    out = tmp_path / "rig"  # a rosbag2 directory
    counts = export(handmade, out, "mcap")
    topics = decode_mcap(out / "rig.mcap")
    assert counts == {t: len(v) for t, v in sorted(topics.items())}
    assert set(topics) == {
        "/occ/rig_7/measured_cp", "/occ/rig_7/base/measured_cp", "/tf",
        "/occ/rig_7/master/measured_cp", "/occ/rig_7/slavetip/measured_cp",
        "/occ/rig_7/input/base/measured_cp", "/occ/rig_7/input/slavetip/measured_cp",
        "/occ/rig_7/measured_cf", "/occ/rig_7/tipforce/measured_cf",
        "/occ/rig_7/slavetip/measured_cf", "/occ/rig_7/input/tipforce/measured_cf",
        "/occ/rig_7/force/measured_cf", "/occ/rig_7/input/force/measured_cf",
        "/occ/rig_7/measured_js", "/occ/rig_7/setpoint_js", "/occ/rig_7/state",
    }  # fmt: skip
    meta = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["custom_data"] == {"occ.core.robot": "Rig 7"}
    c = read_content(handmade)
    offset = c.wall_offset
    assert offset is not None
    # the tip in its own tick's base (the base moves every tick), stamped as the Tip was
    tips = c.streams[("out", "Tip")]
    for k, ((msg, t), (tf, tft)) in enumerate(zip(topics["/occ/rig_7/measured_cp"],
                                                   topics["/tf"], strict=True)):  # fmt: skip
        local = np.linalg.solve(turned(k), tip_pose(k))
        assert msg.header.frame_id == "rig_7_base"
        assert stamp_ns(msg.header) == round(tips.stamp[k] * 1e9)
        assert t == tft == log_ns(tips.t[k], offset)
        got = pose_mm(msg.pose.position, msg.pose.orientation)
        assert np.abs(got - local).max() < 1e-3
        a, b = tf.transforms
        assert (a.header.frame_id, a.child_frame_id) == ("world", "rig_7_base")
        assert (b.header.frame_id, b.child_frame_id) == ("rig_7_base", "rig_7_tip")
        assert stamp_ns(a.header) == stamp_ns(b.header) == stamp_ns(msg.header)
        assert (
            np.abs(pose_mm(a.transform.translation, a.transform.rotation) - turned(k)).max() < 1e-3
        )
        assert np.abs(pose_mm(b.transform.translation, b.transform.rotation) - local).max() < 1e-3
    for k, (msg, t) in enumerate(topics["/occ/rig_7/base/measured_cp"]):
        assert msg.header.frame_id == "world" and t == log_ns(
            c.streams[("out", "Base")].t[k], offset
        )
        assert np.abs(pose_mm(msg.pose.position, msg.pose.orientation) - turned(k)).max() < 1e-3
    # the other pose streams: outputs in world, inputs in their sender's reference; an input
    # on a name taken (Base, an output's SlaveTip) under input/
    for topic, key, frame in (
        ("/occ/rig_7/master/measured_cp", ("in", "Master"), "master_reference"),
        ("/occ/rig_7/slavetip/measured_cp", ("out", "SlaveTip"), "world"),
        ("/occ/rig_7/input/base/measured_cp", ("in", "Base"), "base_reference"),
        ("/occ/rig_7/input/slavetip/measured_cp", ("in", "SlaveTip"), "slavetip_reference"),
    ):
        s = c.streams[key]
        assert len(topics[topic]) == len(s.t), topic
        for (msg, t), pose, stamp, rt in zip(topics[topic], s.pose, s.stamp, s.t, strict=True):
            assert msg.header.frame_id == frame and t == log_ns(rt, offset)
            assert stamp_ns(msg.header) == round(stamp * 1e9)
            assert np.abs(pose_mm(msg.pose.position, msg.pose.orientation) - pose).max() < 1e-3
    # forces: the own stream with the most samples (the return channel) on measured_cf; the
    # others on their own topics, a received one on a name an output took under input/
    for topic, key, frame in (
        ("/occ/rig_7/measured_cf", ("out", "SlaveTip"), "world"),
        ("/occ/rig_7/tipforce/measured_cf", ("out", "TipForce"), "world"),
        ("/occ/rig_7/slavetip/measured_cf", ("in", "SlaveTip"), "slavetip_reference"),
        ("/occ/rig_7/input/tipforce/measured_cf", ("in", "TipForce"), "tipforce_reference"),
        ("/occ/rig_7/force/measured_cf", ("out", "Force"), "rig_7_base"),
        ("/occ/rig_7/input/force/measured_cf", ("in", "Force"), "force_reference"),
    ):
        fs = c.forces[key]
        assert len(topics[topic]) == len(fs.t), topic
        for (msg, t), f, stamp, rt in zip(topics[topic], fs.force, fs.stamp, fs.t, strict=True):
            assert msg.header.frame_id == frame and t == log_ns(rt, offset)
            assert stamp_ns(msg.header) == round(stamp * 1e9)
            w = msg.wrench
            assert (w.force.x, w.force.y, w.force.z) == f
            assert (w.torque.x, w.torque.y, w.torque.z) == (0.0, 0.0, 0.0)
    # the state rows: joints measured and commanded, the efforts a master displays, the
    # state when it changes
    js, sp = topics["/occ/rig_7/measured_js"], topics["/occ/rig_7/setpoint_js"]
    assert len(js) == len(sp) == len(c.state_rows) == 9
    for (m, t), (s, ts), row, wall, rt in zip(js, sp, c.state_rows, c.state_wall, c.state_t,
                                              strict=True):  # fmt: skip
        assert t == ts == log_ns(rt, offset)
        assert m.header.frame_id == s.header.frame_id == "rig_7_base"
        assert stamp_ns(m.header) == stamp_ns(s.header) == round(wall * 1e9)
        assert list(m.name) == list(s.name) == ["a", "b"]
        assert list(m.position) == list(row[2:4]) and list(s.position) == list(row[4:6])
        assert list(s.effort) == list(row[9:11])
        assert len(m.velocity) == len(m.effort) == len(s.velocity) == 0
    states = topics["/occ/rig_7/state"]
    assert [m.data for m, _ in states] == ["READY", "ENABLED", "RUNNING", "STOPPED", "RUNNING"]
    assert [t for _, t in states] == [log_ns(c.state_t[i], offset) for i in (0, 2, 4, 6, 8)]


def test_mcap_single_file_name_and_devices(handmade: Path, tmp_path: Path) -> None:
    require("rosbags", "pip install -e .[record]")
    from occ.recording.export import export

    out = tmp_path / "one.mcap"
    counts = export(handmade, out, "mcap", name="Other Arm", devices={"Tip"})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one.mcap"]  # no bag directory left
    topics = decode_mcap(out)
    # --name: the namespace and frames; --device: the pose streams exported (the tip, in the
    # world now: no base), forces and state rows all the same
    assert set(topics) == {
        "/occ/other_arm/measured_cp", "/tf", "/occ/other_arm/measured_cf",
        "/occ/other_arm/tipforce/measured_cf", "/occ/other_arm/slavetip/measured_cf",
        "/occ/other_arm/input/tipforce/measured_cf", "/occ/other_arm/force/measured_cf",
        "/occ/other_arm/input/force/measured_cf",
        "/occ/other_arm/measured_js", "/occ/other_arm/setpoint_js", "/occ/other_arm/state",
    }  # fmt: skip
    assert counts["/occ/other_arm/measured_cp"] == 10
    for k, (msg, _) in enumerate(topics["/occ/other_arm/measured_cp"]):
        assert msg.header.frame_id == "other_arm_base"
        assert np.abs(pose_mm(msg.pose.position, msg.pose.orientation) - tip_pose(k)).max() < 1e-3
    a, b = topics["/tf"][0][0].transforms
    assert (a.child_frame_id, b.child_frame_id) == ("other_arm_base", "other_arm_tip")
    assert np.abs(pose_mm(a.transform.translation, a.transform.rotation) - np.eye(4)).max() < 1e-9


def test_an_upper_case_mcap_name_is_one_mcap_file_as_the_format_guess_says(
    handmade: Path, tmp_path: Path
) -> None:
    """`occ-record export REC OUT.MCAP` (no --format): the name asks for mcap, and the export
    is the single MCAP file of that name, not a rosbag2 directory called OUT.MCAP."""
    require("rosbags", "pip install -e .[record]")
    out = tmp_path / "CASE.MCAP"
    assert main(["export", str(handmade), str(out)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["CASE.MCAP"]  # one file, no bag dir
    assert "/occ/rig_7/measured_cp" in decode_mcap(out)


def test_mcap_state_rows_without_setpoints_or_joints(tmp_path: Path) -> None:
    require("rosbags", "pip install -e .[record]")
    from occ.recording.export import RecordingContent, write_mcap

    c = RecordingContent(columns=["t", "state", "q.a", "q.b", "sp.a", "eff.a", "eff.b"])
    c.state_t, c.state_wall = [0.0, 2.0], [11.0, 12.0]
    c.state_rows = [
        np.array([1.0, 3.0, 0.5, 0.6, 0.7, 0.8, 0.9]),
        np.array([2.0, 9, 0, 0, 0, 0, 0]),
    ]
    counts = write_mcap(c, tmp_path / "a.mcap")
    # one commanded joint of two: no setpoint_js; an unknown state code: no state message
    assert counts == {"/occ/robot/measured_js": 2, "/occ/robot/state": 1}
    topics = decode_mcap(tmp_path / "a.mcap")
    assert [list(m.position) for m, _ in topics["/occ/robot/measured_js"]] == [[0.5, 0.6], [0, 0]]
    # no wall clock known: the log times are the recording's times
    assert [t for _, t in topics["/occ/robot/measured_js"]] == [0, 2_000_000_000]
    c.columns = ["t", "state", "sp.a", "eff.a"]
    c.state_rows = [np.array([1.0, 3.0, 0.5, 0.6]), np.array([2.0, 4.0, 0.5, 0.6])]
    c.robot = "Rig 7"
    counts = write_mcap(c, tmp_path / "b.mcap")
    assert counts == {"/occ/rig_7/state": 2}
    # commanded joints with the efforts of some: setpoint_js without efforts
    c.columns = ["t", "state", "q.a", "q.b", "sp.a", "sp.b", "eff.a"]
    c.state_rows = [np.array([1.0, 3.0, 0.5, 0.6, 0.7, 0.8, 0.9])] * 2
    write_mcap(c, tmp_path / "c.mcap")
    sp = decode_mcap(tmp_path / "c.mcap")["/occ/rig_7/setpoint_js"]
    assert [(list(m.position), len(m.effort)) for m, _ in sp] == [([0.7, 0.8], 0)] * 2


def test_mcap_refusals(handmade: Path, tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    require("rosbags", "pip install -e .[record]")
    from occ.recording.export import ExportError, RecordingContent, export, read_content, write_mcap

    c = read_content(handmade)
    with monkeypatch.context() as m:  # rosbags without its writer: the same advice
        m.setitem(sys.modules, "rosbags.rosbag2", None)
        with pytest.raises(
            ExportError, match=r"needs rosbags: pip install 'occ-igtl\[record\]'"
        ) as err:
            write_mcap(c, tmp_path / "w.mcap")
        assert err.value.code == 2 and list(tmp_path.iterdir()) == []
    with pytest.raises(ExportError) as err:
        write_mcap(RecordingContent(), tmp_path / "none.mcap")
    assert str(err.value) == "nothing to export: no pose stream and no state rows"
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "x.mcap").write_bytes(b"keep")
    with pytest.raises(ExportError, match="exists; not overwriting"):
        write_mcap(c, tmp_path / "x.mcap")
    (tmp_path / "y.mcap.bagdir").mkdir()
    with pytest.raises(ExportError, match="a leftover of an export"):
        write_mcap(c, tmp_path / "y.mcap")
    (tmp_path / "dir").mkdir()
    with pytest.raises(ExportError, match="exists"):
        write_mcap(c, tmp_path / "dir")
    # export: an existing file is kept unless force, which replaces a file, never a
    # directory; an unknown format is a usage error
    with pytest.raises(ExportError, match="x.mcap exists; not overwriting"):
        export(handmade, tmp_path / "x.mcap", "mcap")
    assert (tmp_path / "x.mcap").read_bytes() == b"keep"
    assert export(handmade, tmp_path / "x.mcap", "mcap", force=True)["/tf"] == 10
    assert (tmp_path / "x.mcap").read_bytes()[:8] == b"\x89MCAP0\r\n"
    with pytest.raises(ExportError, match="is a directory; remove it yourself") as err:
        export(handmade, tmp_path / "dir", "mcap", force=True)
    assert err.value.code == 1 and (tmp_path / "dir").is_dir()
    with pytest.raises(ExportError, match="unknown format 'tiff'") as err:
        export(handmade, tmp_path / "z.tiff", "tiff")
    assert err.value.code == 2 and not (tmp_path / "z.tiff").exists()


def test_names_for_slicer_plus_and_ros() -> None:
    from occ.recording.export import _ros_name, guess_format, transform_names

    devices = ["a_b", "a-b", "a.b", "3d", "Transform1", "Status", "AToBToC", "stylusToTracker"]
    devices += ["StylusToTracker", "", "ToTool", "toTarget", "TipTo"]
    ins = ["a_b", "a+b", "a-b", "x", "X"]
    names = transform_names([("out", d) for d in devices] + [("in", d) for d in ins])
    # by device, outputs first; a name taken: In for the first input, then a number
    assert names == {
        ("out", "a-b"): "AbToWorld",
        ("out", "a.b"): "Ab2ToWorld",
        ("out", "a_b"): "Ab3ToWorld",
        ("out", "3d"): "S3dToWorld",
        ("out", "Transform1"): "Xform1ToWorld",
        ("out", "Status"): "StateToWorld",
        ("out", "AToBToC"): "AtoBtoCToWorld",
        ("out", "stylusToTracker"): "StylustoTrackerToWorld",
        ("out", "StylusToTracker"): "StylusToTracker",
        ("out", ""): "StreamToWorld",
        ("out", "ToTool"): "StoToolToWorld",
        ("out", "toTarget"): "StoTargetToWorld",
        ("out", "TipTo"): "TiptoToWorld",
        ("in", "X"): "XToReference",
        ("in", "a+b"): "AbToReference",
        ("in", "a-b"): "AbInToReference",
        ("in", "a_b"): "Ab3ToReference",
        ("in", "x"): "XInToReference",
    }
    for name in names.values():  # one From/To split for PLUS, a capital first
        frm, to = plus_split(name)
        assert frm[0].isupper() and to in ("World", "Reference", "Tracker")
    # PLUS names (once the name's other characters are dropped) kept; a PLUS name an output
    # and an input share is the output's, whichever comes first; the words Slicer reads
    # replaced inside a name
    keys = [("in", "StylusToTracker"), ("out", "StylusToTracker"), ("out", "AToB")]
    keys += [("out", "Probe_ToRef"), ("out", "MyTransform"), ("out", "LastStatus")]
    assert transform_names(keys) == {
        ("out", "AToB"): "AToB",
        ("out", "LastStatus"): "LastStateToWorld",
        ("out", "MyTransform"): "MyXformToWorld",
        ("out", "Probe_ToRef"): "ProbeToRef",
        ("out", "StylusToTracker"): "StylusToTracker",
        ("in", "StylusToTracker"): "StylusInToTracker",
    }
    assert (_ros_name("Rig 7"), _ros_name("3D Probe"), _ros_name("--"), _ros_name("A__b")) == (
        "rig_7", "s3d_probe", "stream", "a_b",
    )  # fmt: skip
    assert [guess_format(n) for n in ("a.seq.mha", "A.MHD", "b.MCAP", "c", "d.mha.csv")] == [
        "seq", "seq", "mcap", "csv", "csv",
    ]  # fmt: skip


def test_quaternions_of_every_kind_of_rotation() -> None:
    """quaternion_xyzw against the rotation it came from: the four branches of Shepperd's
    method (a turn of 180 degrees about each axis, and near them), w >= 0, a float32 matrix."""
    from occ.recording.export import quaternion_xyzw

    rng = np.random.default_rng(7)
    cases = [np.eye(4), rot("x", 180), rot("y", 180), rot("z", 180), rot("x", 179) @ rot("y", 2)]
    cases += [
        rot("y", 178) @ rot("z", 3),
        rot("z", 177) @ rot("x", -2),
        rot("x", 90) @ rot("z", 180),
    ]
    cases += [
        rot("x", a) @ rot("y", b) @ rot("z", c) for a, b, c in rng.uniform(-180, 180, (40, 3))
    ]
    for m in cases:
        r = m[:3, :3]
        for mat in (r, r.astype(np.float32)):
            q = quaternion_xyzw(mat)
            assert math.isclose(math.fsum(v * v for v in q), 1.0, abs_tol=1e-9)
            assert q[3] >= 0.0
            qq = type("Q", (), dict(zip("xyzw", q, strict=True)))
            assert np.abs(quat_matrix(qq) - r).max() < 1e-6, (r, q)
    # a turn about z by +90 and -90: the sign of the axis is the turn's direction
    assert quaternion_xyzw(rot("z", 90)[:3, :3]) == pytest.approx(
        (0, 0, math.sqrt(0.5), math.sqrt(0.5))
    )
    assert quaternion_xyzw(rot("z", -90)[:3, :3]) == pytest.approx(
        (0, 0, -math.sqrt(0.5), math.sqrt(0.5))
    )


# ---------------------------------------------------------------------- damaged recordings
def cut(recording: Path, tmp_path: Path, at: int, name: str = "cut.igtl") -> Path:
    """The recording's first ``at`` bytes: a crash, an interrupted copy."""
    out = tmp_path / name
    out.write_bytes(recording.read_bytes()[:at])
    return out


def message_ends(path: Path) -> list[int]:
    """The byte offset after each message of a whole recording."""
    dec = igtl.StreamDecoder()
    dec.feed(path.read_bytes())
    ends = []
    for _ in dec:
        ends.append(dec.offset)
    return ends


@pytest.mark.req("SR-REC-2")
def test_a_recording_cut_in_half_exports_up_to_the_cut(
    recording: Path, tmp_path: Path, capsys
) -> None:  # type: ignore[no-untyped-def]
    """seq, mcap and CSV of a recording cut mid-message: made of every whole message before
    the cut, exit 3, and the message says where (byte, message count, time)."""
    ends = message_ends(recording)
    half = len(ends) // 2
    at = ends[half - 1] + 30  # 30 bytes into message half + 1: inside its header
    damaged = cut(recording, tmp_path, at)
    whole = read_recording(recording)[:half]
    last_t = float(whole[-1].metadata["rec.t"])
    expected = (
        f"{damaged}: DAMAGED; salvaged {half} messages up to message {half} ending at byte "
        f"{ends[half - 1]} (t={last_t:.6f} s on the daemon's clock, "
    )
    stop = (
        f"stopped at byte {ends[half - 1]} of {at} (the file ends inside a message, 30 bytes "
        "of it); the 30 bytes from there are not exported"
    )
    seq = tmp_path / "cut.seq.mha"
    assert main(["export", str(damaged), str(seq)]) == 3
    err = capsys.readouterr().err
    assert err.startswith(f"occ-record: SALVAGED: {expected}") and err.rstrip().endswith(stop)
    # the sequence holds the poses up to the cut, read by SimpleITK and by Slicer's rules
    _, sequences, _ = slicer_parse(seq)
    tips = [m for m in whole if m.message_type == "TRANSFORM" and m.device_name == "Tip"]
    tips = [
        m
        for i, m in enumerate(tips)
        if i == 0 or m.metadata["rec.t"] != tips[i - 1].metadata["rec.t"]
    ]
    assert 3 <= len(sequences["TipToWorld"]) == len(tips)
    sitk = require("SimpleITK", "pip install -e .[test] (SimpleITK reads MetaImage files)")
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(seq))
    reader.ReadImageInformation()
    assert reader.GetSize()[2] > 0
    # CSV: every message before the cut, one row each
    out = tmp_path / "csv"
    assert main(["export", str(damaged), str(out)]) == 3
    assert expected in capsys.readouterr().err
    states = (out / "state.csv").read_text().splitlines()
    n_states = sum(1 for m in whole if m.device_name == STATE_DEVICE)
    assert len(states) == n_states + 1  # and the header
    n_msgs = len((out / "messages.csv").read_text().splitlines()) - 1
    assert n_msgs + n_states == half
    # the ROS 2 bag
    if find_spec("rosbags") is not None:
        bag = tmp_path / "cut.mcap"
        assert main(["export", str(damaged), str(bag)]) == 3
        assert expected in capsys.readouterr().err
        assert len(decode_mcap(bag)["/occ/slave/measured_cp"]) == len(tips)
    # the whole recording: exit 0, nothing on stderr
    assert main(["export", str(recording), str(tmp_path / "whole.seq.mha")]) == 0
    assert capsys.readouterr().err == ""


@pytest.mark.req("SR-REC-2")
def test_a_damaged_message_is_skipped_and_the_rest_exported(
    recording: Path, tmp_path: Path, capsys
) -> None:  # type: ignore[no-untyped-def]
    """A message whose body is damaged (its CRC fails) but whose framing holds: skipped and
    named, everything after it exported (exit 3)."""
    ends = message_ends(recording)
    data = bytearray(recording.read_bytes())
    k = len(ends) // 3
    data[ends[k] - 1] ^= 0xFF  # the last byte of message k + 1's body
    damaged = tmp_path / "bitflip.igtl"
    damaged.write_bytes(bytes(data))
    out = tmp_path / "csv"
    assert main(["export", str(damaged), str(out)]) == 3
    err = capsys.readouterr().err
    assert f"1 damaged messages skipped (byte {ends[k - 1]}: " in err, err
    assert "CRC" in err and "stopped at" not in err
    rows = len((out / "state.csv").read_text().splitlines()) - 1
    rows += len((out / "messages.csv").read_text().splitlines()) - 1
    assert rows == len(ends) - 1


@pytest.mark.req("SR-REC-2")
def test_an_export_that_fails_leaves_nothing_behind(
    recording: Path, tmp_path: Path, capsys
) -> None:  # type: ignore[no-untyped-def]
    """Nothing readable (the cut inside the first message): exit 1 naming the damage, no CSV
    directory (nor the directories made for it), no sequence file; an existing output kept."""
    damaged = cut(recording, tmp_path, 40)
    out = tmp_path / "new" / "deeper" / "csv"
    assert main(["export", str(damaged), str(out)]) == 1
    err = capsys.readouterr().err
    assert "nothing to export" in err and "stopped at byte 0 of 40" in err
    assert not (tmp_path / "new").exists()
    assert main(["export", str(damaged), str(tmp_path / "x.seq.mha")]) == 1
    capsys.readouterr()
    existing = tmp_path / "kept.seq.mha"
    existing.write_text("an earlier export")
    assert main(["export", str(damaged), str(existing), "--force"]) == 1
    capsys.readouterr()
    assert existing.read_text() == "an earlier export"
    # an existing CSV directory: its files kept unless --force
    out = tmp_path / "csvdir"
    assert main(["export", str(recording), str(out)]) == 0
    before = (out / "state.csv").read_text()
    assert main(["export", str(damaged), str(out)]) == 1
    assert "state.csv exists; not overwriting" in capsys.readouterr().err
    assert main(["export", str(damaged), str(out), "--force"]) == 1
    assert (out / "state.csv").read_text() == before
    assert sorted(p.name for p in out.iterdir()) == ["messages.csv", "state.csv"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["csvdir", "cut.igtl", "kept.seq.mha"]


@pytest.mark.req("SR-REC-4")
def test_an_output_name_the_exporter_cannot_write_is_refused(
    recording: Path, tmp_path: Path, capsys
) -> None:  # type: ignore[no-untyped-def]
    """``X.seq.nrrd`` (issue 41: exit 0 and a CSV directory of that name): refused, exit 2,
    nothing written, the supported forms said; a format that does not fit the name too."""
    from occ.recording.export import SUPPORTED

    for name, extra in [
        ("X.seq.nrrd", []),
        ("X.nhdr", []),
        ("X.csv", []),
        ("X.json", []),
        ("X.mcap", ["--format", "seq"]),
        ("X.seq.mha", ["--format", "csv"]),
        ("X.seq.mha", ["--format", "mcap"]),
    ]:
        assert main(["export", str(recording), str(tmp_path / name), *extra]) == 2, name
        err = capsys.readouterr().err
        assert SUPPORTED in err and repr(name) in err, err
        assert list(tmp_path.iterdir()) == [], name
    main(["export", str(recording), str(tmp_path / "X.seq.nrrd")])
    assert "its NRRD sequences are image volumes" in capsys.readouterr().err
    # what it writes: a dated directory is a directory, not a file suffix
    assert main(["export", str(recording), str(tmp_path / "run.2025-01-31")]) == 0
    assert (tmp_path / "run.2025-01-31" / "state.csv").is_file()
    assert main(["export", str(recording), str(tmp_path / "a.MHD")]) == 0
    assert (tmp_path / "a.MHD").read_text().startswith("ObjectType = Image\n")


@pytest.mark.req("SR-REC-3")
def test_no_pose_in_a_sequence_was_not_measured(tmp_path: Path) -> None:
    """Slicer's reader takes every ``...Transform`` field as a pose, whatever its status: a
    stream that starts late (the master's, 80 ms in) is in no frame before its first sample,
    and every pose read (SimpleITK, and Slicer's rules) is one measured at that frame's time:
    never the origin (issue 41: the identity before the first sample, shown as real)."""
    sitk = require("SimpleITK", "pip install -e .[test] (SimpleITK reads MetaImage files)")
    recording = tmp_path / "late_master.igtl"
    rec = Recorder(recording, rate_hz=100).start()
    sim = SimRobot(ROOT / "configs" / "slave.yaml", recorder=rec)
    master = sim.peer("master", address=("127.0.0.1", 5000))
    sim.peer("slicer")
    for k in range(200):  # the robot's outputs from the start, the master's stream from 80 ms
        if k >= 80 and k % 2 == 0:
            assert master.send_position((1.0 + k / 100.0, 50.0, 270.0), seq=k // 2 - 39) == 1
        sim.tick()
    sim.close()
    rec.close()
    out = tmp_path / "slave.seq.mha"
    assert main(["export", str(recording), str(out)]) == 0
    poses = recorded_poses(recording)
    frames, per = expected_frames(poses)
    master_poses = per[("in", "Master")]
    first = min(master_poses)
    assert frames.index(first) >= 35  # frames of the other streams before the master's first
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(out))
    reader.ReadImageInformation()
    for source, samples in (
        ("MasterToReference", master_poses),
        ("TipToWorld", per[("out", "Tip")]),
    ):
        read = {}
        for n, ms in enumerate(frames):
            field = f"Seq_Frame{n:04d}_{source}Transform"
            if reader.HasMetaDataKey(field):
                values = [float(v) for v in reader.GetMetaData(field).split()]
                read[ms] = np.array(values).reshape(4, 4)
        assert sorted(read) == sorted(samples), source
        for ms, pose in read.items():
            assert np.abs(pose - samples[ms]).max() < TOL_MM
            assert np.linalg.norm(pose[:3, 3]) > 1.0  # not the world's origin
    _, sequences, _ = slicer_parse(out)
    t0 = frames[0]
    got = sorted(float(v) for v in sequences["MasterToReference"])
    assert got[0] == pytest.approx((first - t0) / 1000.0) and len(got) == len(master_poses)


# ------------------------------------------------------------------------------ CSV
def test_csv_of_a_handmade_recording_row_by_row(handmade: Path, tmp_path: Path) -> None:
    """``state.csv``: the first state row's ``columns`` as its header, then each state row's
    numbers (9 significant digits) with the state by its name; ``messages.csv``: a header and one
    row per other message, in the file's order, with its recording time, direction and
    interface ("" where no daemon recorded them), its type, device, ID, header time stamp and
    a summary of its content (JSON, at most 200 characters). Read back with Python's csv."""
    import csv
    import json

    from occ.recording.export import export_csv
    from occ.recording.record import STATE_NAMES

    out = tmp_path / "out"
    assert export_csv(handmade, out) == (out / "state.csv", out / "messages.csv")
    states, others = [], []
    for m in read_recording(handmade):
        (
            states if m.message_type == "NDARRAY" and m.device_name == STATE_DEVICE else others
        ).append(m)
    with open(out / "state.csv", newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == COLUMNS.split(",")
    want = []
    for m in states:
        values = np.asarray(m.array).ravel().tolist()
        want.append([f"{v:.9g}" for v in values])
        want[-1][1] = STATE_NAMES[int(values[1])]
    assert rows[1:] == want and {r[1] for r in want} == {"READY", "ENABLED", "RUNNING", "STOPPED"}
    with open(out / "messages.csv", newline="") as f:
        mrows = list(csv.reader(f))
    assert mrows[0] == [
        "t", "dir", "interface", "type", "device", "message_id", "timestamp", "content"
    ]  # fmt: skip
    assert len(mrows) == len(others) + 1
    for row, m in zip(mrows[1:], others, strict=True):
        meta = m.metadata
        summary = json.dumps(m.content_summary(), separators=(",", ":"), default=str)
        assert row == [
            meta.get("rec.t", ""), meta.get("rec.dir", ""), meta.get("rec.if", ""),
            m.message_type, m.device_name, str(m.message_id), f"{m.timestamp:.6f}",
            summary if len(summary) <= 200 else summary[:197] + "...",
        ], (row, m)  # fmt: skip
    assert mrows[1][:3] == ["", "", ""]  # the first message: no daemon recorded it
    assert {r[1] for r in mrows[2:]} == {"in", "out"}


def test_csv_state_rows_short_unknown_and_without_columns(tmp_path: Path) -> None:
    """A state row of two numbers has its state named, one of one number has none to name, an
    unknown code stays a number, and a first row without ``columns`` gives an empty header; an
    existing CSV directory is written into only with ``force``."""
    import csv
    import json

    from occ.recording.export import ExportError, export_csv

    path = tmp_path / "short.igtl"
    rec = Recorder(path).start()
    for k, row in enumerate(([1.5, 3.0], [2.5], [3.5, 99.0])):
        msg = igtl.NDArrayMessage(
            array=np.asarray(row, dtype=np.float64), device_name=STATE_DEVICE, header_version=2
        )
        rec.record_message(msg, "out", "*", float(k))
    # a content summary of exactly 200 characters kept whole, a longer one cut to 200

    def summary(n: int) -> str:
        wire = igtl.StringMessage("a" * n, device_name="S").pack()
        text = igtl.unpack(wire).content_summary()  # as the recording reads it back
        return json.dumps(text, separators=(",", ":"), default=str)

    n200 = next(n for n in range(300) if len(summary(n)) == 200)
    for n in (n200, n200 + 1):
        rec.record_message(igtl.StringMessage("a" * n, device_name="S"), "in", "op", 4.0)
    rec.close()
    out = tmp_path / "csv"
    out.mkdir()
    (out / "messages.csv").write_text("before")
    with pytest.raises(ExportError, match="messages.csv exists; not overwriting"):
        export_csv(path, out)
    assert export_csv(path, out, force=True) == (out / "state.csv", out / "messages.csv")
    with open(out / "state.csv", newline="") as f:
        assert list(csv.reader(f)) == [[""], ["1.5", "RUNNING"], ["2.5"], ["3.5", "99"]]
    with open(out / "messages.csv", newline="") as f:
        whole, cut = [r[7] for r in list(csv.reader(f))[1:]]
    assert whole == summary(n200)
    assert len(cut) == 200 and cut == summary(n200 + 1)[:197] + "..."


@pytest.mark.req("SR-REC-2")
def test_a_bag_export_that_fails_midway_leaves_nothing_and_raises_its_own_error(
    handmade: Path, tmp_path: Path, monkeypatch
) -> None:  # type: ignore[no-untyped-def]
    """The bag is begun (its directory made by rosbags' writer) and the export fails: the
    error is the export's own, and neither the bag's directory nor the output is left, for a
    single file and for a directory bag alike; and when the clean-up meets what it cannot
    remove."""
    require("rosbags", "pip install -e .[record]")
    import occ.recording.export as export_module

    content = export_module.read_content(handmade)

    def fails(bag: Any, content: Any, robot: str) -> dict[str, Any]:
        bag.writer.open()
        assert any(tmp_path.iterdir())  # begun: there is something to remove
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(export_module, "_fill_bag", fails)
    for name in ("one.mcap", "bagdir"):
        with pytest.raises(OSError, match="No space left on device"):
            export_module.write_mcap(content, tmp_path / name)
        assert list(tmp_path.iterdir()) == []
    # the clean-up cannot remove what it finds (the bag's directory replaced by a link): the
    # error is still the export's own
    elsewhere = tmp_path / "elsewhere"

    def fails_after_a_link(bag: Any, content: Any, robot: str) -> dict[str, Any]:
        bag.writer.open()
        bag_dir = tmp_path / "two.mcap.bagdir"
        bag_dir.rename(elsewhere)
        bag_dir.symlink_to(elsewhere, target_is_directory=True)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(export_module, "_fill_bag", fails_after_a_link)
    with pytest.raises(OSError, match="No space left on device"):
        export_module.write_mcap(content, tmp_path / "two.mcap")
    assert not (tmp_path / "two.mcap").exists()


@pytest.mark.req("SR-REC-2")
def test_a_damaged_recording_is_salvaged_into_an_existing_csv_directory(
    recording: Path, tmp_path: Path
) -> None:
    """The report reaches the reading in an existing directory too: the CSV is made of the
    messages before the cut, and the report says where the reading stopped."""
    from occ.recording.export import export_csv
    from occ.recording.record import ReadReport

    ends = message_ends(recording)
    damaged = cut(recording, tmp_path, ends[9] + 20)  # ten whole messages and a piece
    out = tmp_path / "existing"
    out.mkdir()
    report = ReadReport()
    state_path, msg_path = export_csv(damaged, out, report=report)
    assert report.messages == 10 and report.stop is not None and report.stop[0] == ends[9]
    rows = len(state_path.read_text().splitlines()) - 1
    rows += len(msg_path.read_text().splitlines()) - 1
    assert rows == 10


# ------------------------------------------------------------------------------ outputs
def test_the_refusals_of_an_output_name_word_for_word(tmp_path: Path) -> None:
    """The refusal is what the user reads: a NRRD name (``.nrrd`` and ``.nhdr``, in any case)
    gets the reason Slicer cannot read it before the supported forms; another file suffix gets
    the supported forms alone; an unknown ``--format`` names the known ones; the CSV export
    refuses a file in the way and a recording with nothing readable."""
    from occ.recording.export import SUPPORTED, ExportError, export_csv, output_format

    nrrd = (
        "3D Slicer reads a transform sequence only from a MetaImage header (.seq.mha); "
        "its NRRD sequences are image volumes. "
    )
    for name, why in [
        ("X.seq.nrrd", nrrd),
        ("X.nhdr", nrrd),
        ("Y.NHDR", nrrd),
        ("X.csv", ""),
        ("X.json", ""),
    ]:
        with pytest.raises(ExportError) as caught:
            output_format(tmp_path / name)
        assert str(caught.value) == f"cannot write {name!r}: {why}{SUPPORTED}"
        assert caught.value.code == 2
    with pytest.raises(ExportError) as caught:
        output_format(tmp_path / "x.seq.mha", "nrrd")
    assert str(caught.value) == "unknown format 'nrrd' (one of csv, seq, mcap)"
    assert caught.value.code == 2
    # the CSV export's own refusals
    taken = tmp_path / "taken"
    taken.write_text("a file")
    with pytest.raises(ExportError) as caught:
        export_csv(tmp_path / "any.igtl", taken)
    assert str(caught.value) == f"{taken} exists and is not a directory"
    empty = tmp_path / "empty.igtl"
    empty.write_bytes(b"")
    with pytest.raises(ExportError) as caught:
        export_csv(empty, tmp_path / "csv")
    assert str(caught.value) == "nothing to export: no message could be read"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.igtl", "taken"]


def test_a_csv_export_reports_its_two_files_and_replaces_them_only_with_force(
    recording: Path, tmp_path: Path
) -> None:
    """``export`` to a directory says the paths of the two files it wrote; run again, it
    refuses to replace them, and with ``force`` replaces them."""
    from occ.recording.export import ExportError, export

    out = tmp_path / "csv"
    paths = {"state": str(out / "state.csv"), "messages": str(out / "messages.csv")}
    assert export(recording, out) == paths
    for name in ("state.csv", "messages.csv"):
        (out / name).write_text("an earlier export\n")
    with pytest.raises(ExportError, match="state.csv exists; not overwriting"):
        export(recording, out)
    assert (out / "state.csv").read_text() == "an earlier export\n"
    assert export(recording, out, force=True) == paths
    for name in ("state.csv", "messages.csv"):
        assert (out / name).read_text() != "an earlier export\n"


@pytest.mark.req("SR-REC-2")
def test_write_whole_writes_aside_and_any_failure_keeps_its_own_error(
    tmp_path: Path, monkeypatch
) -> None:  # type: ignore[no-untyped-def]
    """The part being written is a hidden ``.NAME.*.part`` beside the output (same file
    system, so the final rename is atomic; a reader of the directory sees what it is). When the
    writing fails, the caller gets the writer's error even when the writer had already removed
    or replaced its part, the directories made for the output are removed, and a directory
    that existed before (even empty) stays."""
    import tempfile

    from occ.recording.export import write_whole

    class WriterFailed(Exception):
        pass

    parts: list[Path] = []

    def into_file(tmp: Path) -> None:
        parts.append(tmp)
        tmp.write_text("whole")

    def into_dir(tmp: Path) -> None:
        parts.append(tmp)
        (tmp / "f.csv").write_text("whole")

    for out, write, directory in [
        (tmp_path / "a.seq.mha", into_file, False),
        (tmp_path / "d", into_dir, True),
    ]:
        parts.clear()
        write_whole(out, write, directory=directory)
        (part,) = parts
        assert part.parent == out.parent
        assert part.name.startswith(f".{out.name}.") and part.name.endswith(".part"), part
        assert not part.exists()
    assert (tmp_path / "a.seq.mha").read_text() == "whole"
    assert (tmp_path / "d" / "f.csv").read_text() == "whole"

    def removes_its_part_and_fails(tmp: Path) -> None:
        tmp.unlink()
        raise WriterFailed("disk gone")

    with pytest.raises(WriterFailed):
        write_whole(tmp_path / "new" / "b.seq.mha", removes_its_part_and_fails)
    assert not (tmp_path / "new").exists()

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()

    def replaces_its_part_by_a_link_and_fails(tmp: Path) -> None:
        tmp.rmdir()
        tmp.symlink_to(elsewhere, target_is_directory=True)
        raise WriterFailed("disk gone")

    with pytest.raises(WriterFailed):
        write_whole(tmp_path / "e", replaces_its_part_by_a_link_and_fails, directory=True)
    assert elsewhere.is_dir() and not (tmp_path / "e").exists()

    empty = tmp_path / "empty"
    empty.mkdir()

    def fails(tmp: Path) -> None:
        raise WriterFailed("disk gone")

    for directory in (False, True):
        with pytest.raises(WriterFailed):
            write_whole(empty / "c", fails, directory=directory)
        assert empty.is_dir() and list(empty.iterdir()) == []

    def no_temporary_file(*args: Any, **kwargs: Any) -> Any:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(tempfile, "mkstemp", no_temporary_file)
    with pytest.raises(OSError, match="No space left on device"):
        write_whole(tmp_path / "made" / "deeper" / "f.seq.mha", into_file)
    assert not (tmp_path / "made").exists()


def test_a_bag_is_written_in_time_order_poses_before_forces_before_state_rows(
    handmade: Path, tmp_path: Path
) -> None:
    """In the file (the order ``ros2 bag play`` publishes equal log times in), the messages go
    by log time, and within one log time the Base, then the Tip, then the other poses, then
    the forces, then the state rows: the hand-made recording receives a tracker's Base and a
    slave's Force at the same time every tick."""
    require("rosbags", "pip install -e .[record]")
    from mcap.reader import make_reader

    from occ.recording.export import export

    out = tmp_path / "rig.mcap"
    export(handmade, out)
    ns = "/occ/rig_7"

    def rank(topic: str) -> int:
        if topic == f"{ns}/base/measured_cp":
            return 0
        if topic == f"{ns}/measured_cp":
            return 1
        if topic.endswith("/measured_cp"):
            return 2
        if topic.endswith("/measured_cf"):
            return 3
        return 4  # measured_js, setpoint_js, state

    with open(out, "rb") as f:
        written = [
            (message.log_time, channel.topic)
            for _, channel, message in make_reader(f).iter_messages(log_time_order=False)
            if channel.topic != "/tf"
        ]
    assert [t for t, _ in written] == sorted(t for t, _ in written)
    ranks: dict[int, list[int]] = {}
    for t, topic in written:
        ranks.setdefault(t, []).append(rank(topic))
    assert all(r == sorted(r) for r in ranks.values()), ranks
    # the case that tells, a pose and a force at one time: at least the tracker's and the
    # slave's of each of the ten ticks
    assert len([r for r in ranks.values() if 2 in r and 3 in r]) >= 10


def test_the_wall_clock_offset_comes_from_the_first_stamped_sample(tmp_path: Path) -> None:
    """A daemon on a board without a real-time clock starts its wall clock at 0 (1970): its
    first stamps are under a second. The offset (wall clock - daemon clock) that the bag's log
    times take is the first stamped state row's, or without state rows the first stamped
    output pose's, however small its stamp; later samples (their stamps taken a little later
    in the tick) do not change it."""
    from occ.recording.export import read_content

    def recorded(name: str, with_rows: bool) -> Path:
        path = tmp_path / name
        rec = Recorder(path).start()
        for t, stamp in [(0.25, 0.5), (1.25, 1.5002), (2.25, 2.5003)]:
            if with_rows:
                row = igtl.NDArrayMessage(
                    array=np.array([t, 1.0]), device_name=STATE_DEVICE, header_version=2,
                    metadata={"columns": "t,state"}, timestamp=stamp,
                )  # fmt: skip
                rec.record_message(row, "out", "*", t)
            tip = igtl.TransformMessage.from_matrix(
                np.eye(4), device_name="Tip", header_version=2, timestamp=stamp + 0.0001
            )
            seen = igtl.PositionMessage(
                (1.0, 2.0, 3.0), device_name="Master", header_version=2, timestamp=0.2
            )
            rec.record_message(seen, "in", "master", t)  # an input's stamp is the peer's
            rec.record_message(tip, "out", "slicer", t)
        rec.close()
        return path

    # (a stamp is 32.32 fixed point on the wire: exact to 1e-9 s)
    offset = read_content(recorded("rows.igtl", True)).wall_offset
    assert offset == pytest.approx(0.5 - 0.25, abs=1e-6)
    offset = read_content(recorded("poses.igtl", False)).wall_offset
    assert offset == pytest.approx(0.5 + 0.0001 - 0.25, abs=1e-6)
