"""The OCC paper's virtual-fixture motion test, reproduced in simulated time (issue 10).

Arata et al. (IJCARS 2010) test their fixture with the operator's motion on the master
(X = 50 mm sine, Y = 50 mm cosine, 0.1 Hz, Z constant), an accessible sphere of 200 mm
diameter with stiffness 1 N/mm, and 10:1 motion scaling: the trajectory stayed inside and at
most 10 N was displayed. Here the shipped pair runs on one :class:`~occ.clock.SimClock` with
in-process interfaces (:class:`occ_testkit.testing.SimRobot`): the master (``configs/master.yaml``:
a simulated hand that intends the paper's motion and yields to the displayed force) streams its
measured handle to the slave (``configs/slave.yaml``), which follows at 10:1 and sends its
measured tip back (the return channel, ``SlaveTip``): the force is computed where the slave's
tool is. The fixture goes to the master as a VFIXTURE in the patient frame (the frame of the
``Tip`` 3D Slicer shows; the paper's meaning: accessible): the sphere the paper draws on the
master's workspace, placed where the slave's tip is for that handle position (its centre and
radius at 10:1), as a 3D Slicer user places it on the ``Tip``.

Two cases (``--case``): ``paper`` (the paper's sphere, centred on the motion: it stays
inside, no force) and ``small`` (a sphere of 50 mm radius 10 mm off the motion's centre, which
the intended motion leaves by up to 10 mm: the handle is pushed back and the slave's path
bends inward). Each run writes a plot (XY paths and the force) and prints the figures::

    python tools/fixture_motion.py --case paper --out docs/fixture_paper.png
    python tools/fixture_motion.py --case small --out docs/fixture_small.png
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import igtl
from occ.clock import SimClock
from occ_testkit.testing import SimRobot

ROOT = Path(__file__).resolve().parents[1]

#: relative to the workspace centre (mm): (x, y, z, radius)
CASES = {
    "paper": (0.0, 0.0, 20.0, 100.0),
    "small": (-10.0, 0.0, 20.0, 50.0),
}


@dataclass
class Result:
    """Samples every ``every`` ticks. Master positions in the master's frame relative to its
    workspace centre (mm); slave positions mapped back onto the master's scale (the slave's
    displacement since it re-indexed, divided by the scale, plus the master's reference) so
    both paths share one plot and one sphere."""

    sphere: tuple[float, float, float, float] | None
    stiffness: float
    t: list[float] = field(default_factory=list)
    intended: list[tuple[float, float, float]] = field(default_factory=list)
    handle: list[tuple[float, float, float]] = field(default_factory=list)
    slave: list[tuple[float, float, float]] = field(default_factory=list)
    force: list[float] = field(default_factory=list)
    peak_force_n: float = 0.0
    master_state: str = ""
    slave_state: str = ""

    def outside_mm(self, path: list[tuple[float, float, float]]) -> float:
        """How far the path gets outside the sphere (mm; <= 0: it stays inside)."""
        assert self.sphere is not None
        c, r = self.sphere[:3], self.sphere[3]
        return max(math.dist(p, c) - r for p in path)

    def max_radius(self, path: list[tuple[float, float, float]]) -> float:
        assert self.sphere is not None
        return max(math.dist(p, self.sphere[:3]) for p in path)


def run(
    sphere: tuple[float, float, float, float] | None,
    *,
    stiffness: float = 1.0,
    seconds: float = 10.0,
    every: int = 10,
) -> Result:
    """One run of the pair with ``sphere`` (relative to the workspace centre, mm; None: no
    fixture) for ``seconds`` of simulated time after both are RUNNING."""
    clock = SimClock()
    master = SimRobot(ROOT / "configs" / "master.yaml", clock=clock)
    slave = SimRobot(ROOT / "configs" / "slave.yaml", clock=clock)
    try:
        box: dict[str, Any] = {}
        # the stream master -> slave and the return channel slave -> master, both ways
        m_link = master.peer("slave", on_message=lambda m: box["link"].send(m))
        link = slave.peer("master", address=("127.0.0.1", 40000), on_message=m_link.send)
        box["link"] = link
        m_op = master.peer("operator", address=("127.0.0.1", 41000))
        s_op = slave.peer("operator", address=("127.0.0.1", 41001))
        ctrl = master.robot.controller.controllers[0]
        scontrol = slave.robot.controller.controllers[0]
        origin = [v * 1000.0 for v in ctrl.origin]
        hand = master.robot.hardware.drivers[0]

        def both(n: int) -> None:
            for _ in range(n):
                master.tick()
                slave.tick()

        for op in (s_op, m_op):
            for name in ("Enable", "Run"):
                op.send_command(name)
                both(1)
        both(1)  # the slave re-indexes on the master's first run=1 sample
        if sphere is not None:
            # where the slave's tip is (patient mm) for the handle at the sphere's centre: the
            # slave's own mapping, base + slave_ref + scale (master - master_ref)
            assert scontrol.master_ref is not None and scontrol.slave_ref is not None
            base = slave.robot.data.base[:3, 3]
            centre = tuple(
                (b + sr + scontrol.scale * ((o + c) * 1e-3 - mr)) * 1000.0
                for b, sr, mr, o, c in zip(
                    base,
                    scontrol.slave_ref,
                    scontrol.master_ref,
                    origin,
                    sphere[:3],
                    strict=True,
                )
            )
            m_op.send(
                igtl.VirtualFixtureMessage(
                    hardness=stiffness,
                    spheres=((*centre, sphere[3] * scontrol.scale),),
                    device_name="Fixture",
                    header_version=2,
                    metadata={"MRMLNodeName": "AccessibleArea", "kind": "accessible"},
                )
            )
        res = Result(sphere, stiffness)
        scale = scontrol.scale
        for k in range(round(seconds / master.period)):
            both(1)
            if k % every:
                continue
            res.t.append(k * master.period)
            hx, hy, hz = (
                v * 1000.0 - o
                for v, o in zip(
                    master.robot.frame.tip_position(master.robot.data.q), origin, strict=True
                )
            )
            res.handle.append((hx, hy, hz))
            res.intended.append(tuple(v * 1000.0 for v in hand.intended()))  # type: ignore[arg-type]
            if scontrol.master_ref is not None and scontrol.slave_ref is not None:
                s = slave.robot.frame.tip_position(slave.robot.data.q)
                res.slave.append(
                    tuple(
                        (mr + (sv - sr) / scale) * 1000.0 - o
                        for sv, sr, mr, o in zip(
                            s, scontrol.slave_ref, scontrol.master_ref, origin, strict=True
                        )
                    )
                )  # type: ignore[arg-type]
            f = ctrl.fixtures.force_n
            res.force.append(math.sqrt(f[0] ** 2 + f[1] ** 2 + f[2] ** 2))
        res.peak_force_n = ctrl.fixtures.peak_force_n
        res.master_state = master.robot.state.value
        res.slave_state = slave.robot.state.value
        return res
    finally:
        master.close()
        slave.close()


def plot(res: Result, free: Result | None, out: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, axf) = plt.subplots(1, 2, figsize=(11, 5), gridspec_kw={"width_ratios": [1, 1.2]})
    if res.sphere is not None:
        cx, cy, _cz, r = res.sphere
        ax.add_patch(
            plt.Circle(
                (cx, cy),
                r,
                fill=False,
                ls="--",
                color="grey",
                label="accessible sphere (z section)",
            )
        )
    ax.plot(
        *zip(*[(p[0], p[1]) for p in res.intended], strict=True),
        color="0.6",
        lw=1,
        label="intended (the hand's motion)",
    )
    ax.plot(
        *zip(*[(p[0], p[1]) for p in res.handle], strict=True),
        color="C0",
        lw=1.5,
        label="master handle (measured)",
    )
    if res.slave:
        ax.plot(
            *zip(*[(p[0], p[1]) for p in res.slave], strict=True),
            color="C3",
            lw=1,
            ls=":",
            label="slave tip / scale",
        )
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm, master frame)")
    ax.set_ylabel("y (mm)")
    ax.legend(loc="lower left", fontsize=8)
    ax.set_title(title, fontsize=10)
    axf.plot(res.t, res.force, color="C1", label="displayed force |F|")
    axf.axhline(10.0, color="grey", ls="--", lw=0.8, label="clamp 10 N")
    axf.set_xlabel("t (s)")
    axf.set_ylabel("N")
    axf.set_ylim(bottom=0.0, top=max(11.0, max(res.force) * 1.1))
    if free is not None:
        axr = axf.twinx()
        c = res.sphere[:3] if res.sphere else (0.0, 0.0, 20.0)
        axr.plot(
            free.t,
            [math.dist(p, c) for p in free.slave],
            color="0.6",
            lw=1,
            label="slave radius, no fixture (mm)",
        )
        axr.plot(
            res.t[: len(res.slave)],
            [math.dist(p, c) for p in res.slave],
            color="C3",
            lw=1,
            label="slave radius, fixture (mm)",
        )
        axr.set_ylabel("distance from the sphere's centre (mm, master scale)")
        axr.legend(loc="upper right", fontsize=8)
    axf.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--case", choices=sorted(CASES), default="paper")
    p.add_argument("--seconds", type=float, default=10.0, help="simulated seconds (10: one lap)")
    p.add_argument("--stiffness", type=float, default=1.0, help="N/mm (the paper: 1)")
    p.add_argument("--out", type=Path, default=None, help="plot file (PNG)")
    args = p.parse_args(argv)
    sphere = CASES[args.case]
    res = run(sphere, stiffness=args.stiffness, seconds=args.seconds)
    free = run(sphere, stiffness=0.0, seconds=args.seconds) if args.case == "small" else None
    print(
        f"case {args.case}: sphere (rel. centre) {sphere[:3]} r {sphere[3]} mm, "
        f"{args.stiffness} N/mm, {args.seconds} s"
    )
    print(f"  peak force {res.peak_force_n:.2f} N")
    for name, path in (
        ("intended", res.intended),
        ("handle", res.handle),
        ("slave/scale", res.slave),
    ):
        print(
            f"  {name:12s} max distance from centre {res.max_radius(path):7.2f} mm "
            f"(outside by {res.outside_mm(path):6.2f} mm)"
        )
    if free is not None:
        print(
            f"  without the fixture: handle {free.max_radius(free.handle):.2f} mm, "
            f"slave/scale {free.max_radius(free.slave):.2f} mm"
        )
    print(f"  states: master {res.master_state}, slave {res.slave_state}")
    if args.out is not None:
        title = (
            f"OCC motion test: sphere r {sphere[3]:.0f} mm, {args.stiffness:g} N/mm, 10:1"
            f" (peak {res.peak_force_n:.1f} N)"
        )
        plot(res, free, args.out, title)
        print(f"  plot: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
