"""The trace from hazards to requirements to tests, read from the documents and the test sources.

docs/SAFETY.md lists the safety requirements, one table row each (``| **SR-AREA-N** | ... |``),
with the tests that verify it in the last column (```tests/x/test_y.py::test_z```). A test
carries the IDs it verifies in a ``req`` marker (``@pytest.mark.req("SR-LOSS-1")``, or
``pytestmark = pytest.mark.req(...)`` for a whole file). docs/HAZARDS.md lists the hazards, one
row each (``| **HAZ-N** | ... |``), with the code that mitigates each and the requirements that
implement those mitigations. Everything here reads text and ``ast`` (no import, no collection),
so a check costs milliseconds and sees the realtime and interop tests a plain run deselects.

    python -m occ_testkit.trace hazards    # each hazard, its requirements and their tests
    python -m occ_testkit.trace check      # every problem of the trace, one a line (exit 1 if any)

tests/test_safety_trace.py holds SAFETY.md and the markers together, tests/test_hazards.py
HAZARDS.md and SAFETY.md. Given the outcome of each test in a run, :func:`requirement_outcomes`
and :func:`hazard_outcomes` judge each requirement and hazard by its worst test;
occ_testkit/evidence.py writes that up as the release report.
"""

from __future__ import annotations

import ast
import re
import sys
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAFETY = ROOT / "docs" / "SAFETY.md"
HAZARDS = ROOT / "docs" / "HAZARDS.md"

ID = re.compile(r"\bSR-[A-Z]+-\d+\b")
ROW = re.compile(r"^\|\s*\*\*(SR-[A-Z]+-\d+)\*\*\s*\|(.*)\|\s*$")
TEST_REF = re.compile(r"`([\w/]+\.py)::(\w+)`")
HAZ_ID = re.compile(r"\bHAZ-\d+\b")
HAZ_ROW = re.compile(r"^\|\s*\*\*(HAZ-\d+)\*\*\s*\|(.*)\|\s*$")
#: a piece of code a mitigation names: ``path/to/file.py::Name`` or ``...::Class.method``
CODE_REF = re.compile(r"`([\w/]+\.py)::([\w.]+)`")

#: the columns of a hazard's row after its ID, in order (docs/HAZARDS.md)
HAZ_COLUMNS = (
    "hazard",
    "cause",
    "effect",
    "severity",
    "probability",
    "mitigations",
    "sr",
    "residual",
)
#: the qualitative scales of docs/HAZARDS.md, "How to read the table", least first
SEVERITY = ("negligible", "minor", "serious", "critical", "catastrophic")
PROBABILITY = ("improbable", "remote", "occasional", "probable", "frequent")

#: ``{ID: (pending, {tests listed})}``: a requirement's row of docs/SAFETY.md
Requirements = dict[str, tuple[bool, set[str]]]


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
                raise ValueError(f"req marker with a non-literal argument: {ast.unparse(node)}")
            ids.append(arg.value)
        return ids
    return None


def _module_ids(tree: ast.Module) -> set[str]:
    ids: set[str] = set()
    for stmt in tree.body:
        if isinstance(stmt, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "pytestmark" for t in stmt.targets
        ):
            values = (
                stmt.value.elts if isinstance(stmt.value, ast.List | ast.Tuple) else [stmt.value]
            )
            for value in values:
                ids.update(_req_ids(value) or [])
    return ids


