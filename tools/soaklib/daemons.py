"""The daemons of a real soak: their configs on free ports, their processes."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

from loopback import free_port, stop_processes

from .common import ROOT


def write_configs(out: Path, slave_cfg: Path, master_cfg: Path) -> dict[str, Any]:
    """Temporary copies with every port moved to a free one and the master sent to the proxy."""
    import yaml

    slave = yaml.safe_load(slave_cfg.read_text())
    master = yaml.safe_load(master_cfg.read_text())
    loss_input = slave["safety"]["loss"]["input"]
    ports: dict[str, Any] = {}
    for cfg in (slave, master):
        frame = cfg["robot"].get("frame", {})
        if frame.get("urdf"):
            base = slave_cfg.parent if cfg is slave else master_cfg.parent
            frame["urdf"] = str((base / frame["urdf"]).resolve())
        if cfg.get("recording"):
            cfg["recording"]["path"] = None
    for iface in slave["interfaces"]:
        if iface["transport"] == "tcp-server":
            key = "slave_op" if iface.get("role") == "operator" else "slave_tcp"
            iface["port"] = ports.setdefault(key, free_port(socket.SOCK_STREAM))
            iface["host"] = "127.0.0.1"
        elif iface["name"] == loss_input:
            iface["port"] = ports["slave_udp"] = free_port(socket.SOCK_DGRAM)
            iface["host"] = "127.0.0.1"
    for iface in master["interfaces"]:
        if iface["transport"] == "tcp-server":
            iface["port"] = ports.setdefault("master_tcp", free_port(socket.SOCK_STREAM))
            iface["host"] = "127.0.0.1"
        elif iface["transport"] == "udp" and iface.get("remote"):
            iface["port"] = 0
            iface["host"] = "127.0.0.1"
            ports["master_udp_iface"] = iface["name"]
    if "slave_udp" not in ports or "master_udp_iface" not in ports or "slave_op" not in ports:
        raise SystemExit(
            "soak real: could not find the slave's loss input / the master's UDP output "
            "/ the slave's operator interface in the configs"
        )
    ports["slave_yaml"] = str(out / "slave.yaml")
    ports["master_yaml"] = str(out / "master.yaml")
    ports["_slave"] = slave
    ports["_master"] = master
    return ports


def set_master_remote(ports: dict[str, Any], proxy_port: int) -> None:
    import yaml

    master = ports.pop("_master")
    slave = ports.pop("_slave")
    for iface in master["interfaces"]:
        if iface["name"] == ports["master_udp_iface"]:
            iface["remote"] = f"127.0.0.1:{proxy_port}"
    Path(ports["slave_yaml"]).write_text(yaml.safe_dump(slave, sort_keys=False))
    Path(ports["master_yaml"]).write_text(yaml.safe_dump(master, sort_keys=False))


def start_occd(
    config: str,
    stats: Path,
    log: Path,
    duration: float,
    start: str = "running",
    extra: list[str] | None = None,
) -> subprocess.Popen[bytes]:
    cmd = [
        sys.executable,
        "-m",
        "occ.cli",
        config,
        "--start",
        start,
        "--stats",
        str(stats),
        "--log-level",
        "WARNING",
        "--duration",
        f"{duration:.1f}",
        *(extra or []),
    ]
    fh = open(log, "wb")  # noqa: SIM115 - closed by the caller via proc.stderr_file
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT)
    proc.log_file = fh  # type: ignore[attr-defined]
    return proc


def stop_proc(proc: subprocess.Popen[bytes], timeout: float = 10.0) -> int | None:
    stop_processes([proc], timeout)
    fh = getattr(proc, "log_file", None)
    if fh is not None:
        fh.close()
    return proc.returncode
