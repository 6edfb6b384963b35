"""Fixtures of the ROS 2 bridge's tests.

They need the ``ros2`` extra (cyclonedds) and rosbags, both installed by the ``test`` extra
(scripts/test). Each module skips without them, except with ``OCC_REQUIRE_INTEROP=1`` (CI, as
for the reference OpenIGTLink peers), where the import error fails the run instead.
"""

from __future__ import annotations

import os
import random
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from occ_testkit.testing import wait_until

#: how long ``poll`` waits by default: 10 s; scripts/mutate sets 2 (OCC_BRIDGE_WAIT_S) since a
#: killed mutant is often a reply or a sample that never comes (a loopback answer takes
#: milliseconds here)
WAIT_S = float(os.environ.get("OCC_BRIDGE_WAIT_S", "10"))


def poll(pred: Callable[[], Any], timeout: float | None = None, every: float = 0.005) -> Any:
    """:func:`occ_testkit.testing.wait_until`, by default for :data:`WAIT_S` (the ros2 tests import
    it from here)."""
    return wait_until(pred, WAIT_S if timeout is None else timeout, every)


#: the DDS configuration of the tests that run DDS in the test process, on the host: loopback,
#: unicast only (its comment says why; test_rclpy.py runs the shipped one in a namespace)
UNICAST_CONFIG = Path(__file__).with_name("cyclonedds-unicast.xml")


def require_extra() -> None:
    """Skip the calling module when the ROS 2 packages are missing (not in CI: see above)."""
    if os.environ.get("OCC_REQUIRE_INTEROP") != "1":
        pytest.importorskip("cyclonedds", reason="pip install -e .[test] (includes .[ros2])")
        pytest.importorskip("rosbags", reason="pip install -e .[test]")


def _unique_domain() -> int:
    """A DDS domain id for this test run: random in 100..232 (the upper part of the range, away
    from the ROS 2 default 0 and small ids people pick), so two runs on one machine rarely
    share one; the tests' namespaces carry the pid too, so even then they read only their own
    topics."""
    return random.SystemRandom().randint(100, 232)


@pytest.fixture(scope="session")
def dds() -> Iterator[tuple[int, Any]]:
    """(domain id, participant) on loopback without multicast (:data:`UNICAST_CONFIG`)."""
    require_extra()
    from cyclonedds.domain import Domain, DomainParticipant

    domain_id = _unique_domain()
    # the Domain carries the configuration; it must exist before (and outlive) the participant
    domain = Domain(domain_id, UNICAST_CONFIG.read_text())
    participant = DomainParticipant(domain_id)
    yield domain_id, participant
    del participant, domain


@pytest.fixture
def namespace(request: pytest.FixtureRequest) -> str:
    """A namespace no other test or run uses: the test's name, cut to 24 characters, and a
    checksum of the whole (two tests whose names start alike must not share one: a bridge
    of the first not yet collected would still publish its latched state there)."""
    name = "".join(c if c.isalnum() else "_" for c in request.node.name)[:24]
    crc = zlib.crc32(request.node.nodeid.encode())
    return f"/occtest{os.getpid()}_{name}_{crc:08x}/slave"


@pytest.fixture
def netns() -> Iterator[Any]:
    """A private network namespace (netns.py) for a test that runs real ROS 2 nodes; skipped
    without rclpy or root, failed instead in CI (rig.require)."""
    from occ_testkit.netns import Netns

    from .rig import require

    require()
    with Netns() as ns:
        yield ns


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[Any]) -> Iterator[None]:
    """A failed test of a daemon in a namespace rig (rig.py) shows what every daemon it started
    logged (WARNING and up): a daemon's FAULT names its cause there, and the test's temporary
    directory is gone a few runs later."""
    outcome = yield
    report = outcome.get_result()  # type: ignore[attr-defined]
    if report.when == "call" and report.failed:
        from .rig import Rig

        for rig in Rig.started:
            text = rig.daemon_log()
            if text:
                report.sections.append(("daemon log", text))
        Rig.started.clear()
    elif report.when == "teardown":
        from .rig import Rig

        Rig.started.clear()

