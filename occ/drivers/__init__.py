"""Joint drivers and their registry.

Drivers are looked up by a short plugin name, in the way python-can looks up its bus
interfaces: a table maps each name to ``"module:Class"``, the table is extended by the entry
points of group ``occ.drivers`` of installed distributions, and a module is imported only
when its driver is chosen, so a missing vendor library breaks only the user who picked it.

Built in:

=======  ====================================  =====================================
name     target                                what
=======  ====================================  =====================================
``sim``  ``occ.drivers.sim:SimDriver``         simulated second-order joints (default)
``can``  ``occ.drivers.can:CANDriver``         drives on a CAN bus through python-can
=======  ====================================  =====================================

A third-party package adds a driver with, in its ``pyproject.toml``::

    [project.entry-points."occ.drivers"]
    mydrive = "mypkg.drive:MyDriver"

Precedence: :func:`register_driver` (explicit, at run time) > built-ins > entry points. An
entry point cannot silently replace a built-in such as ``sim``; it is ignored with a warning.
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Mapping, Sequence
from importlib.metadata import entry_points
from typing import Any

from occ.drivers.base import CommandInterface, Driver, DriverState, LimitPolicy
from occ.errors import DriverError
from occ.joint import Joint

__all__ = [
    "Driver",
    "DriverState",
    "BUILTIN_DRIVERS",
    "ENTRY_POINT_GROUP",
    "available_drivers",
    "create_driver",
    "load_driver_class",
    "register_driver",
]

logger = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "occ.drivers"

BUILTIN_DRIVERS: dict[str, str] = {
    "sim": "occ.drivers.sim:SimDriver",
    "can": "occ.drivers.can:CANDriver",
}

# Explicit registrations: a "module:Class" string or an already imported class.
_registered: dict[str, str | type[Driver]] = {}
# Entry points are read once (reading them scans installed distributions: not free).
_entry_point_table: dict[str, str] | None = None


def _entry_points() -> dict[str, str]:
    global _entry_point_table
    if _entry_point_table is None:
        table: dict[str, str] = {}
        for ep in entry_points(group=ENTRY_POINT_GROUP):
            if ep.name in BUILTIN_DRIVERS:
                logger.warning(
                    "entry point %s=%s ignored: %r is a built-in driver", ep.name, ep.value, ep.name
                )
                continue
            table[ep.name] = ep.value
        _entry_point_table = table
    return _entry_point_table


def register_driver(name: str, target: str | type[Driver]) -> None:
    """Register (or replace) a driver under ``name``.

    ``target`` is ``"package.module:ClassName"`` (imported lazily on first use) or a
    :class:`Driver` subclass. Explicit registrations take precedence over everything else,
    which is what tests and embedding applications want.
    """
    if not name or not isinstance(name, str):
        raise ValueError("driver name must be a non-empty string")
    if isinstance(target, str):
        if target.count(":") != 1 or not all(target.split(":")):
            raise ValueError(f"driver target must look like 'module:Class', got {target!r}")
    elif not (isinstance(target, type) and issubclass(target, Driver)):
        raise ValueError(f"driver target must be 'module:Class' or a Driver subclass: {target!r}")
    _registered[name] = target


def available_drivers() -> list[str]:
    """All driver names that can be chosen (nothing is imported), sorted."""
    return sorted(set(BUILTIN_DRIVERS) | set(_entry_points()) | set(_registered))


def _target_of(plugin: str) -> str | type[Driver]:
    if plugin in _registered:
        return _registered[plugin]
    if plugin in BUILTIN_DRIVERS:
        return BUILTIN_DRIVERS[plugin]
    eps = _entry_points()
    if plugin in eps:
        return eps[plugin]
    raise DriverError(f"unknown driver plugin {plugin!r}; known: {', '.join(available_drivers())}")


def load_driver_class(plugin: str) -> type[Driver]:
    """Import (if needed) and return the driver class registered as ``plugin``."""
    target = _target_of(plugin)
    if isinstance(target, type):
        return target
    module_name, _, class_name = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise DriverError(
            f"driver {plugin!r}: cannot import {module_name!r} ({err}); is its package installed?"
        ) from err
    try:
        cls = getattr(module, class_name)
    except AttributeError as err:
        raise DriverError(f"driver {plugin!r}: {module_name!r} has no {class_name!r}") from err
    if not (isinstance(cls, type) and issubclass(cls, Driver)):
        raise DriverError(f"driver {plugin!r}: {target} is not a Driver subclass")
    return cls


def create_driver(
    plugin: str,
    name: str,
    joints: Sequence[Joint],
    params: Mapping[str, Any] | None = None,
    on_limit: LimitPolicy = "clamp",
    command_interface: CommandInterface | None = None,
) -> Driver:
    """Build a driver by plugin name (e.g. ``"sim"``); it starts UNCONFIGURED."""
    cls = load_driver_class(plugin)
    return cls(name, joints, params, on_limit=on_limit, command_interface=command_interface)
