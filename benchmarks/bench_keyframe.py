#!/usr/bin/env python3
"""What the keyframe controller costs the 1 kHz loop (issue 11).

1. ``update()`` per tick while a plan runs (simulated time, configs/keyframe.yaml): the joint
   plan of configs/keyframes/demo.yaml and the Cartesian one of entry_target.yaml (through the
   Frame's IK). Median and p99 µs over the whole run.
2. Planning and checking off the loop (``build_plan``, the planner thread's work): ms per plan
   and µs per tick of motion.
3. The real loop (RealClock, in-process interfaces) for ``--seconds`` idle, then as long again
   while an operator keeps the planner busy (the next KeyframePlan as soon as the last is
   answered): tick lateness and compute time. The planner thread gives the interpreter back
   every 16 samples; this shows what is left.
4. ``--port``: a laparoscopic tool through its port (issue 40; configs/ur5-port.yaml, the UR5
   with ``rcm_mm`` and configs/keyframes/ur5-port.yaml): ``update()`` per tick and
   ``build_plan`` for the same keyframes with the port and without it (``rcm_mm: null``: the
   tip's position only, the orientation left to the IK), and beside them the full-pose plan
   of configs/ur5-keyframe.yaml (orientations given, slerp/squad), linear and spline.

    python benchmarks/bench_keyframe.py --seconds 10
    python benchmarks/bench_keyframe.py --port      # part 4 only
"""

from __future__ import annotations

import argparse
import statistics
import sys
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

import igtl  # noqa: E402
from occ.clock import RealClock  # noqa: E402
from occ.controllers.keyframe import KeyframeController  # noqa: E402
from occ.controllers.keyframe.plan import PlanRequest, build_plan  # noqa: E402
from occ.core.loader import load_config  # noqa: E402
from occ.core.robot import build_robot  # noqa: E402
from occ_testkit.testing import SimPeer, SimRobot, inproc_config  # noqa: E402

CONFIG = ROOT / "configs" / "keyframe.yaml"
PORT_CONFIG = ROOT / "configs" / "ur5-port.yaml"


def command(name: str, cid: int, **args: str) -> igtl.Message:
    attrs = "".join(f' {k}="{v}"' for k, v in args.items())
    return igtl.CommandMessage(
        command_id=cid,
        command_name=name,
        command=f'<Command Name="{name}"{attrs}/>' if args else "",
        header_version=2,
    )


def update_cost(
    file: str | None, interpolation: str, cfg: Path = CONFIG, params: dict[str, Any] | None = None
) -> tuple[float, float, int, Any]:
    with SimRobot(cfg, params=params) as sim:
        (kf,) = sim.robot.controller.controllers
        assert isinstance(kf, KeyframeController)
        peer = sim.peer("slicer", on_message=lambda m: None)
        ids = iter(range(1, 1000))

        def send(name: str, **args: str) -> None:
            peer.send(command(name, next(ids), **args))
            sim.step(1)
            kf.wait_idle(60)

        if file is not None:
            send("KeyframeLoad", File=file)
        send("Enable")
        send("Run")
        send("KeyframePlan", Interpolation=interpolation)
        sim.step(200)
        plan = kf.plan
        assert plan is not None, kf.stats()
        times: list[float] = []
        original = kf.update

        def timed(now: float) -> Any:
            t0 = time.perf_counter()
            out = original(now)
            times.append(time.perf_counter() - t0)
            return out

        kf.update = timed  # type: ignore[method-assign]
        send("KeyframeAck", Plan=str(plan.id))
        sim.run_for(plan.traj.duration + 0.1)
        us = sorted(t * 1e6 for t in times[: plan.ticks])
        return statistics.median(us), us[int(0.99 * len(us))], len(us), plan


def plan_cost(
    kf_plan: Any,
    sim_cfg: Path,
    file: str | None,
    interpolation: str,
    params: dict[str, Any] | None = None,
) -> float:
    """ms of build_plan for the same request, median of 5."""
    with SimRobot(sim_cfg, params=params) as sim:
        (kf,) = sim.robot.controller.controllers
        assert isinstance(kf, KeyframeController)
        peer = sim.peer("slicer", on_message=lambda m: None)
        if file is not None:
            peer.send(command("KeyframeLoad", 1, File=file))
            sim.step(1)
            kf.wait_idle(60)
        captured: list[PlanRequest] = []
        import occ.controllers.keyframe.planner as module

        real = module.build_plan

        def capture(req: PlanRequest, frame: Any) -> Any:
            captured.append(req)
            return real(req, frame)

        module.build_plan = capture  # type: ignore[assignment]
        try:
            peer.send(command("KeyframePlan", 2, Interpolation=interpolation))
            sim.step(1)
            kf.wait_idle(60)
        finally:
            module.build_plan = real  # type: ignore[assignment]
        (req,) = captured
        frame = sim.robot.frame.copy()
        runs = []
        for _ in range(5):
            t0 = time.perf_counter()
            build_plan(req, frame)
            runs.append(time.perf_counter() - t0)
        return statistics.median(runs) * 1e3


