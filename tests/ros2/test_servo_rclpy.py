"""CRTK ``servo_cp`` on the robot's own namespace from a real ROS 2 node (issue 25, item 2).

In a private network namespace (rig.py): the servo slave (configs/servo.yaml: the OCC slave
whose command source is an external stream, ``mapping: absolute``), occ-ros2 with
``--connect``/``--operator`` for its topics and ``--servo /occ/slave=127.0.0.1:18948``, and a
real rclpy node (rmw_fastrtps_cpp) that reads ``measured_cp`` and streams
geometry_msgs/PoseStamped on ``/occ/slave/servo_cp`` at 100 Hz, as a CRTK servo client does.

- A target a few mm from the tip, in the world frame of ``measured_cp``: the tip gets there
  (``measured_cp`` within 0.05 mm).
- A target 20 mm away (beyond ``max_jump_mm``): refused, the tip stays, the daemon's ALERT on
  ``/occ/slave/status``; the robot stays RUNNING (a refused command holds).
- A pose stamped in another frame (``slave_base``, the frame of ``local/measured_cp``) is refused
  by the bridge; the robot holds.
- The node stops publishing: ``run=0`` on the stream, the robot holds, RUNNING.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import pytest

from occ_testkit.netns import Netns
from occ_testkit.testing import wait_until

from .rig import NS, ROOT, Rig, clean_env

pytestmark = [pytest.mark.interop, pytest.mark.realtime]

LOCALHOST = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
PORTS = ("--connect", f"127.0.0.1:18944={NS}", "--operator", f"127.0.0.1:18947={NS}")


def tip(rig: Rig, since: float = 0.0) -> list[float] | None:
    rows = [r for r in rig.ask("snapshot")["poses"]["measured_cp"] if r[0] >= since]
    return rows[-1][3:6] if rows else None


def near(a: list[float] | None, b: list[float], tol: float) -> bool:
    return a is not None and math.dist(a, b) <= tol


def test_servo_cp_from_rclpy_moves_the_tip_and_far_targets_are_refused(
    netns: Netns, tmp_path: Path
) -> None:
    rig = Rig(netns, tmp_path, clean_env(**LOCALHOST))
    rig.start_daemon(ROOT / "configs" / "servo.yaml", "--start", "running")
    rig.start_bridge("--servo", f"{NS}=127.0.0.1:18948", ports=PORTS)
    rig.start_node()
    try:
        assert wait_until(lambda: tip(rig), timeout=10.0), "no measured_cp"
        assert wait_until(lambda: rig.ask("matched")["servo_cp"] >= 1, timeout=5.0)
        start = tip(rig)
        assert start is not None
        goal = [start[0] + 0.003, start[1] - 0.002, start[2] + 0.004]
        rig.ask("servo", frame="world", position=goal, rate_hz=100, seconds=20)
        assert wait_until(lambda: near(tip(rig), goal, 5e-5), timeout=8.0), (tip(rig), goal)
        # far: refused, held, alerted
        far = [goal[0], goal[1], goal[2] + 0.020]
        t_far = rig.ask("servo", frame="world", position=far, rate_hz=100, seconds=20)["t"]

        def alerted() -> list[str]:
            return [s[1] for s in rig.ask("snapshot")["statuses"] if "servo target" in s[1]]

        assert wait_until(alerted, timeout=5.0), rig.ask("snapshot")["statuses"]
        assert "refused" in alerted()[0]
        time.sleep(1.0)
        assert near(tip(rig, t_far + 0.5), goal, 5e-5), (tip(rig), goal)
        # another frame: refused by the bridge (the robot holds where it is)
        other = [goal[0] + 0.002, goal[1], goal[2]]
        t_other = rig.ask("servo", frame="slave_base", position=other, seconds=20)["t"]
        time.sleep(1.5)
        assert near(tip(rig, t_other + 1.0), goal, 5e-5)
        # the node stops: run=0, the robot holds, still RUNNING
        rig.ask("servo_stop")
        time.sleep(1.0)
        snap: dict[str, Any] = rig.ask("snapshot")
        assert snap["states"][-1][1] == "RUNNING", snap["states"]
        assert near(tip(rig), goal, 5e-5)
    finally:
        rig.stop_node()
        stats = rig.stop_bridge()
    servo = stats[f"servo {NS}"]
    assert servo["poses"] > 0 and servo["refused_frames"] > 0, servo
