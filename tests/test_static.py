"""House rules as tests: ``mypy``, ``ruff check`` and ``ruff format --check`` are clean on igtl,
occ, occ_ros2, occ_console and occ_testkit (and the two ruff checks on tools, benchmarks and
scripts).

Both tools come with the ``test`` extra (``pip install -e .[test]``, which the README's test
command runs); they read their settings from pyproject.toml, so they run from the repository root.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow  # subprocesses; mypy alone takes ~30 s on a cold cache

PACKAGES = ("igtl", "occ", "occ_ros2", "occ_console", "occ_testkit")
#: held to ruff too (not to mypy: scripts and measurements)
SCRIPTS = ("tools", "benchmarks", "scripts")


def _run(tool: str, *args: str, paths: tuple[str, ...] = PACKAGES) -> None:
    if importlib.util.find_spec(tool) is None:
        pytest.skip(f"{tool} is not installed (pip install -e .[test] installs it)")
    proc = subprocess.run(
        [sys.executable, "-m", tool, *args, *paths],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    if proc.returncode != 0:
        print(proc.stdout)
        print(proc.stderr, file=sys.stderr)
    assert proc.returncode == 0, f"{tool} {' '.join(args)} failed:\n{proc.stdout}{proc.stderr}"


def test_mypy_clean() -> None:
    _run("mypy")


def test_ruff_check_clean() -> None:
    _run("ruff", "check", paths=PACKAGES + SCRIPTS)


def test_ruff_format_clean() -> None:
    _run("ruff", "format", "--check", paths=PACKAGES + SCRIPTS)
