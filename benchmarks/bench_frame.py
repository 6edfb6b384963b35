"""Time the per-tick kinematics and driver paths (run: .venv/bin/python benchmarks/bench_frame.py).

Prints one table: median of ``repeat`` timeit runs, in microseconds per call. The 1 kHz loop
has 1000 us per tick for everything, so these numbers say how much of it kinematics and a
simulated driver take.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import timeit
from collections.abc import Callable

import numpy as np
import pinocchio as pin

from occ.drivers.sim import SimDriver
from occ.joint import Joint, JointLimits, PIDGains
from occ.kinematics.frame import Frame


def per_call_us(func: Callable[[], object], number: int, repeat: int) -> float:
    times = timeit.repeat(func, number=number, repeat=repeat)
    return statistics.median(times) / number * 1e6


def sim_tick(interface: str) -> Callable[[], None]:
    gains = PIDGains(kp=40.0, ki=5.0, kd=1.0) if interface == "effort" else None
    joints = [
        Joint(name, "revolute", JointLimits(-1.0, 1.0, 10.0, 20.0), gains=gains)
        for name in ("yaw", "pitch", "insertion")
    ]
    driver = SimDriver("bench", joints, {"command_interface": interface})
    driver.configure()
    driver.read(0.0)
    driver.activate()
    setpoints = [0.1, -0.1, 0.05]
    clock = [0.0]

    def tick() -> None:
        clock[0] += 0.001
        now = clock[0]
        driver.read(now)
        driver.write(setpoints, now)

    tick.driver = driver  # type: ignore[attr-defined]
    return tick


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--number", type=int, default=20000)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()

    slave = Frame.builtin("occ_slave")
    master = Frame.builtin("master3")
    q = np.array([0.3, -0.4, 0.07])
    target = slave.position(q)
    qm = np.array([0.02, -0.03, 0.05])
    target_m = master.position(qm)

    rows = [
        ("occ_slave fk (4x4)", lambda: slave.fk(q)),
        ("occ_slave position (3,)", lambda: slave.position(q)),
        ("occ_slave jacobian", lambda: slave.jacobian(q)),
        ("occ_slave ik analytic", lambda: slave.ik(target)),
        ("occ_slave dls_step", lambda: slave.dls_step(q, target)),
        ("occ_slave ik dls (full solve)", lambda: slave.ik(target, method="dls")),
        ("master3 fk (4x4)", lambda: master.fk(qm)),
        ("master3 ik analytic", lambda: master.ik(target_m)),
        ("sim 3 joints read+write (position)", sim_tick("position")),
        ("sim 3 joints read+write (effort+PID)", sim_tick("effort")),
    ]
    versions = f"pinocchio {pin.__version__}, numpy {np.__version__}"
    print(f"python {platform.python_version()}, {versions}")
    print(f"median of {args.repeat} runs x {args.number} calls")
    print(f"{'operation':40s} {'us/call':>10s}")
    print("-" * 51)
    for label, func in rows:
        number = args.number if "full solve" not in label else max(1, args.number // 20)
        print(f"{label:40s} {per_call_us(func, number, args.repeat):10.2f}")
        driver = getattr(func, "driver", None)
        if driver is not None:
            driver.shutdown()


if __name__ == "__main__":
    main()
