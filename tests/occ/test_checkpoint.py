"""The checkpoint of a robot's state (occ/core/checkpoint.py; issue 41, item 4), piece by
piece and without a robot: what a replay.pkl may load (the restricted unpickler: a dump from
elsewhere must not run code), and which attributes are slots, how they are copied, written
and set again. The whole robot's checkpoint is tests/occ/test_replay.py's."""

from __future__ import annotations

import array
import enum
import io
import itertools
import pickle
import pickletools
import random
from collections import OrderedDict, deque
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import pytest

from occ.core.checkpoint import KEEP, OURS, Checkpointer, Unsaved, _PartUnpickler, restore

pytestmark = pytest.mark.req("SR-BOX-6")


class Mode(enum.Enum):
    """A plugin's enum: a value, never a part."""

    A = 1


class Kept:
    """A class of this module's root (``tests``): a plugin's, when its root is given."""

    def __init__(self, x: Any = None) -> None:
        self.x = x


def _load(blob: bytes, roots: frozenset[str] = OURS) -> Any:
    return _PartUnpickler(io.BytesIO(blob), {}, roots).load()


def _global(module: str, name: str) -> bytes:
    """A pickle of ``module.name`` alone, nothing called (protocol 4: a dotted name is a path
    through the module's attributes)."""
    m, n = module.encode(), name.encode()
    return b"\x80\x04\x8c" + bytes([len(m)]) + m + b"\x8c" + bytes([len(n)]) + n + b"\x93."


def _respell(blob: bytes, old: str, new: str) -> bytes:
    """``blob`` (a pickle of any protocol) with every string ``old`` written ``new`` (numpy 1's
    module names for numpy 2's): its frames dropped, each string op written again."""
    out = bytearray()
    ops = list(pickletools.genops(blob))
    for i, (op, arg, pos) in enumerate(ops):
        end = ops[i + 1][2] if i + 1 < len(ops) else len(blob)
        if op.name == "FRAME":
            continue
        if op.name == "SHORT_BINUNICODE" and arg == old:
            raw = new.encode()
            out += b"\x8c" + bytes([len(raw)]) + raw
        else:
            out += blob[pos:end]
    return bytes(out)


# ------------------------------------------------------------------ the restricted unpickler
def test_a_checkpoint_that_would_run_a_command_is_refused_before_anything_runs(
    tmp_path: Path,
) -> None:
    """The classic payload: ``getattr(<an occ module>.os, 'system')('touch ...')``. Before
    2026-11-29 it ran: ``builtins.getattr`` was allowed, and so was anything an occ module
    holds (its ``os``, ``subprocess``, ``pickle``)."""
    marker = tmp_path / "ran"
    for holder in ("occ.core.loader", "occ.config.base"):
        payload = (
            f"cbuiltins\ngetattr\n(c{holder}\nos\nS'system'\ntR(S'touch {marker}'\ntR."
        ).encode()
        with pytest.raises(pickle.UnpicklingError, match="may not load builtins.getattr"):
            _load(payload)
        assert not marker.exists()


@pytest.mark.parametrize(
    ("module", "name"),
    [
        ("builtins", "getattr"),
        ("builtins", "eval"),
        ("builtins", "__import__"),
        ("os", "system"),
        ("subprocess", "Popen"),
        ("copyreg", "_reconstructor"),
        ("_codecs", "encode"),
        ("types", "MappingProxyType"),
        ("fractions", "Fraction"),
        # what an occ module holds that this project does not define
        ("occ.core.loader", "os"),  # a module
        ("occ.core.checkpoint", "pickle"),
        ("occ.core.checkpoint", "pickle.loads"),  # a dotted name to a foreign function
        ("occ.core.checkpoint", "io.FileIO"),  # a foreign class (it opens files)
        ("occ.core.checkpoint", "deque"),  # allowed as collections.deque, not through occ
        ("occ.core.checkpoint", "restore"),  # a function of ours: only classes
        ("occ.core.checkpoint", "_PartUnpickler.find_class"),
        ("igtl.auth", "hmac"),
        # numpy: arrays, scalars and generators only
        ("numpy", "save"),
        ("numpy", "memmap"),  # an array's class that opens a file
        ("numpy", "float64"),
        ("numpy.ctypeslib", "load_library"),
        ("numpy.random", "default_rng"),
        ("numpy.random._pcg64", "np"),  # a module in a bits module
        ("numpy.random.bit_generator", "np"),
        ("numpy.random._mt19937", "np"),
        ("numpy.random._philox", "np"),
        ("numpy.random._sfc64", "np"),
        ("numpy.random._generator", "Generator"),
        ("numpy.random.mtrand", "RandomState"),
        ("numpy.lib.npyio", "DataSource"),
        # a plugin's root is given to the checkpointer: the tests' are not ours
        ("tests.occ.test_checkpoint", "Kept"),
    ],
)
def test_a_checkpoint_may_not_load_anything_else(module: str, name: str) -> None:
    with pytest.raises(pickle.UnpicklingError, match=f"may not load {module}.{name}$"):
        _load(_global(module, name))


