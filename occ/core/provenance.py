"""Where a robot's software comes from: what a black box dump (occ/recording/dump.py) says of
the daemon that wrote it, computed once when the robot is built (never on the loop).

The ``occ`` version and the hot path's build (compiled or pure, occ/_native.py), Python's and
the libraries' versions that compute the numbers (numpy, pinocchio), the SHA-256 of the URDF
the kinematics were built from and of every plugin's source file (each driver's and
controller's class, wherever it was loaded from: a built-in or an entry point), and the
daemon's configuration as YAML (the validated model, which :class:`~occ.config.DaemonConfig`
loads again).
"""

from __future__ import annotations

import hashlib
import inspect
import platform
from collections.abc import Iterable
from importlib import metadata
from pathlib import Path
from typing import Any

import yaml

from occ import _native
from occ.config import DaemonConfig
from occ.kinematics.frame import BUILTIN_MODELS, robots_dir


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 16), b""):
            h.update(block)
    return h.hexdigest()


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def urdf_of(config: DaemonConfig) -> Path | None:
    """The URDF file the robot's kinematics come from (a built-in model's too)."""
    fc = config.robot.frame
    path = fc.urdf_path()
    if path is None and fc.model is not None and fc.model in BUILTIN_MODELS:
        path = robots_dir() / BUILTIN_MODELS[fc.model][0]
    return path


def plugin_entry(obj: object) -> dict[str, Any]:
    """A plugin instance's class, module, source file and that file's SHA-256."""
    cls = type(obj)
    entry: dict[str, Any] = {"class": f"{cls.__module__}.{cls.__qualname__}"}
    try:
        src = inspect.getsourcefile(cls)
    except (TypeError, OSError):  # a built-in, compiled or interactive class: no source
        src = None
    if src is not None and Path(src).is_file():
        entry["file"] = src
        entry["sha256"] = file_sha256(Path(src))
    return entry


def provenance(
    config: DaemonConfig, drivers: Iterable[Any], controllers: Iterable[Any]
) -> dict[str, Any]:
    """What a dump's manifest says of the software and its inputs (module docstring)."""
    urdf = urdf_of(config)
    return {
        "software": {
            "occ": _version("occ-igtl"),
            "build": _native.BUILD,
            "python": platform.python_version(),
            "numpy": _version("numpy"),
            "pinocchio": _version("pin"),
        },
        "urdf": (
            {"path": str(urdf), "sha256": file_sha256(urdf)}
            if urdf is not None and urdf.is_file()
            else None
        ),
        "plugins": {
            "drivers": {d.name: plugin_entry(d) for d in drivers},
            "controllers": {
                getattr(c, "name", type(c).__name__): plugin_entry(c) for c in controllers
            },
        },
    }


def config_yaml(config: DaemonConfig) -> str:
    """The configuration as it runs, as YAML that validates again."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)
