"""Real-time integration on loopback: occd slave + occd master processes + the Slicer stand-in.

Checks behaviour, not timing numbers (this machine is shared): the tip streams to the stand-in
at about 10 Hz, the slave follows the master, operator commands work over IGTL, and killing the
master stops the slave with a STATUS alert naming the cause. Benchmarks measure the numbers.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))

from loopback import pair_configs, stop_processes, wait_port, write_yaml  # noqa: E402
from slicer_standin import SlicerStandIn  # noqa: E402

from occ_testkit.testing import wait_until as wait_for

pytestmark = pytest.mark.realtime


def write_configs(tmp: Path) -> dict[str, int]:
    slave, master, ports = pair_configs()
    write_yaml(tmp / "slave.yaml", slave)
    write_yaml(tmp / "master.yaml", master)
    return ports


def start(cfg: Path, stats: Path, *extra: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "occ.cli",
            str(cfg),
            "--stats",
            str(stats),
            "--log-level",
            "WARNING",
            *extra,
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )


@pytest.fixture
def daemons(tmp_path: Path):  # type: ignore[no-untyped-def]
    ports = write_configs(tmp_path)
    procs: list[subprocess.Popen[bytes]] = []
    slave = start(tmp_path / "slave.yaml", tmp_path / "slave.json")
    procs.append(slave)
    assert wait_port(ports["slave_tcp"]), (
        slave.stderr.read().decode() if slave.poll() is not None else "slave did not listen"
    )
    master = start(tmp_path / "master.yaml", tmp_path / "master.json", "--start", "running")
    procs.append(master)
    assert wait_port(ports["master_tcp"]), "master did not listen"
    yield ports, slave, master, tmp_path
    stop_processes(procs)


def test_slicer_sees_tip_follow_master_and_dead_master_stops_slave(daemons) -> None:  # type: ignore[no-untyped-def]
    ports, slave, master, tmp = daemons
    with (
        SlicerStandIn("127.0.0.1", ports["slave_tcp"]) as s,
        SlicerStandIn("127.0.0.1", ports["slave_op"]) as op,
    ):
        assert s.connected.wait(5.0) and op.connected.wait(5.0)
        # 3D Slicer's connection is a viewer: it may not move the robot
        refused = s.wait_reply(s.send_command("Enable"), 5.0)
        assert refused is not None and refused.metadata["Status"] == "FAIL", refused
        # operator: Enable + Run over COMMAND / RTS_COMMAND on the operator interface
        for name in ("Enable", "Run"):
            cid = op.send_command(name)
            reply = op.wait_reply(cid, 5.0)
            assert reply is not None and reply.metadata["Status"] == "SUCCESS", reply
        assert wait_for(lambda: len(s.arrivals.get("Tip", [])) >= 20, 10.0)
        first = s.last["Tip"].translation

        def moved() -> bool:
            # On a heavily loaded machine a stalled master can legitimately trip the loss
            # monitor (no packet for 7 ms); the operator then sends Run again, as they would.
            if s.statuses and s.statuses[-1].error_name == "STOPPED":
                op.send_command("Run")
            return max(abs(a - b) for a, b in zip(s.last["Tip"].translation, first)) > 0.3

        # the master's simulated hand moves 50 mm at 0.1 Hz, scaled 10:1: the tip moves
        assert wait_for(moved, 15.0), [f"{st.error_name}: {st.status_message}" for st in s.statuses]
        n_status = len(s.statuses)
        summary = s.summary()
        assert 5.0 < summary["Tip"]["rate_hz"] < 15.0
        # kill the master: the slave stops and tells the operator why
        master.send_signal(signal.SIGKILL)
        assert wait_for(
            lambda: any(
                st.error_name == "STOPPED" and "packet loss" in st.status_message
                for st in s.statuses[n_status:]
            ),
            5.0,
        ), [f"{st.error_name}: {st.status_message}" for st in s.statuses]
        # GetState confirms, and nothing moves any more
        cid = s.send_command("GetState")
        reply = s.wait_reply(cid, 5.0)
        assert reply is not None and "STOPPED" in reply.metadata["Message"]
    # a daemon that ends stopped by a safety stop says so in its exit code
    slave.send_signal(signal.SIGINT)
    assert slave.wait(20) == 4


def test_occd_check_and_bad_config(tmp_path: Path) -> None:
    ok = subprocess.run(
        [sys.executable, "-m", "occ.cli", "--check", str(ROOT / "configs" / "slave.yaml")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert ok.returncode == 0, ok.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        (ROOT / "configs" / "slave.yaml").read_text().replace("rate_hz: 1000", "rate_hz: fast")
    )
    res = subprocess.run(
        [sys.executable, "-m", "occ.cli", "--check", str(bad)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 2
    assert "robot.rate_hz" in res.stderr and "bad.yaml:" in res.stderr


def test_sigterm_stops_cleanly_and_writes_stats(tmp_path: Path) -> None:
    write_configs(tmp_path)
    p = start(tmp_path / "slave.yaml", tmp_path / "s.json")
    try:
        cfg = yaml.safe_load((tmp_path / "slave.yaml").read_text())
        assert wait_port(cfg["interfaces"][0]["port"])
        # the loop is running once the 10 Hz Tip stream flows
        with SlicerStandIn("127.0.0.1", cfg["interfaces"][0]["port"]) as s:
            assert wait_for(lambda: len(s.arrivals.get("Tip", [])) >= 2, 10.0)
        p.send_signal(signal.SIGTERM)
        assert p.wait(timeout=15) == 0
    finally:
        if p.poll() is None:
            p.kill()
    import json

    d = json.loads((tmp_path / "s.json").read_text())
    for key in (
        "ticks",
        "rate_hz",
        "lateness_us",
        "compute_us",
        "late_over_1ms",
        "overruns",
        "cpu_percent",
        "interfaces",
    ):
        assert key in d
    for key in ("p50", "p99", "p99_9", "max"):
        assert key in d["lateness_us"] and key in d["compute_us"]
    for itf in d["interfaces"].values():
        for key in ("received", "sent", "dropped", "malformed"):
            assert key in itf
    assert d["ticks"] > 0 and os.path.getsize(tmp_path / "s.json") > 0


def test_port_in_use_exits_1_with_a_clear_error(tmp_path: Path) -> None:
    import socket

    ports = write_configs(tmp_path)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", ports["slave_tcp"]))
        busy.listen()
        res = subprocess.run(
            [sys.executable, "-m", "occ.cli", str(tmp_path / "slave.yaml"), "--duration", "1"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert res.returncode == 1, res.stderr
    assert "Address already in use" in res.stderr or "in use" in res.stderr.lower()


@pytest.mark.parametrize("check", [False, True])
def test_unknown_driver_param_is_a_config_error_with_its_line(tmp_path: Path, check: bool) -> None:
    """A driver parameter typo is found when the file is loaded (``occd --check`` too), with
    FILE:LINE, exit code 2: not at start-up with exit code 1 as before."""
    slave, _, _ = pair_configs()
    slave["robot"]["drivers"][0]["params"] = {"bandwith_hz": 30}  # typo
    path = write_yaml(tmp_path / "slave.yaml", slave)
    args = ["--check"] if check else ["--duration", "0.1"]
    res = subprocess.run(
        [sys.executable, "-m", "occ.cli", *args, str(path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 2, res.stderr
    lines = path.read_text().splitlines()
    typo = next(i for i, t in enumerate(lines) if "bandwith_hz" in t)
    line = max(i + 1 for i, t in enumerate(lines[: typo + 1]) if "params:" in t)
    assert f"slave.yaml:{line} robot.drivers[0].params: " in res.stderr
    assert "unknown params ['bandwith_hz']" in res.stderr and "bandwidth_hz" in res.stderr
    assert "Traceback" not in res.stderr
