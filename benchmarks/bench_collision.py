#!/usr/bin/env python3
"""Whole-arm collision checking (occ/kinematics/collision.py): what a check costs, and what checking
at run time does to the loop.

``check``
    The UR5 of configs/ur5.yaml (its collision meshes as convex hulls, 15 self pairs from the
    package's SRDF) against N forbidden regions (spheres and planes, and one 1280-triangle mesh
    sphere from N >= 4), at configurations spread around its home pose: the cost of one
    ``Checker.clearance`` (every pair's distance; what the run-time worker does per verdict),
    median and p99, per N. Also the whole-path check of a 2 s keyframe plan (2001 samples,
    advanced by the motion bound): how many samples it checked and what it cost.

``loop``
    Two runs of the UR5 daemon (configs/ur5.yaml, SCHED_FIFO where permitted) followed by the
    6-DOF master (configs/master6.yaml: the paper's circle with a turning gimbal, 500 Hz), one
    without ``safety.collision`` and one with it (four regions out of the arm's way, self
    collision on, the run-time guard checking every setpoint on its own worker thread),
    ``--duration`` seconds each: the slave loop's lateness p99.9 and max, its CPU, and the
    guard's verdicts, holds and stops (both must be zero: nothing is near).

``guard``
    The run-time guard alone, inline, on the master's circle at 1 kHz: CPU per tick with a
    verdict every tick against one when due, with and without a peer arm (issue 40).

``mesh``
    A 3D Slicer model (1k, 10k, 200k triangles) made a region on a thread of its own, in parts,
    while the main thread ticks: the build time, the longest tick wait, the one-call build, and
    a check near it in parts against one hierarchy (issue 40).

Examples::

    python benchmarks/bench_collision.py check
    python benchmarks/bench_collision.py loop --duration 60
    python benchmarks/bench_collision.py loop --duration 60 --runtime-hz 250
    python benchmarks/bench_collision.py guard --seconds 10
    python benchmarks/bench_collision.py mesh

The result is printed as JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_safety import loop_summary, start, state_changes  # noqa: E402
from loopback import pair_configs, stop_processes, wait_port  # noqa: E402

HOME = [0.0, -1.2, 1.5, -1.9, -1.57, 0.0]
#: regions well away from the UR5's home and the master's motion (patient mm)
FAR = [
    {"name": "ceiling", "kind": "plane", "point_mm": [0, 0, 700], "normal": [0, 0, -1]},
    {"name": "wall", "kind": "plane", "point_mm": [900, 0, 0], "normal": [-1, 0, 0]},
    {"name": "ball", "kind": "sphere", "point_mm": [-400, 400, 300], "radius_mm": 50},
    {"name": "ball2", "kind": "sphere", "point_mm": [300, -500, 200], "radius_mm": 80},
]


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(math.ceil(q / 100.0 * len(s))) - 1)]


def icosphere(radius: float, centre: np.ndarray, levels: int = 3) -> tuple[np.ndarray, np.ndarray]:
    t = (1.0 + 5**0.5) / 2.0
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t),
         (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]  # fmt: skip
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
         (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
         (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]  # fmt: skip
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    for _ in range(levels):
        cache: dict[tuple[int, int], int] = {}
        nf = []
        for a, b, c in f:
            ab, bc, ca = (_mid(verts, cache, x, y) for x, y in ((a, b), (b, c), (c, a)))
            nf += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        f = nf
    return np.array(verts) * radius + centre, np.array(f)


def _mid(verts: list[np.ndarray], cache: dict[tuple[int, int], int], a: int, b: int) -> int:
    key = (min(a, b), max(a, b))
    if key not in cache:
        m = verts[a] + verts[b]
        verts.append(m / np.linalg.norm(m))
        cache[key] = len(verts) - 1
    return cache[key]


def timed(checker: Any, qs: list[np.ndarray]) -> dict[str, float]:
    for q in qs[:50]:
        checker.clearance(q)  # warm
    times = []
    for q in qs:
        t0 = time.perf_counter()
        checker.clearance(q)
        times.append((time.perf_counter() - t0) * 1e6)
    return {
        "median_us": round(statistics.median(times), 1),
        "p99_us": round(pct(times, 99.0), 1),
        "max_us": round(max(times), 1),
    }


def run_check(args: argparse.Namespace) -> dict[str, Any]:
    from occ.config import CollisionConfig
    from occ.core.assembly import build_hardware
    from occ.core.loader import load_config
    from occ.kinematics.collision import CollisionModel, mesh_region

    daemon = load_config(ROOT / "configs" / "ur5.yaml")
    _joints, frame, _pairs = build_hardware(daemon.robot)
    rng = np.random.default_rng(1)
    qs = [np.array(HOME) + rng.normal(0.0, 0.3, 6) for _ in range(args.samples)]
    result: dict[str, Any] = {"mode": "check", "samples": args.samples, "by_regions": {}}
    for n in args.regions:
        regions = []
        for i in range(n):
            if i % 2 == 0:
                regions.append(
                    {
                        "name": f"s{i}",
                        "kind": "sphere",
                        "radius_mm": 40.0,
                        "point_mm": [-500.0 + 60 * i, 500.0, 200.0],
                    }  # fmt: skip
                )
            else:
                regions.append(
                    {
                        "name": f"p{i}",
                        "kind": "plane",
                        "point_mm": [0, 0, 800.0 + i],
                        "normal": [0, 0, -1],
                    }  # fmt: skip
                )
        cm = CollisionModel.build(CollisionConfig(regions=regions), daemon.robot.frame, frame)
        if n >= 4:
            v, t = icosphere(60.0, np.array([-300.0, -400.0, 300.0]))
            cm.define("mesh", [mesh_region("mesh", v, t, source="mesh")])
            regions.append({"name": "mesh", "triangles": len(t)})
        checker = cm.checker()
        row: dict[str, Any] = {"pairs": len(checker.pairs(HOME)), **timed(checker, qs)}
        row["exact_pairs_at_home"] = checker.exact
        result["by_regions"][str(len(cm.regions))] = row
    # a Slicer-sized mesh *near* the arm: its pairs are computed exactly (the broad phase
    # cannot settle them), the worst case for the interpreter lock
    cm = CollisionModel.build(CollisionConfig(), daemon.robot.frame, frame)
    checker = cm.checker()
    checker.pairs(HOME)
    wrist = np.asarray(
        checker._centres[cm.links.index(next(lk for lk in cm.links if lk.name == "wrist_2_link"))]
    )
    v, t = icosphere(60.0, wrist * 1e3 + np.array([0.0, 0.0, 150.0]))
    cm.define("mesh", [mesh_region("mesh", v, t, source="mesh")])
    near = timed(checker, [np.array(HOME) + rng.normal(0.0, 0.02, 6) for _ in range(args.samples)])
    checker.pairs(HOME)
    result["mesh_near"] = {"triangles": len(t), "exact_pairs": checker.exact, **near}
    # a plan's whole-path check: 2 s from home, one sample a millisecond
    cm = CollisionModel.build(
        CollisionConfig(
            regions=FAR[:1]
            + [{"name": "near", "kind": "plane", "point_mm": [0, 0, 600], "normal": [0, 0, -1]}]
        ),  # fmt: skip
        daemon.robot.frame,
        frame,
    )
    end = np.array([0.3, -1.1, 1.6, -2.0, -1.57, 0.2])
    path = [list(np.array(HOME) + (end - HOME) * (0.5 - 0.5 * math.cos(math.pi * k / 2000)))
            for k in range(2001)]  # fmt: skip
    check = cm.path_check()
    times = []
    for _ in range(20):
        t0 = time.perf_counter()
        assert check.check_path(path, np.eye(4)) is None
        times.append((time.perf_counter() - t0) * 1e3)
    result["plan_2s"] = {
        "samples": len(path),
        "checked": check.checked,
        "median_ms": round(statistics.median(times), 2),
        "every_sample_ms": round(statistics.median(times) / check.checked * len(path), 1),
    }
    return result


def run_loop(args: argparse.Namespace, out: Path) -> dict[str, Any]:
    runs: dict[str, Any] = {}
    for label, collision in (("without", None), ("with", True)):
        slave, master, ports = pair_configs(
            ROOT / "configs" / "ur5.yaml", ROOT / "configs" / "master6.yaml"
        )
        if collision:
            slave.setdefault("safety", {})["collision"] = {
                "margin_mm": 10.0,
                "regions": FAR,
                "runtime_hz": args.runtime_hz,
            }
        procs = [start(out, f"slave-{label}", slave)]
        try:
            if not wait_port(ports["slave_tcp"], 60.0, procs[0]):
                raise SystemExit(f"slave-{label} did not start; see {out}")
            procs.append(start(out, f"master-{label}", master))
            if not wait_port(ports["master_tcp"], 60.0, procs[1]):
                raise SystemExit(f"master-{label} did not start; see {out}")
            print(f"loop: {label} collision checking, {args.duration:.0f} s", file=sys.stderr)
            end = time.monotonic() + args.duration
            while time.monotonic() < end:
                time.sleep(0.5)
                if any(p.poll() is not None for p in procs):
                    raise SystemExit(f"loop: a daemon exited early; see {out}")
        finally:
            stop_processes(procs)
        d = json.loads((out / f"slave-{label}.json").read_text())
        run = loop_summary(d)
        run["state_changes"] = state_changes(out / f"slave-{label}.log")
        if "collision" in d:
            c = d["collision"]
            run["collision"] = {
                k: c[k] for k in ("verdicts", "holds", "stops", "clearance_mm", "self_pairs")
            }
            run["collision"]["regions"] = len(c["regions"])
        runs[label] = run
    return {
        "mode": "loop",
        "duration_s": args.duration,
        "runtime_hz": args.runtime_hz,
        "load_after": " ".join(Path("/proc/loadavg").read_text().split()[:3]),
        "runs": runs,
    }


def run_mesh(args: argparse.Namespace) -> dict[str, Any]:
    """A 3D Slicer model (POLYDATA, triangles) made a forbidden region as the desk's worker
    makes it (occ/net/operators.py): on a thread of its own, the interpreter lock given up
    between the mesh's parts, while this thread ticks every 0.5 ms; the build's time and the
    longest this thread waited (a tick late by that much is what the loop would see)."""
    import threading

    import coal

    import igtl
    from occ.config import CollisionConfig
    from occ.core.assembly import build_hardware
    from occ.core.loader import load_config
    from occ.kinematics.collision import CollisionModel, regions_from_event
    from occ.kinematics.regions import Region, _bvh
    from occ.net.decoders import event_of

    sys.setswitchinterval(500e-6)  # as the daemon sets it (configs/ur5.yaml switch_interval_us)
    daemon = load_config(ROOT / "configs" / "ur5.yaml")
    _joints, frame, _pairs = build_hardware(daemon.robot)
    probe = CollisionModel.build(CollisionConfig(), daemon.robot.frame, frame).checker()
    probe.pairs(HOME)
    above_wrist = np.asarray(probe._centres[5]) * 1e3 + np.array([0.0, 0.0, 150.0])
    out: dict[str, Any] = {"mode": "mesh", "by_triangles": {}}
    levels = {1280: 3, 20480: 5, 200_000: 7}
    for n in args.triangles:
        level = min(lv for k, lv in levels.items() if k >= n) if n <= 200_000 else 7
        v, t = icosphere(60.0, above_wrist, level)
        t = t[:n]
        msg = igtl.PolyDataMessage(
            points=v.astype(np.float32),
            polygons=tuple(tuple(int(i) for i in tri) for tri in t),
            device_name="Model",
            header_version=2,
            metadata={"kind": "forbidden-region"},
        )
        event = event_of(msg)
        rows = []
        for _ in range(args.repeat):
            gaps: list[float] = []
            done = threading.Event()
            built: list[Any] = []

            def build(ev: Any = event, sink: list[Any] = built, flag: Any = done) -> None:
                t0 = time.perf_counter()
                sink.append(regions_from_event(ev, pause=lambda: time.sleep(0)))
                sink.append(time.perf_counter() - t0)
                flag.set()

            th = threading.Thread(target=build)
            last = time.perf_counter()
            th.start()
            while not done.is_set():
                time.sleep(0.0005)
                now = time.perf_counter()
                gaps.append(now - last)
                last = now
            th.join()
            (_name, (region,)), seconds = built
            rows.append((seconds, max(gaps)))
        t0 = time.perf_counter()  # the same mesh as one hierarchy, built in one call
        single = Region("Model", "mesh", _bvh(v * 1e-3, t), coal.Transform3s())
        one_call = time.perf_counter() - t0
        row: dict[str, Any] = {
            "parts": len(region.parts) or 1,
            "build_ms_median": round(statistics.median(r[0] for r in rows) * 1e3, 1),
            "longest_wait_ms_max": round(max(r[1] for r in rows) * 1e3, 2),
            "one_call_build_ms": round(one_call * 1e3, 1),
        }
        # the check with the mesh 150 mm above the wrist: in parts, and as one hierarchy
        for label, r in (("check_parts", region), ("check_one_bvh", single)):
            cm = CollisionModel.build(CollisionConfig(), daemon.robot.frame, frame)
            cm.define("Model", [r])
            rng = np.random.default_rng(2)
            qs = [np.array(HOME) + rng.normal(0.0, 0.02, 6) for _ in range(args.checks)]
            row[label] = timed(cm.checker(), qs)
        out["by_triangles"][str(len(t))] = row
    return out


def run_guard(args: argparse.Namespace) -> dict[str, Any]:
    """The run-time guard's cost per tick, inline (no thread hand-over): the UR5 following
    the 6-DOF master's circle (configs/master6.yaml's path scaled 0.5: 25 mm at 0.5 Hz, its
    tool turning) with the regions of ``loop``, at 1 kHz for ``--seconds``; a verdict every
    tick (``due`` forced) against one when due, with and without a peer UR5 1.6 m away (its
    state every 5 ticks). CPU per tick, so points of a core at 1 kHz."""
    from occ.config import CollisionConfig
    from occ.core.assembly import build_hardware
    from occ.core.loader import load_config
    from occ.kinematics.collision import CollisionGuard, CollisionModel

    daemon = load_config(ROOT / "configs" / "ur5.yaml")
    _joints, frame, _pairs = build_hardware(daemon.robot)
    ticks = int(args.seconds * 1000)
    home_tip = frame.fk(HOME)
    qs = []
    q = list(HOME)
    for k in range(ticks):
        a = 2.0 * math.pi * 0.5 * k * 1e-3
        target = home_tip.copy()
        target[:3, 3] += 0.0125 * np.array([math.cos(a) - 1.0, math.sin(a), 0.0])
        q = list(frame.ik(target, q))
        qs.append(q)
    b = np.eye(4)
    b[:3, :3] = np.diag([-1.0, -1.0, 1.0])
    b[:3, 3] = [1.6, 0.218, 0.0]
    out: dict[str, Any] = {"mode": "guard", "seconds": args.seconds, "runs": {}}
    for peer in (False, True):
        for rule in ("every tick", "when due"):
            cm = CollisionModel.build(CollisionConfig(regions=FAR), daemon.robot.frame, frame)
            if peer:
                cm.add_peer("ur5-b", daemon.robot.frame, velocities=[1.0] * 6)
            guard = CollisionGuard(cm, inline=True)
            if rule == "every tick":
                guard.due = lambda *_a: True  # type: ignore[method-assign]
            base = np.eye(4)
            t0 = time.process_time()
            for k, qk in enumerate(qs):
                now = k * 1e-3
                if peer and k % 5 == 0:
                    guard.peer_update("ur5-b", HOME, b, now)
                guard.admit(qk, base, now)
                guard.publish(qk, base, now)
            cpu = time.process_time() - t0
            label = f"{rule}{', a peer arm' if peer else ''}"
            out["runs"][label] = {
                "verdicts": guard.verdicts,
                "holds": guard.holds,
                "us_per_tick": round(cpu / ticks * 1e6, 1),
                "points_at_1khz": round(cpu / ticks * 1e3 * 100, 2),
            }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="mode", required=True)
    c = sub.add_parser("check")
    c.add_argument("--samples", type=int, default=2000)
    c.add_argument("--regions", type=int, nargs="+", default=[0, 1, 4, 16])
    lp = sub.add_parser("loop")
    lp.add_argument("--duration", type=float, default=60.0)
    lp.add_argument(
        "--runtime-hz",
        type=float,
        default=None,
        help="safety.collision.runtime_hz (null: every tick)",
    )
    mp = sub.add_parser("mesh")
    mp.add_argument("--triangles", type=int, nargs="+", default=[1000, 10_000, 200_000])
    mp.add_argument("--repeat", type=int, default=3)
    mp.add_argument("--checks", type=int, default=60)
    gp = sub.add_parser("guard")
    gp.add_argument("--seconds", type=float, default=20.0)
    args = ap.parse_args()
    if args.mode == "check":
        result = run_check(args)
    elif args.mode == "mesh":
        result = run_mesh(args)
    elif args.mode == "guard":
        result = run_guard(args)
    else:
        with tempfile.TemporaryDirectory(prefix="bench-collision-") as tmp:
            result = run_loop(args, Path(tmp))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
