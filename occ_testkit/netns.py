"""Private network namespaces for tests and tools: nothing started in one can reach eth0.

A namespace stands for a host of its own: the ROS 2 tests run the daemon, the bridge and a
ROS 2 node in one (tests/ros2), and ``tools/two_machines.py`` joins two with a veth pair
(:meth:`Netns.link`), a console PC and a robot PC with addresses that exist only there.

:class:`Netns` starts a holder process in a new network namespace (``unshare -n``, loopback
up) and runs commands in that namespace (``nsenter -n -t HOLDER``), each a subprocess the
test can stop and start again while the namespace (and the other processes in it) stays. Needs
root (CI and the developers' machines run as root) and util-linux's unshare/nsenter and
iproute2's ip. :func:`available` says why not, when not.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO


def available() -> str | None:
    """None when a namespace can be made here, else the reason it cannot."""
    if os.geteuid() != 0:
        return "network namespaces need root (unshare -n)"
    for tool in ("unshare", "nsenter", "ip"):
        if shutil.which(tool) is None:
            return f"{tool} not found (util-linux, iproute2)"
    return None


class Netns:
    """A network namespace with loopback up, kept alive by a holder process (module doc)."""

    def __init__(self, setup: str = "") -> None:
        # the holder brings lo up (and runs ``setup``, shell commands) then waits to be killed;
        # "ready" on stdout says the namespace is configured
        script = f"ip link set lo up && {setup or 'true'} && echo ready && exec sleep 86400"
        self.holder = subprocess.Popen(
            ["unshare", "-n", "sh", "-c", script],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert self.holder.stdout is not None
        line = self.holder.stdout.readline().strip()
        if line != "ready":
            err = self.holder.stderr.read() if self.holder.stderr else ""
            self.holder.kill()
            raise RuntimeError(f"network namespace setup failed: {line!r} {err}")
        self.procs: list[subprocess.Popen[Any]] = []

    def prefix(self) -> list[str]:
        return ["nsenter", "-n", "-t", str(self.holder.pid)]

    def popen(
        self,
        cmd: Sequence[str],
        *,
        cwd: Path | None = None,
        env: dict[str, str] | None = None,
        stdin: int | None = subprocess.DEVNULL,
        stdout: int | TextIO | None = subprocess.DEVNULL,
        stderr: int | TextIO | None = subprocess.PIPE,
        text: bool = False,
    ) -> subprocess.Popen[Any]:
        """``cmd`` in the namespace (stopped with the namespace at the latest)."""
        proc = subprocess.Popen(
            [*self.prefix(), *cmd],
            cwd=cwd,
            env=env,
            stdin=stdin,
            stdout=stdout,
            stderr=stderr,
            text=text,
            # nsenter execs the command: the pid is the command's, signals reach it
        )
        self.procs.append(proc)
        return proc

    def run(self, cmd: Sequence[str], timeout: float = 10.0) -> str:
        """``cmd`` in the namespace to completion; its stdout."""
        out = subprocess.run(
            [*self.prefix(), *cmd], capture_output=True, text=True, timeout=timeout, check=True
        )
        return out.stdout

    @staticmethod
    def stop(proc: subprocess.Popen[Any], timeout: float = 5.0) -> None:
        """SIGINT (the daemons and the bridge exit cleanly on it), then SIGKILL."""
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout)
        for pipe in (proc.stdin, proc.stdout, proc.stderr):
            if pipe is not None:
                pipe.close()

    def close(self) -> None:
        for proc in reversed(self.procs):
            self.stop(proc)
        self.holder.kill()
        self.holder.wait(5.0)
        for pipe in (self.holder.stdout, self.holder.stderr):
            if pipe is not None:
                pipe.close()

    @property
    def pid(self) -> int:
        """The holder's pid: ``ip link set DEV netns PID`` moves an interface here."""
        return self.holder.pid

    def link(self, other: Netns, mine: str, theirs: str, name: str = "occ") -> tuple[str, str]:
        """Join this namespace and ``other`` with a veth pair (a cable between two hosts):
        ``mine`` and ``theirs`` are ``ADDRESS/PREFIX``. Returns the two interface names
        (``NAMEa`` here, ``NAMEb`` there); they vanish with the namespaces."""
        here, there = f"{name}a", f"{name}b"
        subprocess.run(
            ["ip", "link", "add", here, "netns", str(self.pid), "type", "veth",
             "peer", "name", there, "netns", str(other.pid)],
            check=True, capture_output=True, text=True,
        )  # fmt: skip
        for ns, dev, addr in ((self, here, mine), (other, there, theirs)):
            ns.run(["ip", "addr", "add", addr, "dev", dev])
            ns.run(["ip", "link", "set", dev, "up"])
        return here, there

    def __enter__(self) -> Netns:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
