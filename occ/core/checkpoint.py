"""Checkpoints of a robot's state: where a deterministic replay starts (issue 41, item 4).

A replay rebuilds the robot from its config and must begin from the state every part had at
the checkpoint's tick: the controllers' filters and integrators, the loss monitors' counters
and clock offsets, the motion's re-entry ramp, the drives' checks, the state machine, the
cell. Writing a ``snapshot()`` for each part would miss whatever the next part adds, so the
checkpointer finds the state itself, once, when the robot is built and configured:

- it walks the robot's object graph from the :class:`~occ.core.robot.Robot`; an object of
  this project's code (``occ``, ``igtl``, and the plugins' own modules) reached there is a
  *part*: it exists in every robot built from the same config, at the same *path*
  (``robot.controller.controllers[0].filter``), and keeps its identity;
- every attribute of a part is a *slot*, except what is wiring, not state: callables (bound
  methods, handlers), locks, threads, sockets, queues, loggers, the validated configuration
  (pydantic models, fixed at build) and objects of foreign libraries (a pinocchio model's
  scratch data, rewritten by each use), alone or as the only items of a list or tuple (a
  collision checker's coal transforms, one a link);
- an attribute a class names in ``checkpoint_fixed`` is wiring too: a table its constructor
  derives from the configuration and nothing changes after (the output scheduler's schedule,
  the statistics registry's entries), rebuilt the same by every robot built from that config;
- the subtrees that are I/O or records, not the loop's state, are *opaque*: the interfaces
  (their threads), the black box, the State Data Table, the recorder, the loop and its clock.
  A slot that refers to one keeps the reference, nothing inside is taken.

:meth:`Checkpointer.take` (the loop thread, at the end of a tick) reads every slot: immutable
values as they are, a reference to a part as the reference, anything else (a list, an array,
a sample object made at run time) copied deeply, its references to parts kept as references.
:meth:`Checkpointer.dumps` (the dump writer's thread) pickles it with each part written as its
path, and :func:`restore` (the replay) sets every slot of a robot built from the same config,
each path resolved to that robot's own part. Loading takes only the classes this project
defines, numpy's arrays, scalars, dtypes and random generators, a few builtins and the
checkpoint's own two constructors (:meth:`_PartUnpickler.find_class`): never a function that
could call another (``getattr``), a module or a foreign class one of this project's modules
imports, or the rest of numpy, so a dump from elsewhere cannot run code (the ``find_class``
restriction the :mod:`pickle` documentation recommends; until 2026-11-29 ``getattr`` and
anything an ``occ`` module held, its ``os`` among them, were allowed: a crafted replay.pkl
ran a shell command).

What a checkpoint cannot hold is reported, never silently dropped: a slot whose value cannot be
copied (it holds a thread: a power-up under way), or written, or read back as a replay reads it
(it holds an object of a foreign class) is marked and named by :func:`restore`.
"""

from __future__ import annotations

import copy
import enum
import hashlib
import io
import pickle
import random
from array import array
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from types import MappingProxyType
from typing import Any

import numpy as np

try:
    from pydantic import BaseModel
except ImportError:  # pragma: no cover - pydantic is a dependency of the config
    BaseModel = ()  # type: ignore[assignment,misc]

