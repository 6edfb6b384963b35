"""docs/SAFETY.md and the tests agree: every requirement has a test, every test cites a real one.

A test verifies a safety requirement by carrying its ID in the ``req`` marker
(``@pytest.mark.req("SR-LOSS-1")``, or ``pytestmark = pytest.mark.req(...)`` for a whole file).
The markers are read from the test sources with ``ast`` (no import, no collection), so this check
costs milliseconds and sees the realtime and interop tests that a plain run deselects.

docs/SAFETY.md lists each requirement as a row of its table, ID first, with the tests that carry
it in the last column (``file::test``). The lists must match the markers both ways, so the
document never claims a test that does not exist or forgets one that does. A requirement marked
``pending`` (its code is being rebuilt on another branch) may have no test yet.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAFETY = ROOT / "docs" / "SAFETY.md"
ID = re.compile(r"\bSR-[A-Z]+-\d+\b")
ROW = re.compile(r"^\|\s*\*\*(SR-[A-Z]+-\d+)\*\*\s*\|(.*)\|\s*$")
TEST_REF = re.compile(r"`([\w/]+\.py)::(\w+)`")


def _req_ids(node: ast.expr) -> list[str] | None:
    """The IDs of a ``pytest.mark.req(...)`` expression, or None when it is something else."""
    if (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and node.func.attr == "req"
        and isinstance(node.func.value, ast.Attribute)
        and node.func.value.attr == "mark"
    ):
        ids = []
        for arg in node.args:
            if not (isinstance(arg, ast.Constant) and isinstance(arg.value, str)):
                raise AssertionError(f"req marker with a non-literal argument: {ast.unparse(node)}")
            ids.append(arg.value)
        return ids
    return None


def marked_tests(root: Path = ROOT / "tests") -> dict[str, set[str]]:
    """``{"tests/occ/test_x.py::test_y": {IDs}}`` for every test function carrying a req marker."""
    found: dict[str, set[str]] = {}
    for path in sorted(root.rglob("test_*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        rel = path.relative_to(ROOT).as_posix()
        module_ids: set[str] = set()
        for stmt in tree.body:
            if isinstance(stmt, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "pytestmark" for t in stmt.targets
            ):
                values = stmt.value.elts if isinstance(stmt.value, (ast.List, ast.Tuple)) else [stmt.value]
                for value in values:
                    module_ids.update(_req_ids(value) or [])
        for stmt in ast.walk(tree):
            if not isinstance(stmt, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            if not stmt.name.startswith("test_"):
                continue
            ids = set(module_ids)
            for deco in stmt.decorator_list:
                ids.update(_req_ids(deco) or [])
            if ids:
                found[f"{rel}::{stmt.name}"] = ids
    return found


def requirements(text: str | None = None) -> dict[str, tuple[bool, set[str]]]:
    """``{ID: (pending, {tests listed})}`` from the rows of docs/SAFETY.md."""
    text = SAFETY.read_text() if text is None else text
    out: dict[str, tuple[bool, set[str]]] = {}
    for line in text.splitlines():
        m = ROW.match(line)
        if m is None:
            continue
        rid, rest = m.groups()
        assert rid not in out, f"docs/SAFETY.md: {rid} is listed twice"
        cells = rest.split("|")
        tests = {f"{f}::{t}" for f, t in TEST_REF.findall(cells[-1])}
        out[rid] = ("pending" in cells[-1].lower(), tests)
    return out


def test_the_register_lists_requirements() -> None:
    reqs = requirements()
    assert len(reqs) >= 20, sorted(reqs)
    # every ID the prose mentions is one of the table's rows
    mentioned = set(ID.findall(SAFETY.read_text()))
    assert mentioned <= set(reqs), sorted(mentioned - set(reqs))


def trace_problems(
    reqs: dict[str, tuple[bool, set[str]]], marked: dict[str, set[str]]
) -> list[str]:
    """Everything that keeps the register and the tests from agreeing, one line each."""
    problems = []
    carrying: dict[str, set[str]] = {rid: set() for rid in reqs}
    for test, ids in sorted(marked.items()):
        for rid in sorted(ids):
            if rid in carrying:
                carrying[rid].add(test)
            else:
                problems.append(f"{test} cites {rid}, which docs/SAFETY.md does not list")
    for rid, (pending, listed) in reqs.items():
        if not carrying[rid] and not pending:
            problems.append(f"{rid} has no test (mark one with pytest.mark.req({rid!r}))")
        for test in sorted(listed - carrying[rid]):
            problems.append(f"{rid}: docs/SAFETY.md lists {test}, which does not carry the marker")
        for test in sorted(carrying[rid] - listed):
            problems.append(f"{rid}: add `{test}` to its row in docs/SAFETY.md")
    return problems


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
    global ROOT
    saved = ROOT
    try:
        ROOT = tmp_path
        assert marked_tests(tests) == {"tests/test_a.py::test_x": {"SR-A-1", "SR-B-1", "SR-C-2"}}
    finally:
        ROOT = saved
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
    marked = {"tests/test_a.py::test_x": {"SR-A-1", "SR-B-1"}, "tests/test_a.py::test_y": {"SR-A-1"}}
    assert trace_problems(reqs, marked) == [
        "tests/test_a.py::test_x cites SR-B-1, which docs/SAFETY.md does not list",
        "SR-A-1: add `tests/test_a.py::test_y` to its row in docs/SAFETY.md",
        "SR-D-1 has no test (mark one with pytest.mark.req('SR-D-1'))",
    ]


def test_the_marker_is_registered(pytestconfig: pytest.Config) -> None:
    assert any(line.startswith("req(") for line in pytestconfig.getini("markers"))
