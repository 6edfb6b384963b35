"""The surviving branch mutants of occ.recording.export.quaternion_xyzw, measured
(docs/VERIFICATION.md).

Shepperd's method has four formulas for the quaternion of a rotation matrix; each is exact
whenever its divisor is not zero, and the branch conditions only pick the one with the largest
divisor (the least rounding). A mutant that picks another branch changes the rounding, not the
rotation. This script makes each surviving mutant from the source (the same text replacement
mutmut made) and compares the rotation of its quaternion with the original's over uniform
random rotations, turns of 180 degrees and just short of it about random axes, and turns about
the axes and diagonals, each given in float64 and rounded to float32 (the wire's precision).

    OCC_PURE=1 python scripts/mutants_quaternion.py
"""

from __future__ import annotations

import inspect
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from occ.recording import export as recexport  # noqa: E402

BRANCH_X = "elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:"
BRANCH_Y = "elif r[1, 1] > r[2, 2]:"
#: mutmut's number -> (original line, mutated line)
MUTANTS = {
    18: ("if tr > 0.0:", "if tr >= 0.0:"),
    19: ("if tr > 0.0:", "if tr > 1.0:"),
    48: (BRANCH_X, "elif r[0, 0] > r[1, 1] or r[0, 0] > r[2, 2]:"),
    49: (BRANCH_X, "elif r[1, 0] > r[1, 1] and r[0, 0] > r[2, 2]:"),
    50: (BRANCH_X, "elif r[0, 1] > r[1, 1] and r[0, 0] > r[2, 2]:"),
    51: (BRANCH_X, "elif r[0, 0] >= r[1, 1] and r[0, 0] > r[2, 2]:"),
    52: (BRANCH_X, "elif r[0, 0] > r[2, 1] and r[0, 0] > r[2, 2]:"),
    53: (BRANCH_X, "elif r[0, 0] > r[1, 2] and r[0, 0] > r[2, 2]:"),
    54: (BRANCH_X, "elif r[0, 0] > r[1, 1] and r[1, 0] > r[2, 2]:"),
    55: (BRANCH_X, "elif r[0, 0] > r[1, 1] and r[0, 1] > r[2, 2]:"),
    56: (BRANCH_X, "elif r[0, 0] > r[1, 1] and r[0, 0] >= r[2, 2]:"),
    95: (BRANCH_Y, "elif r[2, 1] > r[2, 2]:"),
    96: (BRANCH_Y, "elif r[1, 2] > r[2, 2]:"),
    97: (BRANCH_Y, "elif r[1, 1] >= r[2, 2]:"),
    178: ("if q[3] < 0.0:", "if q[3] <= 0.0:"),
}


def quat_matrix(q: tuple[float, float, float, float] | np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotations(rng: np.random.Generator) -> list[np.ndarray]:
    qs = list(rng.normal(size=(20000, 4)))
    for a in rng.normal(size=(5000, 3)):
        n = a / np.linalg.norm(a)
        for eps in (0.0, 1e-9, 1e-6, 1e-3):
            h = (math.pi - eps) / 2
            qs.append(np.array([*(n * math.sin(h)), math.cos(h)]))
    for axis in ([1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, 1, 1], [1, 0, 1], [1, 1, 1]):
        n = np.array(axis, dtype=float) / np.linalg.norm(axis)
        for angle in (math.pi, 2 * math.pi / 3, math.pi / 2, 1e-9):
            qs.append(np.array([*(n * math.sin(angle / 2)), math.cos(angle / 2)]))
    qs.append(np.array([0.0, 0.0, 0.0, 1.0]))
    return [quat_matrix(q / np.linalg.norm(q)) for q in qs]


def main() -> int:
    source = inspect.getsource(recexport.quaternion_xyzw)
    mats = rotations(np.random.default_rng(29))
    cases = mats + [m.astype(np.float32) for m in mats]
    original = [quat_matrix(recexport.quaternion_xyzw(r)) for r in cases]
    print(f"{len(mats)} rotations, each in float64 and float32")
    for number, (old, new) in MUTANTS.items():
        assert source.count(old) == 1, old
        ns: dict[str, object] = {"np": np, "math": math}
        exec(source.replace(old, new), ns)  # noqa: S102 - the mutant, made here
        mutant = ns["quaternion_xyzw"]
        worst = 0.0
        for r, want in zip(cases, original, strict=True):
            q = mutant(r)  # type: ignore[operator]
            assert q[3] >= 0.0
            worst = max(worst, float(np.abs(quat_matrix(q) - want).max()))
        print(f"quaternion_xyzw mutant {number}: rotation differs by at most {worst:.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
