"""Run a Python module with cProfile on its main thread between two SIGUSR1s, and group what
the profile found by owner (tools/cia402_e2e.py ``--profile``: where the CiA 402 slave's CPU
goes, docs/BENCHMARKS.md, "CiA 402 drives")::

    python tools/profiled.py OUT.prof -m occ.cli configs/slave-cia402.yaml

The first SIGUSR1 starts the profiler on the main thread (the daemon's loop thread: occd runs
its loop there), the second stops it and writes ``OUT.prof`` (pstats) and ``OUT.prof.json``
(the wall and main-thread CPU seconds between the two). Only the main thread is profiled; the
daemon's other threads (IGTL transports, supervisor, logging) are not.

:func:`owners` groups the profile's own times: a function of a known package by its file
(python-can's ``udp_multicast`` socket I/O and its msgpack packing, python-can's core and its
``Message``, canopen, this project's CiA 402 driver, the driver base), a built-in or
standard-library function split over its callers by the time each spent in it, and
``time.sleep`` as the loop's wait. cProfile times every Python call, so Python-heavy code
weighs more under it than without: the figures are shares under the profiler.
"""

from __future__ import annotations

import collections
import json
import pstats
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

#: (path fragment, owner), first match wins
OWNERS: tuple[tuple[str, str], ...] = (
    ("can/interfaces/udp_multicast/utils.py", "udp_multicast msgpack"),
    ("/msgpack/", "udp_multicast msgpack"),
    ("can/interfaces/udp_multicast/", "udp_multicast socket"),
    ("can/message.py", "python-can Message"),
    ("/can/", "python-can core"),
    ("/canopen/", "canopen"),
    ("occ/drivers/cia402", "our cia402 driver"),
    ("occ/drivers/", "driver base"),
    ("occ/clock.py", "loop wait"),
)
WAIT = "loop wait"
REST = "rest of the loop thread"

Func = tuple[str, int, str]


def owner_of(path: str) -> str | None:
    """A file's owner; None for a built-in or the standard library (its callers decide)."""
    for fragment, owner in OWNERS:
        if fragment in path:
            return owner
    if path == "~" or ("site-packages" not in path and "/lib/python" in path):
        return None
    return REST


def owners(stats: dict[Func, Any]) -> dict[str, float]:
    """Own time (s) per owner, over every function of a ``pstats.Stats(...).stats``."""
    memo: dict[Func, dict[str, float]] = {}

    def split(func: Func, depth: int) -> dict[str, float]:
        if func in memo:
            return memo[func]
        path, _, name = func
        known = owner_of(path)
        if known is not None:
            out = {known: 1.0}
        elif name == "<built-in method time.sleep>":
            out = {WAIT: 1.0}
        else:
            callers = stats[func][4] if func in stats else {}
            if not callers or depth > 20:
                out = {REST: 1.0}
            else:
                # by the time each caller spent in it (a caller that took none: a hair)
                weights = {c: max(v[2], 1e-12) for c, v in callers.items()}
                total = sum(weights.values())
                acc: collections.Counter[str] = collections.Counter()
                for caller, w in weights.items():
                    for owner, f in split(caller, depth + 1).items():
                        acc[owner] += f * w / total
                out = dict(acc)
        memo[func] = out
        return out

    groups: collections.Counter[str] = collections.Counter()
    for func, row in stats.items():
        for owner, f in split(func, 0).items():
            groups[owner] += row[2] * f
    return dict(groups)


def summary(prof: Path, ticks_of: Callable[[dict[Func, Any]], int] | None = None) -> dict[str, Any]:
    """The profile ``prof`` (and its ``.json``) grouped: per owner the own time in s and in µs a
    tick (``ticks_of``: the ticks, from the stats; default: the calls of occ's Robot.tick),
    and the driver's read and write per tick, everything but the loop's wait."""
    stats: dict[Func, Any] = pstats.Stats(str(prof)).stats  # type: ignore[attr-defined]
    times = json.loads(Path(str(prof) + ".json").read_text())

    def calls(file_end: str, name: str) -> tuple[int, float]:
        rows = [v for k, v in stats.items() if k[0].endswith(file_end) and k[2] == name]
        return sum(r[1] for r in rows), sum(r[3] for r in rows)

    ticks = ticks_of(stats) if ticks_of else calls("occ/core/robot.py", "tick")[0]
    groups = owners(stats)
    busy = {k: v for k, v in groups.items() if k != WAIT}
    per_tick = 1e6 / ticks if ticks else 0.0
    read_n, read_s = calls("occ/drivers/base.py", "read")
    write_n, write_s = calls("occ/drivers/base.py", "write")
    return {
        **times,
        "ticks": ticks,
        "busy_s": round(sum(busy.values()), 3),
        "wait_s": round(groups.get(WAIT, 0.0), 3),
        "owners_s": {k: round(v, 3) for k, v in sorted(busy.items(), key=lambda kv: -kv[1])},
        "owners_us_per_tick": {
            k: round(v * per_tick, 1) for k, v in sorted(busy.items(), key=lambda kv: -kv[1])
        },
        "driver_read_us_per_tick": round(read_s * 1e6 / read_n, 1) if read_n else None,
        "driver_write_us_per_tick": round(write_s * 1e6 / write_n, 1) if write_n else None,
        "driver_writes": write_n,
    }


def main(argv: list[str]) -> int:
    """``OUT.prof -m MODULE ARGS...``: run MODULE as ``__main__``, profiled between SIGUSR1s."""
    import cProfile
    import runpy
    import signal
    import time

    if len(argv) < 3 or argv[1] != "-m":
        print("usage: python tools/profiled.py OUT.prof -m MODULE [ARGS...]", file=sys.stderr)
        return 2
    out, module, args = Path(argv[0]), argv[2], argv[3:]
    profiler = cProfile.Profile()
    state: dict[str, Any] = {"on": False}

    def toggle(signum: int, frame: Any) -> None:
        if not state["on"]:
            state.update(on=True, wall=time.monotonic(), cpu=time.thread_time())
            profiler.enable()
            return
        profiler.disable()
        state["on"] = False
        profiler.dump_stats(str(out))
        Path(str(out) + ".json").write_text(
            json.dumps(
                {
                    "wall_s": round(time.monotonic() - state["wall"], 3),
                    "main_thread_cpu_s": round(time.thread_time() - state["cpu"], 3),
                }
            )  # fmt: skip
        )

    signal.signal(signal.SIGUSR1, toggle)
    sys.argv = [module, *args]
    runpy.run_module(module, run_name="__main__", alter_sys=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
