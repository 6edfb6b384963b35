"""Shared fixtures for the igtl tests.

The reference vectors in ``tests/data/igtl-vectors`` come from the OpenIGTLink project's own unit
tests (github.com/openigtlink/OpenIGTLink, ``Testing/igtlutil/igtl_test_data_*.h``, BSD-style
licence, Copyright Insight Software Consortium).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

VECTORS_DIR = Path(__file__).parents[1] / "data" / "igtl-vectors"


@pytest.fixture(scope="session")
def vectors_dir() -> Path:
    return VECTORS_DIR


@pytest.fixture(scope="session")
def manifest() -> dict[str, dict]:
    entries = json.loads((VECTORS_DIR / "MANIFEST.json").read_text())
    return {e["file"]: e for e in entries}


def vector(name: str) -> bytes:
    return (VECTORS_DIR / name).read_bytes()
