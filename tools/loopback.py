"""Helpers for running the daemons on loopback: free ports, waiting for a listener, and copies
of the master/slave configurations moved to free ports (tests, benchmarks, soaks, the demo)."""

from __future__ import annotations

import signal
import socket
import subprocess
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[1]


_HANDED_OUT: set[int] = set()


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port on 127.0.0.1 that was free a moment ago (TCP by default, UDP with SOCK_DGRAM),
    never one this process handed out before: the kernel may give the same ephemeral port to
    two binds in a row once the first is closed (a pair's config once got it twice)."""
    for _ in range(100):
        with socket.socket(socket.AF_INET, kind) as s:
            s.bind(("127.0.0.1", 0))
            port = int(s.getsockname()[1])
        if port not in _HANDED_OUT:
            _HANDED_OUT.add(port)
            return port
    raise OSError("no free port on 127.0.0.1 that was not handed out already")


def wait_port(
    port: int,
    timeout: float = 20.0,
    proc: subprocess.Popen[bytes] | None = None,
    host: str = "127.0.0.1",
) -> bool:
    """True once a TCP listener accepts on host:port; False on timeout or if ``proc`` exits."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc is not None and proc.poll() is not None:
            return False
        with socket.socket() as s:
            s.settimeout(0.2)
            if s.connect_ex((host, port)) == 0:
                return True
        time.sleep(0.05)
    return False


def pair_configs(
    slave_cfg: Path = ROOT / "configs" / "slave.yaml",
    master_cfg: Path = ROOT / "configs" / "master.yaml",
) -> tuple[dict[str, Any], dict[str, Any], dict[str, int]]:
    """The two configurations (as YAML data) with every listening port moved to a free one and
    the master's UDP output aimed at the slave's UDP input. Returns (slave, master, ports) with
    ports ``slave_tcp`` (the slave's 3D Slicer interface, a viewer), ``slave_op`` (its operator
    interface: commands), ``slave_udp``, ``master_tcp``."""
    ports = {
        "slave_tcp": free_port(),
        "slave_op": free_port(),
        "slave_udp": free_port(socket.SOCK_DGRAM),
        "master_tcp": free_port(),
    }
    slave = yaml.safe_load(slave_cfg.read_text())
    master = yaml.safe_load(master_cfg.read_text())
    for itf in slave["interfaces"]:
        if itf["transport"] != "tcp-server":
            itf["port"] = ports["slave_udp"]
        else:
            itf["port"] = ports["slave_op"] if itf.get("role") == "operator" else ports["slave_tcp"]
    for itf in master["interfaces"]:
        if itf["transport"] == "tcp-server":
            itf["port"] = ports["master_tcp"]
        else:
            itf["remote"] = f"127.0.0.1:{ports['slave_udp']}"
    return slave, master, ports


def collab_configs(
    config_dir: Path = ROOT / "configs" / "collab",
) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any], dict[str, int]]:
    """The collaborative trio (configs/collab: slave, mentor, trainee) with every listening
    port moved to a free one and each master's stream aimed at its slave interface. Returns
    (slave, mentor, trainee, ports); ports are named after the slave's interfaces (``slicer``,
    ``operator``, ``mentor_desk``, ``trainee_desk``, ``mentor``, ``trainee``: UDP) and the
    masters' operator ports (``mentor_op``, ``trainee_op``)."""
    slave = yaml.safe_load((config_dir / "slave.yaml").read_text())
    masters = {
        n: yaml.safe_load((config_dir / f"{n}.yaml").read_text()) for n in ("mentor", "trainee")
    }
    ports: dict[str, int] = {}
    for itf in slave["interfaces"]:
        kind = socket.SOCK_DGRAM if itf["transport"] == "udp" else socket.SOCK_STREAM
        itf["port"] = ports[itf["name"]] = free_port(kind)
    for name, cfg in masters.items():
        for itf in cfg["interfaces"]:
            if itf["transport"] == "tcp-server":
                itf["port"] = ports[f"{name}_op"] = free_port()
            else:
                itf["remote"] = f"127.0.0.1:{ports[name]}"
    return slave, masters["mentor"], masters["trainee"], ports


def write_yaml(path: Path, data: dict[str, Any]) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def stop_processes(procs: Iterable[subprocess.Popen[bytes]], timeout: float = 10.0) -> None:
    """Stop daemons as an operator would: SIGINT to all (they stop their drivers and write their
    statistics), then wait for each; kill one that has not exited after ``timeout`` seconds."""
    procs = list(procs)
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    for proc in procs:
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5.0)