#: module roots whose objects are parts (plus the plugins' own, found at discovery)
OURS = frozenset({"occ", "igtl"})
#: modules whose objects are never state (I/O, threads, logging)
_WIRING_MODULES = frozenset(
    {"_thread", "threading", "socket", "queue", "logging", "selectors", "_io", "io", "ssl"}
)
#: module roots of the values a slot may hold besides this project's objects; a value of any
#: other library is not the loop's state (a pinocchio model's scratch data, a bus handle)
_VALUE_ROOTS = frozenset(
    {"builtins", "collections", "numpy", "array", "itertools", "random", "enum", "datetime"}
)
_IMMUTABLE = frozenset({float, int, bool, str, bytes, type(None), complex, MappingProxyType})
_CONTAINERS = frozenset({tuple, frozenset, list, set, deque, dict})
#: what a checkpoint may load besides this project's classes: the builtins and standard
#: library classes a slot's value may hold (containers, numbers, a random generator), numpy's
#: arrays, scalars and dtypes (the constructors pickle writes for them, in numpy 1's spelling
#: too: a dump written elsewhere) and random generators' constructors; never a function that
#: could do anything else (``getattr``: with it any object reached is a way to ``os.system``;
#: numpy's others: they write files, and one runs a string as code)
_SAFE_GLOBALS = frozenset(
    {
        ("builtins", "set"),
        ("builtins", "frozenset"),
        ("builtins", "complex"),
        ("builtins", "slice"),
        ("builtins", "bytearray"),
        ("builtins", "object"),
        ("collections", "deque"),
        ("collections", "OrderedDict"),
        ("array", "array"),
        ("array", "_array_reconstructor"),
        ("random", "Random"),
        ("itertools", "count"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("numpy.core.numeric", "_frombuffer"),
        ("numpy._core.numeric", "_frombuffer"),
        ("numpy.random._pickle", "__generator_ctor"),
        ("numpy.random._pickle", "__bit_generator_ctor"),
        ("numpy.random._pickle", "__randomstate_ctor"),
        ("numpy.random.bit_generator", "__pyx_unpickle_SeedSequence"),
    }
)
#: numpy's modules of the random generators' bits, whose classes may load when they are one
#: (numpy.random.PCG64 and its kin, SeedSequence)
_NUMPY_BITS = frozenset(
    {
        "numpy.random.bit_generator",
        "numpy.random._mt19937",
        "numpy.random._pcg64",
        "numpy.random._philox",
        "numpy.random._sfc64",
    }
)
_BITS_CLASSES = (np.random.BitGenerator, np.random.SeedSequence)


class _Keep:
    """A slot whose value is not state (an object of a class marked ``checkpoint_opaque``
    made after the robot was built: the supervisor's thread): the replay keeps its own."""

    def __repr__(self) -> str:
        return "<kept as built>"


KEEP = _Keep()


class Unsaved:
    """A slot whose value could not be copied at the checkpoint (named by :func:`restore`)."""

    def __init__(self, why: str) -> None:
        self.why = why

    def __repr__(self) -> str:
        return f"<not saved: {self.why}>"


def _root(obj: object) -> str:
    return type(obj).__module__.partition(".")[0]


def _attrs(obj: object) -> Iterator[tuple[str, Any]]:
    """An object's stored attributes (its ``__dict__`` and its slots), never properties."""
    d = getattr(obj, "__dict__", None)
    if d is not None:
        yield from list(d.items())
    for cls in type(obj).__mro__:
        for name in getattr(cls, "__slots__", ()):
            if name in ("__dict__", "__weakref__") or (d is not None and name in d):
                continue
            if name.startswith("__") and not name.endswith("__"):
                name = f"_{cls.__name__.lstrip('_')}{name}"  # a private slot's mangled name
            try:
                yield name, getattr(obj, name)
            except AttributeError:
                continue  # an unset slot: nothing to keep


def _wiring(value: object, roots: frozenset[str] = OURS) -> bool:
    """A value that is wiring, not state (module docstring)."""
    root = _root(value)
    if callable(value) and not isinstance(value, type) and root not in roots:
        return True  # functions, bound methods, partials (our callable objects are parts)
    if isinstance(value, type) or isinstance(value, BaseModel):
        return True
    return root not in roots and root not in _VALUE_ROOTS


def _scratch(value: object, roots: frozenset[str]) -> bool:
    """A list or tuple of foreign objects only (a collision checker's coal transforms, one a
    link): a foreign library's scratch data as its items are, rewritten by each use."""
    if type(value) not in (list, tuple) or not value:
        return False
    return all(
        not callable(v) and _root(v) not in roots and _root(v) not in _VALUE_ROOTS
        for v in value  # type: ignore[attr-defined]
    )


class Checkpointer:
    """The slots of one robot (module docstring): found once, read by :meth:`take`."""

    def __init__(
        self,
        root: object,
        *,
        opaque: Iterable[object] = (),
        io: Iterable[object] = (),
        roots: Iterable[str] = (),
    ) -> None:
        """``opaque``: parts whose attributes are not state (records, the loop); ``io``: the
        same, and every part reached from them (the interfaces: their transports, links and
        peers); ``roots``: the plugins' module roots."""
        self.roots = OURS | frozenset(roots)
        #: id(part) -> its path (the parts are kept alive by ``parts``: ids stay theirs)
        self.paths: dict[int, str] = {}
        self.parts: dict[str, object] = {}
        #: (part, attribute, path) of every slot, in discovery order
        self.slots: list[tuple[object, str, str]] = []
        self._opaque: set[int] = {id(o) for o in opaque if o is not None}
        for o in io:  # and every part reached from it: the interfaces' transports...
            if o is not None:
                self._close(o)
        self._discover(root)
        self._memo = {i: self.parts[p] for i, p in self.paths.items()}

    def _is_part(self, value: object) -> bool:
        if type(value) in _IMMUTABLE or isinstance(value, enum.Enum | BaseException):
            return False
        if isinstance(value, type) or isinstance(value, BaseModel):
            return False
        return _root(value) in self.roots and (
            hasattr(value, "__dict__") or hasattr(type(value), "__slots__")
        )

    def _close(self, top: object) -> None:
        todo = [top]
        while todo:
            obj = todo.pop()
            if id(obj) in self._opaque:
                continue
            self._opaque.add(id(obj))
            for _, value in _attrs(obj):
                if not _wiring(value, self.roots):
                    todo.extend(_parts_in(value, self._is_part))

    def _discover(self, root: object) -> None:
        todo: deque[tuple[object, str]] = deque([(root, "robot")])
        self.paths[id(root)] = "robot"
        self.parts["robot"] = root
        while todo:
            obj, path = todo.popleft()
            if id(obj) in self._opaque:
                continue
            fixed = getattr(type(obj), "checkpoint_fixed", ())
            for name, value in _attrs(obj):
                if name in fixed or _wiring(value, self.roots) or _scratch(value, self.roots):
                    continue
                where = f"{path}.{name}"
                self.slots.append((obj, name, where))
                self._find_parts(value, where, todo, 0)

    def _find_parts(
        self, value: object, path: str, todo: deque[tuple[object, str]], depth: int
    ) -> None:
        if type(value) in _IMMUTABLE or depth > 6:
            return
        if isinstance(value, list | tuple | deque | set | frozenset):
            for i, v in enumerate(value):
                self._find_parts(v, f"{path}[{i}]", todo, depth + 1)
        elif isinstance(value, dict):
            for k, v in value.items():
                self._find_parts(v, f"{path}[{k!r}]", todo, depth + 1)
        elif id(value) in self.paths:
            return
        elif _wiring(value, self.roots):  # a handler in a table: the same one by its place
            self.paths[id(value)] = path
            self.parts[path] = value
        elif self._is_part(value):
            if getattr(type(value), "checkpoint_opaque", False):
                self._opaque.add(id(value))
            self.paths[id(value)] = path
            self.parts[path] = value
            todo.append((value, path))

    # ------------------------------------------------------------------ the loop thread
    def take(self) -> list[Any]:
        """Every slot's value now (module docstring), in slot order. One copy of an object
        that several slots share (the copies share it as the originals did)."""
        out: list[Any] = []
        add = out.append
        paths = self.paths
        memo: dict[int, Any] = dict(self._memo)
        snap = self._snap
        for obj, name, _ in self.slots:
            try:
                v = getattr(obj, name)
            except AttributeError:
                add(Unsaved("unset"))
                continue
            if type(v) in _IMMUTABLE or id(v) in paths:
                add(v)
                continue
            try:
                add(snap(v, memo, 0))
            except Exception as err:  # noqa: BLE001 - one slot, named on restore
                add(Unsaved(f"{type(v).__name__}: {err}"))
        return out

    def _flat(self, items: Iterable[Any]) -> bool:
        """Every item immutable, a part or wiring: a shallow copy is a whole one."""
        paths = self.paths
        for x in items:
            if type(x) not in _IMMUTABLE and id(x) not in paths and not _wiring(x, self.roots):
                return False
        return True

    def _snap(self, v: Any, memo: dict[int, Any], depth: int) -> Any:
        """A copy of ``v`` that the loop's next ticks cannot change: containers copied (and
        their contents, as far as they are not immutable, parts or wiring), arrays copied,
        any other object copied deeply with its references to parts kept."""
        t = type(v)
        if t in _IMMUTABLE or isinstance(v, enum.Enum):
            return v
        got = memo.get(id(v), memo)  # parts map to themselves; a copy made already: it
        if got is not memo:
            return got
        out: Any
        if depth < 8 and t in _CONTAINERS:
            if t is dict:
                out = (
                    v.copy()
                    if self._flat(v.values())
                    else {k: self._snap(x, memo, depth + 1) for k, x in v.items()}
                )
            else:
                items = v if self._flat(v) else [self._snap(x, memo, depth + 1) for x in v]
                if t is tuple and items is v:
                    out = v
                else:
                    out = deque(items, v.maxlen) if t is deque else t(items)
        elif t is np.ndarray and v.dtype != object:
            out = v.copy()
        elif t is array:
            out = array(v.typecode, v)
        elif t is random.Random:  # its state as a tuple: a seventh of a deep copy's time
            out = random.Random(0)
            out.setstate(v.getstate())
        elif _wiring(v, self.roots):
            return v
        elif getattr(t, "checkpoint_opaque", False):
            return KEEP
        else:
            return copy.deepcopy(v, memo)  # it records what it copied in the memo
        memo[id(v)] = out
        return out

    # ------------------------------------------------------------------ the writer thread
    def dumps(
        self,
        values: list[Any],
        baseline: list[Any] | None = None,
        pace: Callable[[], None] | None = None,
    ) -> bytes:
        """``values`` (a :meth:`take`) pickled with every part written as its path; with the
        ``baseline`` (the :meth:`take` of the robot as built, before its first tick), only
        the slots that changed since, a digest of every slot's baseline and every slot's value
        as built (``built``), the drivers' own named (``drives``): a replay of the same
        configuration takes the recorded build where its own differs (a boot number, the
        time of a reading), one with another configuration keeps what its build made of it,
        so the change counts, but always takes the recorded drives (:func:`restore`).
        ``pace()`` is called every few slots (the black box's writer: out of the loop's
        way)."""
        step = _paced(pace)
        items = [(path, v) for (_, _, path), v in zip(self.slots, values, strict=True)]
        digests: dict[str, str] = {}
        drives: dict[str, Any] = {}
        built: dict[str, Any] = {}
        if baseline is not None:
            # the drives as the build left them: every slot of each driver (a part with the
            # readings ``raw``), among them the readings the build took (a replay's configure)
            held = {p.rpartition(".")[0] for _, name, p in self.slots if name == "raw"}
            built = {p: v for (_, _, p), v in zip(self.slots, baseline, strict=True)}
            drives = {p: v for p, v in built.items() if p.rpartition(".")[0] in held}
            base = [step(self._bytes(v)) for v in baseline]
            digests = {
                p: hashlib.sha256(b).hexdigest()[:16]
                for (_, _, p), b in zip(self.slots, base, strict=True)
            }
            # a baseline that could not be pickled (b""; no pickle is empty) compares equal
            # to nothing: the slot is written, and marked if it still cannot be (before
            # 2026-11-29 a slot unpicklable in both was skipped and never named)
            items = [
                (path, v)
                for (path, v), b in zip(items, base, strict=True)
                if isinstance(v, Unsaved) or not b or step(self._bytes(v)) != b
            ]
        kept = [(path, step(self._writable(v))) for path, v in items]
        drives = {p: step(self._writable(v)) for p, v in drives.items()}
        built = {p: step(self._writable(v)) for p, v in built.items()}
        saved = {"slots": kept, "baseline": digests, "drives": drives, "built": built}
        return self.dumps_values(saved)

    def _writable(self, v: Any) -> Any:
        """``v``, or Unsaved when it cannot be written, or read back as :func:`restore`
        reads it (it holds an object of a class no checkpoint may load: one slot marked,
        not the whole checkpoint lost)."""
        try:
            _PartUnpickler(io.BytesIO(self.dumps_values(v)), {}, self.roots).load()
        except Exception as err:  # noqa: BLE001 - this slot cannot be kept: marked
            return Unsaved(f"cannot be written: {type(err).__name__}: {err}")
        return v

    def _bytes(self, v: Any) -> bytes:
        try:
            return self.dumps_values(v)
        except Exception:  # noqa: BLE001 - compared as unequal to anything
            return b""

    def digests(self) -> dict[str, str]:
        """Each slot's digest now (a replay compares its own build with the recorded one)."""
        return {
            p: hashlib.sha256(self._bytes(v)).hexdigest()[:16]
            for (_, _, p), v in zip(self.slots, self.take(), strict=True)
        }

    def dumps_values(self, obj: Any) -> bytes:
        """Any object (a dump's inputs) pickled with every part written as its path."""
        buf = io.BytesIO()
        _PartPickler(buf, self.paths).dump(obj)
        return buf.getvalue()

    def loads(self, blob: bytes) -> Any:
        """What :meth:`dumps_values` wrote, every part resolved to this robot's (classes
        outside this project, numpy and a few builtins refused)."""
        return _PartUnpickler(io.BytesIO(blob), self.parts, self.roots).load()


def _keep() -> _Keep:
    return KEEP


def _paced(pace: Callable[[], None] | None) -> Callable[[Any], Any]:
    """``step(x)``: ``x``, with ``pace()`` called every eighth step."""
    if pace is None:
        return lambda x: x
    n = [0]

    def step(x: Any) -> Any:
        n[0] += 1
        if n[0] & 7 == 0:
            pace()
        return x

    return step


def _mapping_proxy(d: dict[Any, Any]) -> MappingProxyType[Any, Any]:
    return MappingProxyType(d)


def _leaves(value: object, depth: int = 0) -> Iterator[tuple[object, int]]:
    """What ``value`` holds that is not a container (itself, or in its containers, nested up
    to six deep), each with its depth; immutable values left out."""
    if type(value) in _IMMUTABLE or depth > 6:
        return
    if isinstance(value, list | tuple | deque | set | frozenset):
        for v in value:
            yield from _leaves(v, depth + 1)
    elif isinstance(value, dict):
        for v in value.values():
            yield from _leaves(v, depth + 1)
    else:
        yield value, depth


def _parts_in(value: object, is_part: Any) -> list[object]:
    """The parts ``value`` holds (itself, or in its containers)."""
    return [v for v, _ in _leaves(value) if is_part(v)]


class _PartPickler(pickle.Pickler):
    def __init__(self, f: io.BytesIO, paths: dict[int, str]) -> None:
        super().__init__(f, protocol=pickle.HIGHEST_PROTOCOL)
        self._paths = paths

    def persistent_id(self, obj: Any) -> str | None:  # noqa: D102 - pickle's hook
        if type(obj) in _IMMUTABLE:
            return None
        return self._paths.get(id(obj))

    def reducer_override(self, obj: Any) -> Any:
        if isinstance(obj, Unsaved):
            return (Unsaved, (obj.why,))
        if obj is KEEP:
            return (_keep, ())
        if type(obj) is MappingProxyType:  # a message's metadata, read-only
            return (_mapping_proxy, (dict(obj),))
        return NotImplemented


class _PartUnpickler(pickle.Unpickler):
    def __init__(self, f: io.BytesIO, parts: dict[str, object], roots: frozenset[str]) -> None:
        super().__init__(f)
        self._parts = parts
        self._roots = roots

    def persistent_load(self, pid: Any) -> object:  # noqa: D102 - pickle's hook
        part = self._parts.get(str(pid))
        if part is None:
            return Unsaved(f"part {pid} is not in this robot")
        return part

    def find_class(self, module: str, name: str) -> Any:  # noqa: D102 - pickle's hook
        """A class this project defines (not a module, a function or a foreign class one of
        its modules imports, whatever the dotted name), the checkpoint's own two
        constructors, one of :data:`_SAFE_GLOBALS`, or a random generator's bits; anything
        else refused, and imported only when it is in this project."""
        if (module, name) in _SAFE_GLOBALS:
            return super().find_class(module, name)
        ours = module.partition(".")[0] in self._roots
        if ours or module in _NUMPY_BITS:
            obj = super().find_class(module, name)
            if obj is _keep or obj is _mapping_proxy:
                return obj
            if isinstance(obj, type) and (
                _root_of(obj) in self._roots if ours else issubclass(obj, _BITS_CLASSES)
            ):
                return obj
        raise pickle.UnpicklingError(f"a checkpoint may not load {module}.{name}")


def _root_of(cls: type) -> str:
    """The module root a class is defined in."""
    return str(cls.__module__).partition(".")[0]


def build_readings(blob: bytes, roots: frozenset[str] = OURS) -> dict[str, Any]:
    """The drivers' slots as the recorded robot's build left them, by path, among them the
    readings it took (``X.raw``, ``X.raw_now``): what a replay's drives answer while it is
    configured. ``roots``: the module roots whose classes may load (a checkpointer's)."""
    loader = _PartUnpickler(io.BytesIO(blob), {}, roots)
    saved: dict[str, Any] = loader.load()
    return dict(saved.get("drives", {}))


def restore(
    checkpointer: Checkpointer, blob: bytes, same_config: bool = False
) -> tuple[list[str], list[str]]:
    """Set the slots of ``checkpointer``'s robot that ``blob`` holds (a
    :meth:`Checkpointer.dumps` of a robot built from the same config: the slots changed since
    its build). Returns what could not be restored, by path (empty: the whole state), and the
    slots whose value as built here differs from the recorded robot's as built (a changed
    configuration, or a build that is not repeatable). A driver's own slot built differently
    is set as the recorded build left it: a replay answers the drives' hooks from the record
    (occ/core/replay.py), so their side of the drive (a simulated drive's model, filled by
    the hooks the replay does not run) is the recorded one, and a changed driver parameter
    changes nothing in a replay. Its checks (a part of their own) are the loop's and count.
    ``same_config``: the replay's configuration is the recorded one, so every slot built
    differently is a build that is not repeatable (a boot number, the time of a reading, a
    real clock's worker where the replay has none): set as the recorded build left it, or
    kept as built here where that value is a part this robot has not (the replay's clock
    is simulated: the collision guard's worker thread); none is reported."""
    loader = _PartUnpickler(io.BytesIO(blob), checkpointer.parts, checkpointer.roots)
    saved: dict[str, Any] = loader.load()
    problems: list[str] = []
    recorded = saved["baseline"]
    here = checkpointer.digests() if recorded else {}
    restored = {p for p, _ in saved["slots"]}
    drives = saved.get("drives", {})
    differ = [p for p, d in recorded.items() if here.get(p, d) != d and p not in restored]
    as_built = saved.get("built", {}) if same_config else drives
    built = sorted(p for p in differ if p not in as_built)
    from_build = [(p, as_built[p]) for p in differ if p in as_built]
    for path, value in from_build:  # what could not load is kept as built here
        if not isinstance(value, Unsaved) and not _unsaved_in(value):
            _set(checkpointer, path, value, problems)
    for path, value in saved["slots"]:
        inside = _unsaved_in(value)
        if inside:  # kept as built here: a value holding what cannot load is not set
            problems += [f"{path}: {why}" for why in inside]
        else:
            _set(checkpointer, path, value, problems)
    return problems, built


def _unsaved_in(value: Any) -> list[str]:
    """What could not be loaded inside a container value (a part this robot has not)."""
    return [v.why for v, depth in _leaves(value) if depth and isinstance(v, Unsaved)]


def _set(checkpointer: Checkpointer, path: str, value: Any, problems: list[str]) -> None:
    """One slot set (or why not, in ``problems``)."""
    holder_path, _, name = path.rpartition(".")
    holder = checkpointer.parts.get(holder_path)
    if holder is None:
        problems.append(f"{path}: no such part here")
    elif isinstance(value, Unsaved):
        problems.append(f"{path}: {value.why}")
    elif value is not KEEP:
        try:
            object.__setattr__(holder, name, value)
        except (AttributeError, TypeError) as err:
            problems.append(f"{path}: {err}")
