"""Which mutation scores are older than their code: for every module of scripts/mutate, the
newest row of docs/VERIFICATION.md's Scores table that names one of its source files (under its
name now or any name git followed it by), against the code as it was at that row (issue 29:
"re-run after the last change to each module"; issue 42: "the staleness check clean").

    python scripts/mutants_stale.py          # every module, stale ones marked; exit 1 if any
    python scripts/mutants_stale.py -v       # and every changed unit of each stale module

A row's time is the latest HH:MM in its date cell (the end of its last run), on the cell's
date; a run on code committed only after it ended names that commit in its date cell ("code as
committed in abc1234"), and its code is read there. mutmut makes its mutants from the code of
functions and methods, and their verdicts depend on that code and the module-level and class-
level statements around it; it makes none from docstrings, comments or import lines. So a
module is judged by its *units*, each a function, a method (``Class.method``) or another top-
level or class-level statement, compared as Python's AST with docstrings and imports taken out:
a module is fresh when every unit of its files, as they are now, existed word for word (same
qualified name, same code) somewhere in the project at the commit its row was made on; a move
to another file or package (the rooms of issue 39, a module split into a package), a reworded
docstring or a changed import keeps it fresh, any changed line of code makes it stale and is
named. A file with no row under any of its names makes its module stale. A module split into a
package of its import name (occ/controllers/keyframe.py into occ/controllers/keyframe/) keeps
its rows for the package's files: git follows a rename, not a split. A row counts for the
module of the first file it names, not for another module that shares a file it names later
(the `collab` row names occ/net/streams.py: it did not score `streams`). Modules that score
parts of one file (`interfaces` and `roles`, `teleop` and `teleop6`) share its rows here. A
scoped module (scripts/mutate's SCOPES, read with `scripts/mutate --scope MODULE`) is judged by
the units its scope mutates, with the statements at the top of their files and the bodies of
their classes; `-v` lists its changed units outside the scope.

It also checks docs/VERIFICATION.md's register of the files no module mutates: every Python file
of the code is in a module or in the register (with what verifies it instead), never both.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from datetime import datetime
from fnmatch import fnmatchcase
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENTRY = re.compile(r'^\s*(?:\[(\w+)\]|MODULES\[(\w+)\])="([^"|]+)\|')
DATE = re.compile(r"(\d{4}-\d{2}-\d{2})")
TIME = re.compile(r"\b(\d{2}):(\d)(\d|x)(?::\d{2})?\b")  # "10:5x": the end of that ten minutes
#: where the project's code lives (a unit may have moved anywhere among them)
CODE_DIRS = ("occ", "igtl", "occ_ros2", "occ_console", "occ_testkit")


def modules() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in (ROOT / "scripts" / "mutate").read_text().splitlines():
        m = ENTRY.match(line)
        if m and "/" in m.group(3):
            out[m.group(1) or m.group(2)] = m.group(3).split()
    return out


#: a row whose run mutated code committed after the run ended names that commit
COMMITTED = re.compile(r"code as committed in `?([0-9a-f]{7,40})`?")


def rows() -> list[tuple[str, datetime, str | None]]:
    """(the row's module cell, the end of its last run, the commit its code is in when the
    date cell names one) for each row of the Scores table."""
    text = (ROOT / "docs" / "VERIFICATION.md").read_text()
    table = text.split("## Scores", 1)[1].split("\n## ", 1)[0]
    found = []
    for line in table.splitlines():
        cells = line.split(" | ")
        if not line.startswith("| `") or len(cells) < 3:
            continue
        date_cell = cells[1]
        day = DATE.search(date_cell)
        if day is None:
            continue
        times = [
            (int(h), int(tens) * 10 + (9 if unit == "x" else int(unit)))
            for h, tens, unit in TIME.findall(date_cell)
            if int(h) < 24
        ]
        h, m = max(times) if times else (0, 0)
        when = datetime.fromisoformat(f"{day.group(1)}T{h:02d}:{m:02d}:59+00:00")
        named = COMMITTED.search(date_cell)
        found.append((cells[0], when, named.group(1) if named else None))
    return found


def git(*args: str) -> str:
    return subprocess.run(
        ["git", *args], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout


@cache
def names(path: str) -> frozenset[str]:
    """Every path the file had, as git follows its renames (the path now included)."""
    out = git("log", "--follow", "--name-only", "--format=", "--", path)
    found = {path} | {line for line in out.splitlines() if line.strip()}
    # a module split into a package of the same import name (occ/controllers/keyframe.py into
    # occ/controllers/keyframe/): the package's files were the module (git follows a rename,
    # not a split)
    parent = Path(path).parent
    if parent.name and path.startswith(tuple(f"{d}/" for d in CODE_DIRS)):
        found.add(f"{parent.as_posix()}.py")
    return frozenset(found)


def _strip(body: list[ast.stmt], docstring: bool = True) -> list[ast.stmt]:
    """A body without its import lines and (``docstring``) its docstring; one left empty is
    ``pass``."""
    if docstring and body and isinstance(body[0], ast.Expr):
        if isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str):
            body = body[1:]
    return [s for s in body if not isinstance(s, ast.Import | ast.ImportFrom)] or [ast.Pass()]


class _Normal(ast.NodeTransformer):
    """Docstrings out of every function and class, import lines out of every block (an
    ``if TYPE_CHECKING:`` of imports alone becomes ``pass``)."""

    def generic_visit(self, node: ast.AST) -> ast.AST:
        super().generic_visit(node)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            node.body = _strip(node.body)
        else:
            for name in ("body", "orelse", "finalbody"):
                block = getattr(node, name, None)
                if isinstance(block, list) and block and isinstance(block[0], ast.stmt):
                    setattr(node, name, _strip(block, docstring=False))
        return node


def _empty(stmt: ast.stmt) -> bool:
    """``pass``, or an ``if`` that holds nothing else (imports taken out)."""
    if isinstance(stmt, ast.If):
        return all(_empty(s) for s in [*stmt.body, *stmt.orelse])
    return isinstance(stmt, ast.Pass)


def units(source: str) -> set[tuple[str, str]]:
    """(qualified name, code) of each unit of a module's source (module docstring); an
    unparsable source has none."""
    try:
        tree = ast.parse(source)
    except SyntaxError:
        return set()
    out: set[tuple[str, str]] = set()

    def add(name: str, node: ast.AST) -> None:
        node = _Normal().visit(node)
        out.add((name, ast.dump(node, include_attributes=False)))

    for stmt in _strip(tree.body):
        if isinstance(stmt, ast.ClassDef):
            for inner in _strip(stmt.body):
                if isinstance(inner, ast.FunctionDef | ast.AsyncFunctionDef):
                    add(f"{stmt.name}.{inner.name}", inner)
                else:
                    add(stmt.name, inner)
            head = ast.ClassDef(
                name=stmt.name, bases=stmt.bases, keywords=stmt.keywords, body=[ast.Pass()],
                decorator_list=stmt.decorator_list, type_params=[],
            )  # fmt: skip
            add(stmt.name, head)
        elif isinstance(stmt, ast.FunctionDef | ast.AsyncFunctionDef):
            add(stmt.name, stmt)
        elif not _empty(_Normal().visit(stmt)):
            add("<module>", stmt)
    return out


@cache
def commit_at(when: datetime) -> str:
    return git("rev-list", "-1", f"--before={when.isoformat()}", "HEAD").strip()


@cache
def project_units(commit: str) -> frozenset[tuple[str, str]]:
    """Every unit of the project's code at ``commit``."""
    listing = git("ls-tree", "-r", "--name-only", commit, "--", *CODE_DIRS).splitlines()
    paths = [p for p in listing if p.endswith(".py")]
    blobs = subprocess.run(
        ["git", "cat-file", "--batch"],
        cwd=ROOT,
        input="".join(f"{commit}:{p}\n" for p in paths).encode(),
        capture_output=True,
        check=True,
    ).stdout
    found: set[tuple[str, str]] = set()
    at = 0
    while at < len(blobs):
        end = blobs.index(b"\n", at)
        size = int(blobs[at:end].split()[2])
        found |= units(blobs[end + 1 : end + 1 + size].decode("utf-8", "replace"))
        at = end + 1 + size + 1
    return frozenset(found)


