"""``occd --check`` names the line of an EDS that does not load (occ/drivers/eds_lines.py):
small broken EDS files written here, each through the console script's function on the
shipped CiA 402 slave; and the finder against canopen itself, the reader that refuses them."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from occ.cli import main
from occ.drivers.cia402 import DEFAULT_EDS
from occ.drivers.eds_lines import eds_problems, eds_refusal

ROOT = Path(__file__).resolve().parents[2]

SMALL = """\
; a CiA 402 drive's first objects, enough for canopen to read
[FileInfo]
FileName=small.eds

[DeviceInfo]
VendorNumber=0x0
NrOfTXPDO=1

[1000]
ParameterName=Device type
ObjectType=0x7
DataType=0x0007
AccessType=ro
DefaultValue=0x00020192

[1A00]
ParameterName=TPDO 1 mapping
ObjectType=0x9
SubNumber=2

[1A00sub0]
ParameterName=Number of entries
DataType=0x0005
AccessType=rw
DefaultValue=1

[1A00sub1]
ParameterName=Entry 1
DataType=0x0007
AccessType=rw
DefaultValue=0x60410010

[6064]
ParameterName=Position actual value
ObjectType=0x7
DataType=0x0004  ; INTEGER32
AccessType=ro
PDOMapping=1
"""


def check(tmp_path: Path, eds_text: str, capsys: pytest.CaptureFixture[str]) -> tuple[Path, str]:
    """``occd --check`` of the shipped CiA 402 slave whose yaw drive has ``eds_text`` for its
    EDS: the EDS file and what the check printed (it must refuse)."""
    eds = tmp_path / "drive.eds"
    eds.write_text(eds_text)
    raw = yaml.safe_load((ROOT / "configs" / "slave-cia402.yaml").read_text())
    raw["robot"]["drivers"][0]["params"]["nodes"]["yaw"]["eds"] = str(eds)
    config = tmp_path / "slave.yaml"
    config.write_text(yaml.safe_dump(raw, sort_keys=False))
    capsys.readouterr()
    assert main(["--check", str(config)]) == 2
    return eds, capsys.readouterr().err


def line_of(text: str, wanted: str, after: str = "") -> int:
    """The number of the first line that is ``wanted``, after the line ``after`` if given."""
    lines = text.splitlines()
    start = lines.index(after) if after else 0
    return lines.index(wanted, start) + 1


def test_the_small_eds_loads_and_only_lacks_objects(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The file the cases below break is read by canopen: the driver refuses it for the
    objects it lacks, not for a line."""
    eds, err = check(tmp_path, SMALL, capsys)
    assert f"nodes.yaw: eds {str(eds)!r} lacks objects" in err, err
    assert "0x1a00" not in err and "0x6064" not in err and f"{eds}:" not in err
    assert eds_problems(eds) == []


