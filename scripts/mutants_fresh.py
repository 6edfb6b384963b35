"""Re-run surviving mutants each in a fresh Python process.

    scripts/mutants_fresh.py SCRATCH GLOB... [-- TEST_FILE...]

mutmut 3 runs every mutant in a process forked from one that has already imported the code and
run the tests once. Code that runs at import (the wire layer's timestamp tables) was therefore
built by the original, and memos filled by that first run answer for the mutant: such mutants
survive whatever the tests check. Here each survivor whose name matches a GLOB is run again
with ``MUTANT_UNDER_TEST`` set in a new interpreter (the module imported afresh, its memos
empty), on the module's own test selection (``pytest_add_cli_args_test_selection`` in
SCRATCH/pyproject.toml, written by scripts/mutate, or the test files given after ``--``),
stopping at the first failure.

Prints ``killed``/``survived`` per mutant and a count; exit 0. Run scripts/mutate first.
"""

from __future__ import annotations

import fnmatch
import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return 0 if argv else 2
    root = Path(argv[0]).resolve()
    rest = argv[1:]
    given = rest[rest.index("--") + 1 :] if "--" in rest else []
    globs = (rest[: rest.index("--")] if "--" in rest else rest) or ["*"]
    cfg = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["mutmut"]
    tests = given or cfg["pytest_add_cli_args_test_selection"]
    names = []
    for meta in sorted((root / "mutants").rglob("*.py.meta")):
        for key, code in json.loads(meta.read_text())["exit_code_by_key"].items():
            if code == 0 and any(fnmatch.fnmatchcase(key, g) for g in globs):
                names.append(key)
    killed = 0
    for name in names:
        env = dict(os.environ, MUTANT_UNDER_TEST=name)
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "pytest",
                "-x",
                "-q",
                "-p",
                "no:cacheprovider",
                "-m",
                "not realtime and not interop",
                *tests,
            ],
            cwd=root / "mutants",
            env=env,
            capture_output=True,
            text=True,
            check=False,
        )
        verdict = "killed" if proc.returncode != 0 else "survived"
        killed += proc.returncode != 0
        print(f"{name}: {verdict}", flush=True)
    print(f"fresh processes: {killed} of {len(names)} killed")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
