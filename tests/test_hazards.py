"""docs/HAZARDS.md, docs/SAFETY.md, the tests and the code agree (occ_testkit/trace.py).

Each hazard cites requirements that docs/SAFETY.md lists, each of those lists tests, and each of
those tests exists and carries the requirement's marker, so every hazard has at least one
mitigation with a test; the code each mitigation names is defined where it says; every
requirement mitigates some hazard. The tests of a hazard are read from SAFETY.md, never copied.
With a release report (``OCC_RELEASE_REPORT=path/report.json``, written by
``scripts/release_evidence``) the hazards' tests must also have passed in that run.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from occ_testkit import trace

ROOT = Path(__file__).resolve().parents[1]


def test_every_hazard_traces_to_tested_requirements_and_named_code() -> None:
    problems = trace.hazard_problems(
        trace.hazards(), trace.requirements(), trace.scan_tests(ROOT / "tests")
    )
    assert not problems, "\n".join(problems)


def test_the_register_covers_the_hazards_of_a_master_slave_controller() -> None:
    haz = trace.hazards()
    text = " ".join(f"{h.title} {h.cause}".lower() for h in haz.values())
    for topic in (
        "unintended motion", "lies", "after reset", "wrong frame", "loss of stop", "hung",
        "stale", "between arms", "forbidden region", "locked out", "two operators", "replayed",
        "forged", "energy", "force on tissue", "stop latched while the tool presses",
        "network loss", "unsafe start", "power-up", "configuration error", "records",
    ):  # fmt: skip
        assert topic in text, f"docs/HAZARDS.md names no hazard of {topic!r}"
    # each hazard's tests come from SAFETY.md: every hazard has some
    reqs = trace.requirements()
    assert all(trace.hazard_tests(h, reqs) for h in haz.values())


SAFETY = """
| **SR-A-1** | a | x | `tests/test_a.py::test_x` |
| **SR-B-1** | b | x | `tests/test_a.py::test_gone` |
| **SR-C-1** | c | x | pending: another branch |
| **SR-D-1** | d | x | `tests/test_a.py::test_y` |
| **SR-E-1** | e | x | `tests/test_a.py::test_x` |
"""

HAZARDS = """
| ID | Hazard | Cause | Effect | Severity | Probability | Mitigations | SR IDs | Residual |
|---|---|---|---|---|---|---|---|---|
| **HAZ-1** | One | c | e | critical | remote | a check (`pkg/mod.py::Checker.check`)<br>\
prose only | SR-A-1, SR-B-1, SR-Z-9 | r |
| **HAZ-2** | Two | c | e | grave | often | another (`pkg/mod.py::missing`, `pkg/nope.py::X`) | \
none | r |
| **HAZ-3** | Three | c | e | minor | remote | a third (`pkg/mod.py::LIMIT`) | SR-C-1, SR-D-1 | r |
"""


def test_the_check_names_each_break_of_the_trace(tmp_path: Path) -> None:
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "mod.py").write_text(
        "LIMIT = 3\nclass Checker:\n    def check(self):\n        pass\n"
    )
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "test_a.py").write_text(
        "import pytest\n"
        "@pytest.mark.req('SR-A-1', 'SR-E-1')\ndef test_x():\n    pass\n"
        "def test_y():\n    pass\n"
    )
    haz = trace.hazards(HAZARDS)
    assert haz["HAZ-1"].mitigations == ("a check (`pkg/mod.py::Checker.check`)", "prose only")
    assert haz["HAZ-1"].code == (("pkg/mod.py", "Checker.check"),)
    tests = trace.scan_tests(tmp_path / "tests", tmp_path)
    assert tests == {
        "tests/test_a.py::test_x": {"SR-A-1", "SR-E-1"},
        "tests/test_a.py::test_y": set(),
    }
    reqs = trace.requirements(SAFETY)
    assert trace.hazard_tests(haz["HAZ-1"], reqs) == [
        "tests/test_a.py::test_gone",
        "tests/test_a.py::test_x",
    ]
    assert trace.hazard_problems(haz, reqs, tests, tmp_path) == [
        "HAZ-1: the mitigation 'prose only' names no code (`file.py::Name`)",
        "HAZ-1: SR-B-1 lists tests/test_a.py::test_gone, which does not exist",
        "HAZ-1 cites SR-Z-9, which docs/SAFETY.md does not list",
        "HAZ-2: severity 'grave' is not one of negligible, minor, serious, critical, catastrophic",
        "HAZ-2: probability 'often' is not one of improbable, remote, occasional, probable, "
        "frequent",
        "HAZ-2 has no SR ID: no requirement implements its mitigations",
        "HAZ-2 names pkg/mod.py::missing: pkg/mod.py defines no missing",
        "HAZ-2 names pkg/nope.py::X: no file pkg/nope.py",
        "HAZ-3 cites SR-C-1, whose row in docs/SAFETY.md lists no test (pending)",
        "HAZ-3: SR-D-1 lists tests/test_a.py::test_y, which does not carry its marker",
        "SR-E-1 mitigates no hazard: cite it in a row of docs/HAZARDS.md",
    ]


def test_a_row_of_the_wrong_shape_is_refused_naming_it() -> None:
    with pytest.raises(ValueError, match=r"HAZ-7 has 3 cells after its ID, not 8"):
        trace.hazards("| **HAZ-7** | a | b | c |\n")
    with pytest.raises(ValueError, match="HAZ-1 is listed twice"):
        trace.hazards(HAZARDS + HAZARDS.splitlines()[3] + "\n")


def test_a_hazard_whose_tests_did_not_pass_fails_the_release() -> None:
    haz = trace.hazards(HAZARDS)
    reqs = trace.requirements(SAFETY)
    outcomes = {"tests/test_a.py::test_x": "passed", "tests/test_a.py::test_y": "failed"}
    result = trace.hazard_outcomes(haz, reqs, outcomes)
    assert result["HAZ-1"] == ("not run", ["tests/test_a.py::test_gone"])
    assert result["HAZ-2"] == ("no test", [])
    assert result["HAZ-3"] == ("failed", ["tests/test_a.py::test_y"])
    outcomes["tests/test_a.py::test_gone"] = "passed"
    outcomes["tests/test_a.py::test_y"] = "skipped"
    result = trace.hazard_outcomes(haz, reqs, outcomes)
    assert result["HAZ-1"] == ("passed", [])
    assert result["HAZ-3"] == ("skipped", ["tests/test_a.py::test_y"])


@pytest.mark.skipif(
    not os.environ.get("OCC_RELEASE_REPORT"),
    reason="no release report given (OCC_RELEASE_REPORT=path/to/report.json)",
)
def test_every_hazards_tests_passed_in_the_release_report() -> None:
    # the report's own verdicts are not trusted: each hazard is judged again from the outcomes
    # of the tests it recorded, against the documents as they are now
    report = json.loads(Path(os.environ["OCC_RELEASE_REPORT"]).read_text(encoding="utf-8"))
    outcomes = {name: t["status"] for name, t in report["tests"].items()}
    result = trace.hazard_outcomes(trace.hazards(), trace.requirements(), outcomes)
    bad = {hid: r for hid, r in result.items() if r[0] != "passed"}
    assert not bad, "\n".join(f"{hid}: {s} {', '.join(t)}" for hid, (s, t) in bad.items())
