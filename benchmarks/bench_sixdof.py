"""Benchmark: what the 6-DOF pose solve costs the UR5 slave's 1 kHz tick, in simulated time.

    python benchmarks/bench_sixdof.py                     # 3000 ticks a case, best of 3 rounds
    python benchmarks/bench_sixdof.py --ticks 5000 --rounds 5 --cases fast,servo-rcm

Cases (configs/ur5.yaml fed by configs/master6.yaml's 500 Hz stream, a SimPair on a SimClock;
the servo cases on a SlaveRig, a target every other tick):

- ``demo``: the shipped motion (0.1 Hz circle and gimbal): never slowed, one solve per sample.
- ``fast``: the gimbal at 2 Hz and 40 degrees about z: the wrist slowed to 0.9 of its limit on
  every tick, so a solve on every tick (the one between two samples too).
- ``rcm-fast``: ``orientation: rcm`` (the port 100 mm up the axis), the master's circle at 2 Hz:
  slowed on every tick; the first slowed step solved twice (the full pose, then the pose a share
  of the straight way on, through the port), the next ones once (the tip as far on as the last
  step went at the limits).
- ``servo-rcm``: ``mapping: absolute`` with ``orientation: rcm``, a servo target drawing a 20 mm
  circle at 1 Hz around the tip.
- ``servo-follow``: ``mapping: absolute`` with ``orientation: follow``, the same circle: one
  solve per new target, the joints stepped together on the ticks between.

For each: the slave's whole tick and its controller's update alone (the solves, with the
mapping around them), µs of thread CPU time per tick (mean, p50, p99, max over the ticks of the
best round by p99: not inflated by other processes taking the core; the tick's wall-time p99
beside it), garbage collection off while timing; and the pose
solves per tick (calls of the damped-least-squares solve) with their mean iterations, the share
of ticks slowed to the velocity limits, and ``speed``: the fastest joint's largest mean speed
over 20 ms as a share of its velocity limit (0.9 when slowed on every tick). The budget
is the 1 kHz loop: 1000 µs a tick for everything, on this 2-core machine (docs/BENCHMARKS.md).
"""

from __future__ import annotations

import argparse
import gc
import math
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from occ.core.assembly import build_hardware
from occ.core.loader import load_config
from occ_testkit.rigs import SlaveRig
from occ_testkit.testing import SimPair

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
CASES = ("demo", "fast", "rcm-fast", "servo-rcm", "servo-follow")


def port_mm() -> list[float]:
    """A port 100 mm up the UR5's tool axis from its tip at home (mm)."""
    joints, frame, _ = build_hardware(load_config(CONFIGS / "ur5.yaml").robot)
    home = np.asarray(frame.fk([j.home for j in joints]))
    return ((home[:3, 3] - 0.1 * home[:3, 2]) * 1e3).tolist()