def scan_tests(tests: Path, root: Path = ROOT) -> dict[str, set[str]]:
    """``{"tests/occ/test_x.py::test_y": {IDs}}`` for every test function under ``tests``,
    with the IDs of its req markers (an empty set for a test that carries none)."""
    found: dict[str, set[str]] = {}
    for path in sorted(tests.rglob("test_*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        rel = path.relative_to(root).as_posix()
        module_ids = _module_ids(tree)
        for stmt in ast.walk(tree):
            if isinstance(stmt, ast.FunctionDef | ast.AsyncFunctionDef) and stmt.name.startswith(
                "test_"
            ):
                ids = set(module_ids)
                for deco in stmt.decorator_list:
                    ids.update(_req_ids(deco) or [])
                found[f"{rel}::{stmt.name}"] = ids
    return found


def marked_tests(tests: Path | None = None, root: Path = ROOT) -> dict[str, set[str]]:
    """``{"tests/occ/test_x.py::test_y": {IDs}}`` for every test function carrying a req marker."""
    found = scan_tests(root / "tests" if tests is None else tests, root)
    return {name: ids for name, ids in found.items() if ids}


def _rows(text: str, pattern: re.Pattern[str], doc: str) -> Iterator[tuple[str, str]]:
    """(ID, the rest of the row) of each table row of ``doc`` that ``pattern`` matches; an ID
    listed twice is a ValueError naming it."""
    seen: set[str] = set()
    for line in text.splitlines():
        m = pattern.match(line)
        if m is None:
            continue
        rid, rest = m.groups()
        if rid in seen:
            raise ValueError(f"{doc}: {rid} is listed twice")
        seen.add(rid)
        yield rid, rest


def requirements(text: str | None = None) -> Requirements:
    """``{ID: (pending, {tests listed})}`` from the rows of docs/SAFETY.md."""
    text = SAFETY.read_text(encoding="utf-8") if text is None else text
    out: Requirements = {}
    for rid, rest in _rows(text, ROW, "docs/SAFETY.md"):
        cells = rest.split("|")
        tests = {f"{f}::{t}" for f, t in TEST_REF.findall(cells[-1])}
        out[rid] = ("pending" in cells[-1].lower(), tests)
    return out


def trace_problems(reqs: Requirements, marked: dict[str, set[str]]) -> list[str]:
    """Everything that keeps SAFETY.md and the test markers from agreeing, one line each."""
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


@dataclass(frozen=True)
class Hazard:
    """One row of docs/HAZARDS.md."""

    hid: str
    title: str
    cause: str
    effect: str
    severity: str
    probability: str
    #: one line each, ``<br>`` apart in the table
    mitigations: tuple[str, ...]
    sr_ids: tuple[str, ...]
    residual: str
    #: ``(file, name)`` for each piece of code the mitigations name
    code: tuple[tuple[str, str], ...] = field(default=())


def hazards(text: str | None = None) -> dict[str, Hazard]:
    """The rows of docs/HAZARDS.md by ID; a row of the wrong shape is a ValueError naming it."""
    text = HAZARDS.read_text(encoding="utf-8") if text is None else text
    out: dict[str, Hazard] = {}
    for hid, rest in _rows(text, HAZ_ROW, "docs/HAZARDS.md"):
        cells = [c.strip() for c in rest.split("|")]
        if len(cells) != len(HAZ_COLUMNS):
            raise ValueError(
                f"docs/HAZARDS.md: {hid} has {len(cells)} cells after its ID, not "
                f"{len(HAZ_COLUMNS)} ({', '.join(HAZ_COLUMNS)})"
            )
        c = dict(zip(HAZ_COLUMNS, cells, strict=True))
        mitigations = tuple(p.strip() for p in c["mitigations"].split("<br>") if p.strip())
        out[hid] = Hazard(
            hid=hid,
            title=c["hazard"],
            cause=c["cause"],
            effect=c["effect"],
            severity=c["severity"].lower(),
            probability=c["probability"].lower(),
            mitigations=mitigations,
            sr_ids=tuple(ID.findall(c["sr"])),
            residual=c["residual"],
            code=tuple(ref for m in mitigations for ref in CODE_REF.findall(m)),
        )
    return out


def defines(path: Path, name: str) -> bool:
    """Whether the module at ``path`` defines ``name`` (``Name`` at module level: a class, a
    function or an assignment; ``Class.attr``: a method or attribute of that class)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    first, _, rest = name.partition(".")
    for stmt in tree.body:
        if _binds(stmt, first):
            if not rest:
                return True
            if isinstance(stmt, ast.ClassDef):
                return any(_binds(sub, rest) for sub in stmt.body)
    return False


def _binds(stmt: ast.stmt, name: str) -> bool:
    if isinstance(stmt, ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
        return stmt.name == name
    if isinstance(stmt, ast.Assign):
        return any(isinstance(t, ast.Name) and t.id == name for t in stmt.targets)
    if isinstance(stmt, ast.AnnAssign):
        return isinstance(stmt.target, ast.Name) and stmt.target.id == name
    return False


def hazard_tests(hazard: Hazard, reqs: Requirements) -> list[str]:
    """The tests that verify a hazard's mitigations: those SAFETY.md lists for its requirements."""
    return sorted({t for rid in hazard.sr_ids if rid in reqs for t in reqs[rid][1]})


def hazard_problems(
    haz: dict[str, Hazard],
    reqs: Requirements,
    tests: dict[str, set[str]],
    root: Path = ROOT,
) -> list[str]:
    """Everything that keeps HAZARDS.md from tracing each hazard to tested mitigations, one line
    each. ``tests`` is :func:`scan_tests` (every test function, marked or not)."""
    problems = []
    for h in haz.values():
        problems += _row_problems(h)
        for rid in h.sr_ids:
            if rid not in reqs:
                problems.append(f"{h.hid} cites {rid}, which docs/SAFETY.md does not list")
                continue
            pending, listed = reqs[rid]
            if not listed:
                why = " (pending)" if pending else ""
                problems.append(
                    f"{h.hid} cites {rid}, whose row in docs/SAFETY.md lists no test{why}"
                )
            for test in sorted(listed):
                if test not in tests:
                    problems.append(f"{h.hid}: {rid} lists {test}, which does not exist")
                elif rid not in tests[test]:
                    problems.append(f"{h.hid}: {rid} lists {test}, which does not carry its marker")
        for file, name in h.code:
            path = root / file
            if not path.is_file():
                problems.append(f"{h.hid} names {file}::{name}: no file {file}")
            elif not defines(path, name):
                problems.append(f"{h.hid} names {file}::{name}: {file} defines no {name}")
    cited = {rid for h in haz.values() for rid in h.sr_ids}
    for rid in sorted(set(reqs) - cited):
        problems.append(f"{rid} mitigates no hazard: cite it in a row of docs/HAZARDS.md")
    return problems


def _row_problems(h: Hazard) -> list[str]:
    problems = []
    for column in ("title", "cause", "effect", "residual"):
        if not getattr(h, column):
            problems.append(f"{h.hid}: its {column} is empty")
    if h.severity not in SEVERITY:
        problems.append(f"{h.hid}: severity {h.severity!r} is not one of {', '.join(SEVERITY)}")
    if h.probability not in PROBABILITY:
        problems.append(
            f"{h.hid}: probability {h.probability!r} is not one of {', '.join(PROBABILITY)}"
        )
    if not h.sr_ids:
        problems.append(f"{h.hid} has no SR ID: no requirement implements its mitigations")
    if not h.mitigations:
        problems.append(f"{h.hid} has no mitigation")
    for m in h.mitigations:
        if not CODE_REF.search(m):
            problems.append(f"{h.hid}: the mitigation {m[:60]!r} names no code (`file.py::Name`)")
    return problems


#: worst first: a requirement or a hazard takes the worst outcome of its tests
ORDER = ("failed", "not run", "skipped", "passed")


def worst(statuses: Iterable[str]) -> str:
    found = set(statuses)
    return next((s for s in ORDER if s in found), "passed")


def requirement_outcomes(
    reqs: Requirements, outcomes: Mapping[str, str]
) -> dict[str, tuple[str, list[str]]]:
    """``{ID: (status, [its tests that did not pass])}``; a requirement with no test is
    ``pending`` or ``no test``."""
    out: dict[str, tuple[str, list[str]]] = {}
    for rid, (pending, tests) in reqs.items():
        if not tests:
            out[rid] = ("pending" if pending else "no test", [])
            continue
        statuses = {t: outcomes.get(t, "not run") for t in sorted(tests)}
        out[rid] = (worst(statuses.values()), [t for t, s in statuses.items() if s != "passed"])
    return out


def hazard_outcomes(
    haz: Mapping[str, Hazard], reqs: Requirements, outcomes: Mapping[str, str]
) -> dict[str, tuple[str, list[str]]]:
    """``{HAZ-N: (status, [its tests that did not pass])}`` from the outcome of each test
    (``passed``, ``failed``, ``skipped``; a test absent from ``outcomes`` did not run); a hazard
    whose requirements list no test is ``no test``."""
    out: dict[str, tuple[str, list[str]]] = {}
    for hid, h in haz.items():
        tests = hazard_tests(h, reqs)
        if not tests:
            out[hid] = ("no test", [])
            continue
        statuses = {t: outcomes.get(t, "not run") for t in tests}
        out[hid] = (worst(statuses.values()), [t for t, s in statuses.items() if s != "passed"])
    return out


def _main(argv: list[str]) -> int:
    if argv not in (["hazards"], ["check"]):
        print(__doc__.split("\n\n")[1], file=sys.stderr)
        return 2
    reqs, haz = requirements(), hazards()
    if argv == ["hazards"]:
        for h in haz.values():
            print(f"{h.hid} {h.title} [{', '.join(h.sr_ids)}]")
            for test in hazard_tests(h, reqs):
                print(f"    {test}")
        return 0
    problems = trace_problems(reqs, marked_tests()) + hazard_problems(
        haz, reqs, scan_tests(ROOT / "tests")
    )
    for p in problems:
        print(p)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
