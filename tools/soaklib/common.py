"""What every mode of the soak shares: the requirement it judges and where the repository is."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: the requirement (configs/slave.yaml safety.loss): 2 tolerated, 3 stop, within 7 ms
MAX_TOLERATED = 2
STOP_WITHIN_MS = 7.0
PERIOD_MS = 2.0


def daemon_ends(stats: dict[str, dict]) -> str:
    """Each daemon's state at the end of its run and its last alert, from its statistics: what
    a check on the exit codes names, so a failure says why without the run's logs."""
    parts = []
    for name in ("master", "slave"):
        s = stats.get(name) or {}
        alert = s.get("last_alert") or "none"
        parts.append(f"{name} ended {s.get('final_state', '?')} (last alert: {alert})")
    return "; ".join(parts)
