"""The third-party software (SOUP) the project installs: its lock, and docs/SOUP.md made from it.

``constraints.txt`` is the lock: every third-party distribution a full install of the project
pulls in (pyproject.toml's dependencies and every extra but the opt-in ``native``, on CPython
3.11, Linux x86_64), each
at the version the tests passed with, with its licence and what pulls it in as comment lines
below it. ``scripts/_venv.sh`` installs with ``-c constraints.txt``, so the environment the
tests run in is the lock. docs/soup.yaml is the hand-kept part: for each package the project
depends on directly, what it relies on it for, how that reliance is tested and its known
anomalies that matter here, with their sources. docs/SOUP.md is generated from the two.

    python -m occ_testkit.soup --lock      # write constraints.txt from the installed environment
    python -m occ_testkit.soup --update    # write docs/SOUP.md from the lock and docs/soup.yaml
    python -m occ_testkit.soup --check     # exit 1 when docs/SOUP.md, the lock, docs/soup.yaml
                                           # and pyproject.toml disagree (what, one a line)

``scripts/soup`` runs it with the project's interpreter. tests/test_soup.py runs the check.
"""

from __future__ import annotations

import importlib.metadata as md
import re
import sys
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from packaging.requirements import InvalidRequirement, Requirement

ROOT = Path(__file__).resolve().parents[1]
LOCK = ROOT / "constraints.txt"
DATA = ROOT / "docs" / "soup.yaml"
DOC = ROOT / "docs" / "SOUP.md"
PYPROJECT = ROOT / "pyproject.toml"
PROJECT = "occ-igtl"
#: the extras that ship with the software (optional parts of what runs beside a robot)
RUNTIME_EXTRAS = ("arms", "plot", "record", "ros2", "console")
#: the extras that test and verify it (not part of what runs)
TOOL_EXTRAS = ("test", "verify")
#: not locked: the opt-in compiled build's extra (scripts/build_native.py), whose setuptools is
#: the build's own and newer than the one a plain venv has
UNLOCKED_EXTRAS = ("native",)
#: not locked: the installer's own tools, as ``pip freeze`` leaves them out (a ROS 2 wheel's
#: plain `setuptools` requirement must not pin the native extra's newer one)
UNLOCKED = ("pip", "setuptools", "wheel")
#: the fields of a direct runtime dependency's entry in docs/soup.yaml, and of a tool's
RUNTIME_FIELDS = ("relied_on", "tested_by", "anomalies", "checked")
TOOL_FIELDS = ("used_for",)

LOCK_HEADER = """\
# The lock: every third-party distribution a full install of occ-igtl pulls in (pyproject.toml's
# dependencies and every extra but the opt-in `native`, on CPython 3.11, Linux x86_64; pip and
# setuptools, the installer's, left out), each at the version the tests passed with.
# scripts/_venv.sh installs with `pip install -c constraints.txt`. Below each pin: its licence
# (from its metadata) and what pulls it in. docs/SOUP.md is generated from this file and
# docs/soup.yaml. Written by `scripts/soup --lock` from a tested environment; do not edit.
"""


class SoupError(ValueError):
    """A lock, data file or pyproject.toml that cannot be read: the message says where."""


def canonical(name: str) -> str:
    """PEP 503's normalised form of a distribution's name."""
    return re.sub(r"[-_.]+", "-", name).lower()


@dataclass(frozen=True)
class Locked:
    """One pinned distribution of the lock."""

    name: str
    version: str
    licence: str
    #: what requires it: another distribution's name, or ``occ-igtl`` / ``occ-igtl[extra]``
    via: tuple[str, ...]


# --- pyproject.toml -------------------------------------------------------------------------


def project_requirements(text: str | None = None) -> dict[str, list[Requirement]]:
    """``{"core": [...], extra: [...]}``: pyproject.toml's requirements whose markers hold
    here, references to the project's own extras (``occ-igtl[ros2]``) left as they are; the
    extras of :data:`UNLOCKED_EXTRAS` left out."""
    text = PYPROJECT.read_text(encoding="utf-8") if text is None else text
    project = tomllib.loads(text)["project"]
    groups: dict[str, list[str]] = {"core": project.get("dependencies", [])}
    groups.update(project.get("optional-dependencies", {}))
    for extra in UNLOCKED_EXTRAS:
        groups.pop(extra, None)
    out: dict[str, list[Requirement]] = {}
    for group, lines in groups.items():
        reqs = []
        for line in lines:
            try:
                req = Requirement(line)
            except InvalidRequirement as err:
                raise SoupError(f"pyproject.toml, {group}: {line!r}: {err}") from err
            if req.marker is None or req.marker.evaluate({"extra": ""}):
                reqs.append(req)
        out[group] = reqs
    return out


