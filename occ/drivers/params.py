"""The parameters every driver takes, read and checked once at construction.

:func:`driver_params` merges a backend's ``DEFAULT_PARAMS`` and the base's
:data:`BASE_PARAMS` with the configured values, refuses unknown keys and bad values (each
``ValueError`` names the driver and the key) and returns the figures the base works with as a
:class:`DriverParams`. What the figures mean is in the "Feedback checks" part of
:mod:`occ.drivers.base`'s docstring.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from occ.joint import Joint

__all__ = ["BASE_PARAMS", "FOLLOWING_DEFAULTS", "DriverParams", "driver_params"]

_INTERFACES = ("position", "effort")

#: Parameters every driver takes (the base reads them), whatever its own DEFAULT_PARAMS say:
#: the device heartbeat, and the feedback checks (see "Feedback checks" in the base's docstring).
BASE_PARAMS: dict[str, Any] = {
    "heartbeat_ms": 50.0,
    "feedback_jump": 2.0,
    "frozen_feedback_ms": 50.0,
    "feedback_noise": None,
    "limit_margin": None,
    "following_error": {},
}

#: ``following_error``'s keys and defaults (None: by joint type, or from the backend)
FOLLOWING_DEFAULTS: dict[str, Any] = {
    "window": None,
    "time_ms": 3.0,
    "lag_ms": None,
    "stiffness": None,
}


@dataclass(frozen=True)
class DriverParams:
    """What the base reads of a driver's parameters, checked."""

    #: the backend's defaults, the base's and the configured values, merged
    values: dict[str, Any]
    #: the command interface chosen (the argument, the parameter, or the class default)
    interface: str
    #: the nominal loop period, s
    period: float
    #: the device heartbeat, s (0 = off)
    heartbeat_s: float
    #: ``feedback_jump`` (0 = off)
    jump: float
    #: ``frozen_feedback_ms`` (0 = off)
    frozen_ms: float
    #: ``feedback_noise`` per joint, None when not configured
    noise: list[float] | None
    #: ``limit_margin`` per joint, None when not configured
    margin: list[float] | None
    #: ``following_error`` checked (:func:`following_params`), None when off
    following: dict[str, Any] | None


def _number(name: str, key: str, raw: Any, *, positive: bool = False) -> float:
    try:
        value = float(raw)
    except (TypeError, ValueError):
        value = math.nan
    if not (value > 0.0 if positive else value >= 0.0) or value == math.inf:
        want = "> 0" if positive else ">= 0"
        raise ValueError(f"driver {name!r}: {key} must be a finite number {want}, got {raw!r}")
    return value


def per_joint_param(
    name: str, key: str, raw: Any, joints: Sequence[Joint], *, positive: bool = False
) -> list[float] | None:
    """``raw`` as one value per joint: None (the default applies), one number for every
    joint, or ``{joint: number}`` naming every joint. ValueError naming the key otherwise."""
    if raw is None:
        return None
    if isinstance(raw, Mapping):
        names = [j.name for j in joints]
        unknown = sorted(set(map(str, raw)) - set(names))
        missing = [n for n in names if n not in raw]
        if unknown or missing:
            raise ValueError(
                f"driver {name!r}: {key} names joints {sorted(map(str, raw))}; its joints are "
                f"{names}"
                + (f" (unknown: {unknown})" if unknown else "")
                + (f" (missing: {missing})" if missing else "")
            )
        return [_number(name, f"{key}.{n}", raw[n], positive=positive) for n in names]
    if isinstance(raw, (bool, str)) or not isinstance(raw, (int, float)):
        raise ValueError(
            f"driver {name!r}: {key} must be a number or {{joint: number}}, got {raw!r}"
        )
    value = _number(name, key, raw, positive=positive)
    return [value] * len(joints)


