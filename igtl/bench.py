"""Codec micro-benchmarks, shared by ``igtl bench`` and ``benchmarks/bench_codec.py``.

It stays in ``igtl`` (not in the test harness, ``occ_testkit``): it backs ``igtl bench``, a
command the installed package gives its users to measure the codec on their own machine, and it
needs nothing but ``igtl`` itself (pyigtl, for the comparison, only when importable).

For each message type we time, on one pre-built message:

- ``pack``: ``msg.pack()`` (header, CRC-64 over the body, content);
- ``unpack``: ``igtl.unpack(data)`` with the CRC verified (our default);
- ``unpack_nocrc`` (ours only): ``igtl.unpack(data, crc_check=False)``, to compare like with like,
  because pyigtl never verifies the CRC;
- and the same pack/unpack for pyigtl when it is importable and supports the type. pyigtl's
  unpack is timed the way its receive loop decodes (``parse_header`` + ``create_message`` +
  ``unpack``), i.e. without any CRC check.

Each figure is the best of ``repeat`` rounds of ``n`` calls with the garbage collector off
(as :mod:`timeit` does), reported in microseconds per call.
"""

from __future__ import annotations

import gc
import importlib
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import messages as _messages
from .codec import unpack

#: Types with a ready-made benchmark case, in table order.
BENCH_TYPES: tuple[str, ...] = ("TRANSFORM", "POSITION", "STRING", "IMAGE")

#: A fixed pose (rotation about z by 30 degrees, translation in mm) so runs are comparable.
_C, _S = float(np.cos(np.pi / 6)), float(np.sin(np.pi / 6))
_MATRIX = np.array(
    [[_C, -_S, 0.0, 12.5], [_S, _C, 0.0, -40.25], [0.0, 0.0, 1.0, 101.0], [0.0, 0.0, 0.0, 1.0]]
)
_TEXT = "move_to target=entry-point-3 speed=slow"
_IMAGE_SHAPE = (512, 512)
_TIMESTAMP = 1_700_000_000.25


@dataclass(frozen=True, slots=True)
class Case:
    """One benchmark case: how to build our message and, if possible, pyigtl's."""

    type_name: str
    label: str
    ours: Callable[[], Any]
    pyigtl: Callable[[Any], Any] | None  # receives the pyigtl module


@dataclass(frozen=True, slots=True)
class Result:
    type_name: str
    label: str
    impl: str  # "igtl" or "pyigtl"
    size: int  # encoded message size in bytes
    pack_us: float
    unpack_us: float  # ours: with CRC check; pyigtl: never checks
    unpack_nocrc_us: float | None = None

    @property
    def roundtrip_us(self) -> float:
        return self.pack_us + self.unpack_us

    @property
    def roundtrip_per_s(self) -> float:
        return 1e6 / self.roundtrip_us


def _image_pixels() -> np.ndarray:
    rng = np.random.default_rng(7)
    return rng.integers(0, 256, size=_IMAGE_SHAPE, dtype=np.uint8)


def _ours_image() -> Any:
    cls = getattr(_messages, "ImageMessage", None)
    if cls is None:
        raise LookupError("igtl.ImageMessage is not available in this build")
    pixels = _image_pixels()
    # The image type builds from a numpy array; accept both classmethod and plain spellings.
    for name in ("from_array", "from_numpy"):
        factory = getattr(cls, name, None)
        if factory is not None:
            return factory(pixels, device_name="US", timestamp=_TIMESTAMP)
    return cls(data=pixels, device_name="US", timestamp=_TIMESTAMP)


def _cases() -> dict[str, Case]:
    return {
        "TRANSFORM": Case(
            "TRANSFORM",
            "TRANSFORM (48 B content)",
            lambda: _messages.TransformMessage.from_matrix(
                _MATRIX, device_name="Tool", timestamp=_TIMESTAMP
            ),
            lambda p: p.TransformMessage(_MATRIX, timestamp=_TIMESTAMP, device_name="Tool"),
        ),
        # pyigtl's POSITION is a non-standard 148-byte layout (IGTL-PROTOCOL.md 6.3): no peer.
        "POSITION": Case(
            "POSITION",
            "POSITION (28 B content)",
            lambda: _messages.PositionMessage(
                position=(12.5, -40.25, 101.0),
                quaternion=(0.0, 0.0, 0.2588190451, 0.9659258263),
                device_name="Tool",
                timestamp=_TIMESTAMP,
            ),
            None,
        ),
        "STRING": Case(
            "STRING",
            f"STRING ({len(_TEXT)} chars)",
            lambda: _messages.StringMessage(string=_TEXT, device_name="Cmd", timestamp=_TIMESTAMP),
            lambda p: p.StringMessage(_TEXT, timestamp=_TIMESTAMP, device_name="Cmd"),
        ),
        "IMAGE": Case(
            "IMAGE",
            "IMAGE 512x512 uint8",
            _ours_image,
            # pyigtl wants (k, j, i[, components]); one slice of 512 x 512.
            lambda p: p.ImageMessage(
                _image_pixels()[np.newaxis, :, :], timestamp=_TIMESTAMP, device_name="US"
            ),
        ),
    }


