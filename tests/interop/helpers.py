"""Helpers for the interop tests: peer processes, polling, output parsers and an independent
byte-level decoder.

The decoder here is deliberately separate from ``igtl``: interop tests check our library
against the reference peers, so they must not reuse our own codec to judge our own output.
Everything is written from the protocol document (shared/IGTL-PROTOCOL.md, sections 1-3).
"""

from __future__ import annotations

import math
import os
import re
import socket
import struct
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES_ENV = "OCC_IGTL_EXAMPLES"
REQUIRE_ENV = "OCC_REQUIRE_INTEROP"
DEFAULT_EXAMPLES = ROOT / ".cache" / "igtl-examples"
INSTALL_HINT = "run bash scripts/install_reference_peers.sh"

#: Upper bound for any single wait in these tests (seconds). Generous for loaded CI machines;
#: the normal case returns within milliseconds because every wait is a poll, not a sleep.
WAIT = 10.0


# --------------------------------------------------------------------------------------------
# skip / require
def interop_required() -> bool:
    return os.environ.get(REQUIRE_ENV, "").strip().lower() in ("1", "true", "yes", "on")


def skip_or_fail(reason: str) -> None:
    """Skip the test, or fail it when the environment says interop is mandatory (CI)."""
    if interop_required():
        pytest.fail(f"{reason} [{REQUIRE_ENV}=1: interop peers are mandatory]", pytrace=False)
    pytest.skip(reason)


def examples_root() -> Path:
    env = os.environ.get(EXAMPLES_ENV)
    return Path(env) if env else DEFAULT_EXAMPLES


def examples_bin() -> Path:
    return examples_root() / "bin"


def need_igtl(name: str) -> Any:
    """An ``igtl`` attribute (message class) the test needs; skip/fail clearly if not there."""
    import igtl

    obj = getattr(igtl, name, None)
    if obj is None:
        skip_or_fail(f"igtl.{name} is not available (message type not implemented yet)")
    return obj


# --------------------------------------------------------------------------------------------
# polling and ports
def poll(predicate: Callable[[], Any], timeout: float = WAIT, interval: float = 0.005) -> Any:
    """Call ``predicate`` until it returns a truthy value or ``timeout`` passes; return it."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() >= deadline:
            return value
        time.sleep(interval)


def free_port() -> int:
    """A TCP port that is free on all interfaces right now (reference servers bind INADDR_ANY)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("", 0))
        return s.getsockname()[1]


def _listening_ports() -> set[int] | None:
    ports: set[int] = set()
    found = False
    for name in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            with open(name) as f:
                lines = f.readlines()[1:]
        except OSError:
            continue
        found = True
        for line in lines:
            parts = line.split()
            if len(parts) > 3 and parts[3] == "0A":  # TCP_LISTEN
                ports.add(int(parts[1].rsplit(":", 1)[1], 16))
    return ports if found else None


def is_listening(port: int) -> bool | None:
    """Whether something listens on ``port`` (None when /proc is not available).

    Used instead of probe connections: the reference servers serve the first connection they
    accept, so a probe would be taken for the real client.
    """
    ports = _listening_ports()
    return None if ports is None else port in ports


