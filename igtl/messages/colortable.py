"""COLORT: a colour lookup table for label maps (protocol doc 3.14).

The library sends type "COLORT"; the reference test vector uses "COLORTABLE". Both decode with
this class, which keeps the name it was received under (``type_name``) and encodes with it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from ..errors import ContentError
from .base import Message, common_equal, register

INDEX_UINT8 = 3
INDEX_UINT16 = 5
MAP_UINT8 = 3
MAP_UINT16 = 5
MAP_RGB = 19
_INDEX_LEN = {INDEX_UINT8: 256, INDEX_UINT16: 65536}
_MAP_DTYPE: dict[int, np.dtype] = {
    MAP_UINT8: np.dtype("u1"),
    MAP_UINT16: np.dtype(">u2"),
    MAP_RGB: np.dtype("u1"),
}


@register("COLORT", "COLORTABLE")
@dataclass(frozen=True, slots=True, eq=False)
class ColorTableMessage(Message):
    """``table``: 256 (uint8 index) or 65536 (uint16 index) entries, each a uint8 or uint16
    grey value (shape (N,)) or an RGB triple of uint8 (shape (N, 3)). Index and map types are
    derived from the table's length, dtype and shape."""

    NEEDS_TYPE_NAME: ClassVar[bool] = True

    table: np.ndarray = field(default_factory=lambda: np.arange(256, dtype=np.uint8))
    type_name: str = "COLORT"

    def __post_init__(self) -> None:
        if self.type_name not in ("COLORT", "COLORTABLE"):
            raise ValueError(f"type_name must be COLORT or COLORTABLE, got {self.type_name!r}")
        t = np.asarray(self.table)
        if t.shape[:1] not in ((256,), (65536,)):
            raise ValueError(f"colour table needs 256 or 65536 entries, got shape {t.shape}")
        if t.ndim == 2:
            if t.shape[1] != 3 or t.dtype != np.uint8:
                raise ValueError("an RGB colour table is (N, 3) uint8")
        elif t.ndim != 1 or t.dtype.kind != "u" or t.dtype.itemsize not in (1, 2):
            raise ValueError(f"a grey colour table is (N,) uint8 or uint16, got {t.dtype}")
        object.__setattr__(self, "table", t)

    @property
    def message_type(self) -> str:
        return self.type_name

    @property
    def index_type(self) -> int:
        return INDEX_UINT8 if len(self.table) == 256 else INDEX_UINT16

    @property
    def map_type(self) -> int:
        t = self.table
        return MAP_RGB if t.ndim == 2 else MAP_UINT8 if t.dtype.itemsize == 1 else MAP_UINT16

    def pack_content(self) -> bytes:
        dt = _MAP_DTYPE[self.map_type]
        return (
            bytes((self.index_type, self.map_type))
            + np.ascontiguousarray(self.table, dtype=dt).tobytes()
        )

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> ColorTableMessage:
        name = common.pop("message_type")
        if len(content) < 2:
            raise ContentError(f"{name} content must be >= 2 bytes, got {len(content)}", offset=0)
        index_type, map_type = content[0], content[1]
        n = _INDEX_LEN.get(index_type)
        if n is None:
            raise ContentError(f"{name} index type {index_type} is not 3 or 5", offset=0)
        dt = _MAP_DTYPE.get(map_type)
        if dt is None:
            raise ContentError(f"{name} map type {map_type} is not 3, 5 or 19", offset=1)
        per = 3 if map_type == MAP_RGB else 1
        if len(content) != 2 + n * per * dt.itemsize:
            raise ContentError(
                f"{name} table needs {n * per * dt.itemsize} bytes, got {len(content) - 2}",
                offset=2,
            )
        t = np.frombuffer(content, dtype=dt, offset=2).astype(dt.newbyteorder("="))
        if per == 3:
            t = t.reshape(n, 3)
        t.flags.writeable = False
        return cls(t, name, **common)

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        assert isinstance(other, ColorTableMessage)
        return (
            common_equal(self, other)
            and self.type_name == other.type_name
            and self.map_type == other.map_type
            and np.array_equal(self.table, other.table)
        )

    __hash__ = None  # type: ignore[assignment]
