"""The release report (occ_testkit/evidence.py, scripts/release_evidence) from a handmade JUnit
XML against a small set of documents: a requirement whose tests passed, one with a failed test,
one whose test did not run, one whose test skipped, and the hazards they mitigate; the exit
code, the JSON and the Markdown say which, and CI's policy (``--ci``) fails a skip too."""

from __future__ import annotations

import importlib.metadata as md
import json
import re
import subprocess
from pathlib import Path

import pytest

from occ_testkit import evidence

ROOT = Path(__file__).resolve().parents[1]

SAFETY = """\
| ID | Requirement | Source | Verified by |
|---|---|---|---|
| **SR-A-1** | a | x | `tests/test_a.py::test_x`<br>`tests/test_a.py::test_p` |
| **SR-B-1** | b | x | `tests/test_a.py::test_y` |
| **SR-C-1** | c | x | `tests/test_a.py::test_z` |
| **SR-D-1** | d | x | `tests/test_a.py::test_s` |
"""

HAZARDS = """\
| ID | Hazard | Cause | Effect | Severity | Probability | Mitigations | SR IDs | Residual |
|---|---|---|---|---|---|---|---|---|
| **HAZ-1** | One | c | e | critical | remote | it (`pkg/mod.py::f`) | SR-A-1 | r |
| **HAZ-2** | Two | c | e | serious | remote | it (`pkg/mod.py::f`) | SR-B-1, SR-C-1 | r |
| **HAZ-3** | Three | c | e | minor | remote | it (`pkg/mod.py::f`) | SR-D-1 | r |
"""

TESTS = """\
import pytest
pytestmark = pytest.mark.slow
@pytest.mark.req("SR-A-1")
def test_x():
    pass
@pytest.mark.req("SR-A-1")
@pytest.mark.parametrize("n", [1, 2])
def test_p(n):
    pass
@pytest.mark.req("SR-B-1")
def test_y():
    pass
@pytest.mark.req("SR-C-1")
def test_z():
    pass
@pytest.mark.req("SR-D-1")
def test_s():
    pass
"""


def _case(name: str, inner: str = "", cls: str = "tests.test_a", time: str = "0.5") -> str:
    return f'<testcase classname="{cls}" name="{name}" time="{time}">{inner}</testcase>'


RED = (
    '<?xml version="1.0" encoding="utf-8"?><testsuites><testsuite name="pytest" tests="7">'
    + _case("test_x", time="1.25")
    + _case("test_p[1]")
    + _case("test_p[2]", '<skipped type="pytest.skip" message="no peer here"/>')
    + _case("test_y", '<failure message="assert 1 == 2">trace</failure>')
    + _case("test_s", '<skipped type="pytest.skip" message="no namespace"/>')
    + _case("test_other", cls="tests.test_b", time="3.0")
    + "</testsuite></testsuites>"
)


@pytest.fixture()
def tree(tmp_path: Path) -> Path:
    root = tmp_path / "repo"
    for d in ("docs", "tests", "pkg"):
        (root / d).mkdir(parents=True)
    (root / "docs" / "SAFETY.md").write_text(SAFETY)
    (root / "docs" / "HAZARDS.md").write_text(HAZARDS)
    (root / "tests" / "test_a.py").write_text(TESTS)
    (root / "pkg" / "mod.py").write_text("def f():\n    pass\n")
    (root / "pyproject.toml").write_text(
        '[project]\nname = "occ-igtl"\ndependencies = ["pytest"]\n'
    )
    pytest_version = md.version("pytest")
    (root / "constraints.txt").write_text(
        f"pytest=={pytest_version}\n    # licence: MIT\n    # via: occ-igtl\n"
        "surely-not-installed-here==1.0\n    # licence: MIT\n    # via: pytest\n"
    )
    return root


def _run(tree: Path, xml: str, *args: str) -> tuple[int, dict, str]:  # type: ignore[type-arg]
    (tree / "junit.xml").write_text(xml)
    out = tree / "out"
    code = evidence.main(["--root", str(tree), "--junit", str(tree / "junit.xml"),
                          "--out", str(out), *args])  # fmt: skip
    report = json.loads((out / "report.json").read_text()) if code != 2 else {}
    md_text = (out / "report.md").read_text() if code != 2 else ""
    return code, report, md_text