def direct(reqs: Mapping[str, list[Requirement]]) -> dict[str, set[str]]:
    """``{canonical name: {groups naming it}}`` for every third-party requirement, the
    project's own extras followed (``occ-igtl[ros2]`` in ``test`` names ros2's packages in
    ``ros2``, where they are declared)."""
    out: dict[str, set[str]] = {}
    for group, lines in reqs.items():
        for req in lines:
            if canonical(req.name) != PROJECT:
                out.setdefault(canonical(req.name), set()).add(group)
    return out


def roots(reqs: Mapping[str, list[Requirement]], group: str) -> set[str]:
    """The third-party packages a group names, through the project's own extras it names."""
    seen, todo, out = {group}, [group], set()
    while todo:
        for req in reqs.get(todo.pop(), []):
            if canonical(req.name) == PROJECT:
                for extra in req.extras - seen:
                    seen.add(extra)
                    todo.append(extra)
            else:
                out.add(canonical(req.name))
    return out


# --- the installed environment --------------------------------------------------------------


def licence_of(meta: Any) -> str:
    """A distribution's licence from its metadata: its SPDX expression, else a short License
    field, else its licence classifiers."""
    expr = meta.get("License-Expression")
    if expr:
        return str(expr).strip()
    text = (meta.get("License") or "").strip()
    if text and "\n" not in text and len(text) <= 60 and text.upper() != "UNKNOWN":
        return text
    classifiers = [
        c.split(" :: ")[-1] for c in meta.get_all("Classifier") or [] if c.startswith("License ::")
    ]
    if classifiers:
        return " / ".join(classifiers)
    return "not stated in its metadata"


def installed_lock(reqs: Mapping[str, list[Requirement]]) -> dict[str, Locked]:
    """The lock of the installed environment: every distribution the project's requirements
    (every group) pull in, walked through the installed metadata with each requirement's
    extras and markers. A requirement that is not installed is a SoupError naming it."""
    found: dict[str, tuple[Any, set[str], set[str]]] = {}  # name: (dist, extras, via)
    todo: list[tuple[Requirement, str]] = []
    for group, lines in reqs.items():
        label = PROJECT if group == "core" else f"{PROJECT}[{group}]"
        todo += [(r, label) for r in lines if canonical(r.name) != PROJECT]
    while todo:
        req, parent = todo.pop()
        key = canonical(req.name)
        if key in UNLOCKED:
            continue
        try:
            dist = md.distribution(req.name)
        except md.PackageNotFoundError as err:
            raise SoupError(f"{req} (required by {parent}) is not installed") from err
        if not req.specifier.contains(dist.version, prereleases=True):
            raise SoupError(
                f"{req.name} {dist.version} is installed, which {req} ({parent}) refuses"
            )
        if key in found:
            _, extras, via = found[key]
            new = set(req.extras) - extras
            via.add(parent)
            if not new:
                continue
            extras |= new
        else:
            extras = set(req.extras)
            found[key] = (dist, extras, {parent})
        for line in dist.requires or []:
            sub = Requirement(line)
            envs = [{"extra": e} for e in sorted(extras | {""})]
            if sub.marker is None or any(sub.marker.evaluate(env) for env in envs):
                todo.append((sub, dist.metadata["Name"]))
    return {
        key: Locked(
            name=dist.metadata["Name"],
            version=dist.version,
            licence=licence_of(dist.metadata),
            via=tuple(sorted({canonical(v) if "[" not in v else v for v in via})),
        )
        for key, (dist, _, via) in sorted(found.items())
    }


def installed_versions(names: Iterable[str]) -> dict[str, str | None]:
    """The installed version of each distribution, None where it is not installed."""
    out: dict[str, str | None] = {}
    for name in names:
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            out[name] = None
    return out


# --- the lock -------------------------------------------------------------------------------


