"""Whole-arm collision checking (issue 28, item 4; occ/collision.py, docs/SAFETY.md SR-COLL-1..3).

- A UR5 (configs/ur5.yaml) keyframe plan whose *elbow* (the forearm), not its tip, crosses a
  forbidden plane is refused naming the link, the region and the time; the same plan passes the
  tip-only check; a plan that stays clear passes and runs.
- Teleoperation toward the plane (a scripted master stream raising the tool) stops the robot
  before contact, with an ALERT naming the link and the region; a late verdict holds the loop.
- Self-collision, a mesh region from a Slicer-like POLYDATA, config errors with their lines.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import igtl
from occ.collision import CollisionGuard, CollisionModel, regions_from_message
from occ.config import CollisionConfig
from occ.errors import ConfigError
from occ.loader import load_config, parse_config
from occ.safety import RobotState
from occ.testing import CONFIGS, SimRobot

HOME = [0.0, -1.2, 1.5, -1.9, -1.57, 0.0]
#: the shoulder and elbow raised: the forearm rises through z = 560 mm, the tip sinks to 236 mm
RAISED = [0.0, -1.5, 2.0, -2.0, -1.57, 0.0]
CEILING = {"name": "ceiling", "kind": "plane", "point_mm": [0, 0, 560], "normal": [0, 0, -1]}


def ur5(collision: dict[str, Any] | None, controller: dict[str, Any] | None = None) -> dict[str, Any]:
    cfg: dict[str, Any] = yaml.safe_load((CONFIGS / "ur5.yaml").read_text())
    if collision is not None:
        cfg["safety"]["collision"] = collision
    if controller is not None:
        cfg["controller"] = controller
        cfg["safety"]["loss"] = {"enabled": False}
        cfg["interfaces"] = cfg["interfaces"][:2]  # no master stream
        cfg["interfaces"][1]["outputs"] = [
            {"type": "POLYDATA", "device": "KeyframePath", "source": "keyframe-path", "rate_hz": 10}
        ]
    cfg["interfaces"][1]["inputs"] = [
        {"type": t, "queue": "command", "depth": 16} for t in ("POINT", "TRANSFORM", "POLYDATA")
    ]
    return cfg


def keyframe_robot(collision: dict[str, Any] | None, **params: Any) -> SimRobot:
    return SimRobot(ur5(collision, {"plugin": "keyframe", "params": {"space": "joint", **params}}))


def command(sim: SimRobot, name: str, **args: Any) -> Any:
    op = sim.peer("operator")
    attrs = "".join(f' {k}="{v}"' for k, v in args.items())
    cid = op.send_command(name, f'<Command Name="{name}"{attrs}/>')
    sim.step(1)
    kf = sim.robot.controller.controllers[0]
    if hasattr(kf, "wait_idle"):
        assert kf.wait_idle(60.0)
    sim.step(1)
    reply = op.reply_to(cid)
    assert reply is not None, name
    return reply.metadata


def raise_keyframes() -> list[dict[str, Any]]:
    return [{"t": 2.0, "pose": RAISED, "name": "raised"}]


# ------------------------------------------------------------------------------ plans
@pytest.mark.req("SR-COLL-1")
def test_a_plan_whose_elbow_crosses_a_forbidden_plane_is_refused_naming_the_link() -> None:
    sim = keyframe_robot({"margin_mm": 10.0, "regions": [CEILING]}, keyframes=raise_keyframes())
    try:
        command(sim, "Enable")
        reply = command(sim, "KeyframePlan")
        assert reply["Status"] == "FAIL", reply
        error = reply["Error"]
        assert "link 'forearm_link'" in error and "forbidden region 'ceiling'" in error, error
        assert "margin 10 mm" in error and "between the start" in error and "raised" in error
        t = float(error.split("t=")[1].split()[0])
        assert 0.0 < t < 2.0
    finally:
        sim.close()


@pytest.mark.req("SR-COLL-1")
def test_the_tip_alone_never_comes_near_the_plane() -> None:
    # the keyframe controller's own tip check, against the same plane: the plan passes (the
    # tip stays below 300 mm), which is why the whole arm is checked
    tip_only = {"forbidden": [{"point_mm": [0, 0, 560], "normal": [0, 0, -1], "name": "ceiling"}]}
    sim = keyframe_robot(None, keyframes=raise_keyframes(), **tip_only)
    try:
        command(sim, "Enable")
        assert command(sim, "KeyframePlan")["Status"] == "SUCCESS"
    finally:
        sim.close()


@pytest.mark.req("SR-COLL-1")
def test_a_plan_clear_of_the_regions_passes_and_runs() -> None:
    low = [0.3, -1.1, 1.6, -2.0, -1.57, 0.2]
    sim = keyframe_robot(
        {"margin_mm": 10.0, "regions": [CEILING]},
        keyframes=[{"t": 2.0, "pose": low, "name": "low"}],
    )
    try:
        command(sim, "Enable")
        command(sim, "Run")
        reply = command(sim, "KeyframePlan")
        assert reply["Status"] == "SUCCESS", reply
        plan_id = reply["Message"].split(":")[0].split()[1]
        sim.step(150)  # the preview goes out
        assert command(sim, "KeyframeAck", Plan=plan_id)["Status"] == "SUCCESS"
        sim.run_for(2.2)
        assert sim.robot.state is RobotState.RUNNING
        assert np.allclose(sim.robot.data.setpoint, low, atol=1e-9)
        guard = sim.robot.collision
        assert guard is not None and guard.stops == 0 and guard.verdicts > 2000
    finally:
        sim.close()
