"""docs/SAFETY.md and the tests agree: every requirement has a test, every test cites a real one.

A test verifies a safety requirement by carrying its ID in the ``req`` marker
(``@pytest.mark.req("SR-LOSS-1")``, or ``pytestmark = pytest.mark.req(...)`` for a whole file).
The markers are read from the test sources with ``ast`` (no import, no collection), so this check
costs milliseconds and sees the realtime and interop tests that a plain run deselects.

docs/SAFETY.md lists each requirement as a row of its table, ID first, with the tests that carry
it in the last column (``file::test``). The lists must match the markers both ways, so the
document never claims a test that does not exist or forgets one that does. A requirement marked
``pending`` (its code is being rebuilt on another branch) may have no test yet.

The reading of both lives in occ_testkit/trace.py, shared with the hazard trace
(tests/test_hazards.py) and the release report (occ_testkit/evidence.py).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from occ_testkit.trace import ID, SAFETY, marked_tests, requirements, trace_problems


def test_the_register_lists_requirements() -> None:
    reqs = requirements()
    assert len(reqs) >= 20, sorted(reqs)
    # every ID the prose mentions is one of the table's rows
    mentioned = set(ID.findall(SAFETY.read_text()))
    assert mentioned <= set(reqs), sorted(mentioned - set(reqs))


def test_every_requirement_has_a_test_and_the_document_lists_them() -> None:
    problems = trace_problems(requirements(), marked_tests())
    assert not problems, "\n".join(problems)


def test_the_check_itself_sees_a_missing_test_and_an_unknown_id(tmp_path: Path) -> None:
    # the parser reads markers in both forms, and a row with no test is reported as untested
    tests = tmp_path / "tests"
    tests.mkdir()
    (tests / "test_a.py").write_text(
        "import pytest\n"
        "pytestmark = [pytest.mark.slow, pytest.mark.req('SR-A-1')]\n"
        "@pytest.mark.req('SR-B-1', 'SR-C-2')\n"
        "def test_x():\n    pass\n"
        "def helper():\n    pass\n"
    )
    assert marked_tests(tests, root=tmp_path) == {
        "tests/test_a.py::test_x": {"SR-A-1", "SR-B-1", "SR-C-2"}
    }
    doc = (
        "| **SR-A-1** | a | DESIGN | `tests/test_a.py::test_x` |\n"
        "| **SR-D-1** | d | DESIGN | none yet |\n"
        "| **SR-E-1** | e | DESIGN | pending: fixtures branch |\n"
    )
    reqs = requirements(doc)
    assert reqs == {
        "SR-A-1": (False, {"tests/test_a.py::test_x"}),
        "SR-D-1": (False, set()),
        "SR-E-1": (True, set()),
    }
    marked = {
        "tests/test_a.py::test_x": {"SR-A-1", "SR-B-1"},
        "tests/test_a.py::test_y": {"SR-A-1"},
    }
    assert trace_problems(reqs, marked) == [
        "tests/test_a.py::test_x cites SR-B-1, which docs/SAFETY.md does not list",
        "SR-A-1: add `tests/test_a.py::test_y` to its row in docs/SAFETY.md",
        "SR-D-1 has no test (mark one with pytest.mark.req('SR-D-1'))",
    ]


def test_the_marker_is_registered(pytestconfig: pytest.Config) -> None:
    assert any(line.startswith("req(") for line in pytestconfig.getini("markers"))
