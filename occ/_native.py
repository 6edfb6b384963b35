"""Which build of the control loop's hot path runs: mypyc-compiled or the pure Python sources.

The modules in :data:`MODULES` (the tick: robot, hardware, streams, motion, drivers, joints,
data, safety, interfaces, outputs, kinematics, the teleop controllers) can be compiled with
mypyc into C extension modules next to their sources (``python scripts/build_native.py``; an
option, ``OCC_NATIVE=1 scripts/test``: what ships is the pure build, since compiling saved only
10-18 % of a daemon's CPU, docs/BENCHMARKS.md "The compiled hot path"); the behaviour is the
same.

Python itself prefers an extension module to a source file of the same name, so stale ``.so``
files would silently run old code. This module, imported by ``occ/__init__.py`` before any of
them, decides once per process:

- ``OCC_PURE=1`` in the environment: pure (mutation testing, debugging, coverage);
- no build, or one for another interpreter: pure;
- a build whose recorded source hashes no longer match the sources: pure, with a warning
  naming the first changed file (a build is all or nothing: compiled modules assume each
  other's native layout, so a half-compiled set is never loaded);
- otherwise compiled.

When the answer is pure and extension files exist, a finder placed first on ``sys.meta_path``
loads these modules from their ``.py`` files. :data:`BUILD` says which build runs and why; the
daemon logs it at start and puts it in its statistics.

The module itself is never compiled and imports nothing from ``occ``.
"""

from __future__ import annotations

import ast
import hashlib
import importlib.abc
import importlib.machinery
import importlib.util
import json
import os
import sys
import warnings
from pathlib import Path
from types import ModuleType
from typing import Any

#: the compiled modules, in build order (mypyc compiles them as one group)
MODULES: tuple[str, ...] = (
    "occ.joint",
    "occ.core.data",
    "occ.core.safety",
    "occ.drivers.params",
    "occ.drivers.checks",
    "occ.drivers.base",
    "occ.drivers.sim_model",
    "occ.drivers.sim_faults",
    "occ.drivers.sim",
    "occ.drivers.sim_hand",
    "occ.net.interfaces",
    "occ.net.outputs",
    "occ.kinematics.frame",
    "occ.haptics.master_fixtures",
    "occ.controllers",
    "occ.controllers.teleop.common",
    "occ.controllers.teleop.phaselock",
    "occ.controllers.teleop.sixdof",
    "occ.controllers.teleop.checks",
    "occ.controllers.teleop.display",
    "occ.controllers.teleop.stream",
    "occ.controllers.teleop.shaping",
    "occ.controllers.teleop.returnsrc",
    "occ.controllers.teleop.instrument",
    "occ.controllers.teleop.absolute",
    "occ.controllers.teleop.master",
    "occ.controllers.teleop.slave",
    "occ.controllers.teleop",
    "occ.samples",
    "occ.net.decoders",
    "occ.net.packers",
    "occ.core.hardware",
    "occ.net.streams",
    "occ.core.motion",
    "occ.core.robot",
    "occ.core.transitions",
    "occ.core.wiring",
)

ROOT = Path(__file__).resolve().parent.parent
#: written by scripts/build_native.py: the sources' hashes, the interpreter, mypyc's version
MANIFEST = Path(__file__).resolve().with_name("_native.json")


def source_path(module: str, root: Path = ROOT) -> Path:
    """The ``.py`` file of one of :data:`MODULES` (a package's ``__init__.py``)."""
    rel = Path(*module.split("."))
    pkg = root / rel / "__init__.py"
    return pkg if pkg.is_file() else (root / rel).with_suffix(".py")


def extension_path(module: str, root: Path = ROOT) -> Path:
    """Where the compiled extension of ``module`` lives for this interpreter."""
    src = source_path(module, root)
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    return src.with_name(src.stem + suffix)


def source_hashes(root: Path = ROOT) -> dict[str, str]:
    return {m: hashlib.sha256(source_path(m, root).read_bytes()).hexdigest() for m in MODULES}


