"""VFIXTURE: Open Core Control virtual fixtures (spherical forbidden regions).

Layout (big-endian, packed): uint8 VERSION (1) | uint16 N | float32 HARDNESS (N/mm) | N x
float32 (x, y, z, r) in mm, i.e. 7 + 16 N bytes. The OCC paper's table gives 8 + 16 N; our
reading is one reserved byte after VERSION (which also aligns N to 2 bytes). Both sizes are
accepted on decode (they cannot be confused: they differ by 1 modulo 16); we always encode
7 + 16 N, and the layout read is recorded in ``padded`` (excluded from equality).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

from ..errors import ContentError
from .base import Message, check_uint, register

_HEAD7 = struct.Struct(">BHf")
_HEAD8 = struct.Struct(">BxHf")
_SPHERE = struct.Struct(">4f")


@register("VFIXTURE")
@dataclass(frozen=True, slots=True)
class VirtualFixtureMessage(Message):
    """``spheres``: (x, y, z, r) in mm; ``hardness`` in N/mm; ``version`` 1."""

    TYPE: ClassVar[str] = "VFIXTURE"

    hardness: float = 0.0
    spheres: tuple[tuple[float, float, float, float], ...] = ()
    version: int = 1
    padded: bool = field(default=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        check_uint(self.version, 8, "VFIXTURE version")
        spheres = tuple(_sphere(s) for s in self.spheres)
        if len(spheres) > 0xFFFF:
            raise ValueError(f"at most 65535 spheres, got {len(spheres)}")
        object.__setattr__(self, "spheres", spheres)

    def pack_content(self) -> bytes:
        return _HEAD7.pack(self.version, len(self.spheres), self.hardness) + b"".join(
            _SPHERE.pack(*s) for s in self.spheres
        )

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> VirtualFixtureMessage:
        size = len(content)
        if size >= 7 and (size - 7) % 16 == 0:
            head, padded = _HEAD7, False
        elif size >= 8 and (size - 8) % 16 == 0:
            head, padded = _HEAD8, True
        else:
            raise ContentError(
                f"VFIXTURE content of {size} bytes is neither 7 + 16n nor 8 + 16n",
                offset=0,
            )
        version, n, hardness = head.unpack_from(content, 0)
        if head.size + 16 * n != size:
            raise ContentError(
                f"VFIXTURE count {n} needs {head.size + 16 * n} bytes, got {size}",
                offset=head.size - 6,
            )
        spheres = tuple(_SPHERE.unpack_from(content, head.size + 16 * i) for i in range(n))
        return cls(hardness, spheres, version, padded, **common)


def _sphere(s: Sequence[float]) -> tuple[float, float, float, float]:
    t = tuple(float(v) for v in s)
    if len(t) != 4:
        raise ValueError(f"a sphere is (x, y, z, r), got {s!r}")
    return t  # type: ignore[return-value]