CASES = {
    # a bad value of a key in an object's section: its own line
    "bad number": (
        ("DataType=0x0004  ; INTEGER32", "DataType=0xZZ"),
        "DataType=0xZZ",
        "[6064] DataType=0xZZ is not a number",
    ),
    "bad object type": (
        ("ObjectType=0x9", "ObjectType=record"),
        "ObjectType=record",
        "[1A00] ObjectType=record is not a number",
    ),
    # a missing required key: the section's line
    "missing key": (
        ("DataType=0x0004  ; INTEGER32\n", ""),
        "[6064]",
        "[6064] lacks DataType (required of a variable, ObjectType 0x7)",
    ),
    "key in the wrong case": (
        ("AccessType=ro\nDefaultValue=0x00020192", "accesstype=ro\nDefaultValue=0x00020192"),
        "[1000]",
        "[1000] lacks AccessType (required of a variable, ObjectType 0x7) (it has accesstype: "
        "keys are case-sensitive)",
    ),
    # a malformed line
    "malformed line": (
        ("AccessType=rw\nDefaultValue=1", "AccessType=rw\nDefaultValue 1"),
        "DefaultValue 1",
        "[1A00sub0] 'DefaultValue 1' is neither a [section] nor a key=value line",
    ),
    "key given twice": (
        ("PDOMapping=1", "PDOMapping=1\nAccessType=rw"),
        "AccessType=rw",
        "[6064] AccessType again (first on line",
    ),
    "sub-object without its object": (
        ("[1A00]\n", "[1A01]\n"),
        "[1A00sub0]",
        "[1A00sub0] has no object [1A00]",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_occd_check_names_the_eds_file_and_line_that_is_wrong(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str
) -> None:
    (old, new), line_text, words = CASES[case]
    assert SMALL.count(old) == 1
    broken = SMALL.replace(old, new)
    eds, err = check(tmp_path, broken, capsys)
    after = "[6064]" if line_text == "AccessType=rw" else ""  # the second of two
    line = line_of(broken, line_text, after)
    assert f"cia402 driver 'arm': nodes.yaw: {eds}:{line}: {words}" in err, err
    assert "does not load" not in err  # the line, not canopen's words


def test_every_problem_is_named_by_line_up_to_five(tmp_path: Path) -> None:
    broken = SMALL.replace("=0x0007", "=0xQ").replace("AccessType=ro\n", "")
    eds = tmp_path / "many.eds"
    eds.write_text(broken)
    found = eds_problems(eds)
    assert [line for line, _ in found] == sorted(line for line, _ in found)
    assert len(found) == 4, found  # two DataTypes, two sections without AccessType
    assert found[0] == (line_of(broken, "[1000]"), "[1000] lacks AccessType (required of a "
                        "variable, ObjectType 0x7)")  # fmt: skip
    text = eds_refusal(eds, ValueError("canopen's words"))
    assert text.count(f"{eds}:") == 4 and "canopen's words" not in text
    many = broken + "".join(f"junk{k}\n" for k in range(4))
    eds.write_text(many)
    text = eds_refusal(eds, ValueError("canopen's words"))
    assert text.count(f"{eds}:") == 5 and text.endswith("(and 3 more)")


def test_without_a_line_to_name_canopens_words_are_kept(tmp_path: Path) -> None:
    eds = tmp_path / "fine.eds"
    eds.write_text(SMALL)
    assert eds_refusal(eds, ValueError("boom")) == f"eds {str(eds)!r} does not load: boom"
    gone = tmp_path / "gone.eds"
    text = eds_refusal(gone, ValueError("boom"))
    assert text.startswith(f"eds {str(gone)!r} does not load: boom (and cannot be read:")


def test_a_byte_that_is_no_text_is_named_by_line(tmp_path: Path) -> None:
    eds = tmp_path / "bytes.eds"
    eds.write_bytes(SMALL.encode().replace(b"Device type", b"Device \xff type"))
    found = eds_problems(eds)
    assert len(found) == 1 and found[0][0] == line_of(SMALL, "ParameterName=Device type")
    assert "byte 0xff is not text in" in found[0][1]


@pytest.mark.parametrize("start", range(5))
def test_the_finder_agrees_with_canopen_on_the_shipped_eds_broken(
    tmp_path: Path, start: int
) -> None:
    """Lines of the shipped EDS deleted (every 25th from ``start``), or their values spoiled:
    canopen refuses the file exactly when the finder names a line."""
    import canopen

    lines = DEFAULT_EDS.read_text().splitlines()
    eds = tmp_path / "spoilt.eds"
    refused = 0
    for i in range(start * 5, len(lines), 25):
        spoilt = lines[:i] + lines[i + 1 :]
        if "=" in lines[i] and not lines[i].startswith(";"):
            key = lines[i].split("=")[0]
            spoilt = lines[:i] + [f"{key}=0x{key}"] + lines[i + 1 :]
        if i % 2:
            spoilt = lines[:i] + lines[i + 1 :]
        eds.write_text("\n".join(spoilt) + "\n")
        try:
            canopen.import_od(str(eds))
        except Exception:  # noqa: BLE001 - whatever canopen raises is a refusal
            loads = False
        else:
            loads = True
        found = eds_problems(eds)
        assert loads == (found == []), (i + 1, lines[i], found)
        refused += not loads
    assert refused > 0  # the cases include refusals