def test_what_a_checkpoint_may_load_round_trips() -> None:
    """Every kind a slot's value may hold, written as the checkpointer writes it and read
    back as a replay reads it."""
    cp = Checkpointer(Kept())
    rng = random.Random(7)
    values: list[Any] = [
        {1, 2},
        frozenset({3}),
        complex(1.0, -2.0),
        slice(1, 9, 2),
        bytearray(b"ab"),
        deque([1, 2], maxlen=4),
        OrderedDict(a=1, b=2),
        array.array("d", [1.5, 2.5]),
        itertools.count(5),
        np.arange(4.0),
        np.asfortranarray(np.ones((2, 3))),
        np.arange(10.0)[::3],  # not contiguous: numpy's other constructor
        np.float64(0.1),
        np.int32(-3),
        np.dtype("f4"),
        np.random.default_rng(3),  # PCG64 and its SeedSequence
        np.random.Generator(np.random.Philox(4)),
        np.random.Generator(np.random.SFC64(5)),
        np.random.Generator(np.random.MT19937(6)),
        np.random.RandomState(8),
    ]
    back = cp.loads(cp.dumps_values(values))
    for v, b in zip(values, back, strict=True):
        assert type(b) is type(v)
        if isinstance(v, np.ndarray):
            assert (
                np.array_equal(v, b)
                and b.flags.f_contiguous == v.flags.f_contiguous
                or (not v.flags.contiguous and b.flags.c_contiguous)
            )
        elif isinstance(v, np.random.Generator | np.random.RandomState):
            assert v.random() == b.random()
        elif isinstance(v, itertools.count):
            assert next(b) == 5
        else:
            assert b == v
    assert back[5].maxlen == 4
    r = cp.loads(cp.dumps_values(rng))
    assert type(r) is random.Random and r.random() == rng.random()
    assert type(cp.loads(cp.dumps_values(object()))) is object
    # the checkpoint's own: a value kept as built, one not saved, a message's metadata
    assert cp.loads(cp.dumps_values(KEEP)) is KEEP
    got = cp.loads(cp.dumps_values(Unsaved("why")))
    assert isinstance(got, Unsaved) and got.why == "why"
    meta = cp.loads(cp.dumps_values(MappingProxyType({"k": "v"})))
    assert type(meta) is MappingProxyType and dict(meta) == {"k": "v"}


@pytest.mark.parametrize(
    "value",
    [
        np.float64(2.5),
        np.arange(3.0),
        np.arange(10.0)[::2],
    ],
    ids=["scalar", "array", "strided"],
)
def test_numpy_1s_spelling_of_an_array_and_a_scalar_loads(value: Any) -> None:
    """A replay.pkl written with numpy 1 names numpy.core where numpy 2 writes numpy._core."""
    blob = _respell(
        pickle.dumps(value, protocol=5), "numpy._core.multiarray", "numpy.core.multiarray"
    )
    blob = _respell(blob, "numpy._core.numeric", "numpy.core.numeric")
    assert b"numpy._core" not in blob and b"numpy.core" in blob
    got = _load(blob)
    assert np.array_equal(got, value) and type(got) is type(value)