def loop_run(seconds: float, busy: bool) -> dict[str, Any]:
    cfg = inproc_config(load_config(CONFIG))
    robot = build_robot(cfg, clock=RealClock(spin_us=0.0))
    robot.configure()
    robot.activate()
    answered = threading.Event()
    plans = [0]

    def on_message(m: igtl.Message) -> None:
        if m.message_type == "RTS_COMMAND" and m.command_name == "KeyframePlan":  # type: ignore[attr-defined]
            plans[0] += 1
            answered.set()

    peer = SimPeer(cfg.interface("slicer").channel or "", on_message=on_message)
    stop = threading.Event()

    def operator() -> None:
        cid = 1
        while not stop.is_set():
            answered.clear()
            peer.send(command("KeyframePlan", cid, Interpolation="spline"))
            cid += 1
            answered.wait(5.0)

    helper = threading.Thread(target=operator, daemon=True)
    if busy:
        helper.start()
    try:
        robot.run(duration=seconds)
    finally:
        stop.set()
        if busy:
            helper.join(10.0)
        robot.shutdown()
        peer.close()
    snap = robot.stats.snapshot()
    (kf,) = robot.controller.controllers
    return {
        "planner_fifo": kf.stats()["planner_fifo"],
        "late": snap["lateness_us"],
        "compute": snap["compute_us"],
        "late_over_1ms": snap["late_over_1ms"],
        "overruns": snap["overruns"],
        "plans": plans[0],
        "realtime": robot.loop.realtime_report,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument(
        "--pace",
        choices=("phase", "rest", "yield"),
        default="phase",
        help="how the planner shares the interpreter (occ.controllers.keyframe.pacer.Pacer)",
    )
    p.add_argument("--only-loop", action="store_true", help="part 3 only")
    p.add_argument("--port", action="store_true", help="part 4 only (a tool through its port)")
    args = p.parse_args(argv)
    import occ.controllers.keyframe.pacer as module

    module.PACE_MODE = args.pace
    if args.only_loop:
        return loop_part(args.seconds, args.pace)
    if args.port:
        return port_part()

    print("1. update() per tick while running (simulated time)")
    plans = {}
    for label, file, interp in (
        ("joint, demo.yaml, spline stop", None, "spline"),
        ("cartesian, entry_target.yaml, linear stop", "entry_target.yaml", "linear"),
    ):
        med, p99, n, plan = update_cost(file, interp)
        plans[label] = (file, interp, plan)
        print(f"   {label}: median {med:.1f} us, p99 {p99:.1f} us ({n} ticks)")
    print("2. build_plan (planner thread)")
    for label, (file, interp, plan) in plans.items():
        ms = plan_cost(plan, CONFIG, file, interp)
        print(
            f"   {label}: {ms:.1f} ms for {plan.ticks} ticks = {ms * 1e3 / plan.ticks:.1f} us/tick"
        )
    return loop_part(args.seconds, args.pace)


def port_part() -> int:
    print("4. a tool through its port (configs/ur5-port.yaml, 7 s of motion; simulated time)")
    cases: tuple[tuple[str, Path, dict[str, Any] | None], ...] = (
        ("port", PORT_CONFIG, None),
        ("no port (position IK)", PORT_CONFIG, {"rcm_mm": None}),
        ("orientations given (ur5-keyframe.yaml)", ROOT / "configs" / "ur5-keyframe.yaml", None),
    )
    for interp in ("linear", "spline"):
        for label, cfg, params in cases:
            med, p99, n, plan = update_cost(None, interp, cfg, params)
            ms = plan_cost(plan, cfg, None, interp, params)
            print(
                f"   {interp:6} {label}: update() median {med:.1f} us, p99 {p99:.1f} us "
                f"({n} ticks); build_plan {ms:.1f} ms = {ms * 1e3 / plan.ticks:.1f} us/tick"
            )
    return 0


def loop_part(seconds: float, pace: str) -> int:
    print(f"3. the real loop, {seconds:g} s each (pace {pace})")
    for busy in (False, True):
        r = loop_run(seconds, busy)
        late, comp = r["late"], r["compute"]
        print(
            f"   {'planner busy' if busy else 'idle        '}: late p50 {late['p50']:.0f} "
            f"p99 {late['p99']:.0f} p99.9 {late['p99_9']:.0f} max {late['max']:.0f} us; compute "
            f"p99 {comp['p99']:.0f} max {comp['max']:.0f} us; late>1ms {r['late_over_1ms']}; "
            f"overruns {r['overruns']}; plans {r['plans']} (loop {r['realtime']}; planner FIFO "
            f"{r['planner_fifo']})"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
