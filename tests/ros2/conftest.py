"""Fixtures of the ROS 2 bridge's tests.

They need the ``ros2`` extra (cyclonedds) and rosbags, both installed by the ``test`` extra
(scripts/test). Each module skips without them, except with ``OCC_REQUIRE_INTEROP=1`` (CI, as
for the reference OpenIGTLink peers), where the import error fails the run instead.
"""

from __future__ import annotations

import os

import pytest


def require_extra() -> None:
    """Skip the calling module when the ROS 2 packages are missing (not in CI: see above)."""
    if os.environ.get("OCC_REQUIRE_INTEROP") != "1":
        pytest.importorskip("cyclonedds", reason="pip install -e .[test] (includes .[ros2])")
        pytest.importorskip("rosbags", reason="pip install -e .[test]")