def _best_us(fns: Sequence[Callable[[], Any]], n: int, repeat: int) -> list[float]:
    """Best per-call time in microseconds of each function over ``repeat`` rounds of ``n`` calls.

    Rounds are interleaved (a, b, c, a, b, c, ...) so that a burst of load from other processes
    on the machine hits every contender alike instead of one of them.
    """
    gc_was_enabled = gc.isenabled()
    gc.disable()
    best = [float("inf")] * len(fns)
    try:
        for _ in range(repeat):
            for i, fn in enumerate(fns):
                t0 = time.perf_counter_ns()
                for _ in range(n):
                    fn()
                best[i] = min(best[i], time.perf_counter_ns() - t0)
    finally:
        if gc_was_enabled:
            gc.enable()
    return [b / n / 1000.0 for b in best]


def _pyigtl_unpacker(pyigtl: Any, data: bytes) -> Callable[[], Any]:
    base = pyigtl.MessageBase
    head, body = data[:58], data[58:]

    def run() -> Any:
        # What pyigtl's receive loop does with a header and a body (comm.py): no CRC check.
        fields = base.parse_header(head)
        msg = base.create_message(fields["message_type"])
        msg.unpack(fields, body)
        return msg

    return run


def default_n(type_name: str, n: int) -> int:
    """Images are ~4000x bigger than poses: scale the call count so a run stays short."""
    return max(1, n // 200) if type_name == "IMAGE" else n


def run_codec_bench(
    types: Iterable[str] = BENCH_TYPES,
    n: int = 20_000,
    repeat: int = 5,
    *,
    with_pyigtl: bool = True,
    warn: Callable[[str], None] | None = None,
) -> list[Result]:
    """Time pack/unpack for each type, ours and (when importable) pyigtl's, in one process."""
    cases = _cases()
    pyigtl: Any = None
    if with_pyigtl:
        try:
            pyigtl = importlib.import_module("pyigtl")
        except ImportError:
            if warn:
                warn("pyigtl is not importable: comparing nothing, timing igtl only")
    results: list[Result] = []
    for type_name in types:
        case = cases.get(type_name.upper())
        if case is None:
            raise ValueError(f"no benchmark case for {type_name!r}; choose from {BENCH_TYPES}")
        calls = default_n(case.type_name, n)
        try:
            msg = case.ours()
        except LookupError as err:
            if warn:
                warn(f"skipping {case.type_name}: {err}")
            continue
        data = msg.pack()
        same = unpack(data)
        if same.message_type != case.type_name:  # pragma: no cover - a codec bug, not ours
            raise RuntimeError(f"{case.type_name} did not round-trip: got {same.message_type}")
        fns: list[Callable[[], Any]] = [
            msg.pack,
            lambda data=data: unpack(data),  # type: ignore[misc]
            lambda data=data: unpack(data, crc_check=False),  # type: ignore[misc]
        ]
        pdata = b""
        if pyigtl is not None and case.pyigtl is not None:
            pmsg = case.pyigtl(pyigtl)
            pdata = pmsg.pack()
            fns += [pmsg.pack, _pyigtl_unpacker(pyigtl, pdata)]
        t = _best_us(fns, calls, repeat)
        results.append(Result(case.type_name, case.label, "igtl", len(data), t[0], t[1], t[2]))
        if pdata:
            results.append(Result(case.type_name, case.label, "pyigtl", len(pdata), t[3], t[4]))
    return results


def format_table(results: Sequence[Result]) -> str:
    """A plain-text table; the speedup column is pyigtl time / igtl time for the same type."""
    head = (
        f"{'type':<26} {'impl':<7} {'bytes':>7} {'pack us':>9} {'unpack us':>10} "
        f"{'(no crc)':>9} {'pack+unpack':>12} {'msgs/s':>10} {'speedup':>8}"
    )
    lines = [head, "-" * len(head)]
    ours = {r.type_name: r for r in results if r.impl == "igtl"}
    for r in results:
        nocrc = f"{r.unpack_nocrc_us:9.2f}" if r.unpack_nocrc_us is not None else f"{'-':>9}"
        speed = f"{'':>8}"
        if r.impl == "pyigtl" and r.type_name in ours:
            speed = f"{r.roundtrip_us / ours[r.type_name].roundtrip_us:7.2f}x"
        lines.append(
            f"{r.label:<26} {r.impl:<7} {r.size:>7} {r.pack_us:9.2f} {r.unpack_us:10.2f} "
            f"{nocrc} {r.roundtrip_us:12.2f} {r.roundtrip_per_s:10,.0f} {speed}"
        )
    lines.append(
        "unpack: igtl verifies CRC-64 (the '(no crc)' column does not); pyigtl never verifies it."
    )
    lines.append("speedup: pyigtl (pack+unpack) time / igtl (pack+unpack, CRC verified) time.")
    return "\n".join(lines)