def write_lock(lock: Mapping[str, Locked]) -> str:
    lines = [LOCK_HEADER.rstrip("\n")]
    for key in sorted(lock):
        e = lock[key]
        lines += [f"{e.name}=={e.version}", f"    # licence: {e.licence}"]
        lines.append(f"    # via: {', '.join(e.via)}")
    return "\n".join(lines) + "\n"


def read_lock(text: str | None = None) -> dict[str, Locked]:
    """The lock's entries by canonical name; a line of another form is a SoupError naming it."""
    text = LOCK.read_text(encoding="utf-8") if text is None else text
    out: dict[str, Locked] = {}
    current: dict[str, Any] | None = None
    entries: list[dict[str, Any]] = []
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or (line.startswith("#") and not raw.startswith("    #")):
            continue
        m = re.fullmatch(r"([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s#]+)", line)
        if m:
            current = {"name": m.group(1), "version": m.group(2), "licence": "", "via": ()}
            entries.append(current)
            continue
        m = re.fullmatch(r"#\s*(licence|via):\s*(.*)", line)
        if m and current is not None:
            if m.group(1) == "licence":
                current["licence"] = m.group(2)
            else:
                current["via"] = tuple(v.strip() for v in m.group(2).split(",") if v.strip())
            continue
        raise SoupError(f"constraints.txt:{n}: not a pin (name==version) or its comment: {raw!r}")
    for e in entries:
        key = canonical(e["name"])
        if key in out:
            raise SoupError(f"constraints.txt: {e['name']} is pinned twice")
        out[key] = Locked(**e)
    return out


def closure(lock: Mapping[str, Locked], start: Iterable[str]) -> set[str]:
    """The packages ``start`` pulls in according to the lock's ``via`` lines, ``start`` included."""
    children: dict[str, set[str]] = {}
    for key, e in lock.items():
        for parent in e.via:
            children.setdefault(canonical(parent), set()).add(key)
    seen: set[str] = set()
    todo = [canonical(s) for s in start]
    while todo:
        key = todo.pop()
        if key in seen or key not in lock:
            continue
        seen.add(key)
        todo += children.get(key, ())
    return seen


def groups(lock: Mapping[str, Locked], reqs: Mapping[str, list[Requirement]]) -> dict[str, str]:
    """Each locked package's place: ``core``, the runtime extras whose install pulls it in
    (``extra: ros2``), or ``tools``."""
    core = closure(lock, roots(reqs, "core"))
    extras = {x: closure(lock, roots(reqs, x)) - core for x in RUNTIME_EXTRAS if x in reqs}
    out = {}
    for key in lock:
        if key in core:
            out[key] = "core"
        else:
            names = [x for x, members in extras.items() if key in members]
            out[key] = f"extra: {', '.join(names)}" if names else "tools"
    return out


# --- the checks -----------------------------------------------------------------------------


def lock_problems(lock: Mapping[str, Locked], reqs: Mapping[str, list[Requirement]]) -> list[str]:
    """pyproject.toml's requirements against the lock: each one pinned, at a version it allows."""
    problems = []
    for group, lines in reqs.items():
        for req in lines:
            key = canonical(req.name)
            if key == PROJECT:
                continue
            if key not in lock:
                problems.append(
                    f"{req.name} ({group}) is not in constraints.txt (install it, run the tests, "
                    "then scripts/soup --lock)"
                )
            elif not req.specifier.contains(lock[key].version, prereleases=True):
                problems.append(
                    f"constraints.txt pins {lock[key].name} {lock[key].version}, which "
                    f"pyproject.toml's {req} ({group}) does not allow"
                )
    return problems


def installed_problems(lock: Mapping[str, Locked]) -> list[str]:
    """Locked distributions installed at another version (one not installed is no problem:
    the lock constrains, it does not require)."""
    have = installed_versions(e.name for e in lock.values())
    return [
        f"{e.name} {have[e.name]} is installed, constraints.txt pins {e.version} "
        "(reinstall: scripts/_venv.sh; or update the lock: scripts/soup --lock)"
        for e in lock.values()
        if have[e.name] is not None and have[e.name] != e.version
    ]


