"""The compiled hot path and its pure fallback (occ/_native.py, scripts/build_native.py).

Each build decision is checked in a fresh interpreter, as a daemon makes it at start. The tests
that need the build skip where it was not made (``python scripts/build_native.py``), and fail
instead under ``OCC_REQUIRE_NATIVE=1`` (CI).
"""

from __future__ import annotations

import ast
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from occ import _native
from occ.errors import DriverError, caused

ROOT = Path(__file__).resolve().parents[1]
BUILT = _native.MANIFEST.is_file() and all(
    _native.extension_path(m).exists() for m in _native.MODULES
)

PROBE = """
import json, importlib, warnings
warnings.simplefilter("always")
import occ._native as n
mods = {m: importlib.import_module(m).__file__ for m in n.MODULES}
print(json.dumps({"build": n.BUILD, "reason": n.REASON, "files": mods}))
"""


def needs_build() -> None:
    if BUILT:
        return
    if os.environ.get("OCC_REQUIRE_NATIVE") == "1":
        pytest.fail("the compiled build is required (OCC_REQUIRE_NATIVE=1) and missing")
    pytest.skip("not built: python scripts/build_native.py")


def probe(path: Path = ROOT, pure: bool = False, cwd: Path | None = None) -> tuple[dict, str]:
    """The build a fresh interpreter picks with ``path`` first on ``sys.path`` (None: nothing
    added, the installed package, as for a console script run from ``cwd``)."""
    env = {k: v for k, v in os.environ.items() if k not in ("OCC_PURE", "PYTHONPATH")}
    if pure:
        env["OCC_PURE"] = "1"
    if cwd is None:
        env["PYTHONPATH"] = os.pathsep.join([str(path), str(ROOT)])  # igtl from ROOT
    out = subprocess.run(
        [sys.executable, "-c", PROBE], cwd=cwd or path, env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout), out.stderr


def copy_build(tmp: Path) -> Path:
    """The package and the build (extensions, manifest, the group's shared library) in ``tmp``."""
    shutil.copytree(ROOT / "occ", tmp / "occ", ignore=shutil.ignore_patterns("__pycache__"))
    for lib in ROOT.glob("*__mypyc*.so"):
        shutil.copy2(lib, tmp / lib.name)
    return tmp


def all_sources(files: dict[str, str], under: Path) -> bool:
    return all(f.endswith(".py") and Path(f).is_relative_to(under) for f in files.values())


def all_extensions(files: dict[str, str], under: Path) -> bool:
    return all(f.endswith(".so") and Path(f).is_relative_to(under) for f in files.values())


def test_occ_pure_runs_the_sources_whatever_is_built() -> None:
    info, err = probe(pure=True)
    assert (info["build"], info["reason"]) == ("pure", "OCC_PURE is set")
    assert all_sources(info["files"], ROOT / "occ")
    assert "Warning" not in err


def test_a_current_build_runs_compiled() -> None:
    needs_build()
    info, err = probe()
    assert info["build"] == "compiled", info["reason"]
    assert all_extensions(info["files"], ROOT / "occ")
    assert "Warning" not in err


def test_the_installed_package_runs_compiled_from_any_directory(tmp_path: Path) -> None:
    """``occd`` and programs in tools/ or benchmarks/ do not have the project root on sys.path,
    where mypyc leaves the build's shared library: it is loaded by its path."""
    needs_build()
    info, err = probe(cwd=tmp_path)
    if not all(Path(f).is_relative_to(ROOT) for f in info["files"].values()):
        pytest.skip("occ is not installed from this tree (pip install -e .)")
    assert info["build"] == "compiled", info["reason"]
    assert all_extensions(info["files"], ROOT / "occ")
    assert "Warning" not in err


def test_a_changed_source_runs_every_module_pure_and_says_which(tmp_path: Path) -> None:
    needs_build()
    root = copy_build(tmp_path)
    info, _ = probe(root)
    assert info["build"] == "compiled" and all_extensions(info["files"], root / "occ")
    safety = root / "occ" / "core" / "safety.py"
    safety.write_text(safety.read_text() + "\n# edited after the build\n")
    info, err = probe(root)
    why = "stale build: occ/core/safety.py changed since (python scripts/build_native.py)"
    assert (info["build"], info["reason"]) == ("pure", why)
    # all or nothing: the unchanged modules run from their sources too, the extensions beside
    assert all_sources(info["files"], root / "occ")
    assert _native.extension_path("occ.core.robot", root).exists()
    assert f"occ: running the pure Python hot path: {why}" in err


