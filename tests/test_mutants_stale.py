"""scripts/mutants_stale.py judges a mutation score by the code it was made from: a reworded
docstring, a changed import or a move to another file keeps a score; a changed line of code,
a changed constant beside the functions or a new function makes its module stale and is named.
Checked on the units of sources (no repository) and on a small git repository of its own."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def load(root: Path | None = None):  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location(
        "mutants_stale", ROOT / "scripts" / "mutants_stale.py"
    )
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["mutants_stale"] = mod
    spec.loader.exec_module(mod)
    if root is not None:
        mod.ROOT = root
    return mod


BASE = '''"""A module."""
from __future__ import annotations

import math

LIMIT = 3


class Judge:
    """Judges."""

    bound = 2

    def check(self, x: float) -> bool:
        """True when in bounds."""
        return abs(x) <= self.bound * LIMIT


def scale(x: float) -> float:
    return math.sqrt(x) * 2
'''


def test_units_ignore_docstrings_imports_and_a_type_checking_block() -> None:
    m = load()
    reworded = BASE.replace('"""True when in bounds."""', '"""Whether it is in bounds."""')
    reworded = reworded.replace(
        "import math", "import math\nimport os\nif TYPE_CHECKING:\n    import x"
    )
    assert m.units(reworded) == m.units(BASE)


@pytest.mark.parametrize(
    ("edit", "changed"),
    [
        (("<= self.bound", "< self.bound"), {"Judge.check"}),
        (("LIMIT = 3", "LIMIT = 4"), {"<module>"}),
        (("bound = 2", "bound = 1"), {"Judge"}),
        (("class Judge:", "class Judge(object):"), {"Judge"}),
        (("* 2\n", "* 3\n"), {"scale"}),
        (("return math.sqrt", "y = 1\n    return math.sqrt"), {"scale"}),
    ],
)
def test_a_changed_line_of_code_changes_its_unit_alone(
    edit: tuple[str, str], changed: set[str]
) -> None:
    m = load()
    old, new = m.units(BASE), m.units(BASE.replace(*edit))
    assert {name for name, code in new - old} == changed


def git(cwd: Path, *args: str, when: str = "") -> None:
    env = {"GIT_AUTHOR_DATE": when, "GIT_COMMITTER_DATE": when} if when else {}
    subprocess.run(
        ["git", "-c", "user.name=t", "-c", "user.email=t@t", *args],
        cwd=cwd, check=True, capture_output=True,
        env={**__import__("os").environ, **env},
    )  # fmt: skip


def repo(tmp_path: Path, after: dict[str, str]) -> Path:
    """A repository: occ/judge.py scored at 10:00 (a row of 10:05), then ``after`` (path:
    source, "" to remove) committed at 11:00."""
    root = tmp_path / "r"
    (root / "occ").mkdir(parents=True)
    (root / "scripts").mkdir()
    (root / "docs").mkdir()
    (root / "occ" / "judge.py").write_text(BASE)
    git(root, "init", "-q")
    git(root, "add", ".")
    git(root, "commit", "-qm", "one", when="2026-01-01T10:00:00+00:00")
    for path, text in after.items():
        p = root / path
        if text:
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text(text)
        else:
            p.unlink()
    git(root, "add", "-A")
    git(root, "commit", "-qm", "two", when="2026-01-01T11:00:00+00:00")
    target = next(p for p in after if after[p]) if any(after.values()) else "occ/judge.py"
    (root / "scripts" / "mutate").write_text(
        f'MODULES[judge]="{target}|tests/x.py"\n[ "$1" = --scope ] && echo ""\n'
    )
    (root / "docs" / "VERIFICATION.md").write_text(
        "## Scores\n\n| module | date | t |\n|---|---|---|\n"
        "| `occ/judge.py` | 2026-01-01 10:05 | x | 1 |\n\n## Next\n"
    )
    return root


def test_a_move_with_its_docstrings_reworded_keeps_the_score(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    moved = BASE.replace('"""Judges."""', '"""Judges, in a room now."""')
    m = load(repo(tmp_path, {"occ/judge.py": "", "occ/core/judge.py": moved}))
    assert m.main([]) == 0
    assert capsys.readouterr().out.startswith("ok    judge")


def test_a_changed_comparison_after_the_row_is_named(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    m = load(repo(tmp_path, {"occ/judge.py": BASE.replace("<= self.bound", "< self.bound")}))
    assert m.main(["-v"]) == 1
    out = capsys.readouterr().out
    assert out.startswith("STALE judge") and "Judge.check" in out and "scale" not in out


def test_a_file_with_no_row_under_any_name_is_stale(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    root = repo(tmp_path, {"occ/other.py": BASE})
    (root / "docs" / "VERIFICATION.md").write_text("## Scores\n\n| module | date |\n\n## Next\n")
    m = load(root)
    assert m.main([]) == 1
    assert "no row" in capsys.readouterr().out


def test_a_scoped_module_is_judged_by_the_units_its_scope_mutates() -> None:
    """scripts/mutate's scope of cia402sim, read back as unit names: its emulated node's
    methods are in it, the process's main and a class body of one of its classes count, a
    function it does not name does not."""
    m = load()
    scope = m.scope("cia402sim")
    names = scope["occ/drivers/cia402_sim.py"]
    assert "EmulatedNode._controlword" in names and "DriveEmulator.inject_emcy" in names
    assert m.in_scope("EmulatedNode.sync", names) and m.in_scope("EmulatedNode", names)
    assert m.in_scope("<module>", names)
    assert not m.in_scope("main", names) and not m.in_scope("EmulatedNode.sdo_server", names)
    assert m.scope("safety") is None  # whole
    assert m.scope("cia402")["occ/drivers/cia402_protocol.py"] == ["*"]
    assert m.in_scope("x_anything", ["*"])


def test_a_row_of_another_module_that_names_a_shared_file_does_not_count(  # type: ignore[no-untyped-def]
    tmp_path: Path, capsys
) -> None:
    """Two modules share occ/judge.py; the only row after the change is about the other one
    (its first file is occ/other.py) and names occ/judge.py later: judge stays stale."""
    changed = BASE.replace("<= self.bound", "< self.bound")
    root = repo(tmp_path, {"occ/judge.py": changed})
    (root / "scripts" / "mutate").write_text(
        'MODULES[judge]="occ/judge.py|tests/x.py"\n'
        'MODULES[other]="occ/other.py occ/judge.py|tests/y.py"\n'
        '[ "$1" = --scope ] && echo ""\n'
    )
    (root / "occ" / "other.py").write_text("X = 1\n")
    (root / "docs" / "VERIFICATION.md").write_text(
        "## Scores\n\n| module | date | t |\n|---|---|---|\n"
        "| `occ/judge.py` | 2026-01-01 10:05 | x | 1 |\n"
        "| `occ/other.py` (its functions in `occ/judge.py` too) | 2026-01-01 11:30 | x | 1 |\n"
        "\n## Next\n"
    )
    m = load(root)
    assert m.main([]) == 1
    out = capsys.readouterr().out.splitlines()
    judge = next(line for line in out if " judge " in line)
    assert judge.startswith("STALE") and "2026-01-01 10:05" in judge


def test_a_module_split_into_a_package_of_its_name_keeps_its_rows(  # type: ignore[no-untyped-def]
    tmp_path: Path, capsys
) -> None:
    """occ/judge.py becomes the package occ/judge/ (a split git does not follow as a rename):
    the module's row still counts for the package's files, judged unit by unit (scale.py, too
    small a part of the old file for git to follow, has no row under any name of its own)."""
    head, tail = BASE.split("\n\ndef scale", 1)
    split = {
        "occ/judge.py": "",
        "occ/judge/__init__.py": '"""The judge, a package now."""\n',
        "occ/judge/check.py": head + "\n",
        "occ/judge/scale.py": "import math\n\n\ndef scale" + tail,
    }
    root = repo(tmp_path, split)
    (root / "scripts" / "mutate").write_text(
        'MODULES[judge]="occ/judge/scale.py|tests/x.py"\n[ "$1" = --scope ] && echo ""\n'
    )
    doc = root / "docs" / "VERIFICATION.md"  # the package's other files are in no module
    doc.write_text(
        doc.read_text()
        + REGISTER
        + "| `occ/judge/__init__.py`, `occ/judge/check.py` | a | b | c |\n"
    )
    m = load(root)
    assert m.main([]) == 0, capsys.readouterr().out
    # and a changed line in one of them is named
    (root / "occ" / "judge" / "scale.py").write_text(split["occ/judge/scale.py"].replace("2", "3"))
    assert m.main(["-v"]) == 1
    assert "occ/judge/scale.py changed since 2026-01-01 10:05: scale" in capsys.readouterr().out


REGISTER = (
    "\n## The files no module mutates, and how each is verified\n\n"
    "| File | What | Verified by | Why |\n|---|---|---|---|\n"
)


def test_every_code_file_is_mutated_or_in_the_register_never_both(tmp_path: Path) -> None:
    """A file in no module and not in the register is named, as is one in both, one the
    register names that is gone, and a row with an empty cell; one in either is not."""
    root = repo(tmp_path, {"occ/judge.py": BASE, "occ/extra.py": BASE, "occ/both.py": BASE})
    (root / "scripts" / "mutate").write_text(
        'MODULES[judge]="occ/judge.py occ/both.py|tests/x.py"\n[ "$1" = --scope ] && echo ""\n'
    )
    doc = root / "docs" / "VERIFICATION.md"
    doc.write_text(doc.read_text() + REGISTER + "| `occ/both.py` | a | b | c |\n"
                   "| `occ/gone.py`, `occ/empty.py` | a |  | c |\n")  # fmt: skip
    m = load(root)
    assert m.register_problems() == [
        "occ/extra.py: in no module of scripts/mutate and not in the register",
        "occ/both.py: in the register and in a module",
        "occ/empty.py: in the register, not in the code",
        "occ/gone.py: in the register, not in the code",
        "occ/empty.py: a row with an empty cell",
        "occ/gone.py: a row with an empty cell",
    ]
    doc.write_text(doc.read_text().split("| `occ/both.py`")[0] + "| `occ/extra.py` | a | b | c |\n")
    assert m.register_problems() == []


def test_the_projects_register_names_every_file_no_module_mutates() -> None:
    problems = load().register_problems()
    assert problems == [], "\n".join(problems)