def test_a_class_of_a_plugins_root_loads_only_when_the_root_is_given() -> None:
    blob = pickle.dumps(Kept(3), protocol=5)
    with pytest.raises(pickle.UnpicklingError, match="may not load tests.occ.test_checkpoint.Kept"):
        _load(blob)
    got = _load(blob, OURS | {"tests"})
    assert type(got) is Kept and got.x == 3
    # and a checkpointer given the root reads it, one without refuses it
    assert Checkpointer(Kept(), roots=["tests"]).loads(blob).x == 3
    with pytest.raises(pickle.UnpicklingError):
        Checkpointer(Kept()).loads(blob)
    # this project's own classes always: an enum, a class of igtl
    from igtl.transport.common import RateLimit
    from occ.core.safety import RobotState

    assert _load(pickle.dumps(RobotState.STOPPED, protocol=5)) is RobotState.STOPPED
    assert _load(_global("igtl.transport.common", "RateLimit")) is RateLimit


# ------------------------------------------------------------------ slots, copies, restore
class Slotted:
    """A part with ``__slots__``: a private one (name-mangled), one unset."""

    __slots__ = ("a", "__hidden", "unset", "__weakref__")

    def __init__(self) -> None:
        self.a = 1.0
        self.__hidden = [1]


class Opaque:
    """A record (``checkpoint_opaque``): kept, nothing inside is state."""

    checkpoint_opaque = True

    def __init__(self) -> None:
        self.inner = Kept([1.0])


class Box:
    """A robot in miniature: every kind of attribute a part has."""

    def __init__(self) -> None:
        import threading

        self.gain = 1.5  # immutable: as it is
        self.history = [0.0, [1.0]]  # copied deeply
        self.arr = np.zeros(3)
        self.tab = array.array("d", [1.0])
        self.handler = self.on  # wiring: a bound method
        self.lock = threading.Lock()  # wiring: threading's
        self.kind = int  # a class: wiring
        self.child = Kept(2.0)  # a part, reached through its path
        self.kids = [Kept(3.0), {"k": Kept(4.0)}]  # parts in containers
        self.slotted = Slotted()
        self.record = Opaque()  # opaque: its attributes are no slots
        self.io = Kept(Kept(9.0))  # given as io: it and what it reaches are no slots
        self.scratch = (Fraction(1, 2),)  # a foreign library's scratch only: no slot
        self.table = {"go": self.on}  # a handler in a table: a part by its place
        self.shared = [1.0]
        self.also = self.shared  # one list in two slots: one copy, shared
        self.deep = [[[[[[[[[Kept(1.0)]]]]]]]]]  # deeper than parts are looked for

    def on(self) -> None:
        return None


from fractions import Fraction  # noqa: E402 - the scratch's foreign class


def _paths(cp: Checkpointer) -> list[str]:
    return [p for _, _, p in cp.slots]


def test_the_slots_are_the_state_and_the_parts_are_found_by_path() -> None:
    box = Box()
    cp = Checkpointer(box, io=[box.io, None], opaque=[None], roots=["tests"])
    assert _paths(cp) == [
        "robot.gain",
        "robot.history",
        "robot.arr",
        "robot.tab",
        "robot.child",
        "robot.kids",
        "robot.slotted",
        "robot.record",
        "robot.io",
        "robot.table",
        "robot.shared",
        "robot.also",
        "robot.deep",
        "robot.child.x",
        "robot.kids[0].x",
        "robot.kids[1]['k'].x",
        "robot.slotted.a",
        "robot.slotted._Slotted__hidden",
    ]
    assert cp.parts["robot"] is box and cp.parts["robot.child"] is box.child
    assert cp.parts["robot.kids[1]['k']"] is box.kids[1]["k"]
    assert cp.parts["robot.table['go']"] == box.on  # the handler: by its place
    assert cp.parts["robot.record"] is box.record and "robot.record.inner" not in cp.parts
    assert "robot.io.x" not in cp.parts and "robot.io" in cp.parts
    assert not any(p.startswith("robot.deep[") for p in cp.parts)
    # without the plugin's root, the tests' objects are no parts: their slots are not taken
    plain = Checkpointer(Box())
    assert "robot.child.x" not in _paths(plain) and "robot.child" not in plain.parts