def _decide() -> tuple[str, str, bool, Path | None]:
    """(build, reason, extensions present, the build's shared library when compiled)."""
    present = any(extension_path(m).exists() for m in MODULES)
    if os.environ.get("OCC_PURE", "") not in ("", "0"):
        return "pure", "OCC_PURE is set", present, None
    if not MANIFEST.is_file():
        return "pure", "not built (python scripts/build_native.py)", present, None
    try:
        manifest = json.loads(MANIFEST.read_text())
        recorded: dict[str, str] = manifest["modules"]
        soabi = manifest["soabi"]
        group = ROOT / manifest["group"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        return "pure", f"unreadable build manifest {MANIFEST.name}: {err}", present, None
    if soabi != importlib.machinery.EXTENSION_SUFFIXES[0]:
        return "pure", f"built for another interpreter ({soabi})", present, None
    missing = [m for m in MODULES if not extension_path(m).exists()]
    if missing or set(recorded) != set(MODULES) or not group.is_file():
        return "pure", "incomplete build (python scripts/build_native.py)", present, None
    for module, digest in source_hashes().items():
        if recorded[module] != digest:
            rel = source_path(module).relative_to(ROOT)
            why = f"stale build: {rel} changed since (python scripts/build_native.py)"
            return "pure", why, True, None
    return "compiled", f"mypyc, {len(MODULES)} modules", True, group


class _PureFinder(importlib.abc.MetaPathFinder):
    """Loads :data:`MODULES` from their sources even where an extension module sits beside
    them (the default finder would take the extension)."""

    def find_spec(
        self, fullname: str, path: Any = None, target: ModuleType | None = None
    ) -> importlib.machinery.ModuleSpec | None:
        if fullname not in MODULES:
            return None
        leaf = fullname.rpartition(".")[2]
        for entry in path or ():
            pkg = Path(entry) / leaf / "__init__.py"
            if pkg.is_file():
                return importlib.util.spec_from_file_location(
                    fullname, pkg, submodule_search_locations=[str(pkg.parent)]
                )
            mod = Path(entry) / f"{leaf}.py"
            if mod.is_file():
                return importlib.util.spec_from_file_location(fullname, mod)
        return None


def _load_group(lib: Path) -> None:
    """Load the build's shared library (mypyc puts it at the project root, named
    ``<hash>__mypyc``) by its path, so that the compiled modules find it in ``sys.modules``
    whatever ``sys.path`` holds: console scripts (``occd``) and programs run from another
    directory do not have the project root on it."""
    name = lib.name.split(".", 1)[0]
    if name in sys.modules:
        return
    spec = importlib.util.spec_from_file_location(name, lib)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)


def _select() -> tuple[str, str]:
    build, reason, present, group = _decide()
    # a build that exists but cannot be used is worth a warning; pure by choice or for lack of
    # a build is not
    broken = reason.startswith(("stale", "incomplete"))
    if group is not None:
        try:
            _load_group(group)
        except (ImportError, OSError) as err:
            build, reason = "pure", f"the build's shared library does not load: {err}"
            broken = True
    if build == "pure" and present:
        if not any(isinstance(f, _PureFinder) for f in sys.meta_path):
            sys.meta_path.insert(0, _PureFinder())
    if broken:
        warnings.warn(f"occ: running the pure Python hot path: {reason}", stacklevel=3)
    return build, reason


BUILD, REASON = _select()


def describe() -> str:
    """One line for logs: which build runs, and why."""
    return f"{BUILD} ({REASON})"


def is_compiled(module: ModuleType) -> bool:
    """Whether an imported module is a compiled extension (not a ``.py`` file)."""
    return not str(getattr(module, "__file__", "") or "").endswith(".py")


def class_doc(cls: type) -> str:
    """A class's docstring, also for a compiled class (mypyc leaves ``__doc__`` empty): then
    read from the class's source file."""
    if cls.__doc__:
        return cls.__doc__
    module = cls.__module__
    if module not in MODULES:
        return ""
    tree = ast.parse(source_path(module).read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.ClassDef) and node.name == cls.__name__:
            return ast.get_docstring(node, clean=False) or ""
    return ""
