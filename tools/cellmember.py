#!/usr/bin/env python3
"""``occd`` with a drive that can be made to fail from outside (tools/cell_faults.py).

The driver plugin ``sim-signal`` is the shipped ``sim`` drive whose next write fails once the
process gets SIGUSR1 (a drive fault the robot notices as the shipped one does: FAULT naming the
drive); its Reset repairs it (the repair is real: the injected fault is cleared). Everything
else is ``occd`` as shipped: ``python tools/cellmember.py CONFIG [occd options]``.
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from occ import cli  # noqa: E402
from occ.drivers import register_driver  # noqa: E402
from occ.drivers.sim import SimDriver  # noqa: E402


class SignalFaultSim(SimDriver):
    """The sim drive; after SIGUSR1 its next write fails (until a Reset)."""

    asked = False

    def _write(self, values: Sequence[float], now: float) -> None:
        if SignalFaultSim.asked:
            SignalFaultSim.asked = False
            self.inject("write")
        super()._write(values, now)

    def _reset(self) -> None:
        self.clear_faults()
        super()._reset()


def _on_usr1(_signum: int, _frame: Any) -> None:
    SignalFaultSim.asked = True


def main(argv: list[str] | None = None) -> int:
    register_driver("sim-signal", SignalFaultSim)
    signal.signal(signal.SIGUSR1, _on_usr1)
    return cli.main(argv)


if __name__ == "__main__":
    sys.exit(main())
