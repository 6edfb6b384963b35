"""The third-party software: pyproject.toml, the lock (constraints.txt), docs/soup.yaml,
docs/SOUP.md and the installed environment agree (occ_testkit/soup.py).

Every requirement of pyproject.toml is pinned in the lock at a version it allows; every package
the project depends on directly has its entry in docs/soup.yaml (a runtime one: what it is
relied on for, the tests of that reliance, which must exist, its anomalies with their sources),
and no entry names a package the lock does not have; docs/SOUP.md is exactly what the lock and
the entries make; a locked package that is installed is installed at its pinned version; the
install scripts install with the lock.
"""

from __future__ import annotations

import email.message
import re
from pathlib import Path

import pytest

from occ_testkit import soup

ROOT = Path(__file__).resolve().parents[1]


def test_the_lock_the_entries_and_the_document_agree() -> None:
    problems = soup.problems(installed=False)
    assert not problems, "\n".join(problems)


def test_what_is_installed_is_the_lock() -> None:
    problems = soup.installed_problems(soup.read_lock())
    assert not problems, "\n".join(problems)


def test_the_install_uses_the_lock() -> None:
    # every `pip install` of the project in the scripts CI runs passes the lock, by its name
    # or by a variable set to it
    for script in ("scripts/_venv.sh", ".ci/run"):
        text = (ROOT / script).read_text(encoding="utf-8")
        lock = [r"\S*constraints\.txt"]
        lock += [rf'"?\${name}"?' for name in re.findall(r"^(\w+)=\S*constraints\.txt", text, re.M)]
        lines = [
            line
            for line in text.splitlines()
            if "pip install" in line and "-e" in line and not line.lstrip().startswith("#")
        ]
        assert lines, f"{script} installs nothing"
        for line in lines:
            assert re.search(rf"-c\s+({'|'.join(lock)})", line), f"{script}: {line.strip()}"


def test_every_runtime_package_is_placed_and_the_core_is_small() -> None:
    reqs = soup.project_requirements()
    lock = soup.read_lock()
    place = soup.groups(lock, reqs)
    core = {k for k, g in place.items() if g == "core"}
    # the core's direct dependencies and what they pull in, and none of the tools
    assert {"numpy", "pin", "coal", "python-can", "pyyaml", "pydantic"} <= core
    assert not core & {"pytest", "mypy", "ruff", "mutmut", "hypothesis"}
    assert place["cyclonedds"] == "extra: ros2" and place["starlette"] == "extra: console"


PYPROJECT = """
[project]
name = "occ-igtl"
dependencies = ["alpha>=1", "beta", "nowhere; python_version < '3'"]
[project.optional-dependencies]
test = ["gamma", "occ-igtl[plot]"]
plot = ["delta>=3"]
native = ["setuptools>=77"]
"""

LOCK = """\
# a header
alpha==1.2
    # licence: MIT
    # via: occ-igtl
beta==0.5
    # licence: BSD-3-Clause
    # via: occ-igtl
delta==2
    # licence: Apache-2.0
    # via: occ-igtl[plot]
gamma==1
    # licence: MIT
    # via: occ-igtl[test]
zeta==3
    # licence: not stated in its metadata
    # via: alpha
"""

DATA = """
intro: Some words.
packages:
  alpha:
    relied_on: Everything.
    tested_by: [tests/test_x.py, SR-A-1]
    anomalies:
      - {what: A bug., source: "https://example.org/1"}
      - {what: Another., source: "elsewhere"}
    checked: Its tracker.
  delta:
    relied_on: Plots.
    tested_by: [tests/test_gone.py]
    anomalies: []
  gamma:
    used_for: testing
  omega:
    used_for: nothing
"""


