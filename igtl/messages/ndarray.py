"""NDARRAY: an N-dimensional array of numbers (protocol doc 3.10)."""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from ..errors import ContentError
from .base import Message, common_equal, register

#: SCALAR_TYPE -> big-endian numpy dtype (complex: real f64 then imaginary f64, both big-endian).
SCALAR_DTYPES: dict[int, np.dtype] = {
    2: np.dtype("i1"),
    3: np.dtype("u1"),
    4: np.dtype(">i2"),
    5: np.dtype(">u2"),
    6: np.dtype(">i4"),
    7: np.dtype(">u4"),
    10: np.dtype(">f4"),
    11: np.dtype(">f8"),
    13: np.dtype(">c16"),
}
_BY_KIND = {(dt.kind, dt.itemsize): code for code, dt in SCALAR_DTYPES.items()}


def scalar_type_of(dtype: np.dtype) -> int:
    """OpenIGTLink SCALAR_TYPE code of a numpy dtype (ValueError if unsupported)."""
    try:
        return _BY_KIND[(dtype.kind, dtype.itemsize)]
    except KeyError:
        raise ValueError(
            f"dtype {dtype} not supported (int8/16/32, uint8/16/32, float32/64, complex128)"
        ) from None


@register("NDARRAY")
@dataclass(frozen=True, slots=True, eq=False)
class NDArrayMessage(Message):
    """``array``: a numpy array (any supported dtype, 0..255 dimensions each <= 65535).

    Decoded arrays are native-endian, C-ordered and read-only. Equality compares dtype, shape
    and the exact element bits.
    """

    TYPE: ClassVar[str] = "NDARRAY"

    array: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.float64))

    def __post_init__(self) -> None:
        a = np.asarray(self.array)
        scalar_type_of(a.dtype)
        if a.ndim > 255 or any(s > 0xFFFF for s in a.shape):
            raise ValueError(f"NDARRAY shape {a.shape}: at most 255 dims of <= 65535")
        object.__setattr__(self, "array", a)

    @property
    def scalar_type(self) -> int:
        return scalar_type_of(self.array.dtype)

    def pack_content(self) -> bytes:
        a = self.array
        code = scalar_type_of(a.dtype)
        head = struct.pack(f">BB{a.ndim}H", code, a.ndim, *a.shape)
        return head + np.ascontiguousarray(a, dtype=SCALAR_DTYPES[code]).tobytes()

    @classmethod
    def unpack_content(cls, content: bytes, common: dict[str, Any]) -> NDArrayMessage:
        if len(content) < 2:
            raise ContentError(f"NDARRAY content must be >= 2 bytes, got {len(content)}", offset=0)
        code, dim = content[0], content[1]
        dtype = SCALAR_DTYPES.get(code)
        if dtype is None:
            raise ContentError(f"NDARRAY scalar type {code} is not defined", offset=0)
        if len(content) < 2 + 2 * dim:
            raise ContentError(f"NDARRAY of {dim} dims: size table truncated", offset=2)
        shape = struct.unpack_from(f">{dim}H", content, 2)
        count = 1
        for s in shape:
            count *= s
        start = 2 + 2 * dim
        if len(content) - start != count * dtype.itemsize:
            raise ContentError(
                f"NDARRAY {shape} of type {code} needs {count * dtype.itemsize} data bytes, "
                f"got {len(content) - start}",
                offset=start,
            )
        a = np.frombuffer(content, dtype=dtype, count=count, offset=start).reshape(shape)
        a = a.astype(dtype.newbyteorder("="))
        a.flags.writeable = False
        return cls(a, **common)

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        assert isinstance(other, NDArrayMessage)
        a, b = self.array, other.array
        return (
            common_equal(self, other)
            and a.shape == b.shape
            and scalar_type_of(a.dtype) == scalar_type_of(b.dtype)
            and np.ascontiguousarray(a, SCALAR_DTYPES[scalar_type_of(a.dtype)]).tobytes()
            == np.ascontiguousarray(b, SCALAR_DTYPES[scalar_type_of(b.dtype)]).tobytes()
        )

    __hash__ = None  # type: ignore[assignment]
