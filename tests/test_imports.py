"""House rules on imports: ``igtl`` never imports ``occ``, no runtime package imports the
harness ``occ_testkit``, and no module of ``occ`` imports itself back through others at import
time (an import cycle: the order modules happen to load in would decide whether the daemon
starts).

Only imports that run when a module loads count: those at module level outside ``if
TYPE_CHECKING:``. Imports inside functions are deliberate late binding (e.g. the loader
importing the plugin registries) and cannot form a load-time cycle.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imported(sub: ast.AST, package: str) -> set[str]:
    """The modules one import statement names (relative ones resolved against ``package``)."""
    if isinstance(sub, ast.Import):
        return {a.name for a in sub.names}
    if not isinstance(sub, ast.ImportFrom):
        return set()
    if sub.level:
        base = package.split(".")
        base = base[: len(base) - (sub.level - 1)]
        mod = ".".join(base + ([sub.module] if sub.module else []))
    else:
        mod = sub.module or ""
    found = {f"{mod}.{a.name}" for a in sub.names}  # `from pkg import module`
    if sub.module:  # `from . import a` loads the submodule a, not the package
        found.add(mod)
    return found


def _load_time_imports(path: Path, name: str) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in tree.body:  # module level only
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            continue
        for sub in ast.walk(node) if isinstance(node, ast.If | ast.Try) else [node]:
            found |= _imported(sub, package)
    return found


def _graph(package: str) -> dict[str, set[str]]:
    modules = {_module_name(p): p for p in (ROOT / package).rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        graph[name] = {m for m in _load_time_imports(path, name) if m in modules and m != name}
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def test_no_import_cycle_in_occ() -> None:
    cycle = _cycle(_graph("occ"))
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_no_import_cycle_in_igtl() -> None:
    cycle = _cycle(_graph("igtl"))
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def _named_imports(path: Path) -> list[str]:
    """The module names every import statement of ``path`` names, anywhere in it."""
    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            names.append(node.module or "")
        elif isinstance(node, ast.Import):
            names.extend(a.name for a in node.names)
    return names


def test_igtl_never_imports_occ() -> None:
    for path in (ROOT / "igtl").rglob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("occ"):
                raise AssertionError(f"{path.relative_to(ROOT)} imports {node.module}")
            if isinstance(node, ast.Import) and any(a.name.startswith("occ") for a in node.names):
                raise AssertionError(f"{path.relative_to(ROOT)} imports occ")


def test_the_cycle_finder_finds_cycles() -> None:
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


#: the one place in the core that may import rosbags: ``occ-record export --format mcap``
#: (occ/recording/export.py, the optional ``record`` extra), inside its functions only, and no daemon
#: module imports that file at module level (test below)
ROSBAGS_EXPORTER = Path("occ") / "recording" / "export.py"


def _function_local(tree: ast.AST) -> set[int]:
    """ids of the import nodes inside a function body."""
    inside: set[int] = set()
    for fn in ast.walk(tree):
        if isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
            inside.update(id(n) for n in ast.walk(fn) if isinstance(n, ast.Import | ast.ImportFrom))
    return inside


def test_the_core_never_imports_dds() -> None:
    """DDS is the optional ``ros2`` extra: neither ``igtl`` nor ``occ`` may import it (or the
    bridge package that does), anywhere, so the daemons run without it installed. rosbags
    only in the MCAP exporter's functions (:data:`ROSBAGS_EXPORTER`)."""
    banned = ("cyclonedds", "occ_ros2", "rosbags")
    for package in ("igtl", "occ"):
        for path in (ROOT / package).rglob("*.py"):
            tree = ast.parse(path.read_text(encoding="utf-8"))
            exempt = _function_local(tree) if path.relative_to(ROOT) == ROSBAGS_EXPORTER else set()
            for node in ast.walk(tree):
                if id(node) in exempt and (
                    isinstance(node, ast.ImportFrom)
                    and (node.module or "").startswith("rosbags")
                    or isinstance(node, ast.Import)
                    and all(a.name.split(".")[0] == "rosbags" for a in node.names)
                ):
                    continue
                names = (
                    [node.module or ""]
                    if isinstance(node, ast.ImportFrom)
                    else [a.name for a in node.names]
                    if isinstance(node, ast.Import)
                    else []
                )
                for name in names:
                    where = path.relative_to(ROOT)
                    assert name.split(".")[0] not in banned, f"{where} imports {name}"