def test_the_check_names_each_disagreement() -> None:
    reqs = soup.project_requirements(PYPROJECT)
    assert set(reqs) == {"core", "test", "plot"}  # native is not locked; a false marker dropped
    lock = soup.read_lock(LOCK)
    assert soup.groups(lock, reqs) == {
        "alpha": "core", "beta": "core", "zeta": "core", "delta": "extra: plot", "gamma": "tools",
    }  # fmt: skip
    assert soup.lock_problems(lock, reqs) == [
        "constraints.txt pins delta 2, which pyproject.toml's delta>=3 (plot) does not allow"
    ]
    refs = {"tests/test_x.py", "SR-A-1"}
    assert soup.data_problems(lock, soup.read_data(DATA), reqs, refs) == [
        "docs/soup.yaml: omega is not in constraints.txt",
        "docs/soup.yaml: alpha: the source 'elsewhere' is no URL or file here",
        "docs/soup.yaml has no entry for beta (core)",
        "docs/soup.yaml: delta has no `checked`",
        "docs/soup.yaml: delta is tested by 'tests/test_gone.py', which does not exist",
    ]
    missing = soup.read_lock(LOCK.split("delta==2")[0])  # alpha and beta only
    hint = " (install it, run the tests, then scripts/soup --lock)"
    assert soup.lock_problems(missing, reqs) == [
        "gamma (test) is not in constraints.txt" + hint,
        "delta (plot) is not in constraints.txt" + hint,
    ]


def test_the_document_is_checked_against_what_it_is_made_from(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "test_x.py").write_text("def test_a():\n    pass\n")
    (tmp_path / "pyproject.toml").write_text(PYPROJECT.replace("delta>=3", "delta>=2"))
    (tmp_path / "constraints.txt").write_text(LOCK)
    data = DATA.replace("SR-A-1", "tests/test_x.py::test_a").replace('"elsewhere"', '"README.md"')
    data = data.replace("tests/test_gone.py]", "tests/test_x.py]\n    checked: Nothing.")
    data = data.replace("  omega:\n    used_for: nothing\n", "  beta:\n    relied_on: B.\n")
    data += "    tested_by: [tests/test_x.py]\n    anomalies: []\n    checked: B.\n"
    (tmp_path / "README.md").write_text("readme\n")
    (tmp_path / "docs" / "soup.yaml").write_text(data)
    assert soup.problems(tmp_path, installed=False) == [
        "docs/SOUP.md is not what the lock and docs/soup.yaml make: scripts/soup --update"
    ]
    reqs = soup.project_requirements((tmp_path / "pyproject.toml").read_text())
    doc = soup.render(soup.read_lock(LOCK), soup.read_data(data), reqs)
    (tmp_path / "docs" / "SOUP.md").write_text(doc)
    assert soup.problems(tmp_path, installed=False) == []
    # what the document says, from where: a direct package in full, a pulled-in one by its parent
    assert "### alpha 1.2" in doc and "- A bug. (<https://example.org/1>)" in doc
    assert "| zeta | 3 | not stated in its metadata | core | alpha |" in doc
    assert "| gamma | 1 | MIT | testing |" in doc
    (tmp_path / "docs" / "SOUP.md").write_text(doc.replace("1.2", "1.3"))
    assert len(soup.problems(tmp_path, installed=False)) == 1


def test_the_lock_reads_back_what_was_written_and_refuses_what_it_cannot_read() -> None:
    lock = soup.read_lock(LOCK)
    assert lock["zeta"] == soup.Locked("zeta", "3", "not stated in its metadata", ("alpha",))
    assert soup.read_lock(soup.write_lock(lock)) == lock
    with pytest.raises(soup.SoupError, match=r"constraints.txt:3: not a pin .*'beta>=0.5'"):
        soup.read_lock("alpha==1\n    # via: x\nbeta>=0.5\n")
    with pytest.raises(soup.SoupError, match="Alpha is pinned twice"):
        soup.read_lock("alpha==1\nAlpha==2\n")
    with pytest.raises(soup.SoupError, match="a mapping with `intro` and `packages`"):
        soup.read_data("- just a list\n")


def test_a_licence_is_read_from_the_metadata_best_first() -> None:
    def meta(**fields: str | list[str]) -> email.message.Message:
        m = email.message.Message()
        for key, value in fields.items():
            for v in value if isinstance(value, list) else [value]:
                m[key.replace("_", "-")] = v
        return m

    classifier = ["License :: OSI Approved :: MIT License", "Topic :: Other"]
    assert soup.licence_of(meta(License_Expression="BSD-3-Clause", License="MIT")) == "BSD-3-Clause"
    assert soup.licence_of(meta(License="Zlib", Classifier=classifier)) == "Zlib"
    long_text = "Permission is hereby granted, free of charge, to any person obtaining a copy"
    assert soup.licence_of(meta(License=long_text, Classifier=classifier)) == "MIT License"
    assert soup.licence_of(meta(License="UNKNOWN")) == "not stated in its metadata"
