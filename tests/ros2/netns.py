"""A private network namespace for DDS tests: nothing a test starts in it can reach eth0.

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
import time
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

    def __enter__(self) -> Netns:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def wait_until(pred: Any, timeout: float, period: float = 0.05) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(period)
    return bool(pred())
