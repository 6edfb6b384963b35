"""The namespace rig of the ROS 2 tests: daemon, bridge and DDS agents as restartable processes.

Everything runs in one private network namespace (netns.py): the slave daemon (``occd
configs/slave.yaml`` with its shipped ports: the namespace has them to itself; or another
config, e.g. a keyframe robot, or the master and the slave together), the bridge (``occ-ros2``
with its shipped DDS configuration), a real ROS 2 node (rclpy_agent.py), a Cyclone participant
for the crtk_msgs/tf2_msgs topics (cyclone_agent.py) and an OpenIGTLink operator
(igtl_agent.py), each driven over JSON lines.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from occ_testkit.netns import Netns, available

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
NS = "/occ/slave"


class Agent:
    """A JSON-lines subprocess (rclpy_agent.py, cyclone_agent.py): one answer per request."""

    def __init__(self, proc: subprocess.Popen[Any]) -> None:
        self.proc = proc
        assert proc.stdout is not None
        hello = proc.stdout.readline()
        assert hello and json.loads(hello).get("ready"), _stderr(proc)

    def ask(self, op: str, **kw: Any) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps({"op": op, **kw}) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        assert line, f"the agent died: {_stderr(self.proc)}"
        return dict(json.loads(line))

    def stop(self) -> None:
        try:
            self.ask("exit")
            self.proc.wait(10.0)
        finally:
            Netns.stop(self.proc)


def _stderr(proc: subprocess.Popen[Any]) -> str:
    if proc.poll() is None or proc.stderr is None:
        return f"(running, pid {proc.pid})"
    return str(proc.stderr.read())[-3000:]


def require() -> None:
    """Skip without rclpy or namespaces; in CI (OCC_REQUIRE_INTEROP=1) fail instead."""
    import importlib.util

    missing = [
        name
        for name in ("rclpy", "geometry_msgs", "sensor_msgs", "std_msgs", "cyclonedds")
        if importlib.util.find_spec(name) is None
    ]
    why = available()
    problem = f"missing {', '.join(missing)} (pip install -e .[test])" if missing else why
    if problem is None:
        return
    if os.environ.get("OCC_REQUIRE_INTEROP") == "1":
        pytest.fail(f"a real ROS 2 node is required here (OCC_REQUIRE_INTEROP=1): {problem}")
    pytest.skip(problem)


def clean_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "RMW_", "CYCLONE"))}
    env["ROS_DOMAIN_ID"] = "0"
    env.update(extra)
    return env


class Rig:
    """The daemon, the bridge and the node in one namespace, each restartable."""

    #: the rigs of the test running (conftest.py shows their daemons' logs when it fails)
    started: list[Rig] = []

    def __init__(self, ns: Netns, tmp: Path, node_env: dict[str, str], topics: str = NS) -> None:
        self.ns, self.tmp, self.node_env = ns, tmp, node_env
        #: the ROS 2 namespace the node and the Cyclone participant use
        self.topics = topics
        self.daemon: subprocess.Popen[Any] | None = None
        self.bridge: subprocess.Popen[Any] | None = None
        self.node: Agent | None = None
        self.bridge_runs = 0
        self.daemon_runs = 0
        Rig.started.append(self)

    # -------------------------------------------------------------- daemon
    def start_daemon(
        self,
        config: Path = ROOT / "configs" / "slave.yaml",
        *args: str,
        ports: tuple[int, ...] = (18944, 18947),
    ) -> subprocess.Popen[Any]:
        """``occd config args...``, waited for until it listens on ``ports``."""
        self.daemon_runs += 1
        log = (self.tmp / f"daemon{self.daemon_runs}.log").open("w")  # read by daemon_log()
        proc = self.ns.popen(
            [sys.executable, "-m", "occ.cli", str(config), "--log-level", "WARNING", *args],
            cwd=ROOT, env=clean_env(), stderr=log,
        )  # fmt: skip
        log.close()  # the child has its own descriptor
        self.daemon = self.daemon or proc
        wait = (
            "import socket,time,sys\n"
            "end=time.monotonic()+30\n"
            "while time.monotonic()<end:\n"
            "    s=socket.socket(); s.settimeout(0.2)\n"
            "    ok=s.connect_ex(('127.0.0.1',int(sys.argv[1])))==0; s.close()\n"
            "    if ok: sys.exit(0)\n"
            "    time.sleep(0.05)\n"
            "sys.exit(1)\n"
        )
        for port in ports:
            self.ns.run([sys.executable, "-c", wait, str(port)], timeout=35.0)
        return proc

    def daemon_log(self) -> str:
        """What every daemon started here logged (WARNING and above), for a failure's message."""
        logs = sorted(self.tmp.glob("daemon*.log"))
        return "\n".join(f"--- {p.name}\n{p.read_text()[-3000:]}" for p in logs)

    # -------------------------------------------------------------- bridge
    def start_bridge(self, *extra: str, ports: tuple[str, ...] | None = None) -> None:
        """occ-ros2 with ``ports`` (default: the slave's viewer and operator ports) and
        ``extra``."""
        if ports is None:
            ports = ("--connect", f"127.0.0.1:18944={NS}", "--operator", f"127.0.0.1:18947={NS}")
        self.bridge_runs += 1
        self.bridge = self.ns.popen(
            [sys.executable, "-m", "occ_ros2.cli", *ports,
             "--log-level", "WARNING",
             "--stats", str(self.tmp / f"bridge{self.bridge_runs}.json"), *extra],
            cwd=ROOT, env=clean_env(),
        )  # fmt: skip

    def stop_bridge(self) -> dict[str, Any]:
        assert self.bridge is not None
        assert self.bridge.poll() is None, _stderr(self.bridge)
        Netns.stop(self.bridge)
        self.bridge = None
        path = self.tmp / f"bridge{self.bridge_runs}.json"
        return dict(json.loads(path.read_text()))

    # -------------------------------------------------------------- agents
    def start_node(self) -> Agent:
        """The real ROS 2 node (rclpy_agent.py)."""
        self.node = Agent(self.ns.popen(
            [sys.executable, str(HERE / "rclpy_agent.py"), self.topics],
            env=self.node_env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        ))  # fmt: skip
        return self.node

    def start_cyclone(self) -> Agent:
        """A Cyclone participant for the crtk_msgs and tf2_msgs topics (cyclone_agent.py)."""
        return Agent(self.ns.popen(
            [sys.executable, str(HERE / "cyclone_agent.py"), self.topics],
            cwd=ROOT, env=clean_env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        ))  # fmt: skip

    def start_operator(self, port: int) -> Agent:
        """An OpenIGTLink operator of the daemon on ``port`` (igtl_agent.py)."""
        return Agent(self.ns.popen(
            [sys.executable, str(HERE / "igtl_agent.py"), str(port)],
            cwd=ROOT, env=clean_env(), stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        ))  # fmt: skip

    def ask(self, op: str, **kw: Any) -> dict[str, Any]:
        """A request to the node."""
        assert self.node is not None
        return self.node.ask(op, **kw)

    def stop_node(self) -> None:
        assert self.node is not None
        self.node.stop()
        self.node = None
