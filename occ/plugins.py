"""Plugin registries, the way python-can finds its buses: drivers and controllers alike.

A registry maps a short name to ``"package.module:Class"``: a built-in table, extended by the
entry points of one group of installed distributions (read once, when first needed) and by
explicit :meth:`PluginRegistry.register` calls. A module is imported only when its plugin is
chosen, so a missing vendor library breaks only the user who picked it.

Precedence: :meth:`~PluginRegistry.register` (explicit, at run time) > built-ins > entry points.
An entry point cannot silently replace a built-in name; it is ignored with a warning.
"""

from __future__ import annotations

import importlib
import logging
from importlib.metadata import entry_points
from typing import Generic, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")


class PluginRegistry(Generic[T]):
    """Plugins of one kind (``"driver"``, ``"controller"``): subclasses of ``base``; lookup
    failures raise ``error`` (the package's own exception for that kind)."""

    def __init__(
        self,
        kind: str,
        group: str,
        builtins: dict[str, str],
        base: type[T],
        error: type[Exception],
    ) -> None:
        self.kind = kind
        self.group = group
        self.builtins = builtins
        self.base = base
        self.error = error
        self._registered: dict[str, str | type[T]] = {}
        self._entry_point_table: dict[str, str] | None = None

    def _entry_points(self) -> dict[str, str]:
        if self._entry_point_table is None:
            table: dict[str, str] = {}
            for ep in entry_points(group=self.group):
                if ep.name in self.builtins:
                    log.warning(
                        "entry point %s=%s ignored: %r is a built-in %s",
                        ep.name,
                        ep.value,
                        ep.name,
                        self.kind,
                    )
                    continue
                table[ep.name] = ep.value
            self._entry_point_table = table
        return self._entry_point_table

    def register(self, name: str, target: str | type[T]) -> None:
        """Register (or replace) ``name``: ``"module:Class"`` (imported when first used) or a
        subclass of the base. Explicit registrations take precedence over everything else."""
        kind, base = self.kind, self.base.__name__
        if not name or not isinstance(name, str):
            raise ValueError(f"{kind} name must be a non-empty string")
        if isinstance(target, str):
            if target.count(":") != 1 or not all(target.split(":")):
                raise ValueError(f"{kind} target must look like 'module:Class', got {target!r}")
        elif not (isinstance(target, type) and issubclass(target, self.base)):
            raise ValueError(
                f"{kind} target must be 'module:Class' or a {base} subclass: {target!r}"
            )
        self._registered[name] = target

    def available(self) -> list[str]:
        """Every name that can be chosen (nothing is imported), sorted."""
        return sorted(set(self.builtins) | set(self._entry_points()) | set(self._registered))

    def load(self, plugin: str) -> type[T]:
        """Import (if needed) and return the class registered as ``plugin``."""
        kind = self.kind
        target: str | type[T] | None = self._registered.get(plugin) or self.builtins.get(plugin)
        if target is None:
            target = self._entry_points().get(plugin)
        if target is None:
            raise self.error(
                f"unknown {kind} plugin {plugin!r}; known: {', '.join(self.available())}"
            )
        if isinstance(target, type):
            return target
        module_name, _, class_name = target.partition(":")
        try:
            module = importlib.import_module(module_name)
        except ImportError as err:
            raise self.error(
                f"{kind} {plugin!r}: cannot import {module_name!r} ({err}); is its package "
                "installed?"
            ) from err
        cls = getattr(module, class_name, None)
        if cls is None:
            raise self.error(f"{kind} {plugin!r}: {module_name!r} has no {class_name!r}")
        if not (isinstance(cls, type) and issubclass(cls, self.base)):
            raise self.error(f"{kind} {plugin!r}: {target} is not a {self.base.__name__} subclass")
        return cls
