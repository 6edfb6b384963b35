"""What every mode of the soak shares: the requirement it judges and where the repository is."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: the requirement (configs/slave.yaml safety.loss): 2 tolerated, 3 stop, within 7 ms
MAX_TOLERATED = 2
STOP_WITHIN_MS = 7.0
PERIOD_MS = 2.0
