"""The skip / require logic of conftest.py, checked by running pytest in a subprocess with a
controlled environment: missing peers skip with a clear reason, but fail under
OCC_REQUIRE_INTEROP=1 (CI) so a run without interop cannot go green."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from . import helpers as h

pytestmark = pytest.mark.interop

HERE = "tests/interop"
NEEDS_REFERENCE = f"{HERE}/test_ours_to_reference.py::test_receive_server_prints_our_status"
NEEDS_PYIGTL = f"{HERE}/test_pyigtl.py::test_our_server_downgrades_v2_for_a_v1_pyigtl_client"
NEEDS_ECHO = f"{HERE}/test_ours_to_reference.py::test_string_echo_server_echoes_our_strings"


def _run(tmp_path: Path, tests: list[str], *, examples: Path, require: bool,
         break_pyigtl: bool = False) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k not in (h.REQUIRE_ENV, "PYTEST_ADDOPTS")}
    env[h.EXAMPLES_ENV] = str(examples)
    if require:
        env[h.REQUIRE_ENV] = "1"
    if break_pyigtl:
        fake = tmp_path / "fake" / "pyigtl"
        fake.mkdir(parents=True)
        (fake / "__init__.py").write_text("raise ImportError('pyigtl hidden by the test')\n")
        env["PYTHONPATH"] = os.pathsep.join([str(fake.parent), env.get("PYTHONPATH", "")])
    return subprocess.run(
        # -m "": the named tests run whatever the default marker selection (pyproject addopts)
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-p", "no:hypothesispytest",
         "-q", "-rsfE", "-m", "", *tests],
        cwd=h.ROOT, env=env, capture_output=True, text=True, timeout=120,
    )


def test_missing_peers_skip_with_reason(tmp_path):
    r = _run(tmp_path, [NEEDS_REFERENCE, NEEDS_PYIGTL], examples=tmp_path / "none",
             require=False, break_pyigtl=True)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out
    assert "2 skipped" in out, out
    assert ("reference OpenIGTLink examples not built: run bash "
            "scripts/install_reference_peers.sh") in out
    assert "pyigtl is not importable" in out


def test_missing_peers_fail_when_interop_is_required(tmp_path):
    r = _run(tmp_path, [NEEDS_REFERENCE, NEEDS_PYIGTL], examples=tmp_path / "none",
             require=True, break_pyigtl=True)
    out = r.stdout + r.stderr
    assert r.returncode != 0, out
    assert "skipped" not in out, out
    assert "2 error" in out, out
    assert "reference OpenIGTLink examples not built" in out and "OCC_REQUIRE_INTEROP=1" in out
    assert "pyigtl is not importable" in out


def test_one_missing_program_fails_when_interop_is_required(tmp_path, reference_bin):
    """Examples folder with only the core programs: a test needing StringEchoServer fails under
    OCC_REQUIRE_INTEROP=1 (without it, it is skipped by the same code path as above)."""
    partial = tmp_path / "partial"
    (partial / "bin").mkdir(parents=True)
    for name in ("TrackerClient", "TrackerServer", "ReceiveServer"):
        (partial / "bin" / name).symlink_to(reference_bin / name)
    r = _run(tmp_path, [NEEDS_ECHO], examples=partial, require=True)
    out = r.stdout + r.stderr
    assert r.returncode != 0 and "1 failed" in out, out
    assert "reference program StringEchoServer not built" in out