def read_data(text: str | None = None) -> dict[str, Any]:
    text = DATA.read_text(encoding="utf-8") if text is None else text
    data = yaml.safe_load(text)
    if not isinstance(data, dict) or not isinstance(data.get("packages"), dict):
        raise SoupError("docs/soup.yaml: a mapping with `intro` and `packages` (name: entry)")
    return data


def data_problems(
    lock: Mapping[str, Locked],
    data: Mapping[str, Any],
    reqs: Mapping[str, list[Requirement]],
    refs: set[str],
) -> list[str]:
    """docs/soup.yaml against the lock: every direct dependency has its entry, every entry is a
    locked package, every test or requirement it cites exists (``refs``: the test files, the
    ``file::test`` names and the SR IDs there are)."""
    problems = []
    entries: dict[str, Any] = {canonical(k): v for k, v in data["packages"].items()}
    for name in data["packages"]:
        if canonical(name) not in lock:
            problems.append(f"docs/soup.yaml: {name} is not in constraints.txt")
    names = direct(reqs)
    for key, groups_ in sorted(names.items()):
        runtime = bool(groups_ & ({"core"} | set(RUNTIME_EXTRAS)))
        need = RUNTIME_FIELDS if runtime else TOOL_FIELDS
        entry = entries.get(key)
        if not isinstance(entry, dict):
            problems.append(f"docs/soup.yaml has no entry for {key} ({', '.join(sorted(groups_))})")
            continue
        for f in need:
            if not entry.get(f) and not (f == "anomalies" and entry.get(f) == []):
                problems.append(f"docs/soup.yaml: {key} has no `{f}`")
        problems += _entry_problems(key, entry, refs)
    return problems


def _entry_problems(key: str, entry: Mapping[str, Any], refs: set[str]) -> list[str]:
    problems = []
    for ref in entry.get("tested_by") or []:
        if ref not in refs:
            problems.append(f"docs/soup.yaml: {key} is tested by {ref!r}, which does not exist")
    for a in entry.get("anomalies") or []:
        if not isinstance(a, dict) or not a.get("what") or not a.get("source"):
            problems.append(f"docs/soup.yaml: {key}: an anomaly needs `what` and `source`")
            continue
        source = str(a["source"])
        if not (source.startswith("https://") or source.split("#")[0].split("::")[0] in refs):
            problems.append(f"docs/soup.yaml: {key}: the source {source!r} is no URL or file here")
    return problems


def references(root: Path = ROOT) -> set[str]:
    """What an entry of docs/soup.yaml may cite: the repository's files (relative paths), every
    ``file::test`` of tests/, and the SR IDs of docs/SAFETY.md."""
    from occ_testkit.trace import requirements, scan_tests

    files = {
        p.relative_to(root).as_posix()
        for top in ("tests", "docs", "occ", "igtl", "occ_ros2", "occ_console", "tools", "README.md")
        for p in ([root / top] if (root / top).is_file() else (root / top).rglob("*"))
        if p.is_file()
    }
    return files | set(scan_tests(root / "tests", root)) | set(requirements())


# --- docs/SOUP.md ---------------------------------------------------------------------------


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _source(source: str) -> str:
    return f"<{source}>" if source.startswith("https://") else f"`{source}`"


def _entry_md(e: Locked, place: str, entry: Mapping[str, Any]) -> list[str]:
    out = [f"### {e.name} {e.version}", "", f"Licence: {e.licence}. Place: {place}.", ""]
    out += [f"**Relied on for.** {_cell(entry['relied_on'])}", ""]
    tests = ", ".join(f"`{t}`" for t in entry["tested_by"])
    out += [f"**Tested by.** {tests}", ""]
    anomalies = entry.get("anomalies") or []
    if anomalies:
        out += ["**Known anomalies that matter here.**", ""]
        out += [f"- {_cell(a['what'])} ({_source(str(a['source']))})" for a in anomalies]
    else:
        out.append("**Known anomalies that matter here.** None found.")
    out += ["", f"**Checked.** {_cell(entry['checked'])}", ""]
    return out