def test_take_copies_what_the_next_ticks_could_change_and_keeps_parts_as_parts() -> None:
    box = Box()
    cp = Checkpointer(box, io=[box.io], roots=["tests"])
    values = dict(zip(_paths(cp), cp.take(), strict=True))
    box.history[1].append(2.0)
    box.arr[0] = 5.0
    box.tab[0] = 7.0
    box.shared.append(2.0)
    assert values["robot.history"] == [0.0, [1.0]]
    assert values["robot.arr"][0] == 0.0 and values["robot.tab"][0] == 1.0
    assert values["robot.child"] is box.child and values["robot.kids"][0] is box.kids[0]
    assert values["robot.kids"] is not box.kids and values["robot.kids"][1]["k"] is box.kids[1]["k"]
    assert values["robot.shared"] == [1.0] and values["robot.shared"] is values["robot.also"]
    assert values["robot.record"] is box.record and values["robot.table"]["go"] == box.on
    assert values["robot.slotted._Slotted__hidden"] == [1]
    # a slot unset since, and one that cannot be copied: named, the others taken
    del box.slotted.a
    box.history = [(i for i in ())]  # a generator: no copy of it
    again = dict(zip(_paths(cp), cp.take(), strict=True))
    assert repr(again["robot.slotted.a"]) == "<not saved: unset>"
    assert isinstance(again["robot.history"], Unsaved)
    assert again["robot.history"].why == "list: cannot pickle 'generator' object"


def test_a_checkpoint_restores_the_changed_slots_into_another_build() -> None:
    box = Box()
    cp = Checkpointer(box, io=[box.io], roots=["tests"])
    base = cp.take()
    box.gain = 2.5
    box.child.x = [7.0]
    box.history = [box.kids[0], 1.0]  # a part inside a value: written as its path
    box.slotted.a = 3.0
    paces: list[int] = []
    blob = cp.dumps(cp.take(), base, pace=lambda: paces.append(1))
    assert paces  # the writer was paced
    import pickle as pk

    saved = Checkpointer(Kept(), roots=["tests"]).loads(blob)
    assert [p for p, _ in saved["slots"]] == [
        "robot.gain",
        "robot.history",
        "robot.child.x",
        "robot.slotted.a",
    ]
    assert set(saved["baseline"]) == set(_paths(cp)) and len(saved["baseline"]["robot.gain"]) == 16
    again = Box()
    cp2 = Checkpointer(again, io=[again.io], roots=["tests"])
    problems, built = restore(cp2, blob)
    assert problems == [] and built == []
    assert again.gain == 2.5 and again.child.x == [7.0] and again.slotted.a == 3.0
    assert again.history[0] is again.kids[0]  # this build's own part
    assert pk.loads(pk.dumps(1)) == 1


def test_restore_names_what_it_could_not_set_and_what_was_built_differently() -> None:
    box = Box()
    cp = Checkpointer(box, io=[box.io], roots=["tests"])
    base = cp.take()
    box.gain = 3.0
    box.history = [Fraction(1, 3)]  # a foreign value: marked at the write
    blob = cp.dumps(cp.take(), base)
    other = Box()
    other.kids = [Kept(5.0)]  # built differently: one part fewer
    other.slotted = Kept(1.0)  # a part of another class: its slots are others
    cp2 = Checkpointer(other, io=[other.io], roots=["tests"])
    problems, built = restore(cp2, blob)
    assert other.gain == 3.0
    assert problems == [
        "robot.history: cannot be written: UnpicklingError: a checkpoint may not load "
        "fractions.Fraction"
    ]
    # a slot this build has not (robot.slotted.a: a Kept has x) is not compared
    assert built == ["robot.kids", "robot.kids[0].x"]
    # the same configuration: what was built differently is set as the recorded build left it
    other = Box()
    other.gain = 9.0
    cp3 = Checkpointer(other, io=[other.io], roots=["tests"])
    problems, built = restore(cp3, blob, same_config=True)
    assert built == [] and other.gain == 3.0
    other = Box()
    other.tab = array.array("d", [5.0])
    cp4 = Checkpointer(other, io=[other.io], roots=["tests"])
    restore(cp4, blob, same_config=True)
    assert list(other.tab) == [1.0]  # the recorded build's
    other = Box()
    other.tab = array.array("d", [5.0])
    problems, built = restore(Checkpointer(other, io=[other.io], roots=["tests"]), blob)
    assert built == ["robot.tab"] and list(other.tab) == [5.0]  # another config's: kept