def test_no_daemon_module_imports_the_exporter_at_import_time() -> None:
    """occ/recording/export.py (rosbags, for ``occ-record export``) is imported only inside
    functions: the daemons never load it."""
    for path in (ROOT / "occ").rglob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        local = _function_local(tree)
        for node in ast.walk(tree):
            if id(node) in local:
                continue
            if isinstance(node, ast.ImportFrom) and (node.module or "").endswith("recexport"):
                raise AssertionError(f"{path.relative_to(ROOT)} imports the exporter at import")


def test_the_core_never_imports_the_console() -> None:
    """The staff console (``occ_console``, the ``console`` extra: Starlette, uvicorn) is a
    client of the daemons like any other: nothing in ``igtl``, ``occ`` or ``occ_ros2`` imports
    it or its web stack."""
    banned = ("occ_console", "starlette", "uvicorn")
    for package in ("igtl", "occ", "occ_ros2"):
        for path in (ROOT / package).rglob("*.py"):
            for name in _named_imports(path):
                where = path.relative_to(ROOT)
                assert name.split(".")[0] not in banned, f"{where} imports {name}"


def test_the_runtime_never_imports_the_testkit() -> None:
    """``occ_testkit`` is the test and tool harness (simulated time, the fault matrix, network
    namespaces): no runtime package imports it, anywhere, so the daemons, the bridge and the
    console run without it and it never runs in them."""
    for package in ("igtl", "occ", "occ_ros2", "occ_console"):
        for path in (ROOT / package).rglob("*.py"):
            for name in _named_imports(path):
                where = path.relative_to(ROOT)
                assert name.split(".")[0] != "occ_testkit", f"{where} imports {name}"


