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
``can``  ``occ.drivers.can:CANDriver``         drives on a CAN bus speaking this project's own
                                               simple frame protocol (a lab's own boards)
=======  ====================================  =====================================

and ``cia402`` (``occ.drivers.cia402:CiA402Driver``): CANopen CiA 402 servo drives (Maxon
EPOS4, Elmo, ...) through the ``canopen`` library, with its emulator in
``occ.drivers.cia402_sim``;

and ``sim-hand`` (``occ.drivers.sim_hand:SimHandDriver``): a simulated haptic master in effort
mode moved by a simulated hand (the OCC paper's test motion as the operator's intention).

A third-party package adds a driver with, in its ``pyproject.toml``::

    [project.entry-points."occ.drivers"]
    mydrive = "mypkg.drive:MyDriver"

Precedence: :func:`register_driver` (explicit, at run time) > built-ins > entry points. An
entry point cannot silently replace a built-in such as ``sim``; it is ignored with a warning.

A driver imports only the vocabulary of ``occ`` (errors, joints, plugins) and its vendor's
library: never the Robot, the network or a controller (tests/test_imports.py).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from occ.drivers.base import CommandInterface, Driver, DriverState, LimitPolicy
from occ.errors import DriverError
from occ.joint import Joint
from occ.plugins import PluginRegistry

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

ENTRY_POINT_GROUP = "occ.drivers"

BUILTIN_DRIVERS: dict[str, str] = {
    "sim": "occ.drivers.sim:SimDriver",
    "can": "occ.drivers.can:CANDriver",
    "sim-hand": "occ.drivers.sim_hand:SimHandDriver",
    "cia402": "occ.drivers.cia402:CiA402Driver",
}

_REGISTRY: PluginRegistry[Driver] = PluginRegistry(
    "driver", ENTRY_POINT_GROUP, BUILTIN_DRIVERS, Driver, DriverError
)


def register_driver(name: str, target: str | type[Driver]) -> None:
    """Register (or replace) a driver under ``name``.

    ``target`` is ``"package.module:ClassName"`` (imported lazily on first use) or a
    :class:`Driver` subclass. Explicit registrations take precedence over everything else,
    which is what tests and embedding applications want.
    """
    _REGISTRY.register(name, target)


def available_drivers() -> list[str]:
    """All driver names that can be chosen (nothing is imported), sorted."""
    return _REGISTRY.available()


def load_driver_class(plugin: str) -> type[Driver]:
    """Import (if needed) and return the driver class registered as ``plugin``."""
    return _REGISTRY.load(plugin)


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
