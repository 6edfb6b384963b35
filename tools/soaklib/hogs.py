"""CPU hogs beside a soak, and what a process has used of the CPU (Linux /proc)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path


def proc_cpu_s(pid: int) -> float | None:
    """CPU seconds (user + system) a process has used so far (Linux /proc), None if unknown."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


#: a busy loop at normal priority that ends by itself after argv[1] seconds
_HOG = (
    "import sys, time\n"
    "end = time.monotonic() + float(sys.argv[1])\n"
    "while time.monotonic() < end:\n"
    "    pass\n"
)


def start_hogs(n: int, bound_s: float) -> list[subprocess.Popen[bytes]]:
    """``n`` ordinary CPU hogs (pure Python busy loops, normal priority), bounded by ``bound_s``."""
    return [
        subprocess.Popen(
            [sys.executable, "-c", _HOG, f"{bound_s:.1f}"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for _ in range(n)
    ]


def stop_hogs(hogs: list[subprocess.Popen[bytes]], t_started: float) -> list[float | None]:
    """Kill the hogs; the share of a core each used while it ran (%), None if unknown."""
    wall = time.monotonic() - t_started
    shares = []
    for proc in hogs:
        cpu = proc_cpu_s(proc.pid) if proc.poll() is None else None
        shares.append(round(100.0 * cpu / wall, 1) if cpu is not None and wall > 0 else None)
        proc.kill()
        proc.wait(timeout=5.0)
    return shares


def loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "unknown"