def test_the_testkit_has_no_import_cycle() -> None:
    cycle = _cycle(_graph("occ_testkit"))
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_the_console_has_no_import_cycle() -> None:
    cycle = _cycle(_graph("occ_console"))
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_the_ros2_bridge_has_no_import_cycle() -> None:
    cycle = _cycle(_graph("occ_ros2"))
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def _all_imports(path: Path, name: str, package: str) -> set[str]:
    """Every module ``path`` imports anywhere: module level, ``TYPE_CHECKING``, functions."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    pkg = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for sub in ast.walk(tree):
        found |= _imported(sub, pkg)
    return found


def _design_graph(folder: str) -> dict[str, set[str]]:
    """Who knows whom, at any time: every import counts (type-only and late ones too). The
    tools are top-level modules (tools/ on sys.path): named by their file."""
    root = ROOT / folder
    if folder == "tools":
        modules = {p.stem: p for p in root.glob("*.py")}
    else:
        modules = {_module_name(p): p for p in root.rglob("*.py")}
    return {
        name: {m for m in _all_imports(path, name, folder) if m in modules and m != name}
        for name, path in modules.items()
    }


@pytest.mark.parametrize("folder", ["occ", "tools"])
def test_no_module_knows_one_that_knows_it(folder: str) -> None:
    """Issue 26: collaborators get narrow ports; nothing imports a module that imports it back,
    not even for type hints or inside a function (robot <-> operators <-> alarms,
    record <-> recplot and soak <-> stability once did)."""
    cycle = _cycle(_design_graph(folder))
    assert cycle is None, "circle: " + " -> ".join(cycle or [])


#: the modules of occ/ that may import ``igtl`` at all (issue 39: bytes become typed values
#: in one layer, and typed values become bytes in one place), and why each must
IGTL_ALLOWED = {
    "occ.net.interfaces": "the transports, routing and the replies to refused requests",
    "occ.net.streams": "the polled UDP sockets: the loop reads them itself",
    "occ.net.decoders": "every received message to its typed event (occ/events.py)",
    "occ.net.packers": "every typed output value to its message",
    "occ.net.celllink": "the cell's heartbeats are NDARRAY messages on its own UDP endpoint",
    "occ.net.outputs": "the built-in sources (tip, base, status, joints) build their messages",
    "occ.net.commands": "operator requests and their replies are messages (RTS_, ACK_, STATUS)",
    "occ.net.operators": "the operator desk answers requests with messages",
    "occ.core.alarms": "alerts go to the operators as STATUS messages",
    "occ.core.robot": "the status codes of the alerts it raises",
    "occ.core.transitions": "the status code of the alert a refused Enable raises",
    "occ.core.ports": "the desk's reply port is typed with the reply message (a type hint only)",
    "occ.config.interfaces": "the interfaces' authentication key (igtl.auth.load_key), checked at load",
    "occ.core.loop": "names its native thread (igtl.transport.common.name_native_thread)",
    "occ.core.supervision": "names its native thread, as the loop does",
    "occ.ratelimit": "igtl's log-line budget (a counter, no wire type) named for the rooms "
    "that may not import igtl themselves",
    "occ.recording.record": "a recording is the messages as they were sent and received",
    "occ.recording.cli": "replays and reads recordings (messages)",
}


def test_only_the_edge_of_the_daemon_imports_igtl() -> None:
    """Issue 39: only the modules of :data:`IGTL_ALLOWED` import ``igtl``, at module level,
    under ``TYPE_CHECKING`` or inside a function; every other module of occ/ (the controllers,
    their helpers, the core) sees typed values only."""
    root = ROOT / "occ"
    for path in root.rglob("*.py"):
        name = _module_name(path)
        if name in IGTL_ALLOWED:
            continue
        found = sorted(m for m in _all_imports(path, name, "occ") if m.split(".")[0] == "igtl")
        assert not found, f"{path.relative_to(ROOT)} imports {found[0]}: not in IGTL_ALLOWED"


def test_the_igtl_rule_catches_a_controller_that_imports_it(tmp_path: Path) -> None:
    """The rule above reads every kind of import (late, type-only) the way it reads occ/."""
    src = (
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from igtl.messages.base import Message\n"
        "def f():\n    import igtl\n"
    )
    path = tmp_path / "teleop.py"
    path.write_text(src, encoding="utf-8")
    found = {m for m in _all_imports(path, "occ.controllers.teleop", "occ") if m.startswith("igtl")}
    assert {"igtl", "igtl.messages.base"} <= found
    assert "occ.controllers.teleop" not in IGTL_ALLOWED
    assert not any(k.startswith("occ.controllers") for k in IGTL_ALLOWED)


def test_no_controller_imports_igtl_messages() -> None:
    """Issue 26: controllers take typed samples (occ/samples.py) and return typed outputs
    (occ/net/outputs.py packs them); none imports OpenIGTLink's message classes, not even for
    type hints."""
    for path in (ROOT / "occ" / "controllers").rglob("*.py"):
        for name in _named_imports(path):
            where = path.relative_to(ROOT)
            assert name != "igtl" and not name.startswith("igtl.messages"), (
                f"{where} imports {name}"
            )


# --------------------------------------------------------------------------- the rooms of occ/
#: occ/'s top-level modules: the vocabulary every room speaks (they import no room)
VOCABULARY = {"errors", "plugins", "clock", "joint", "samples", "events", "ratelimit", "_native"}
#: the daemon's commands, which may import anything
ENTRY = {"cli", "configdoc"}
#: room -> the rooms it may import (its own and the vocabulary always); each subpackage's
#: docstring says the same in words (issue 39)
ROOMS: dict[str, set[str]] = {
    "drivers": set(),
    "config": {"kinematics"},  # the robot section loads the URDF through the Frame at check
    "kinematics": {"config"},
    "haptics": {"config", "kinematics"},
    "recording": {"net", "haptics"},
    "controllers": {"config", "kinematics", "haptics", "net"},
    "net": {"config", "kinematics", "haptics", "recording", "controllers"},
    "core": {"config", "kinematics", "haptics", "net", "recording", "controllers", "drivers"},
}
#: the few imports across the rules, each with its reason
ROOM_EXCEPTIONS = {
    # what a controller, the outputs and the recorder read of the robot: its data and state
    ("*", "occ.core.data"): "RobotData: the robot's state as every part reads it",
    ("*", "occ.core.safety"): "RobotState and the loss monitor's verdicts are shared names",
    ("occ.kinematics.collision", "occ.core.supervision"): "the run-time guard checks on the "
    "worker thread",
    ("occ.haptics.forceviz", "occ.net.packers"): "a type hint: the output it fills",
    ("occ.recording.control", "occ.core.ports"): "the recording control's narrow port",
    ("occ.recording.cli", "occ.core.replay"): "replay --deterministic rebuilds the robot from "
    "a black box dump (inside the command's function only)",
    ("occ.net.operators", "occ.core.ports"): "the operator desk's narrow port",
    ("occ.controllers.teleop.slave", "occ.core.stats"): "the loop's Histogram for its latencies",
    ("occ.net.streams", "occ.core.assembly"): "a hand-over rebuilds the loss monitors as the "
    "assembly built them",
}


def _room(module: str) -> str | None:
    parts = module.split(".")
    if parts[0] != "occ" or len(parts) < 2:
        return None
    if parts[1] in VOCABULARY:
        return "vocabulary"
    if parts[1] in ENTRY:
        return "entry"
    return parts[1]


def test_occ_is_a_few_rooms_and_the_vocabulary() -> None:
    """Issue 39: occ/ is subpackages by room plus a small vocabulary at the top; no module of
    the top level is anything else."""
    top = {p.stem for p in (ROOT / "occ").glob("*.py")} - {"__init__"}
    assert top <= VOCABULARY | ENTRY, top - VOCABULARY - ENTRY
    rooms = {p.name for p in (ROOT / "occ").iterdir() if (p / "__init__.py").exists()}
    assert rooms == set(ROOMS), rooms ^ set(ROOMS)
    for room in rooms:
        doc = ast.get_docstring(ast.parse((ROOT / "occ" / room / "__init__.py").read_text()))
        assert doc and "import" in doc, f"occ/{room}/__init__.py: what lives there, what it imports"


def test_each_room_imports_only_what_its_rule_allows() -> None:
    """Issue 39: every import (module level, type-only, late) of a module of occ/ stays in its
    room, the vocabulary and the rooms its rule names, or is one of the named exceptions."""
    bad = []
    for path in (ROOT / "occ").rglob("*.py"):
        name = _module_name(path)
        room = _room(name) or "vocabulary"
        if room == "entry":
            continue
        for imp in sorted(_all_imports(path, name, "occ")):
            other = _room(imp)
            if other is None or other in (room, "vocabulary"):
                continue
            if room != "vocabulary" and other in ROOMS[room]:
                continue
            target = next((m for m in (imp, imp.rpartition(".")[0]) if _room(m) == other), imp)
            if ("*", target) in ROOM_EXCEPTIONS or (name, target) in ROOM_EXCEPTIONS:
                continue
            if any(imp.startswith(t + ".") or imp == t for (w, t) in ROOM_EXCEPTIONS
                   if w in ("*", name)):
                continue
            bad.append(f"{name} ({room}) imports {imp} ({other})")
    assert not bad, "\n".join(bad)


def test_the_room_rule_catches_a_driver_that_reaches_into_the_core(tmp_path: Path) -> None:
    """The rule above would see a driver importing the Robot (a late import too)."""
    src = "def f():\n    from occ.core.robot import Robot\n"
    path = tmp_path / "mydrive.py"
    path.write_text(src, encoding="utf-8")
    imps = _all_imports(path, "occ.drivers.mydrive", "occ")
    assert "occ.core.robot" in imps and _room("occ.core.robot") not in ROOMS["drivers"]