# --------------------------------------------------------------------------------------------
# reference peer processes
class RefPeer:
    """One reference example program, its merged stdout/stderr captured line by line."""

    def __init__(self, exe: Path, args: Sequence[Any], name: str | None = None):
        self.name = name or exe.name
        self.argv = [str(exe), *map(str, args)]
        self._lines: list[str] = []
        self._cond = threading.Condition()
        self._eof = False
        self.proc = subprocess.Popen(
            self.argv,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        self._reader = threading.Thread(target=self._read, name=f"{self.name}-out", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in iter(self.proc.stdout.readline, b""):
            with self._cond:
                self._lines.append(raw.decode("utf-8", "replace").rstrip("\r\n"))
                self._cond.notify_all()
        with self._cond:
            self._eof = True
            self._cond.notify_all()

    # -- output
    @property
    def lines(self) -> list[str]:
        with self._cond:
            return list(self._lines)

    @property
    def text(self) -> str:
        return "\n".join(self.lines)

    def wait_output(
        self, predicate: Callable[[list[str]], Any], timeout: float = WAIT
    ) -> Any:
        """Wait until ``predicate(lines)`` is truthy (or the output ended / timeout)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                value = predicate(list(self._lines))
                if value or self._eof:
                    return value
                left = deadline - time.monotonic()
                if left <= 0:
                    return value
                self._cond.wait(left)

    def wait_count(self, pattern: str, n: int, timeout: float = WAIT) -> int:
        """Wait until at least ``n`` lines match the regex; returns the count reached."""
        rx = re.compile(pattern)
        count = self.wait_output(
            lambda ls: (c if (c := sum(1 for x in ls if rx.search(x))) >= n else 0), timeout
        )
        return count or sum(1 for x in self.lines if rx.search(x))

    # -- lifetime
    def alive(self) -> bool:
        return self.proc.poll() is None

    def wait_exit(self, timeout: float = WAIT) -> int | None:
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()  # this process only (by its pid), never by name
        try:
            self.proc.wait(5)
        except subprocess.TimeoutExpired:  # pragma: no cover - kill cannot be ignored
            pass
        self._reader.join(2)
        if self.proc.stdout:
            self.proc.stdout.close()

    def describe(self) -> str:
        tail = "\n".join(self.lines[-40:])
        return f"{' '.join(self.argv)} (rc={self.proc.poll()}); last output:\n{tail}"


# --------------------------------------------------------------------------------------------
# independent wire decoding (from the protocol document, not from igtl)
def _crc_table() -> list[int]:
    poly = 0x42F0E1EBA9EA3693
    table = []
    for i in range(256):
        crc = i << 56
        for _ in range(8):
            crc = ((crc << 1) ^ poly) if crc & (1 << 63) else (crc << 1)
            crc &= 0xFFFFFFFFFFFFFFFF
        table.append(crc)
    return table


_CRC_TABLE = _crc_table()


def crc64(data: bytes) -> int:
    crc = 0
    for b in data:
        crc = _CRC_TABLE[b ^ (crc >> 56)] ^ ((crc << 8) & 0xFFFFFFFFFFFFFFFF)
    return crc


assert crc64(b"123456789") == 0x6C40DF5F0B497347


def frac_to_nanosec(frac: int) -> int:
    """Reference igtl_frac_to_nanosec (protocol doc 1.4)."""
    base, mask, r = 1_000_000_000, 0x80000000, 0
    for _ in range(32):
        base = (base + 1) >> 1
        if frac & mask:
            r += base
        mask >>= 1
    return r


def cstr(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("latin-1")


@dataclass
class Wire:
    version: int
    type: str
    device: str
    timestamp_raw: int
    body_size: int
    crc: int
    content: bytes
    metadata: dict[str, str] = field(default_factory=dict)
    message_id: int = 0


def split_wire(data: bytes) -> Wire:
    """Parse one complete packed message: header, CRC check, v2 framing, metadata."""
    assert len(data) >= 58, f"{len(data)} bytes is shorter than a header"
    version, typ, dev, ts, size, crc = struct.unpack_from(">H12s20sQQQ", data, 0)
    body = data[58:]
    assert len(body) == size, f"BODY_SIZE {size} but {len(body)} body bytes"
    assert crc64(body) == crc, f"CRC mismatch: header {crc:#x}, body {crc64(body):#x}"
    w = Wire(version, cstr(typ), cstr(dev), ts, size, crc, body)
    if version == 2:
        ext, mh, md, mid = struct.unpack_from(">HHII", body, 0)
        assert ext >= 12 and ext + mh + md <= size, (ext, mh, md, size)
        w.content = body[ext : size - mh - md]
        w.message_id = mid
        meta = body[size - mh - md :]
        (count,) = struct.unpack_from(">H", meta, 0)
        assert mh == 2 + 8 * count, (mh, count)
        pos = mh
        for i in range(count):
            ks, enc, vs = struct.unpack_from(">HHI", meta, 2 + 8 * i)
            key = meta[pos : pos + ks].decode("utf-8")
            val = meta[pos + ks : pos + ks + vs].decode("utf-8" if enc == 106 else "ascii")
            w.metadata[key] = val
            pos += ks + vs
    else:
        assert version == 1, f"header version {version}"
    return w


def decode_transform(c: bytes) -> np.ndarray:
    assert len(c) == 48
    v = struct.unpack(">12f", c)
    m = np.eye(4)
    m[:3, :] = np.asarray(v).reshape(4, 3).T
    return m


def decode_point(c: bytes) -> list[dict]:
    assert len(c) % 136 == 0, len(c)
    out = []
    for i in range(0, len(c), 136):
        name, group, r, g, b, a, x, y, z, diam, owner = struct.unpack_from(">64s32s4B4f20s", c, i)
        out.append(
            dict(name=cstr(name), group=cstr(group), rgba=(r, g, b, a), xyz=(x, y, z),
                 diameter=diam, owner=cstr(owner))
        )
    return out


def decode_traj(c: bytes) -> list[dict]:
    assert len(c) % 150 == 0, len(c)
    out = []
    for i in range(0, len(c), 150):
        v = struct.unpack_from(">64s32sbB4B3f3ff20s", c, i)
        out.append(
            dict(name=cstr(v[0]), group=cstr(v[1]), type=v[2], rgba=tuple(v[4:8]),
                 entry=tuple(v[8:11]), target=tuple(v[11:14]), diameter=v[14], owner=cstr(v[15]))
        )
    return out


def decode_capability(c: bytes) -> list[str]:
    assert len(c) % 12 == 0, len(c)
    return [cstr(c[i : i + 12]) for i in range(0, len(c), 12)]


def decode_status(c: bytes) -> dict:
    code, sub, name = struct.unpack_from(">Hq20s", c, 0)
    assert c[-1:] == b"\0", "STATUS message must end with NUL"
    return dict(code=code, subcode=sub, error_name=cstr(name), message=c[30:-1].decode("utf-8"))


def decode_string(c: bytes) -> tuple[int, str]:
    enc, n = struct.unpack_from(">HH", c, 0)
    assert 4 + n == len(c), (n, len(c))
    return enc, c[4:].decode("utf-8" if enc == 106 else "ascii")


def decode_image(c: bytes) -> dict:
    v = struct.unpack_from(">HBBBB3H12f3H3H", c, 0)
    hdr = dict(
        version=v[0], components=v[1], scalar_type=v[2], endian=v[3], coord=v[4],
        size=tuple(v[5:8]), t=v[8:11], s=v[11:14], n=v[14:17], p=v[17:20],
        sub_offset=tuple(v[20:23]), sub_size=tuple(v[23:26]),
    )
    hdr["pixels"] = c[72:]
    return hdr


def decode_tdata(c: bytes) -> list[dict]:
    assert len(c) % 70 == 0, len(c)
    out = []
    for i in range(0, len(c), 70):
        name, typ, _res = struct.unpack_from(">20sBB", c, i)
        out.append(dict(name=cstr(name), type=typ, matrix=decode_transform(c[i + 22 : i + 70])))
    return out


def decode_qtdata(c: bytes) -> list[dict]:
    assert len(c) % 50 == 0, len(c)
    out = []
    for i in range(0, len(c), 50):
        v = struct.unpack_from(">20sBB3f4f", c, i)
        out.append(dict(name=cstr(v[0]), type=v[1], position=v[3:6], quaternion=v[6:10]))
    return out


def decode_stt_tdata(c: bytes) -> tuple[int, str]:
    assert len(c) == 36, len(c)
    res, coord = struct.unpack(">i32s", c)
    return res, cstr(coord)


def decode_imgmeta(c: bytes) -> list[dict]:
    assert len(c) % 260 == 0, len(c)
    out = []
    for i in range(0, len(c), 260):
        v = struct.unpack_from(">64s20s32s64s64sQ3HBB", c, i)
        out.append(dict(name=cstr(v[0]), device=cstr(v[1]), modality=cstr(v[2]),
                        patient_name=cstr(v[3]), patient_id=cstr(v[4]), timestamp_raw=v[5],
                        size=tuple(v[6:9]), scalar_type=v[9]))
    return out


def decode_lbmeta(c: bytes) -> list[dict]:
    assert len(c) % 116 == 0, len(c)
    out = []
    for i in range(0, len(c), 116):
        v = struct.unpack_from(">64s20sBB4B3H20s", c, i)
        out.append(dict(name=cstr(v[0]), device=cstr(v[1]), label=v[2], rgba=tuple(v[4:8]),
                        size=tuple(v[8:11]), owner=cstr(v[11])))
    return out


def decode_polydata(c: bytes) -> dict:
    counts = struct.unpack_from(">10I", c, 0)
    npts, nv, sv, nl, sl, npoly, spoly, nts, sts, nattr = counts
    pos = 40
    points = np.frombuffer(c, ">f4", 3 * npts, pos).reshape(npts, 3)
    pos += 12 * npts

    def cells(size: int, n: int) -> list[list[int]]:
        nonlocal pos
        blk = np.frombuffer(c, ">u4", size // 4, pos).tolist()
        pos += size
        out, i = [], 0
        while i < len(blk):
            out.append(blk[i + 1 : i + 1 + blk[i]])
            i += 1 + blk[i]
        assert len(out) == n, (len(out), n)
        return out

    verts, lines, polys, strips = cells(sv, nv), cells(sl, nl), cells(spoly, npoly), cells(sts, nts)
    heads = [struct.unpack_from(">BBI", c, pos + 6 * i) for i in range(nattr)]
    pos += 6 * nattr
    names = []
    start = pos
    for _ in range(nattr):
        end = c.index(b"\0", pos)
        names.append(c[pos:end].decode("latin-1"))
        pos = end + 1
    if (pos - start) % 2:
        pos += 1
    attrs = []
    for (typ, ncomp, n), name in zip(heads, names, strict=True):
        data = np.frombuffer(c, ">f4", n * ncomp, pos).reshape(n, ncomp)
        pos += 4 * n * ncomp
        attrs.append(dict(type=typ, ncomp=ncomp, name=name, data=data))
    assert pos == len(c), (pos, len(c))
    return dict(points=points, vertices=verts, lines=lines, polygons=polys, strips=strips,
                attributes=attrs)


def decode_bind(c: bytes) -> list[tuple[str, str, bytes]]:
    """BIND children as (type, name, content)."""
    (n,) = struct.unpack_from(">H", c, 0)
    heads = [struct.unpack_from(">12sQ", c, 2 + 20 * i) for i in range(n)]
    pos = 2 + 20 * n
    (ntable,) = struct.unpack_from(">H", c, pos)
    pos += 2
    names = c[pos : pos + ntable].split(b"\0")[:n]
    pos += ntable
    out = []
    for (typ, size), name in zip(heads, names, strict=True):
        out.append((cstr(typ), name.decode("latin-1"), c[pos : pos + size]))
        pos += size + size % 2
    assert pos == len(c), (pos, len(c))
    return out


# --------------------------------------------------------------------------------------------
# the examples' motion formulas (Tracker*, TrackingData*, QuaternionTrackingData*, Bind*)
def f32(x: float) -> float:
    return struct.unpack("f", struct.pack("f", x))[0]


def quaternion_to_matrix(q: Sequence[float]) -> np.ndarray:
    """igtl::QuaternionToMatrix: normalises (x, y, z, w) then the usual rotation matrix."""
    x, y, z, w = (float(v) for v in q)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w), 0.0],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w), 0.0],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y), 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def example_pose(phi: float, theta: float) -> tuple[tuple[float, ...], tuple[float, ...]]:
    pos = (50.0 * math.cos(phi), 50.0 * math.sin(phi), 50.0 * math.cos(phi))
    quat = (0.0, 0.6666666666 * math.cos(theta), 0.577350269189626, 0.6666666666 * math.sin(theta))
    return pos, quat


def example_matrix(phi: float, theta: float) -> np.ndarray:
    pos, quat = example_pose(phi, theta)
    m = quaternion_to_matrix(quat)
    m[:3, 3] = pos
    return m


def float_steps(step: float, n: int) -> list[float]:
    """``static float x = 0; ... x = x + step;`` as the C++ examples accumulate it."""
    out, x = [], 0.0
    for _ in range(n):
        out.append(x)
        x = f32(x + step)
    return out


def tracker_matrices(n: int) -> list[np.ndarray]:
    """The n first matrices of GetRandomTestMatrix in TrackerClient/TrackerServer/BindClient."""
    return [example_matrix(p, t) for p, t in zip(float_steps(0.2, n), float_steps(0.1, n))]


# --------------------------------------------------------------------------------------------
# output parsers
_FLOAT = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|[-+]?(?:nan|inf)"
_SEP = "============="


def floats(text: str) -> list[float]:
    return [float(x) for x in re.findall(_FLOAT, text)]


def parse_matrices(lines: Sequence[str]) -> list[np.ndarray]:
    """Matrices printed by igtl::PrintMatrix: a '=============' line, 4 rows of 4 comma-separated
    numbers, a '=============' line."""
    out = []
    i = 0
    while i + 5 < len(lines):
        if lines[i].strip() == _SEP and lines[i + 5].strip() == _SEP:
            rows = [floats(lines[i + k]) for k in range(1, 5)]
            if all(len(r) == 4 for r in rows):
                out.append(np.array(rows))
                i += 6
                continue
        i += 1
    return out


def blocks_after(lines: Sequence[str], marker: str) -> list[list[str]]:
    """Split output into blocks, each starting at a line containing ``marker``."""
    out: list[list[str]] = []
    for line in lines:
        if marker in line:
            out.append([line])
        elif out:
            out[-1].append(line)
    return out


def value_of(block: Sequence[str], label: str) -> str:
    """Value after '<label> :' (labels as printed by the examples, spacing-insensitive)."""
    rx = re.compile(r"^\s*" + re.escape(label) + r"\s*:\s?(.*)$")
    for line in block:
        m = rx.match(line)
        if m:
            return m.group(1)
    raise AssertionError(f"no '{label}' in block:\n" + "\n".join(block))


def element_blocks(lines: Sequence[str]) -> list[list[str]]:
    """'========== Element #i ==========' blocks (POINT, TRAJ, TDATA, QTDATA, *META prints)."""
    return blocks_after(lines, "========== Element #")


def close(a: Any, b: Any, rtol: float = 1e-5, atol: float = 1e-5) -> bool:
    return bool(np.allclose(np.asarray(a, float), np.asarray(b, float), rtol=rtol, atol=atol))


# --------------------------------------------------------------------------------------------
# our transports: receiving
def collect(
    endpoint: Any,
    n: int,
    timeout: float = WAIT,
    where: Callable[[Any], bool] | None = None,
) -> list[Any]:
    """Receive until ``n`` messages (matching ``where``) arrived on a TCPServer/TCPClient, or
    ``timeout``. Returns the messages (possibly fewer than ``n``; the caller asserts)."""
    out: list[Any] = []
    deadline = time.monotonic() + timeout
    while len(out) < n:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        item = endpoint.receive(timeout=min(left, 0.5))
        if item is None:
            continue
        _peer, msg = item
        if where is None or where(msg):
            out.append(msg)
    return out


def of_type(*types: str) -> Callable[[Any], bool]:
    return lambda m: m.message_type in types


def assert_typed(msg: Any) -> None:
    """Our codec decoded the message into its type's class, not the RawMessage fallback."""
    import igtl

    assert not isinstance(msg, igtl.RawMessage), (
        f"igtl did not decode {msg.message_type} into a typed message (got RawMessage)"
    )


def typed(msg: Any) -> Wire:
    """Assert ``msg`` is typed, re-encode it and parse that with the independent decoder:
    proves the decoded object kept every field of what the peer sent."""
    assert_typed(msg)
    return split_wire(msg.pack())


def ours(raw: bytes) -> Any:
    """Our typed message for reference-format bytes (decoded by our codec, CRC checked)."""
    import igtl

    msg = igtl.unpack(raw)
    assert_typed(msg)
    return msg


# --------------------------------------------------------------------------------------------
# independent encoders: reference-format bytes for content we choose. Tests turn them into our
# typed messages with igtl.unpack() (so our decoder and encoder are both on the path) before
# sending them with our transports.
def pack_wire(
    type_name: str,
    device: str,
    content: bytes,
    *,
    version: int = 1,
    timestamp_raw: int = 0,
    metadata: dict[str, str] | None = None,
    message_id: int = 0,
) -> bytes:
    if version == 2:
        items = sorted((metadata or {}).items())
        mh = struct.pack(">H", len(items))
        md = b""
        for k, v in items:
            kb, vb = k.encode(), v.encode()
            enc = 3 if vb.isascii() else 106
            mh += struct.pack(">HHI", len(kb), enc, len(vb))
            md += kb + vb
        body = struct.pack(">HHII", 12, len(mh), len(md), message_id) + content + mh + md
    else:
        assert not metadata and not message_id
        body = content
    head = struct.pack(
        ">H12s20sQQQ", version, type_name.encode(), device.encode(), timestamp_raw, len(body),
        crc64(body),
    )
    return head + body


def _s(text: str, size: int) -> bytes:
    raw = text.encode("latin-1")
    assert len(raw) <= size
    return raw


def encode_point(points: Sequence[dict]) -> bytes:
    return b"".join(
        struct.pack(">64s32s4B4f20s", _s(p["name"], 64), _s(p["group"], 32), *p["rgba"],
                    *p["xyz"], p["diameter"], _s(p["owner"], 20))
        for p in points
    )


def encode_traj(items: Sequence[dict]) -> bytes:
    return b"".join(
        struct.pack(">64s32sbB4B3f3ff20s", _s(t["name"], 64), _s(t["group"], 32), t["type"], 0,
                    *t["rgba"], *t["entry"], *t["target"], t["diameter"], _s(t["owner"], 20))
        for t in items
    )


def encode_capability(types: Sequence[str]) -> bytes:
    return b"".join(struct.pack("12s", _s(t, 12)) for t in types)


def matrix_to_elements(m: Any) -> tuple[float, ...]:
    return tuple(np.asarray(m, float)[:3, :].T.ravel().tolist())


def encode_tdata(items: Sequence[dict]) -> bytes:
    return b"".join(
        struct.pack(">20sBB12f", _s(e["name"], 20), e["type"], 0, *matrix_to_elements(e["matrix"]))
        for e in items
    )


def encode_qtdata(items: Sequence[dict]) -> bytes:
    return b"".join(
        struct.pack(">20sBB3f4f", _s(e["name"], 20), e["type"], 0, *e["position"], *e["quaternion"])
        for e in items
    )


def encode_image(
    pixels: np.ndarray,
    *,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    center: Sequence[float] = (0.0, 0.0, 0.0),
    coord: int = 1,
) -> bytes:
    """``pixels`` indexed [k, j, i] (or [k, j, i, c]); written in its own byte order."""
    comps = pixels.shape[3] if pixels.ndim == 4 else 1
    nk, nj, ni = pixels.shape[:3]
    stype = {np.dtype(t).str[1:]: s for t, s in
             (("i1", 2), ("u1", 3), ("i2", 4), ("u2", 5), ("i4", 6), ("u4", 7), ("f4", 10),
              ("f8", 11))}[pixels.dtype.str[1:]]
    endian = 1 if pixels.dtype.byteorder == ">" or (
        pixels.dtype.byteorder == "=" and np.little_endian is False) else 2
    si, sj, sk = spacing
    head = struct.pack(
        ">HBBBB3H12f3H3H", 1, comps, stype, endian, coord, ni, nj, nk,
        si, 0, 0, 0, sj, 0, 0, 0, sk, *center, 0, 0, 0, ni, nj, nk,
    )
    return head + pixels.tobytes()


def encode_imgmeta(items: Sequence[dict]) -> bytes:
    return b"".join(
        struct.pack(">64s20s32s64s64sQ3HBB", _s(e["name"], 64), _s(e["device"], 20),
                    _s(e["modality"], 32), _s(e["patient_name"], 64), _s(e["patient_id"], 64),
                    e["timestamp_raw"], *e["size"], e["scalar_type"], 0)
        for e in items
    )


def encode_lbmeta(items: Sequence[dict]) -> bytes:
    return b"".join(
        struct.pack(">64s20sBB4B3H20s", _s(e["name"], 64), _s(e["device"], 20), e["label"], 0,
                    *e["rgba"], *e["size"], _s(e["owner"], 20))
        for e in items
    )


def encode_polydata(points: Sequence[Sequence[float]], polygons: Sequence[Sequence[int]],
                    lines: Sequence[Sequence[int]] = (),
                    scalars: tuple[str, Sequence[float]] | None = None) -> bytes:
    def cells(cs: Sequence[Sequence[int]]) -> bytes:
        return b"".join(struct.pack(f">I{len(c)}I", len(c), *c) for c in cs)

    poly, lin = cells(polygons), cells(lines)
    nattr = 1 if scalars else 0
    out = struct.pack(">10I", len(points), 0, 0, len(lines), len(lin), len(polygons), len(poly),
                      0, 0, nattr)
    out += b"".join(struct.pack(">3f", *p) for p in points) + lin + poly
    if scalars:
        name, values = scalars
        out += struct.pack(">BBI", 0, 1, len(values))
        names = name.encode() + b"\0"
        out += names + (b"\0" if len(names) % 2 else b"")
        out += struct.pack(f">{len(values)}f", *values)
    return out


def encode_bind(children: Sequence[tuple[str, str, bytes]]) -> bytes:
    out = struct.pack(">H", len(children))
    out += b"".join(struct.pack(">12sQ", _s(t, 12), len(c)) for t, _n, c in children)
    table = b"".join(n.encode() + b"\0" for _t, n, _c in children)
    if len(table) % 2:
        table += b"\0"
    out += struct.pack(">H", len(table)) + table
    out += b"".join(c + (b"\0" if len(c) % 2 else b"") for _t, _n, c in children)
    return out