def test_a_part_this_robot_has_not_is_named_and_its_slot_kept() -> None:
    box = Box()
    cp = Checkpointer(box, io=[box.io], roots=["tests"])
    base = cp.take()
    box.history = [box.kids[1]["k"]]
    box.shared = [box.kids[1]["k"]]  # two slots: both named
    box.child.x = 4.0
    blob = cp.dumps(cp.take(), base)
    other = Box()
    other.kids = [Kept(1.0)]
    other.child = Slotted()  # no slot x: cannot be set? a Slotted has no x
    cp2 = Checkpointer(other, io=[other.io], roots=["tests"])
    problems, _ = restore(cp2, blob)
    assert problems[:2] == [
        "robot.history: part robot.kids[1]['k'] is not in this robot",
        "robot.shared: part robot.kids[1]['k'] is not in this robot",
    ]
    assert other.history == [0.0, [1.0]]  # kept as built
    assert any(p.startswith("robot.child.x: ") for p in problems)
    assert repr(Unsaved("x")) == "<not saved: x>" and repr(KEEP) == "<kept as built>"


def test_restore_reports_a_slot_whose_holder_is_gone() -> None:
    from occ.core.checkpoint import _set

    box = Box()
    cp = Checkpointer(box, io=[box.io], roots=["tests"])
    problems: list[str] = []
    _set(cp, "robot.nothing.x", 1.0, problems)
    _set(cp, "robot.gain", Unsaved("no"), problems)
    _set(cp, "robot.gain", KEEP, problems)
    _set(cp, "robot.slotted.other", 1.0, problems)
    assert problems[:2] == ["robot.nothing.x: no such part here", "robot.gain: no"]
    assert problems[2].startswith("robot.slotted.other: ") and len(problems) == 3
    assert box.gain == 1.5
    _set(cp, "robot.gain", 2.0, problems)
    assert box.gain == 2.0 and len(problems) == 3


def test_the_drives_as_built_are_read_back_alone_with_the_roots_given() -> None:
    """build_readings: every slot of a part holding ``raw`` (a driver) as the recorded build
    left it; a plugin's class loads only with its root."""
    from occ.core.checkpoint import build_readings

    class Drive:
        def __init__(self) -> None:
            self.raw = ([0.5], [0.0], [0.0])
            self.name = "d"
            self.mode = Mode.A  # a value of a plugin's class in a driver's slot

    root = Kept(Drive())
    cp = Checkpointer(root, roots=["tests"])
    base = cp.take()
    blob = cp.dumps(cp.take(), base)
    drives = build_readings(blob, cp.roots)
    assert list(drives) == ["robot.x.raw", "robot.x.name", "robot.x.mode"]
    assert drives["robot.x.raw"] == ([0.5], [0.0], [0.0])
    assert drives["robot.x.mode"] is Mode.A
    with pytest.raises(pickle.UnpicklingError, match="may not load tests.occ.test_checkpoint.Mode"):
        build_readings(blob)  # this project's roots only
    assert build_readings(cp.dumps(cp.take()), cp.roots) == {}  # no baseline: no drives
    with pytest.raises(pickle.UnpicklingError, match="may not load builtins.getattr"):
        build_readings(b"cbuiltins\ngetattr\n.")
    # a checkpoint written before the drives were kept: none
    assert build_readings(pickle.dumps({"slots": [], "baseline": {}})) == {}


class Driver:
    """A driver in miniature: a part with its readings ``raw``."""

    def __init__(self, raw: float) -> None:
        self.raw = ([raw], [0.0], [0.0])
        self.model = [raw]  # its side of the drive, filled by hooks a replay does not run