def test_a_failed_a_missing_and_a_skipped_test_each_say_so(tree: Path) -> None:
    code, report, text = _run(tree, RED)
    assert code == 1 and report["verdict"] == "fail"
    status = {rid: r["status"] for rid, r in report["requirements"].items()}
    assert status == {
        "SR-A-1": "passed",
        "SR-B-1": "failed",
        "SR-C-1": "not run",
        "SR-D-1": "skipped",
    }
    assert {h: r["status"] for h, r in report["hazards"].items()} == {
        "HAZ-1": "passed", "HAZ-2": "failed", "HAZ-3": "skipped",
    }  # fmt: skip
    assert report["hazards"]["HAZ-2"]["not_passed"] == [
        "tests/test_a.py::test_y",
        "tests/test_a.py::test_z",
    ]
    # a parametrised test with one case skipped still passed, and says how many cases it had
    assert report["tests"]["tests/test_a.py::test_p"] == {
        "status": "passed", "cases": 2, "failed": 0, "skipped": 1, "time_s": 1.0, "message": "",
    }  # fmt: skip
    # outside CI a skip is reported, not a failure of the release
    assert report["problems"] == [
        "tests/test_a.py::test_y failed: assert 1 == 2",
        "tests/test_a.py::test_z not run",
    ]
    assert report["run"]["totals"] == {
        "cases": 6.0, "passed": 3.0, "failed": 1.0, "skipped": 2.0, "time_s": 6.25,
    }  # fmt: skip
    assert report["run"]["slowest"][0] == {"case": "tests.test_b::test_other", "time_s": 3.0}
    # the third-party versions: pinned and installed agree, one not installed is no problem
    soup = {s["name"]: s for s in report["soup"]}
    assert soup["pytest"]["installed"] == soup["pytest"]["locked"]
    assert soup["surely-not-installed-here"]["installed"] is None
    assert report["commit"]["sha"] is None  # not a git checkout
    assert "**Verdict: FAIL** (2 problems)" in text
    assert "| HAZ-2 | Two | serious | failed | SR-B-1, SR-C-1 | 0 / 2 |" in text
    assert "| SR-C-1 | not run | 0 / 1 | `tests/test_a.py::test_z` (not run) |" in text


def test_in_ci_a_skip_and_an_unknown_commit_fail_too(tree: Path) -> None:
    code, report, _ = _run(tree, RED, "--ci")
    assert code == 1
    assert report["problems"] == [
        "tests/test_a.py::test_s skipped: no namespace",
        "tests/test_a.py::test_y failed: assert 1 == 2",
        "tests/test_a.py::test_z not run",
        "the commit is not known (not a git checkout?)",
    ]


def test_every_test_passed_in_a_clean_checkout_is_a_release(tree: Path) -> None:
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@example.org"]
    subprocess.run([*git, "init", "-q"], cwd=tree, check=True)
    (tree / ".gitignore").write_text("/out/\n/junit.xml\n")
    subprocess.run([*git, "add", "."], cwd=tree, check=True)
    subprocess.run([*git, "commit", "-q", "-m", "x"], cwd=tree, check=True)
    green = re.sub(r"<(skipped|failure)[^>]*(/>|>[^<]*</failure>)", "", RED)
    green = green.replace("</testsuite>", _case("test_z") + "</testsuite>")
    code, report, text = _run(tree, green, "--ci")
    assert (code, report["verdict"], report["problems"]) == (0, "pass", [])
    assert all(h["status"] == "passed" for h in report["hazards"].values())
    assert re.fullmatch(r"[0-9a-f]{40}", report["commit"]["sha"])
    assert report["commit"]["dirty"] is False
    assert "**Verdict: PASS** (0 problems)" in text
    # a file left uncommitted makes the tree dirty, and the report names it
    (tree / "pkg" / "new.py").write_text("")
    _, report, _ = _run(tree, green, "--ci")
    assert report["commit"]["dirty"] is True and report["commit"]["changed"] == ["pkg/new.py"]


def test_a_file_that_did_not_collect_fails_its_tests(tree: Path) -> None:
    broken = (
        "<testsuite>"
        + _case("tests.test_a", '<error message="collection failure">ImportError</error>', cls="")
        + "</testsuite>"
    )
    code, report, _ = _run(tree, broken)
    assert code == 1
    assert report["tests"]["tests/test_a.py::test_x"]["status"] == "failed"
    assert "its file did not collect: collection failure" in report["problems"][0]


def test_input_that_cannot_be_read_is_refused_naming_it(
    tree: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _run(tree, "<html></html>")[0] == 2
    assert "junit.xml: not a JUnit XML file (its root is <html>)" in capsys.readouterr().err
    assert _run(tree, "not xml at all")[0] == 2
    assert "not a JUnit XML file (syntax error" in capsys.readouterr().err
    (tree / "docs" / "HAZARDS.md").write_text("| **HAZ-1** | too | few |\n")
    assert _run(tree, RED)[0] == 2
    assert "HAZ-1 has 2 cells after its ID, not 8" in capsys.readouterr().err


def test_ci_runs_the_tests_once_and_the_report_from_their_junit_xml() -> None:
    # .ci/run: scripts/test writes the JUnit XML the evidence reads, under CI's policy, and the
    # hazards are judged again from the report by tests/test_hazards.py
    run = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert re.search(r'OCC_JUNIT="\$EVIDENCE/junit.xml" bash scripts/test -q', run)
    assert re.search(r'scripts/release_evidence --ci --junit "\$EVIDENCE/junit.xml"', run)
    assert 'OCC_RELEASE_REPORT="$EVIDENCE/report.json"' in run
    assert run.count("scripts/test") == 1
    test = (ROOT / "scripts" / "test").read_text(encoding="utf-8")
    assert '${OCC_JUNIT:+"--junitxml=$OCC_JUNIT"}' in test