@pytest.mark.parametrize(
    ("damage", "reason"),
    [
        ("soabi", "built for another interpreter (.cpython-39-x86_64-linux-gnu.so)"),
        ("manifest", "not built (python scripts/build_native.py)"),
        ("extension", "incomplete build (python scripts/build_native.py)"),
        ("group", "incomplete build (python scripts/build_native.py)"),
        ("garbage", "unreadable build manifest _native.json: "),
    ],
)
def test_a_build_that_does_not_fit_runs_pure(tmp_path: Path, damage: str, reason: str) -> None:
    needs_build()
    root = copy_build(tmp_path)
    manifest = root / "occ" / "_native.json"
    if damage == "soabi":
        data = json.loads(manifest.read_text())
        data["soabi"] = ".cpython-39-x86_64-linux-gnu.so"
        manifest.write_text(json.dumps(data))
    elif damage == "manifest":
        manifest.unlink()
    elif damage == "extension":
        _native.extension_path("occ.kinematics.frame", root).unlink()
    elif damage == "group":
        (root / json.loads(manifest.read_text())["group"]).unlink()
    else:
        manifest.write_text("{not json")
    info, _ = probe(root)
    assert info["build"] == "pure" and info["reason"].startswith(reason), info["reason"]
    assert all_sources(info["files"], root / "occ")


def test_class_doc_reads_a_compiled_class_s_docstring_from_its_source() -> None:
    from occ.core.robot import Robot
    from occ.core.safety import StateMachine

    for cls, file in ((Robot, "occ/core/robot.py"), (StateMachine, "occ/core/safety.py")):
        tree = ast.parse((ROOT / file).read_text())
        node = next(
            n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == cls.__name__
        )
        expected = ast.get_docstring(node, clean=False)
        assert expected and _native.class_doc(cls) == expected
    assert _native.class_doc(DriverError) == DriverError.__doc__  # an interpreted class


def test_caused_sets_the_cause_and_never_a_cycle() -> None:
    err = OSError("bus gone")
    wrapped = caused(DriverError("read failed"), err)
    assert wrapped.__cause__ is err and wrapped.__suppress_context__
    same = DriverError("x")
    assert caused(same, same) is same and same.__cause__ is None


PLUGINS = '''
import json
import occ._native as n
from occ.controllers import register_controller
from occ.controllers.teleop import SlaveController
from occ.drivers import register_driver
from occ.drivers.sim import SimDriver
from occ_testkit.testing import SimRobot


class CountingSim(SimDriver):
    """A user's driver: the built-in simulation, counting its reads."""

    reads_seen = 0

    def _read(self, now):
        CountingSim.reads_seen += 1
        return super()._read(now)


class LoggingSlave(SlaveController):
    """A user's controller: the built-in teleoperated slave, counting its samples."""

    samples = 0

    def on_sample(self, item, now):
        LoggingSlave.samples += 1
        return super().on_sample(item, now)


register_driver("counting-sim", CountingSim)
register_controller("logging-slave", LoggingSlave)
from occ.core.loader import load_config
base = load_config("configs/slave.yaml")
drv = base.robot.drivers[0].model_copy(update={"plugin": "counting-sim"})
ctl = base.controllers[0].model_copy(update={"plugin": "logging-slave"})
config = base.model_copy(update={"robot": base.robot.model_copy(update={"drivers": (drv,)}),
                                 "controller": ctl})
with SimRobot(config) as sim:
    master = sim.peer("master", address=("127.0.0.1", 40000))
    op = sim.peer("operator")
    op.send_command("Enable"); sim.step(1)
    op.send_command("Run"); sim.step(1)
    for seq in range(1, 51):
        master.send_position((0.0, 0.1 * seq, 0.0), seq=seq)
        sim.step(2)
    state = sim.robot.state.value
print(json.dumps({"build": n.BUILD,
                  "sim_file": __import__("occ.drivers.sim").drivers.sim.__file__,
                  "reads": CountingSim.reads_seen, "samples": LoggingSlave.samples,
                  "state": state}))
'''


def test_a_plugin_subclasses_a_built_in_driver_and_controller_in_the_default_build() -> None:
    """Issue 26: a user's driver may extend ``sim`` (and a controller the teleop slave) in
    the build that runs here (pure as shipped; compiled where it was built, whose classes
    once refused interpreted subclasses)."""
    env = {k: v for k, v in os.environ.items() if k not in ("OCC_PURE", "PYTHONPATH")}
    env["PYTHONPATH"] = str(ROOT)
    out = subprocess.run(
        [sys.executable, "-c", PLUGINS], cwd=ROOT, env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.splitlines()[-1])
    assert got["build"] == ("compiled" if BUILT else "pure"), got
    assert got["sim_file"].endswith(".py") is (got["build"] == "pure"), got
    assert got["state"] == "RUNNING" and got["reads"] > 100 and got["samples"] == 50, got