def test_a_drivers_slots_built_differently_are_the_recorded_builds_in_any_config() -> None:
    root = Kept(Driver(1.0))
    cp = Checkpointer(root, roots=["tests"])
    base = cp.take()
    blob = cp.dumps(cp.take(), base)
    other = Kept(Driver(2.0))  # another configuration: the drive read otherwise when built
    problems, built = restore(Checkpointer(other, roots=["tests"]), blob)
    assert problems == [] and built == []  # the drive's own slots are not the loop's
    assert other.x.raw == ([1.0], [0.0], [0.0]) and other.x.model == [1.0]
    # a checkpoint written before the drives were kept: every slot built differently is told
    cp0 = Checkpointer(Kept(Driver(1.0)), roots=["tests"])
    saved = cp0.loads(blob)
    del saved["drives"], saved["built"]
    old = cp0.dumps_values(saved)
    other = Kept(Driver(2.0))
    problems, built = restore(Checkpointer(other, roots=["tests"]), old)
    assert built == ["robot.x.model", "robot.x.raw"] and other.x.model == [2.0]
    other = Kept(Driver(2.0))
    problems, built = restore(Checkpointer(other, roots=["tests"]), old, same_config=True)
    assert built == ["robot.x.model", "robot.x.raw"]  # no recorded build to set them from


def test_a_recorded_build_holding_a_part_this_robot_has_not_is_kept_as_built_here() -> None:
    """The same configuration, a build that is not repeatable: a slot is set as the recorded
    build left it, but not where that value is (or holds) a part this robot has not (the
    collision guard's worker on a real clock; the replay's is simulated): kept, not told."""
    rec = Kept([Kept(1.0)])
    rec.y = Kept(2.0)  # type: ignore[attr-defined]
    cp = Checkpointer(rec, roots=["tests"])
    blob = cp.dumps(cp.take(), cp.take())
    here = Kept([1.0])
    here.y = 3.0  # type: ignore[attr-defined]
    problems, built = restore(Checkpointer(here, roots=["tests"]), blob, same_config=True)
    assert problems == [] and built == []
    assert here.x == [1.0] and here.y == 3.0


def test_what_an_interface_reaches_is_followed_six_containers_deep() -> None:
    """``io``'s parts (and theirs) are no state: found through up to six containers, as the
    robot's own parts are; deeper, a part reached elsewhere keeps its slots."""
    a, b = Kept(1.0), Kept(2.0)
    link = Kept([[[[[[a]]]]]])  # a in the sixth list
    link.y = [[[[[[[b]]]]]]]  # type: ignore[attr-defined]  # b in the seventh
    c = Kept(3.0)
    link.z = c  # type: ignore[attr-defined]  # a plugin's part held directly: the roots given
    root = Kept(link)
    root.a, root.b, root.c = a, b, c  # type: ignore[attr-defined]
    cp = Checkpointer(root, io=[link], roots=["tests"])
    assert _paths(cp) == ["robot.x", "robot.a", "robot.b", "robot.c", "robot.b.x"]


def test_the_writer_is_paced_every_eighth_step_and_a_take_must_be_this_checkpointers() -> None:
    from occ.core.checkpoint import _paced

    calls: list[int] = []
    step = _paced(lambda: calls.append(1))
    for i in range(1, 17):
        assert step(i) == i
        assert len(calls) == i // 8, i
    assert _paced(None)(5) == 5
    box = Kept([1.0])
    cp = Checkpointer(box, roots=["tests"])
    values = cp.take()
    with pytest.raises(ValueError):
        cp.dumps(values + [1.0])
    with pytest.raises(ValueError):
        cp.dumps(values, values + [1.0])
    # without a baseline every slot is written, and restores whole
    box.x = [2.0]
    blob = cp.dumps(cp.take())
    again = Kept([0.0])
    assert restore(Checkpointer(again, roots=["tests"]), blob) == ([], [])
    assert again.x == [2.0]


