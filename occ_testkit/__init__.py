"""The test and tool harness: the robot in simulated time on in-process channels
(:mod:`occ_testkit.testing`), the slave and master rigs the tests drive most
(:mod:`occ_testkit.rigs`), the hardware fault matrix (:mod:`occ_testkit.faultmatrix`) and
private network namespaces (:mod:`occ_testkit.netns`).

It drives the daemons from outside, the way the tests, ``tools/`` and ``benchmarks/`` do, and is
installed beside them for that; the runtime packages never import it (``occ``, ``igtl``,
``occ_ros2`` and ``occ_console``: tests/test_imports.py holds them to it). Where it needs the
shipped configuration files it reads them from the repository's ``configs/`` (:data:`CONFIGS`):
the harness runs from a source checkout, as the tests and tools it serves do.
"""

from __future__ import annotations

from pathlib import Path

#: the repository's configs/ (the harness runs from a source checkout; an installed daemon finds
#: its robot descriptions through package data, occ/kinematics/frame.py)
CONFIGS = Path(__file__).resolve().parents[1] / "configs"
