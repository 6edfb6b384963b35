"""House rules on size (issue 39): every class of occ/ under 450 lines, no function of occ/, igtl/
and occ_ros2/ over 80 lines unless a comment right above it says why it must be one (a line
starting ``# one function:``), and the Robot's module under 300 lines.

    python tests/test_house.py      # the largest classes and functions, for a look
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_CLASS = 450
MAX_FUNCTION = 80
WHY = "# one function:"


def _sizes(package: str) -> list[tuple[int, str, str, bool, bool]]:
    """(lines, where, name, is a class, has the comment saying why) of every class and
    function of ``package``, from its ``def``/``class`` line (decorators excluded) to its last."""
    out = []
    for path in sorted((ROOT / package).rglob("*.py")):
        lines = path.read_text(encoding="utf-8").splitlines()
        for node in ast.walk(ast.parse("\n".join(lines))):
            if isinstance(node, ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
                first = min([node.lineno] + [d.lineno for d in node.decorator_list])
                above = lines[first - 2].strip() if first >= 2 else ""
                out.append((
                    node.end_lineno - node.lineno + 1,  # type: ignore[operator]
                    f"{path.relative_to(ROOT)}:{node.lineno}",
                    node.name,
                    isinstance(node, ast.ClassDef),
                    above.startswith(WHY),
                ))  # fmt: skip
    return out


def test_every_class_of_occ_is_under_450_lines() -> None:
    big = [f"{w} {n}: {size}" for size, w, n, cls, _ in _sizes("occ") if cls and size >= MAX_CLASS]
    assert not big, big


def test_no_function_is_over_80_lines_without_saying_why() -> None:
    big = [
        f"{w} {n}: {size}"
        for package in ("occ", "igtl", "occ_ros2")
        for size, w, n, cls, why in _sizes(package)
        if not cls and size > MAX_FUNCTION and not why
    ]
    assert not big, big


def test_the_robots_module_stays_small() -> None:
    text = (ROOT / "occ" / "core" / "robot.py").read_text(encoding="utf-8")
    assert len(text.splitlines()) < 300 and "fmt: skip" not in text


if __name__ == "__main__":
    rows = [r for p in ("occ", "igtl", "occ_ros2") for r in _sizes(p)]
    for size, where, name, cls, _ in sorted(rows, reverse=True)[:15]:
        print(f"{size:5d}  {'class' if cls else 'def  '}  {name}  {where}")