def test_a_slot_that_cannot_be_pickled_before_or_after_is_named_not_dropped() -> None:
    """Before 2026-11-29 a slot whose value could be pickled neither at the baseline nor at
    the checkpoint compared equal (both b"") and was left out: a replay of the same
    configuration kept its own value and named nothing."""
    root = Kept([1.0])
    cp = Checkpointer(root, roots=["tests"])
    root.x = [lambda: 1]  # made at run time: no part, no pickle of it
    base = cp.take()
    root.x = [lambda: 2]
    blob = cp.dumps(cp.take(), base)
    again = Kept([0.0])
    problems, built = restore(Checkpointer(again, roots=["tests"]), blob, same_config=True)
    where = "test_a_slot_that_cannot_be_pickled_before_or_after_is_named_not_dropped"
    assert problems == [
        "robot.x: cannot be written: AttributeError: Can't pickle local object "
        f"'{where}.<locals>.<lambda>'"
    ]
    assert built == [] and again.x == [0.0]


def test_a_record_inside_eight_containers_is_still_kept_as_built() -> None:
    """Containers are copied one by one up to eight deep (below, deeply at once): a record
    (``checkpoint_opaque``) in the eighth is still kept as built, not copied."""
    rec = Opaque()
    root = Kept([[[[[[[[rec]]]]]]]])
    cp = Checkpointer(root, roots=["tests"])
    (value,) = cp.take()
    for _ in range(7):
        (value,) = value
    assert value == [KEEP]


@pytest.mark.parametrize("kind", ["list", "dict"])
def test_containers_are_copied_one_by_one_to_eight_deep_and_deeply_below(kind: str) -> None:
    """A record nested in eight containers is kept as built; in nine, the eighth is copied
    deeply at once (the record with it)."""

    def nest(x: Any, n: int) -> Any:
        for _ in range(n):
            x = [x] if kind == "list" else {"k": x}
        return x

    def inner(x: Any, n: int) -> Any:
        for _ in range(n):
            x = x[0] if kind == "list" else x["k"]
        return x

    for n, kept in ((8, True), (9, False)):
        rec = Opaque()
        root = Kept(nest(rec, n))
        (value,) = Checkpointer(root, roots=["tests"]).take()
        got = inner(value, n)
        assert (got is KEEP) is kept, n
        if not kept:
            assert isinstance(got, Opaque) and got is not rec


def test_a_copy_keeps_a_rings_length_an_object_arrays_items_and_its_wiring() -> None:
    import threading

    lock = threading.Lock()
    root = Kept(deque([1.0, [2.0]], maxlen=5))
    root.objs = np.empty(1, dtype=object)  # type: ignore[attr-defined]
    root.objs[0] = [1.0]  # type: ignore[attr-defined]
    root.mixed = [[1.0], lock]  # type: ignore[attr-defined]  # a lock beside a list: kept as is
    root.deep = [[[[[[[[Kept(1.0)]]]]]]]]  # type: ignore[attr-defined]  # no part: copied
    cp = Checkpointer(root, roots=["tests"])
    ring, objs, mixed, deep = cp.take()
    assert ring.maxlen == 5 and list(ring) == [1.0, [2.0]]
    root.objs[0].append(2.0)  # type: ignore[attr-defined]
    assert objs[0] == [1.0]
    assert mixed[1] is lock and mixed[0] == [1.0] and mixed[0] is not root.mixed[0]  # type: ignore[attr-defined]
    leaf = deep
    for _ in range(7):
        (leaf,) = leaf
    assert type(leaf[0]) is Kept and leaf[0] is not root.deep[0][0][0][0][0][0][0][0]  # type: ignore[attr-defined]


class Both:
    """Slots and a ``__dict__``: each attribute once, the slots after an unset one and after
    ``__weakref__``, a dunder slot's name as written."""

    __slots__ = ("__weakref__", "unset", "a", "__dict__", "__x__")

    def __init__(self) -> None:
        self.a = 1.0
        self.__x__ = 2.0
        self.b = 3.0


class _Hidden:
    """A class whose name starts with ``_``: its private slot is ``_Hidden__h``."""

    __slots__ = ("__h",)

    def __init__(self) -> None:
        self.__h = 4.0


