"""tools/profiled.py: a profile's own times grouped by owner (the CiA 402 slave's profile in
docs/BENCHMARKS.md). Functions compiled under the file names of python-can's udp_multicast and
of the driver stand in for them; what is checked is where each function's time goes, and that
no time is lost or counted twice."""

from __future__ import annotations

import cProfile
import json
import math
import pstats
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

from .tooling import ROOT, load_tool

profiled = load_tool("profiled")

UDP = "/v/lib/python3.11/site-packages/can/interfaces/udp_multicast/bus.py"
PACK = "/v/lib/python3.11/site-packages/can/interfaces/udp_multicast/utils.py"
DRIVER = "/w/occ/drivers/cia402.py"
LOOP = "/w/occ/core/robot.py"


def compiled(path: str, source: str) -> dict[str, Any]:
    ns: dict[str, Any] = {}
    exec(compile(source, path, "exec"), ns)  # noqa: S102 - the test's own source
    return ns


def test_owners_by_file_and_builtins_by_their_callers() -> None:
    udp = compiled(UDP, "def recv(n):\n    return sorted(range(n, 0, -1))\n")
    pack = compiled(PACK, "def unpack(n):\n    return sorted(range(n))\n")
    drv = compiled(
        DRIVER,
        "def read(recv, unpack):\n"  # no comprehension, no built-in: its own time only
        "    for _ in range(40):\n"
        "        recv(300)\n"
        "        unpack(300)\n",
    )
    loop = compiled(LOOP, "def tick(read, recv, unpack):\n    return read(recv, unpack)\n")
    prof = cProfile.Profile()
    prof.runcall(loop["tick"], drv["read"], udp["recv"], pack["unpack"])
    stats = pstats.Stats(prof).stats  # type: ignore[attr-defined]
    groups = profiled.owners(stats)
    assert math.isclose(sum(groups.values()), sum(row[2] for row in stats.values()))
    assert set(groups) >= {"udp_multicast socket", "udp_multicast msgpack", "our cia402 driver"}
    # ``sorted`` (a built-in) is called from recv and unpack only: all its time is theirs
    sort = next(k for k in stats if "sorted" in k[2])
    mine = {
        "udp_multicast socket": stats[(UDP, 1, "recv")][2],
        "udp_multicast msgpack": stats[(PACK, 1, "unpack")][2],
    }
    by_caller = {c[0]: v[2] for c, v in stats[sort][4].items()}
    assert math.isclose(
        groups["udp_multicast socket"] + groups["udp_multicast msgpack"],
        mine["udp_multicast socket"] + mine["udp_multicast msgpack"] + stats[sort][2],
    )
    assert math.isclose(groups["udp_multicast socket"],
                        mine["udp_multicast socket"] + by_caller[UDP])  # fmt: skip
    assert math.isclose(groups["our cia402 driver"], stats[(DRIVER, 1, "read")][2])


def test_owner_of_paths() -> None:
    assert profiled.owner_of("/v/site-packages/canopen/network.py") == "canopen"
    assert profiled.owner_of("/v/site-packages/can/message.py") == "python-can Message"
    assert profiled.owner_of("/v/site-packages/can/bus.py") == "python-can core"
    assert profiled.owner_of("/w/occ/drivers/cia402_setup.py") == "our cia402 driver"
    assert profiled.owner_of("/w/occ/drivers/checks.py") == "driver base"
    assert profiled.owner_of("/w/occ/clock.py") == "loop wait"
    assert profiled.owner_of("/w/igtl/wire.py") == profiled.REST
    assert profiled.owner_of("~") is None
    assert profiled.owner_of("/usr/lib/python3.11/logging/__init__.py") is None


def test_the_wrapper_profiles_between_two_signals_and_summarises(tmp_path: Path) -> None:
    """A module run under the wrapper: nothing written before the second SIGUSR1; then the
    statistics, with the main thread's seconds, and :func:`summary` of them."""
    mod = tmp_path / "busy.py"
    mod.write_text(
        "import os, signal, sys\n"
        "print('ready', flush=True)\n"
        "sys.stdin.readline()\n"  # the first signal has been sent
        "sum(sorted(range(100000)))\n"
        "os.kill(os.getpid(), signal.SIGUSR1)\n"
        "print(sys.argv[1:], flush=True)\n"
    )
    out = tmp_path / "busy.prof"
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "tools" / "profiled.py"), str(out), "-m", "busy", "x"],
        cwd=tmp_path, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        env={"PYTHONPATH": str(tmp_path)},
    )  # fmt: skip
    assert proc.stdout is not None and proc.stdin is not None
    assert proc.stdout.readline() == "ready\n"
    assert not out.exists()
    proc.send_signal(signal.SIGUSR1)
    proc.stdin.write("go\n")
    proc.stdin.flush()
    assert proc.stdout.readline() == "['x']\n"
    assert proc.wait(timeout=60) == 0
    times = json.loads(Path(str(out) + ".json").read_text())
    assert set(times) == {"wall_s", "main_thread_cpu_s"}
    got = profiled.summary(out, ticks_of=lambda stats: 1)
    assert got["ticks"] == 1 and got["driver_read_us_per_tick"] is None
    assert got["busy_s"] > 0.0 and "rest of the loop thread" in got["owners_s"]
    bad = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "profiled.py"), "only.prof"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert bad.returncode == 2 and "usage" in bad.stderr
