"""Classify the mutants mutmut left alive: scripts/mutants_report.py SCRATCH_DIR [--all].

Reads mutmut's own records in SCRATCH_DIR/mutants (the ``.meta`` exit codes and the mutated
sources), diffs every survivor against the original function and sorts it into

- ``log``: the change is inside a logging call (its text or arguments); nothing the robot does
  depends on it;
- ``text``: only the text of a string changes, or a message string becomes None, on a line
  that makes a message (a ``raise``, an error or warning constructed, an alert, a refusal, a
  status or last-error text, a help or description string): what the robot does is the same,
  and the tests that matter match the message's substance, not its every character. A string
  anywhere else (compared, a key, a name looked up, a device, a unit, a format) is
  ``behaviour``: before 2026-11-27 any string counted as text, and 15 of teleop's 18 "text"
  survivors then were comparisons (``mode == 'rcm'``);
- ``gc``: inside ``__del__`` (the leak warning at garbage collection);
- ``behaviour``: everything else, a changed default argument included (it shows in the
  signature, ``def (...)``, which is compared along with the body): a test should kill it,
  or docs/VERIFICATION.md says why it is equivalent.

Prints counts per module and class, and each behaviour survivor as ``name: - old / + new``.
"""

from __future__ import annotations

import ast
import difflib
import json
import re
import sys
from collections import Counter
from pathlib import Path

SIGNATURE = "def "
#: a line that makes a message: its strings are what a person reads, not what the code decides on
MESSAGE = re.compile(
    r"\braise\b|Error\(|Exception\(|Warning\(|\bwarn\(|\.fail\(|\b_?tell\(|\balert\(|"
    r"\b_?refuse[ds]?\(|\bProblem\(|\blast_error\b|\bstatus\s*=|\bdescription=|\bhelp="
)
STRING = re.compile(r"""(?:[rbfu]{0,2})("([^"\\]|\\.)*"|'([^'\\]|\\.)*')""", re.I)


def functions(path: Path) -> dict[str, str]:
    tree = ast.parse(path.read_text())
    out = {}
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and "__mutmut_" in node.name:
            # the signature first: a mutated default argument changes only that line
            body = ast.unparse(node.body)  # type: ignore[arg-type]
            out[node.name] = f"{SIGNATURE}({ast.unparse(node.args)})\n{body}"
    return out


def classify(name: str, old: list[str], new: list[str]) -> str:
    if "__del__" in name:
        return "gc"
    if any(line.startswith(SIGNATURE) for line in old + new):
        return "behaviour"  # a default argument changed: what a call without it does
    changed = [line for line in old + new]
    if changed and all(re.search(r"\b(log|logger)\.\w+\(", line) for line in changed):
        return "log"
    if not all(MESSAGE.search(x) for x in old):
        return "behaviour"  # a string the code decides on, not one a person reads
    if [STRING.sub('""', x) for x in old] == [STRING.sub('""', x) for x in new]:
        return "text"
    # a message (a string argument) replaced by None: the same call, without its text
    if any(STRING.search(x) for x in old) and [STRING.sub('""', x) for x in old] == [
        re.sub(r"\bNone\b", '""', STRING.sub('""', x)) for x in new
    ]:
        return "text"
    return "behaviour"


def main(argv: list[str]) -> int:
    root = Path(argv[0])
    show_all = "--all" in argv
    total: Counter[str] = Counter()
    rows = []
    for meta in sorted((root / "mutants").rglob("*.py.meta")):
        source = meta.with_suffix("")
        codes = json.loads(meta.read_text())["exit_code_by_key"]
        funcs = functions(source)
        counts: Counter[str] = Counter()
        for key, code in codes.items():
            state = {0: "survived", 1: "killed", 33: "no tests", None: "not run"}.get(
                code, "killed"
            )
            if state != "survived":
                counts[state] += 1
                continue
            short = key.rsplit(".", 1)[-1]
            orig = funcs.get(short.split("__mutmut_")[0] + "__mutmut_orig", "").splitlines()
            mutated = funcs.get(short, "").splitlines()
            diff = list(difflib.ndiff(orig, mutated))
            old = [d[2:] for d in diff if d.startswith("- ")]
            new = [d[2:] for d in diff if d.startswith("+ ")]
            kind = classify(short, old, new)
            counts["survived: " + kind] += 1
            if kind == "behaviour" or show_all:
                rows.append(f"{key} [{kind}]: - {' | '.join(old)}  /  + {' | '.join(new)}")
        n = sum(counts.values())
        killed = counts["killed"]
        alive = sum(v for k, v in counts.items() if k.startswith("survived"))
        behaviour = counts["survived: behaviour"]
        print(
            f"{source.relative_to(root / 'mutants')}: {n} mutants, killed {killed} "
            f"({100 * killed / max(n, 1):.1f} %), survived {alive} "
            f"(behaviour {behaviour}, text {counts['survived: text']}, "
            f"log {counts['survived: log']}, gc {counts['survived: gc']}), "
            f"no tests {counts['no tests']}, not run {counts['not run']}; "
            f"killed of all but log/text/gc: {100 * killed / max(n - alive + behaviour, 1):.1f} %"
        )
        total.update(counts)
    for row in rows:
        print(row)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
