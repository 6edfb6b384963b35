"""Which mutation scores are older than their code: for every module of scripts/mutate, the
newest row of docs/VERIFICATION.md's Scores table that names one of its source files, against
the last commit that changed each file (issue 29: "re-run after the last change to each
module").

    python scripts/mutants_stale.py          # every module, stale ones marked; exit 1 if any

A row's time is the latest HH:MM in its date cell (the end of its last run), on the cell's
date. Each source file of a module must have a row whose first cell names it, newer than the
file's last change; a file without one makes the module stale. Modules that score parts of one file
(`interfaces` and `roles`, `teleop` and `teleop6`) share its rows here, and a section of
docs/VERIFICATION.md may say why a function-scoped module needed no re-run (its functions did
not change): this file-level check lists, it does not judge.
"""

from __future__ import annotations

import re
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENTRY = re.compile(r'^\s*(?:\[(\w+)\]|MODULES\[(\w+)\])="([^"|]+)\|')
DATE = re.compile(r"(\d{4}-\d{2}-\d{2})")
TIME = re.compile(r"\b(\d{2}):(\d)(\d|x)(?::\d{2})?\b")  # "10:5x": the end of that ten minutes


def modules() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in (ROOT / "scripts" / "mutate").read_text().splitlines():
        m = ENTRY.match(line)
        if m and "/" in m.group(3):
            out[m.group(1) or m.group(2)] = m.group(3).split()
    return out


def rows() -> list[tuple[str, datetime]]:
    """(the row's module cell, the end of its last run) for each row of the Scores table."""
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
        found.append((cells[0], when))
    return found


def last_change(path: str) -> datetime:
    stamp = subprocess.run(
        ["git", "log", "-1", "--format=%ct", "--", path],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    return datetime.fromtimestamp(int(stamp), UTC)


def main() -> int:
    table = rows()
    stale = 0
    for name, files in sorted(modules().items()):
        late = []
        newest: datetime | None = None
        for f in files:
            scored = [when for cell, when in table if f"`{f}`" in cell]
            row = max(scored) if scored else None
            if row is not None and (newest is None or row > newest):
                newest = row
            changed = last_change(f)
            if row is None or changed > row:
                seen = row.strftime("%Y-%m-%d %H:%M") if row else "no row"
                late.append(f"{f} changed {changed:%Y-%m-%d %H:%M} (its newest row: {seen})")
        stale += bool(late)
        shown = newest.strftime("%Y-%m-%d %H:%M") if newest else "no row"
        print(f"{'STALE' if late else 'ok':5} {name:12} newest row {shown}", *late, sep="; ")
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
