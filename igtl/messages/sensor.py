"""SENSOR: an array of float64 readings with a packed SI unit (protocol doc 3.9)."""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from ..errors import ContentError
from .base import Message, check_uint, register

_SENSOR_HEAD = struct.Struct(">BBQ")

#: Prefix codes (bits 63..60 of the unit).
PREFIXES = {
    0: "",
    1: "deka",
    2: "hecto",
    3: "kilo",
    4: "mega",
    5: "giga",
    6: "tera",
    7: "peta",
    9: "deci",
    10: "centi",
    11: "milli",
    12: "micro",
    13: "nano",
    14: "pico",
    15: "femto",
}
#: Unit codes (6 bits each).
UNITS = {
    1: "m",
    2: "g",
    3: "s",
    4: "A",
    5: "K",
    6: "mol",
    7: "cd",
    8: "rad",
    9: "sr",
    10: "Hz",
    11: "N",
    12: "Pa",
    13: "J",
    14: "W",
    15: "C",
    16: "V",
    17: "F",
    18: "ohm",
    19: "S",
    20: "Wb",
    21: "T",
    22: "H",
    23: "lm",
    24: "lx",
    25: "Bq",
    26: "Gy",
    27: "Sv",
}


@dataclass(frozen=True, slots=True)
class Unit:
    """The 64-bit SENSOR unit: a 4-bit prefix and six (unit, exponent) pairs.

    Pair i sits at bit 10*(5-i): 6 bits of unit code above a 4-bit two's-complement exponent
    (-8..7; the doc allows -7..7). ``Unit(0, ((1, 1), (3, -2)))`` is m/s^2 = 0x00443E0000000000.
    Unused pairs are (0, 0); ``units`` may list fewer than six.
    """

    prefix: int = 0
    units: tuple[tuple[int, int], ...] = ()

    def __post_init__(self) -> None:
        check_uint(self.prefix, 4, "unit prefix")
        units = tuple((int(u), int(e)) for u, e in self.units)
        if len(units) > 6:
            raise ValueError(f"at most 6 (unit, exponent) pairs, got {len(units)}")
        for u, e in units:
            check_uint(u, 6, "unit code")
            if not -8 <= e <= 7:
                raise ValueError(f"unit exponent must be in -8..7, got {e}")
        while units and units[-1] == (0, 0):
            units = units[:-1]
        object.__setattr__(self, "units", units)

    def pack(self) -> int:
        value = self.prefix << 60
        for i, (u, e) in enumerate(self.units):
            value |= ((u << 4) | (e & 0xF)) << (10 * (5 - i))
        return value

    @classmethod
    def unpack(cls, value: int) -> Unit:
        check_uint(value, 64, "unit")
        pairs = []
        for i in range(6):
            field = (value >> (10 * (5 - i))) & 0x3FF
            e = field & 0xF
            pairs.append((field >> 4, e - 16 if e & 0x8 else e))
        return cls(value >> 60, tuple(pairs))

    def __str__(self) -> str:
        parts = [UNITS.get(u, f"unit{u}") + ("" if e == 1 else f"^{e}") for u, e in self.units if u]
        return PREFIXES.get(self.prefix, f"prefix{self.prefix}") + "*".join(parts)


@register("SENSOR")
@dataclass(frozen=True, slots=True)
class SensorMessage(Message):
    """Sensor readings: ``data`` (float64, at most 255), ``unit`` and a reserved ``status``."""

    TYPE: ClassVar[str] = "SENSOR"

    data: tuple[float, ...] = ()
    unit: Unit = Unit()
    status: int = 0

    def __post_init__(self) -> None:
        data = tuple(float(v) for v in self.data)
        if len(data) > 255:
            raise ValueError(f"SENSOR holds at most 255 values, got {len(data)}")
        object.__setattr__(self, "data", data)
        if isinstance(self.unit, int):
            object.__setattr__(self, "unit", Unit.unpack(self.unit))
        elif not isinstance(self.unit, Unit):
            raise TypeError(f"unit must be a Unit or an int, got {type(self.unit).__name__}")
        check_uint(self.status, 8, "SENSOR status")

    def pack_content(self) -> bytes:
        n = len(self.data)
        return _SENSOR_HEAD.pack(n, self.status, self.unit.pack()) + struct.pack(
            f">{n}d", *self.data
        )

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> SensorMessage:
        if len(content) < 10:
            raise ContentError(f"SENSOR content must be >= 10 bytes, got {len(content)}", offset=0)
        n, status, unit = _SENSOR_HEAD.unpack_from(content, 0)
        if len(content) != 10 + 8 * n:
            raise ContentError(
                f"SENSOR LARRAY {n} needs {10 + 8 * n} content bytes, got {len(content)}",
                offset=0,
            )
        return cls(struct.unpack_from(f">{n}d", content, 10), Unit.unpack(unit), status, **common)


#: the newton (unit code 11, no prefix): a force sensor's unit
NEWTON = Unit(0, ((11, 1),))


def sensor(values: Sequence[float], unit: Unit | int = 0, **common: Any) -> SensorMessage:
    """Shorthand: ``sensor([1.0, 2.0], Unit(0, ((11, 1),)), device_name="Force")``."""
    return SensorMessage(
        data=tuple(values), unit=unit if isinstance(unit, Unit) else Unit.unpack(unit), **common
    )