def test_every_stored_attribute_is_a_slot_once_by_its_real_name() -> None:
    import functools
    import random as rnd

    root = Kept(Both())
    root.hidden = _Hidden()  # type: ignore[attr-defined]
    root.handlers = [functools.partial(print)]  # type: ignore[attr-defined]  # foreign callables
    root.rng = rnd.Random(1)  # type: ignore[attr-defined]  # a value, not a part
    cp = Checkpointer(root, roots=["tests"])
    assert _paths(cp) == [
        "robot.x",
        "robot.hidden",
        "robot.handlers",
        "robot.rng",
        "robot.x.b",
        "robot.x.a",
        "robot.x.__x__",
        "robot.hidden._Hidden__h",
    ]
    rng = dict(zip(_paths(cp), cp.take(), strict=True))["robot.rng"]
    assert rng is not root.rng and rng.random() == root.rng.random()  # type: ignore[attr-defined]


@pytest.mark.parametrize("kind", ["list", "dict"])
def test_parts_are_found_through_six_containers_not_seven(kind: str) -> None:
    def nest(x: Any, n: int) -> Any:
        for _ in range(n):
            x = [x] if kind == "list" else {"k": x}
        return x

    six, seven = Kept(6.0), Kept(7.0)
    root = Kept(nest(six, 6))
    root.y = nest(seven, 7)  # type: ignore[attr-defined]
    cp = Checkpointer(root, roots=["tests"])
    step = "[0]" if kind == "list" else "['k']"
    assert cp.parts["robot.x" + step * 6] is six
    assert all(part is not seven for part in cp.parts.values())


def test_an_object_made_at_run_time_is_copied_with_its_parts_kept() -> None:
    """A sample made after the build is no part: copied deeply, its references to parts kept
    as the parts themselves (the copy's memo maps every part to itself)."""
    part = Kept(1.0)
    root = Kept(part)
    cp = Checkpointer(root, roots=["tests"])
    root.x = Kept(part)  # made at run time, holding a part
    (value, _) = cp.take()
    assert type(value) is Kept and value is not root.x and value.x is part


def test_what_an_interface_reaches_through_mappings_is_followed_six_deep() -> None:
    def nest(x: Any, n: int) -> Any:
        for _ in range(n):
            x = {"k": x}
        return x

    a, b = Kept(1.0), Kept(2.0)
    link = Kept(nest(a, 6))
    link.y = nest(b, 7)  # type: ignore[attr-defined]
    root = Kept(link)
    root.a, root.b = a, b  # type: ignore[attr-defined]
    cp = Checkpointer(root, io=[link], roots=["tests"])
    assert _paths(cp) == ["robot.x", "robot.a", "robot.b", "robot.b.x"]


def test_wiring_made_at_run_time_is_kept_as_it_is_not_copied() -> None:
    """A lock put in a slot's list after the build (no part: discovery did not see it) is
    wiring: the copy of the list holds the lock itself (a lock has no copy)."""
    import threading

    root = Kept([[1.0]])
    cp = Checkpointer(root, roots=["tests"])
    lock = threading.Lock()
    root.x = [[1.0], lock]
    (value,) = cp.take()
    assert value[1] is lock and value[0] == [1.0] and value[0] is not root.x[0]


class Scheduled:
    """A part with a table fixed at build (``checkpoint_fixed``) beside its state."""

    checkpoint_fixed = ("table",)

    def __init__(self) -> None:
        self.table = [(Kept(1.0), print)] * 3  # derived from the config, never changed
        self.count = [0]  # state
        self.rng = random.Random(7)  # a simulated drive's noise


def test_a_fixed_table_is_no_slot_and_a_generator_is_copied_to_its_exact_state() -> None:
    part = Scheduled()
    cp = Checkpointer(part, roots=["tests"])
    assert _paths(cp) == ["robot.count", "robot.rng"]  # not robot.table, nor what it reaches
    part.rng.random()
    values = dict(zip(_paths(cp), cp.take(), strict=True))
    copied = values["robot.rng"]
    assert type(copied) is random.Random and copied is not part.rng
    ahead = [part.rng.random() for _ in range(3)]
    assert [copied.random() for _ in range(3)] == ahead  # the same sequence from there
    other = Scheduled()  # another build: restored, it draws what the first drew
    other_cp = Checkpointer(other, roots=["tests"])
    restore(other_cp, cp.dumps(cp.take()))
    assert [other.rng.random() for _ in range(3)] == [part.rng.random() for _ in range(3)]