#: a mutant-name glob of a scope: the module, then a method (xǁClassǁname) or a function (x_name)
GLOB = re.compile(
    r"^(?P<mod>[\w.]+?)\.(?:x\u01c1(?P<cls>\w+)\u01c1(?P<meth>.*)|x_(?P<func>.*)|\*)$"
)


def scope(module: str) -> dict[str, list[str]] | None:
    """The units a scoped module mutates, as name patterns per file (``Class.method``,
    ``function``, ``*``: every unit), from ``scripts/mutate --scope``; None: the whole module."""
    globs = subprocess.run(
        ["bash", str(ROOT / "scripts" / "mutate"), "--scope", module],
        capture_output=True, text=True, check=True,
    ).stdout.split()  # fmt: skip
    if not globs:
        return None
    out: dict[str, list[str]] = {}
    for g in globs:
        m = GLOB.match(g)
        if m is None:
            raise ValueError(f"scripts/mutate's scope of {module}: cannot read {g!r}")
        name = m["meth"] if m["cls"] else m["func"]
        name = "*" if name is None else re.sub(r"__mutmut_.*$", "", name)
        pattern = f"{m['cls']}.{name}" if m["cls"] else name
        out.setdefault(m["mod"].replace(".", "/") + ".py", []).append(pattern)
    return out


def in_scope(unit: str, patterns: list[str]) -> bool:
    """A changed unit a scope's mutants see: one it names, a statement at the top of its file,
    or the body of a class one of whose methods it names."""
    if unit == "<module>":
        return True
    return any(fnmatchcase(unit, p) or p.startswith(unit + ".") for p in patterns)


