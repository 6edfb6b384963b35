"""docs/BENCHMARKS.md's contents list names every one of its ``## `` sections, in order (issue 39:
the list had fallen behind the sections added after it).

An entry is the section's heading without its trailing date (`` (2026-11-27)`` or
``, 2026-11-26/27``), optionally followed by ``; `` and words of its own (its subsections).
"""

from __future__ import annotations

import re
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "docs" / "BENCHMARKS.md"
DATE = re.compile(r"(?:,\s*|\s+\()\d{4}-\d{2}-\d{2}[^)]*\)?$")


def title(heading: str) -> str:
    """A ``## `` heading's text without its trailing date."""
    return DATE.sub("", heading[3:].strip())


def sections(text: str) -> list[str]:
    """The titles of the ``## `` headings, outside code blocks, in order."""
    out, fenced = [], False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and line.startswith("## "):
            out.append(title(line))
    return out


def contents(text: str) -> list[str]:
    """The entries of the list that follows the line ``Contents:``."""
    lines = text.splitlines()
    start = lines.index("Contents:") + 1
    while not lines[start].strip():
        start += 1
    out = []
    for line in lines[start:]:
        if not line.startswith("- "):
            break
        out.append(line[2:].strip())
    return out


def names(entry: str, section: str) -> bool:
    return entry == section or entry.startswith(section + "; ")


def test_a_heading_loses_only_its_trailing_date() -> None:
    assert title("## The issue 26 table: two pairs (2026-11-27)") == "The issue 26 table: two pairs"
    assert title("## Late is not lost (issue 26, item 2), 2026-11-26/27") == (
        "Late is not lost (issue 26, item 2)"
    )
    assert title("## igtl: codec") == "igtl: codec"


def test_a_missing_extra_or_misplaced_entry_is_found() -> None:
    doc = (
        "Contents:\n\n- A; its parts\n- B\n\n"
        "## A (2026-11-29)\n\n```\n## not a heading\n```\n## B\n"
    )
    assert sections(doc) == ["A", "B"]
    assert contents(doc) == ["A; its parts", "B"]
    assert not names("B", "A") and not names("Ab", "A") and names("A; x", "A")


def test_the_contents_list_names_every_section_in_order() -> None:
    text = BENCHMARKS.read_text(encoding="utf-8")
    heads, entries = sections(text), contents(text)
    missing = [h for h in heads if not any(names(e, h) for e in entries)]
    assert not missing, f"sections missing from BENCHMARKS.md's contents list: {missing}"
    stray = [e for e in entries if not any(names(e, h) for h in heads)]
    assert not stray, f"contents entries with no section: {stray}"
    assert len(entries) == len(heads), "one entry per section"
    wrong = [(e, h) for e, h in zip(entries, heads, strict=True) if not names(e, h)]
    assert not wrong, f"contents out of order (entry, section): {wrong}"