def following_params(name: str, raw: Any, joints: Sequence[Joint]) -> dict[str, Any] | None:
    """``following_error`` checked: None when off (null, false), else its keys with their
    defaults merged (``FOLLOWING_DEFAULTS``); ValueError naming what is wrong."""
    if raw is None or raw is False:
        return None
    if not isinstance(raw, Mapping):
        raise ValueError(
            f"driver {name!r}: following_error must be a mapping {{window, time_ms, lag_ms, "
            f"stiffness}} or null (off), got {raw!r}"
        )
    unknown = sorted(set(map(str, raw)) - set(FOLLOWING_DEFAULTS))
    if unknown:
        raise ValueError(
            f"driver {name!r}: following_error: unknown keys {unknown}; known: "
            f"{sorted(FOLLOWING_DEFAULTS)}"
        )
    cfg = {**FOLLOWING_DEFAULTS, **raw}
    return {
        "window": per_joint_param(
            name, "following_error.window", cfg["window"], joints, positive=True
        ),
        "time_s": _number(name, "following_error.time_ms", cfg["time_ms"]) * 1e-3,
        "lag": None
        if cfg["lag_ms"] is None
        else [
            v * 1e-3
            for v in per_joint_param(name, "following_error.lag_ms", cfg["lag_ms"], joints) or ()
        ],
        "stiffness": per_joint_param(
            name, "following_error.stiffness", cfg["stiffness"], joints, positive=True
        ),
    }


def _merged(
    name: str, kind: str, params: Mapping[str, Any] | None, defaults: Mapping[str, Any] | None
) -> dict[str, Any]:
    """The configured ``params`` over the defaults; with a backend's ``defaults``, a key
    neither names is refused (a typo in the YAML must not be silently ignored)."""
    given = dict(params or {})
    if defaults is None:
        return {**BASE_PARAMS, **given}
    known = set(defaults) | set(BASE_PARAMS)
    unknown = set(given) - known
    if unknown:
        raise ValueError(
            f"driver {name!r} ({kind}): unknown params {sorted(unknown)}; known: {sorted(known)}"
        )
    return {**BASE_PARAMS, **defaults, **given}


def _off_or_more(name: str, key: str, raw: Any, scale: float = 1.0) -> float:
    """A parameter that is a number >= 0 with 0 (or None) meaning off, times ``scale``."""
    try:
        value = 0.0 if raw is None else float(raw) * scale
    except (TypeError, ValueError):
        value = math.nan
    if not value >= 0.0:
        raise ValueError(f"driver {name!r}: {key} must be a number >= 0 (0 = off), got {raw!r}")
    return value


def driver_params(
    name: str,
    kind: str,
    joints: Sequence[Joint],
    params: Mapping[str, Any] | None,
    defaults: Mapping[str, Any] | None,
    interface: str | None,
    fallback: str,
    supported: tuple[str, ...],
) -> DriverParams:
    """Driver ``name``'s parameters (``kind``: its class's name; ``defaults``: its
    ``DEFAULT_PARAMS``) merged and checked. The command interface is ``interface`` if given,
    else the ``command_interface`` parameter, else ``fallback`` (the class's), and must be one
    of ``supported``. ValueError naming the first fault found."""
    values = _merged(name, kind, params, defaults)
    heartbeat_s = _off_or_more(name, "heartbeat_ms", values["heartbeat_ms"], 1e-3)
    jump = _off_or_more(name, "feedback_jump", values["feedback_jump"])
    frozen_ms = _off_or_more(name, "frozen_feedback_ms", values["frozen_feedback_ms"])
    noise = per_joint_param(name, "feedback_noise", values["feedback_noise"], joints)
    margin = per_joint_param(name, "limit_margin", values["limit_margin"], joints)
    following = following_params(name, values["following_error"], joints)
    chosen = interface or values.get("command_interface") or fallback
    if chosen not in _INTERFACES or chosen not in supported:
        raise ValueError(
            f"driver {name!r} ({kind}): command_interface {chosen!r} not "
            f"supported; choose one of {supported}"
        )
    period = float(values.get("period", 0.001))
    if not period > 0.0:
        raise ValueError(f"driver {name!r}: period must be > 0, got {period}")
    names = [j.name for j in joints]
    if len(set(names)) != len(names):
        raise ValueError(f"driver {name!r}: duplicate joint names {names}")
    return DriverParams(
        values, chosen, period, heartbeat_s, jump, frozen_ms, noise, margin, following
    )
