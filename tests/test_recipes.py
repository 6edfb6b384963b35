"""docs/ARCHITECTURE.md's newcomer recipes, followed as written (issue 39): add a driver, a
controller and an operator command, each in at most three files, and run the robot with it.

Each test writes the newcomer's module into a temporary directory (a package of their own on
``sys.path``), registers it the way the recipe says (the run-time registry stands in for the
built-in table or the entry point: both name ``"module:Class"``), selects it in the YAML of the
shipped slave, and drives the robot in simulated time through its operator interface.
"""

from __future__ import annotations

import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from occ.controllers import register_controller
from occ.drivers import register_driver
from occ_testkit import CONFIGS
from occ_testkit.testing import SimRobot

ROOT = Path(__file__).resolve().parents[1]


def test_the_recipes_are_where_a_newcomer_looks() -> None:
    """The three recipes these tests follow are in docs/ARCHITECTURE.md, each naming at most
    three files to touch: the newcomer's module, its registration (the built-in table or an
    entry point) and the YAML (a driver: the contract test's fixture list too)."""
    doc = (ROOT / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    for recipe in ("**Add a driver**", "**Add a controller**", "**Add an operator command**"):
        assert recipe in doc, recipe


@pytest.fixture
def newcomer(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A directory on sys.path for the newcomer's package; its modules are forgotten after."""
    monkeypatch.syspath_prepend(str(tmp_path))
    before = set(sys.modules)
    yield tmp_path
    for name in set(sys.modules) - before:
        if name.startswith("recipe_"):
            del sys.modules[name]


def _slave(controller: dict[str, Any] | None = None) -> dict[str, Any]:
    """The shipped slave as YAML holds it; another controller in place of teleop-slave (whose
    return link, the master interface's ``teleop-return`` output, goes with it)."""
    cfg = yaml.safe_load((CONFIGS / "slave.yaml").read_text(encoding="utf-8"))
    cfg["robot"]["realtime"] = {}
    if controller is not None:
        cfg["controller"] = controller
        for iface in cfg["interfaces"]:
            if iface["name"] == "master":
                iface["outputs"] = []
    return cfg


def _ok(reply: Any) -> bool:
    return bool(reply.metadata.get("Status") == "SUCCESS")


def test_add_a_driver(newcomer: Path) -> None:
    """"Add a driver": subclass Driver, implement the narrow hooks, declare DEFAULT_PARAMS,
    register it, select it in YAML. The base class checks state and limits; the robot powers it
    on with Enable and writes it while RUNNING."""
    (newcomer / "recipe_drive.py").write_text(
        textwrap.dedent(
            '''
            from occ.drivers.base import Driver

            class RecipeDriver(Driver):
                """A drive that is exactly where it was told to be."""

                DEFAULT_PARAMS = {"gain": 1.0}

                def _configure(self):
                    self.q = [j.home for j in self.joints]
                    self.writes = 0

                def _activate(self):
                    pass

                def _deactivate(self):
                    pass

                def _shutdown(self):
                    pass

                def _read(self, now):
                    n = len(self.q)
                    return list(self.q), [0.0] * n, [0.0] * n

                def _write(self, values, now):
                    self.writes += 1
                    self.q = [self.params["gain"] * v for v in values]
            '''
        ),
        encoding="utf-8",
    )
    register_driver("recipe-drive", "recipe_drive:RecipeDriver")
    drivers = [
        {"name": "arm", "plugin": "recipe-drive", "joints": ["yaw", "pitch", "insertion"]},
    ]
    cfg = _slave({"plugin": "hold"})
    cfg["robot"]["drivers"] = drivers
    with SimRobot(cfg) as sim:
        operator = sim.peer("operator")
        assert _ok(sim.command(operator, "Enable"))
        assert _ok(sim.command(operator, "Run"))
        sim.step(50)
        (drive,) = sim.robot.hardware.drivers
        assert type(drive).__name__ == "RecipeDriver" and drive.writes >= 50
        assert list(sim.robot.data.q) == pytest.approx([0.0, 0.35, 0.05])
    # the base refuses what the recipe says it refuses: an unknown parameter, at load time
    cfg["robot"]["drivers"] = [dict(drivers[0], params={"gian": 2.0})]
    with pytest.raises(Exception, match="gian"):
        SimRobot(cfg)


def test_add_a_controller(newcomer: Path) -> None:
    """"Add a controller": subclass Controller with a Params model, implement configure and
    update, register it, select it with ``controller: {plugin: NAME, params: {...}}``."""
    (newcomer / "recipe_ctl.py").write_text(
        textwrap.dedent(
            '''
            from pydantic import BaseModel, ConfigDict

            from occ.config import Float
            from occ.controllers import Controller

            class Params(BaseModel):
                model_config = ConfigDict(extra="forbid", frozen=True)
                insertion: Float = 0.06

            class Insert(Controller):
                """Moves the insertion to a set depth, 1 mm a tick at most; the rest held."""

                Params = Params

                def configure(self, data, ctx):
                    self.data = data

                def update(self, now):
                    q = list(self.data.q)
                    step = max(-0.001, min(0.001, self.params.insertion - q[2]))
                    return [q[0], q[1], q[2] + step]
            '''
        ),
        encoding="utf-8",
    )
    register_controller("recipe-insert", "recipe_ctl:Insert")
    cfg = _slave({"plugin": "recipe-insert", "params": {"insertion": 0.07}})
    with SimRobot(cfg) as sim:
        operator = sim.peer("operator")
        assert _ok(sim.command(operator, "Enable"))
        assert _ok(sim.command(operator, "Run"))
        sim.run_for(1.0)
        assert sim.robot.data.q[2] == pytest.approx(0.07, abs=5e-4)
    bad = _slave({"plugin": "recipe-insert", "params": {"depth": 0.07}})
    with pytest.raises(Exception, match="depth"):
        SimRobot(bad)


def test_add_an_operator_command(monkeypatch: pytest.MonkeyPatch) -> None:
    """"Add an operator command": one row of ROBOT_COMMANDS with its role, thread, summary and
    handler; the thread column dispatches it (here ``loop``: the handler's text is the reply in
    the tick). A viewer may not send an ``operator`` row."""
    from occ.net import commands

    def where(desk: Any, req: Any, item: Any, now: float) -> str:
        return desk.describe_state()

    row = commands.CommandSpec("WhereAmI", "operator", commands.LOOP, "the state, as text", where)
    monkeypatch.setitem(commands.ROBOT_COMMANDS, "whereami", row)
    with SimRobot(_slave()) as sim:
        operator = sim.peer("operator")
        reply = sim.command(operator, "WhereAmI")
        assert _ok(reply), reply
        assert "READY" in str(reply.metadata) + str(getattr(reply, "command", ""))
        slicer = sim.peer("slicer")
        refused = sim.command(slicer, "WhereAmI")
        assert not _ok(refused)