def file_units_before(path: str, row: datetime) -> frozenset[tuple[str, str]]:
    """The units of ``path`` (under any of its names) as last committed before ``row``, on
    whichever branch: a run made on a branch merged later saw that version."""
    found: set[tuple[str, str]] = set()
    for name in names(path):
        commit = git("log", "-1", f"--before={row.isoformat()}", "--format=%H", "--", name)
        if commit.strip():
            try:
                found |= units(git("show", f"{commit.strip()}:{name}"))
            except subprocess.CalledProcessError:
                continue  # the commit removed it under that name
    return frozenset(found)


def changed_units(path: str, row: datetime, commit: str | None = None) -> list[str]:
    """The units of ``path`` now that the project did not have at ``row``'s commit (the one
    made last before it, or the one it names)."""
    if commit:
        old = project_units(git("rev-parse", commit).strip())
    else:  # the project then, and the file as last committed before the row on any branch
        old = project_units(commit_at(row)) | file_units_before(path, row)
    now = units((ROOT / path).read_text(encoding="utf-8"))
    return sorted({name for name, code in now if (name, code) not in old})


#: the first path a row's module cell names: the module the row scored
FIRST_PATH = re.compile(r"`([\w./]+\.py)`")


def _first_path(cell: str) -> str | None:
    """The file a row is about (its first path): a row counts for the module that file belongs
    to, never for another module that merely shares a file it names (the `collab` row names
    occ/net/streams.py, whose own module `streams` it did not score)."""
    m = FIRST_PATH.search(cell)
    return m.group(1) if m else None


#: the heading of docs/VERIFICATION.md's list of the files no module mutates
REGISTER = "## The files no module mutates, and how each is verified"
REGISTER_PATH = re.compile(r"`([\w/]+\.py)`")


def register() -> dict[str, list[str]]:
    """The files docs/VERIFICATION.md says no module mutates: path -> that row's cells (what
    it is, verified by, why no score)."""
    text = (ROOT / "docs" / "VERIFICATION.md").read_text(encoding="utf-8")
    start = text.find(REGISTER)
    if start < 0:
        return {}
    out: dict[str, list[str]] = {}
    for line in text[start:].split("\n## ", 1)[0].splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if not line.startswith("| `") or len(cells) < 4:
            continue
        for path in REGISTER_PATH.findall(cells[0]):
            out[path] = cells[1:]
    return out


def code_files() -> list[str]:
    """Every Python file of the project's code, as git tracks it."""
    listed = git("ls-files", "--", *CODE_DIRS).split()
    return sorted(f for f in listed if f.endswith(".py"))


def register_problems() -> list[str]:
    """A code file in no module and not in the register, one in both, one the register names
    that is not there, or a row with an empty cell."""
    mutated = {f for files in modules().values() for f in files}
    listed = register()
    code = code_files()
    out = [f"{f}: in no module of scripts/mutate and not in the register" for f in code
           if f not in mutated and f not in listed]  # fmt: skip
    out += [f"{f}: in the register and in a module" for f in sorted(listed) if f in mutated]
    out += [f"{f}: in the register, not in the code" for f in sorted(listed) if f not in code]
    out += [f"{f}: a row with an empty cell" for f, cells in sorted(listed.items())
            if not all(cells[:3])]  # fmt: skip
    return out


def main(argv: list[str]) -> int:
    verbose = "-v" in argv
    table = rows()
    stale = 0
    problems = register_problems()
    for problem in problems:
        print(f"REGISTER {problem}")
    for name, files in sorted(modules().items()):
        late = []
        scoped = scope(name)
        own: dict[str, tuple[datetime, str | None] | None] = {}
        mine = set().union(*(names(f) for f in files))
        for f in files:
            called = names(f)
            scored = [
                (w, c)
                for cell, w, c in table
                if any(f"`{n}`" in cell for n in called) and _first_path(cell) in mine
            ]
            own[f] = max(scored, key=lambda wc: wc[0]) if scored else None
        known = [w for w in own.values() if w is not None]
        last = max(known, key=lambda wc: wc[0]) if known else None
        newest = last[0] if last else None
        for f in files:
            # a file with no row of its own (split out of a scored file, or new): judged
            # against the module's newest row, every unit it has must have existed then
            found = own[f] or last
            if found is None:
                late.append(f"{f}: no row")
                continue
            row, commit = found
            changed = changed_units(f, row, commit)
            if scoped is not None:
                outside = [u for u in changed if not in_scope(u, scoped.get(f, []))]
                changed = [u for u in changed if u not in outside]
                if outside and verbose:
                    print(f"      {name}: {f}: changed outside its scope: {', '.join(outside)}")
            if changed:
                shown = ", ".join(changed) if verbose else f"{len(changed)} units"
                late.append(f"{f} changed since {row:%Y-%m-%d %H:%M}: {shown}")
        stale += bool(late)
        shown = newest.strftime("%Y-%m-%d %H:%M") if newest else "no row"
        print(f"{'STALE' if late else 'ok':5} {name:12} newest row {shown}", *late, sep="; ")
    return 1 if stale or problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
