#!/usr/bin/env python3
"""What planning a cell keyframe set costs (issue 40, item 5; occ/kinematics/cellpaths.py,
occ/controllers/keyframe/cellset.py).

The shipped cell (configs/cell/: two UR5 600 mm apart, margin 20 mm) and its sets
(configs/keyframes/cell-turns.yaml: passes; cell-cross.yaml: refused): each member's part planned
as the planner thread plans it (``build_plan``: samples at 1 kHz, every per-tick check, the arm
against the other standing), then

- ``digest``: the path's SHA-256 (part of planning a part: every sample, float64);
- ``pack``: the NDARRAY ``CellPath`` packed as the desk's worker packs it (CRC-64 included);
- ``cross``: ``cross_check`` of each member's path against the other's (the time-aligned
  arm-vs-arm check on the planner thread), and how many samples it checked.

Each is timed ``--repeat`` times on this machine (no pacing: the planner's Pacer slices it into
the loop's quiet part, which stretches wall time, not work), median and max printed.

    PYTHONPATH=. python benchmarks/bench_cell_plan.py [--repeat 5]
"""

from __future__ import annotations

import argparse
import statistics
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

import igtl
from occ.config import CollisionConfig
from occ.controllers.keyframe.cellset import cell_set, read_any_keyframe_file
from occ.controllers.keyframe.plan import PlanRequest, build_plan
from occ.core.assembly import build_hardware
from occ.core.loader import load_config
from occ.kinematics.cellpaths import ArmPath, cross_check, path_digest
from occ.kinematics.collision import CollisionModel

ROOT = Path(__file__).resolve().parents[1]
HOME = (0.0, -1.2, 1.5, -1.9, -1.57, 0.0)


def model(me: str) -> tuple[Any, Any, CollisionModel]:
    cfg = load_config(ROOT / "configs" / "cell" / f"{me}-keyframe.yaml")
    frame = build_hardware(cfg.robot)[1]
    cc = cfg.safety.collision
    assert isinstance(cc, CollisionConfig) and cfg.cell is not None
    cm = CollisionModel.build(cc, cfg.robot.frame, frame)
    for m in cfg.cell.members:
        if m.name != me and m.frame is not None:
            cm.add_peer(m.name, m.frame, velocities=m.velocities)
    return cfg, frame, cm


def base(me: str) -> np.ndarray:
    b = np.eye(4)
    if me == "ur5-b":
        b[0, 3] = 0.6
    return b


def part_plan(name: str, me: str, cfg: Any, frame: Any, cm: CollisionModel) -> Any:
    cf = read_any_keyframe_file(ROOT / "configs" / "keyframes" / name)
    cs = cell_set(cf, name, me, "joint", 6, 100)  # type: ignore[arg-type]
    st = cs.own.settings
    assert st is not None
    other = next(p for p in cm.peers)
    other.update(HOME, base("ur5-b" if me == "ur5-a" else "ur5-a"), 0.0)
    req = PlanRequest(
        id=1,
        kset=cs.own,
        q_start=HOME,
        base=base(me),
        interpolation=st.interpolation,
        mode=st.mode,
        steepness=st.steepness,
        ramp=st.ramp,
        period=1e-3,
        joint_names=tuple(j.name for j in cfg.robot.joints),
        limits=tuple(j.limits for j in cfg.robot.joints),
        velocity_scale=1.0,
        start_tolerance=1e-3,
        start_tolerance_mm=0.5,
        workspace=None,
        forbidden=(),
        max_duration_s=300.0,
        preview_points=256,
        path_checks=(cm.path_check(),),
        cell_member=me,
    )
    return build_plan(req, frame)


def timed(fn: Any, repeat: int) -> tuple[float, float, Any]:
    out, times = None, []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3, max(times) * 1e3, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    arms = {me: model(me) for me in ("ur5-a", "ur5-b")}
    for name in ("cell-turns.yaml", "cell-cross.yaml"):
        print(f"{name}:")
        paths = {}
        for me, (cfg, frame, cm) in arms.items():
            med, mx, plan = timed(partial(part_plan, name, me, cfg, frame, cm), args.repeat)
            assert plan.qs is not None
            path = ArmPath(me, plan.qs, base(me), 1e-3)
            paths[me] = path
            dmed, dmx, _ = timed(partial(path_digest, path), args.repeat)
            msg = igtl.NDArrayMessage(array=plan.qs, device_name="CellPath", header_version=2)
            pmed, pmx, wire = timed(msg.pack, args.repeat)
            print(
                f"  {me}: plan+checks {med:.0f} ms (max {mx:.0f}), {len(plan.qs)} samples; "
                f"digest {dmed:.2f} ms (max {dmx:.2f}); NDARRAY {len(wire) / 1e6:.2f} MB "
                f"packed in {pmed:.2f} ms (max {pmx:.2f})"
            )
        for me, (_cfg, _frame, cm) in arms.items():
            other = paths["ur5-b" if me == "ur5-a" else "ur5-a"]
            checker = cm.checker()
            med, mx, res = timed(
                partial(cross_check, cm, paths[me], [other], 0.002, checker=checker), args.repeat
            )
            verdict = "clear" if res.clash is None else f"refused ({res.clash.describe()})"
            print(
                f"  {me} cross-check: {med:.1f} ms (max {mx:.1f}), {res.checked} samples "
                f"checked; {verdict}"
            )


if __name__ == "__main__":
    main()