def render(
    lock: Mapping[str, Locked], data: Mapping[str, Any], reqs: Mapping[str, list[Requirement]]
) -> str:
    """docs/SOUP.md from the lock, docs/soup.yaml and pyproject.toml's requirements."""
    place = groups(lock, reqs)
    names = direct(reqs)
    entries = {canonical(k): v for k, v in data["packages"].items()}
    runtime_groups = {"core", *RUNTIME_EXTRAS}
    runtime = sorted(k for k in lock if place[k] != "tools")
    heads = [k for k in runtime if names.get(k, set()) & runtime_groups]
    pulled = [k for k in runtime if k not in heads]
    tools = sorted(k for k in lock if place[k] == "tools")
    out = [
        "# Third-party software (SOUP)",
        "",
        "<!-- Generated by `scripts/soup --update` from constraints.txt (the lock) and",
        "docs/soup.yaml (the prose): edit those, then regenerate. tests/test_soup.py checks. -->",
        "",
        str(data.get("intro", "")).strip(),
        "",
        f"{len(lock)} distributions are locked: {sum(place[k] == 'core' for k in lock)} in a core "
        f"install, {len(runtime) - sum(place[k] == 'core' for k in lock)} more with the runtime "
        f"extras ({', '.join(RUNTIME_EXTRAS)}), {len(tools)} tools.",
        "",
        "## The packages the project depends on directly",
        "",
        "| Package | Version | Licence | Place | Known anomalies |",
        "|---|---|---|---|---|",
    ]
    for k in heads:
        e, n = lock[k], len(entries[k].get("anomalies") or [])
        out.append(
            f"| {e.name} | {e.version} | {_cell(e.licence)} | {place[k]} | {n or 'none found'} |"
        )
    out.append("")
    for k in heads:
        out += _entry_md(lock[k], place[k], entries[k])
    out += [
        "## Pulled in by those (transitive runtime dependencies)",
        "",
        "| Package | Version | Licence | Place | Pulled in by |",
        "|---|---|---|---|---|",
    ]
    for k in pulled:
        e = lock[k]
        out.append(
            f"| {e.name} | {e.version} | {_cell(e.licence)} | {place[k]} | {', '.join(e.via)} |"
        )
    out += [
        "",
        "## Tools: build, test and verification (not part of what runs)",
        "",
        "| Package | Version | Licence | Used for, or pulled in by |",
        "|---|---|---|---|",
    ]
    for k in tools:
        e = lock[k]
        used = entries.get(k, {}).get("used_for")
        why = _cell(used) if used else "pulled in by " + ", ".join(e.via)
        out.append(f"| {e.name} | {e.version} | {_cell(e.licence)} | {why} |")
    return "\n".join(out) + "\n"


def problems(root: Path = ROOT, *, installed: bool = True) -> list[str]:
    """Every disagreement between pyproject.toml, the lock, docs/soup.yaml, docs/SOUP.md and
    (with ``installed``) the installed environment, one line each."""
    reqs = project_requirements((root / "pyproject.toml").read_text(encoding="utf-8"))
    lock = read_lock((root / "constraints.txt").read_text(encoding="utf-8"))
    data = read_data((root / "docs" / "soup.yaml").read_text(encoding="utf-8"))
    out = lock_problems(lock, reqs) + data_problems(lock, data, reqs, references(root))
    if not out:
        doc = root / "docs" / "SOUP.md"
        if not doc.is_file() or doc.read_text(encoding="utf-8") != render(lock, data, reqs):
            out.append(
                "docs/SOUP.md is not what the lock and docs/soup.yaml make: scripts/soup --update"
            )
    if installed:
        out += installed_problems(lock)
    return out


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if args not in (["--lock"], ["--update"], ["--check"]):
        print(__doc__.split("\n\n")[2], file=sys.stderr)
        return 2
    try:
        if args == ["--lock"]:
            LOCK.write_text(write_lock(installed_lock(project_requirements())), encoding="utf-8")
            print(f"wrote {LOCK.relative_to(ROOT)}")
            return 0
        if args == ["--update"]:
            reqs, lock = project_requirements(), read_lock()
            found = lock_problems(lock, reqs) + data_problems(lock, read_data(), reqs, references())
            if found:
                print("\n".join(found), file=sys.stderr)
                return 1
            DOC.write_text(render(lock, read_data(), reqs), encoding="utf-8")
            print(f"wrote {DOC.relative_to(ROOT)}")
            return 0
        found = problems()
    except (SoupError, OSError) as err:
        print(f"soup: {err}", file=sys.stderr)
        return 2
    print("\n".join(found) if found else "SOUP: the lock, docs/soup.yaml and docs/SOUP.md agree")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
