"""The release evidence: every safety requirement and every hazard tied to the tests that ran,
their outcome, the commit, the Python and the versions of the third-party software (SOUP).

    scripts/release_evidence --junit JUNIT.xml [--junit MORE.xml] [--out DIR] [--ci]

It runs no test: it reads the JUnit XML of a run that already happened (``scripts/test``
writes one when ``OCC_JUNIT=path`` is set; ``.ci/run`` does so and then runs this), so CI runs
each test once. It writes ``DIR/report.json`` and ``DIR/report.md`` (DIR defaults to
``.ci/artifacts/release-evidence``) and exits 0 when the release is verified, 1 when it is not
(the problems in the report and on stderr), 2 when its input cannot be read.

The tests of a requirement are those its row of docs/SAFETY.md lists; the tests of a hazard are
those of the requirements docs/HAZARDS.md cites for it (occ_testkit/trace.py). A test is
*passed* when every case of it in the run passed (a parametrised test has several; some of them
skipped is still passed, and the count says so), *failed* when one failed or errored (or its
file did not collect), *skipped* when every case skipped, *not run* when the run has no case of
it. The release is not verified when:

- a test of a requirement failed or did not run;
- with ``--ci``, a test of a requirement was skipped: in CI every test must run
  (``OCC_REQUIRE_INTEROP=1`` already turns a missing peer into a failure, so a skip left there is
  a requirement that was not verified), and the commit must be known;
- the documents do not agree (the checks of tests/test_safety_trace.py and tests/test_hazards.py);
- a locked third-party package is installed at another version than constraints.txt pins.

Without ``--ci`` skipped tests are reported and the release stands or falls on the rest.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from occ_testkit import soup, trace

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = Path(".ci") / "artifacts" / "release-evidence"


class EvidenceError(ValueError):
    """Input the report cannot be made from: the message says which and why."""


@dataclass
class TestResult:
    """What a run says of one test function (all its cases: parameters, classes)."""

    status: str = "not run"
    cases: int = 0
    failed: int = 0
    skipped: int = 0
    time_s: float = 0.0
    message: str = ""


@dataclass
class Run:
    """The cases of one or more JUnit XML files."""

    files: list[str] = field(default_factory=list)
    #: ``(module, function)``: one ``(status, time, message)`` per case
    cases: dict[tuple[str, str], list[tuple[str, float, str]]] = field(default_factory=dict)
    #: modules (dotted) whose collection failed
    broken: dict[str, str] = field(default_factory=dict)
    totals: dict[str, float] = field(default_factory=dict)
    slowest: list[tuple[float, str]] = field(default_factory=list)


def _case_status(case: ET.Element) -> tuple[str, str]:
    for tag in ("failure", "error"):
        el = case.find(tag)
        if el is not None:
            return "failed", (el.get("message") or tag)[:300]
    el = case.find("skipped")
    if el is not None:
        return "skipped", (el.get("message") or "skipped")[:300]
    return "passed", ""


def read_junit(paths: Sequence[Path]) -> Run:
    """The cases of pytest's JUnit XML files; a file that is missing or not JUnit XML is an
    EvidenceError naming it."""
    run = Run()
    counts = {"passed": 0, "failed": 0, "skipped": 0}
    all_cases: list[tuple[float, str]] = []
    for path in paths:
        try:
            tree = ET.parse(path)
        except (OSError, ET.ParseError) as err:
            raise EvidenceError(f"{path}: not a JUnit XML file ({err})") from err
        root = tree.getroot()
        if root.tag not in ("testsuites", "testsuite"):
            raise EvidenceError(f"{path}: not a JUnit XML file (its root is <{root.tag}>)")
        run.files.append(str(path))
        for case in root.iter("testcase"):
            classname, name = case.get("classname", ""), case.get("name", "")
            status, message = _case_status(case)
            time_s = float(case.get("time") or 0.0)
            if not classname:  # a file that did not collect: pytest names the module
                run.broken[name] = message
                counts["failed"] += 1
                continue
            counts[status] += 1
            all_cases.append((time_s, f"{classname}::{name}"))
            base = name.split("[", 1)[0]
            for module in {classname, classname.rsplit(".", 1)[0]}:
                run.cases.setdefault((module, base), []).append((status, time_s, message))
    run.totals = {
        "cases": float(sum(counts.values())),
        **{k: float(v) for k, v in counts.items()},
        "time_s": round(sum(t for t, _ in all_cases), 3),
    }
    run.slowest = sorted(all_cases, reverse=True)[:25]
    return run


def result_of(test: str, run: Run) -> TestResult:
    """What ``run`` says of the test ``tests/x/test_y.py::test_z``."""
    file, _, func = test.partition("::")
    module = file.removesuffix(".py").replace("/", ".")
    cases = run.cases.get((module, func), [])
    if not cases:
        if module in run.broken:
            return TestResult("failed", message=f"its file did not collect: {run.broken[module]}")
        return TestResult()
    failed = [c for c in cases if c[0] == "failed"]
    skipped = [c for c in cases if c[0] == "skipped"]
    if failed:
        status, message = "failed", failed[0][2]
    elif len(skipped) == len(cases):
        status, message = "skipped", skipped[0][2]
    else:
        status, message = "passed", ""
    return TestResult(
        status=status,
        cases=len(cases),
        failed=len(failed),
        skipped=len(skipped),
        time_s=round(sum(c[1] for c in cases), 3),
        message=message,
    )


def _git(root: Path, *args: str) -> str | None:
    try:
        proc = subprocess.run(
            ["git", *args], cwd=root, capture_output=True, text=True, timeout=30, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return proc.stdout.rstrip("\n") if proc.returncode == 0 else None


def commit_info(root: Path) -> dict[str, Any]:
    """The commit the tree is at and whether it has changes not committed (untracked files
    included; what .gitignore ignores, such as the report itself, not)."""
    sha = _git(root, "rev-parse", "HEAD")
    status = _git(root, "status", "--porcelain")
    changed = [line[3:] for line in (status or "").splitlines()]
    return {
        "sha": sha,
        "branch": _git(root, "rev-parse", "--abbrev-ref", "HEAD"),
        "dirty": bool(changed) if status is not None else None,
        "changed": changed[:50],
    }


def soup_versions(root: Path) -> tuple[list[dict[str, Any]], list[str]]:
    """Each locked package with its pinned and installed version and its place, and the
    problems (a locked package installed at another version). No lock: nothing, said once."""
    path = root / "constraints.txt"
    if not path.is_file():
        return [], ["no constraints.txt: the third-party versions are not recorded"]
    lock = soup.read_lock(path.read_text(encoding="utf-8"))
    place: dict[str, str] = {}
    pyproject = root / "pyproject.toml"
    if pyproject.is_file():
        place = soup.groups(lock, soup.project_requirements(pyproject.read_text("utf-8")))
    have = soup.installed_versions(e.name for e in lock.values())
    rows = [
        {
            "name": e.name,
            "locked": e.version,
            "installed": have[e.name],
            "licence": e.licence,
            "place": place.get(key, ""),
        }
        for key, e in sorted(lock.items())
    ]
    return rows, soup.installed_problems(lock)


def build_report(junit: Sequence[Path], root: Path = ROOT, *, ci: bool = False) -> dict[str, Any]:
    """The report (JSON-ready) of the run in ``junit`` against the documents under ``root``."""
    run = read_junit(junit)
    try:
        reqs = trace.requirements((root / "docs" / "SAFETY.md").read_text(encoding="utf-8"))
        haz = trace.hazards((root / "docs" / "HAZARDS.md").read_text(encoding="utf-8"))
        scanned = trace.scan_tests(root / "tests", root)
    except (OSError, ValueError, SyntaxError) as err:
        raise EvidenceError(f"the documents under {root} cannot be read: {err}") from err
    problems = trace.trace_problems(reqs, {t: ids for t, ids in scanned.items() if ids})
    problems += trace.hazard_problems(haz, reqs, scanned, root)
    traced = sorted({t for _, tests in reqs.values() for t in tests})
    results = {t: result_of(t, run) for t in traced}
    outcomes = {t: r.status for t, r in results.items()}
    req_out = trace.requirement_outcomes(reqs, outcomes)
    haz_out = trace.hazard_outcomes(haz, reqs, outcomes)
    fails = {"failed", "not run"} | ({"skipped"} if ci else set())
    for t, r in results.items():
        if r.status in fails:
            why = f": {r.message}" if r.message else ""
            problems.append(f"{t} {r.status}{why}")
    commit = commit_info(root)
    if ci and not commit["sha"]:
        problems.append("the commit is not known (not a git checkout?)")
    soup_rows, soup_problems = soup_versions(root)
    problems += soup_problems
    return {
        "generated": datetime.now(UTC).isoformat(timespec="seconds"),
        "verdict": "fail" if problems else "pass",
        "policy": {"ci": ci, "fails": sorted(fails)},
        "commit": commit,
        "python": {
            "version": platform.python_version(),
            "implementation": platform.python_implementation(),
            "executable": sys.executable,
            "platform": platform.platform(),
        },
        "run": {
            "files": run.files,
            "totals": run.totals,
            "slowest": [{"case": c, "time_s": t} for t, c in run.slowest],
        },
        "problems": problems,
        "requirements": {
            rid: {
                "status": s,
                "pending": reqs[rid][0],
                "tests": sorted(reqs[rid][1]),
                "not_passed": n,
            }
            for rid, (s, n) in req_out.items()
        },
        "hazards": {
            hid: {
                "title": haz[hid].title,
                "severity": haz[hid].severity,
                "probability": haz[hid].probability,
                "requirements": list(haz[hid].sr_ids),
                "tests": len(trace.hazard_tests(haz[hid], reqs)),
                "status": s,
                "not_passed": n,
            }
            for hid, (s, n) in haz_out.items()
        },
        "tests": {t: asdict(r) for t, r in results.items()},
        "soup": soup_rows,
    }


def _count(report: Mapping[str, Any], tests: Iterable[str]) -> str:
    tests = list(tests)
    passed = sum(report["tests"][t]["status"] == "passed" for t in tests)
    return f"{passed} / {len(tests)}"


def render_md(report: Mapping[str, Any]) -> str:
    """The report for a reader (report.md)."""
    c, py, run = report["commit"], report["python"], report["run"]
    dirty = {True: "yes", False: "no", None: "unknown"}[c["dirty"]]
    totals = run["totals"]
    out = [
        "# Release evidence",
        "",
        f"**Verdict: {report['verdict'].upper()}** ({len(report['problems'])} problems). "
        f"Generated {report['generated']} by `scripts/release_evidence` (occ_testkit/evidence.py).",
        "",
        f"- Commit: `{c['sha'] or 'unknown'}` on `{c['branch'] or 'unknown'}`, changes not "
        f"committed: {dirty}" + (f" ({', '.join(c['changed'][:10])})" if c["changed"] else ""),
        f"- Python: {py['implementation']} {py['version']} ({py['platform']})",
        f"- Run: {', '.join(run['files'])}: {totals['cases']:.0f} cases, {totals['passed']:.0f} "
        f"passed, {totals['failed']:.0f} failed, {totals['skipped']:.0f} skipped, "
        f"{totals['time_s']:.0f} s in the tests",
        f"- Policy: a traced test that is {', '.join(report['policy']['fails'])} fails the release"
        + (" (CI)" if report["policy"]["ci"] else ""),
        "",
    ]
    if report["problems"]:
        out += ["## Problems", ""] + [f"- {p}" for p in report["problems"]] + [""]
    out += ["## Hazards", "", "| ID | Hazard | Severity | Status | Requirements | Tests passed |"]
    out.append("|---|---|---|---|---|---|")
    for hid, h in report["hazards"].items():
        out.append(
            f"| {hid} | {h['title']} | {h['severity']} | {h['status']} | "
            f"{', '.join(h['requirements'])} | {h['tests'] - len(h['not_passed'])} / {h['tests']} |"
        )
    out += [
        "",
        "## Requirements",
        "",
        "| ID | Status | Tests passed | Not passed |",
        "|---|---|---|---|",
    ]
    for rid, r in report["requirements"].items():
        not_passed = "<br>".join(f"`{t}` ({report['tests'][t]['status']})" for t in r["not_passed"])
        out.append(f"| {rid} | {r['status']} | {_count(report, r['tests'])} | {not_passed} |")
    out += ["", "## Third-party software (constraints.txt)", ""]
    runtime = [s for s in report["soup"] if s["place"] != "tools"]
    off = [s for s in report["soup"] if s["installed"] not in (s["locked"], None)]
    out.append(
        f"{len(report['soup'])} locked, {len(off)} installed at another version; the runtime "
        f"ones ({len(runtime)}):"
    )
    out += ["", "| Package | Locked | Installed | Place | Licence |", "|---|---|---|---|---|"]
    for s in runtime:
        out.append(
            f"| {s['name']} | {s['locked']} | {s['installed'] or 'not installed'} | "
            f"{s['place']} | {s['licence']} |"
        )
    out += ["", "## The slowest test cases of the run", "", "| Case | s |", "|---|---|"]
    out += [f"| `{s['case']}` | {s['time_s']:.1f} |" for s in run["slowest"]]
    return "\n".join(out) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="release_evidence",
        description="Tie each safety requirement and hazard to the outcome of its tests in a "
        "JUnit XML run, with the commit, the Python and the third-party versions.",
    )
    parser.add_argument(
        "--junit", action="append", type=Path, required=True, metavar="XML",
        help="pytest's JUnit XML (scripts/test writes one with OCC_JUNIT=path)",
    )  # fmt: skip
    parser.add_argument(
        "--out", type=Path, default=None, metavar="DIR",
        help=f"where report.json and report.md go (default {DEFAULT_OUT})",
    )  # fmt: skip
    parser.add_argument(
        "--ci", action="store_true",
        help="a skipped traced test and an unknown commit fail the release",
    )  # fmt: skip
    parser.add_argument("--root", type=Path, default=ROOT, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    out = args.out if args.out is not None else args.root / DEFAULT_OUT
    try:
        report = build_report(args.junit, args.root, ci=args.ci)
    except (EvidenceError, soup.SoupError) as err:
        print(f"release_evidence: {err}", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
    (out / "report.md").write_text(render_md(report), encoding="utf-8")
    hazards = report["hazards"].values()
    print(
        f"release evidence: {report['verdict'].upper()}: "
        f"{sum(h['status'] == 'passed' for h in hazards)} of {len(hazards)} hazards and "
        f"{sum(r['status'] == 'passed' for r in report['requirements'].values())} of "
        f"{len(report['requirements'])} requirements with every test passed; {out / 'report.md'}"
    )
    for p in report["problems"]:
        print(f"  {p}", file=sys.stderr)
    return 1 if report["problems"] else 0


if __name__ == "__main__":
    sys.exit(main())