class Case:
    """One case built and warmed: ``tick()`` runs one slave tick (and what feeds it)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.k = 0
        if name.startswith("servo"):
            orientation = name.split("-")[1]
            self.rig = SlaveRig(
                CONFIGS / "ur5.yaml",
                params={"mapping": "absolute", "orientation": orientation,
                        "rcm_mm": port_mm(), "phase_lock_us": None},
            )  # fmt: skip
            self.rig.running()
            self.robot = self.rig.robot
            self.centre = self.rig.world_tip_mm()
            self._tick: Callable[[], None] = self._servo_tick
        else:
            master: dict[str, Any] = {}
            slave: dict[str, Any] | None = None
            if name == "fast":
                master = {"frequency_hz": 2.0, "orientation_amplitude_deg": [0.0, 0.0, 40.0]}
            elif name == "rcm-fast":
                master = {"frequency_hz": 2.0}
                slave = {"orientation": "rcm", "rcm_mm": port_mm()}
            self.pair = SimPair(CONFIGS / "master6.yaml", CONFIGS / "ur5.yaml",
                                master_params=master, slave_params=slave)  # fmt: skip
            self.pair.start()
            self.robot = self.pair.slave.robot
            self._tick = self._pair_tick
        self.ctl: Any = self.robot.controller.controllers[0]
        self.frame = self.robot.frame
        self.solves = 0
        self.iterations = 0
        solve_ik = self.frame.solve_ik

        def counted(*args: Any, **kw: Any) -> Any:
            res = solve_ik(*args, **kw)
            self.solves += 1
            self.iterations += res.iterations
            return res

        self.frame.solve_ik = counted
        self.update_ns: list[int] = []
        update = self.robot.controller.update

        def timed(now: float, current: Any) -> Any:
            t0 = time.thread_time_ns()
            out = update(now, current)
            self.update_ns.append(time.thread_time_ns() - t0)
            return out

        self.robot.controller.update = timed  # type: ignore[method-assign]
        self.tick_ns: list[int] = []
        self.wall_ns: list[int] = []
        robot_tick = self.robot.tick

        def timed_tick(now: float, k: int) -> Any:
            w0, t0 = time.perf_counter_ns(), time.thread_time_ns()
            out = robot_tick(now, k)
            self.tick_ns.append(time.thread_time_ns() - t0)
            self.wall_ns.append(time.perf_counter_ns() - w0)
            return out

        self.robot.tick = timed_tick  # type: ignore[method-assign]
        for _ in range(500):  # warm: past the start and its re-entry
            self._tick()

    def _pair_tick(self) -> None:
        self.pair.step(1)

    def _servo_tick(self) -> None:
        a = 2.0 * math.pi * self.k * 1e-3
        self.k += 1
        self.rig.target = (
            self.centre + [10.0 * math.sin(a), 10.0 * (1.0 - math.cos(a)), 0.0]
        ).tolist()
        self.rig.step(1)

    def run(self, ticks: int, sleep_s: float) -> dict[str, float]:
        self.update_ns.clear()
        self.tick_ns.clear()
        self.wall_ns.clear()
        self.solves = self.iterations = 0
        limited = self.ctl.rate_limited
        gc.collect()
        gc.disable()
        try:
            written = []
            for _ in range(ticks):
                if sleep_s > 0.0:
                    time.sleep(sleep_s)
                self._tick()
                written.append(list(self.robot.data.setpoint))
        finally:
            gc.enable()
        tick = np.array(self.tick_ns) / 1e3
        upd = np.array(self.update_ns) / 1e3
        assert self.robot.state.name == "RUNNING", self.robot.state
        # the fastest joint's mean speed over 20 ms, as a share of its velocity limit
        q = np.array(written)
        limits = np.array([j.limits.velocity for j in self.robot.joints])
        share = np.abs(q[20:] - q[:-20]) / (20 * 1e-3) / limits
        return {
            "tick_p50": float(np.percentile(tick, 50)),
            "tick_p99": float(np.percentile(tick, 99)),
            "tick_max": float(tick.max()),
            "update_p50": float(np.percentile(upd, 50)),
            "update_p99": float(np.percentile(upd, 99)),
            "update_max": float(upd.max()),
            "tick_mean": float(tick.mean()),
            "wall_p99": float(np.percentile(np.array(self.wall_ns) / 1e3, 99)),
            "solves": self.solves / ticks,
            "iterations": self.iterations / max(self.solves, 1),
            "slowed": (self.ctl.rate_limited - limited) / ticks,
            "speed": float(share.max()),
        }

    def close(self) -> None:
        if hasattr(self, "pair"):
            self.pair.close()
        else:
            self.rig.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ticks", type=int, default=3000)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument(
        "--sleep-us",
        type=float,
        default=0.0,
        help="sleep between ticks, as the real loop does (colder caches: what a daemon pays)",
    )
    args = parser.parse_args()
    print(
        f"{args.ticks} ticks a case, best of {args.rounds} rounds by tick p99 (µs), "
        f"sleep {args.sleep_us:g} µs between ticks"
    )
    head = (
        "| case | tick mean | tick p50 | tick p99 | tick max | tick wall p99 | update p50 "
        "| update p99 | update max | solves/tick | iterations/solve | slowed ticks | speed |"
    )
    print(head)
    print("|" + "---|" * 13)
    for name in args.cases.split(","):
        case = Case(name)
        try:
            rounds = [case.run(args.ticks, args.sleep_us * 1e-6) for _ in range(args.rounds)]
        finally:
            case.close()
        best = min(rounds, key=lambda r: r["tick_p99"])
        print(
            f"| {name} | {best['tick_mean']:.0f} | {best['tick_p50']:.0f} "
            f"| {best['tick_p99']:.0f} | {best['tick_max']:.0f} | {best['wall_p99']:.0f} "
            f"| {best['update_p50']:.0f} | {best['update_p99']:.0f} | {best['update_max']:.0f} "
            f"| {best['solves']:.2f} | {best['iterations']:.1f} | {best['slowed']:.2f} "
            f"| {best['speed']:.3f} |"
        )
        p99s = [r["tick_p99"] for r in rounds]
        print(f"  (tick p99 of the rounds: {', '.join(f'{v:.0f}' for v in p99s)}; "
              f"median {statistics.median(p99s):.0f})")  # fmt: skip


if __name__ == "__main__":
    main()
