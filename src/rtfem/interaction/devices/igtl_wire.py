"""OpenIGTLink on the wire: the framing (the 58-byte header of protocol versions 1-3, header
versions 1 and 2) and the few bodies the bridge reads and writes (TRANSFORM, STRING, POLYDATA);
:mod:`.igtl_net` serves them.

The header (big-endian): version u16, type char[12], device name char[20], timestamp (seconds
u32, fraction u32), body size u64, CRC-64 (ECMA-182 polynomial, as the reference library and pyigtl
compute it) of the body u64. A version-2 body starts with a 12-byte extended header and ends with
metadata (http://openigtlink.org/developers/spec). Every reader here checks sizes and types and
raises ValueError (:class:`FramingError` where the stream cannot go on) saying what was wrong.
"""

from __future__ import annotations

import re
import struct
import time
from typing import NamedTuple

import numpy as np

from ...errors import DeviceError

__all__ = ["Header", "pack", "transform_body", "string_body", "polydata_body", "content_of", "read_transform",
           "read_string", "parse_header", "FramingError", "crc64", "HEADER_SIZE", "BODY_LIMITS", "DEFAULT_BODY_LIMIT"]

HEADER = struct.Struct(">H12s20sIIQQ")
HEADER_SIZE = HEADER.size  # 58
EXTENDED = struct.Struct(">HHII")
#: the largest body read of each type (bytes; version-2 metadata included): what rtfem reads is small
BODY_LIMITS = {"TRANSFORM": 4096, "STRING": 4 + 65535 + 4096, "STATUS": 30 + 20 + 65535 + 4096}
#: the largest body of any other type, read and ignored
DEFAULT_BODY_LIMIT = 1 << 20
_TYPE = re.compile(rb"[A-Za-z0-9_]{1,12}")


def _crc_function():
    try:
        import crcmod
    except ImportError:
        raise DeviceError("the OpenIGTLink bridge needs crcmod (pyigtl's CRC): pip install 'rtfem[igtl]' "
                          "(make installs it)") from None
    return crcmod.mkCrcFun(0x142F0E1EBA9EA3693, rev=False, initCrc=0, xorOut=0)


_CRC = None


def crc64(data) -> int:
    """OpenIGTLink's CRC-64 of ``data`` (crcmod's C code, the function pyigtl uses)."""
    global _CRC
    if _CRC is None:
        _CRC = _crc_function()
    return _CRC(data)


class FramingError(ValueError):
    """A header that cannot start an OpenIGTLink message (the stream cannot go on)."""


class Header(NamedTuple):
    version: int
    kind: str   # the message type: TRANSFORM, STRING, ...
    name: str   # the device name (printable; "" when it was not UTF-8)
    timestamp: float
    body_size: int
    crc: int
    name_ok: bool  # the device name was UTF-8 without control characters


def parse_header(data) -> Header:
    """The 58 bytes of a header; :class:`FramingError` when they cannot start a message (an
    unknown header version, a type that is not a type name, a body over its type's limit)."""
    version, kind_b, name_b, sec, frac, size, crc = HEADER.unpack(bytes(data[:HEADER_SIZE]))
    if version not in (1, 2):
        raise FramingError(f"not an OpenIGTLink header (version {version}; 1 or 2 expected)")
    kind_b = kind_b.rstrip(b"\0")
    if not _TYPE.fullmatch(kind_b):
        raise FramingError(f"not an OpenIGTLink header (message type {kind_b[:12]!r})")
    kind = kind_b.decode("ascii")
    limit = BODY_LIMITS.get(kind, DEFAULT_BODY_LIMIT)
    if size > limit:
        raise FramingError(f"a {kind} body of {size} bytes, more than the {limit} bytes read of a {kind}")
    try:
        name = name_b.rstrip(b"\0").decode("utf-8")
        name_ok = name.isprintable()
    except UnicodeDecodeError:
        name, name_ok = "", False
    return Header(version, kind, name if name_ok else "", sec + frac / 2.0**32, size, crc, name_ok)


def content_of(header: Header, body: bytes) -> bytes:
    """The message's content: the body checked against the header's CRC, less a version-2
    extended header and metadata; ValueError saying what is wrong."""
    if crc64(body) != header.crc:
        raise ValueError("its CRC-64 does not match its body (corrupted, or not computed by the sender)")
    if header.version == 1:
        return body
    if len(body) < EXTENDED.size:
        raise ValueError(f"a version-2 body of {len(body)} bytes has no extended header")
    ext, meta_header, meta_body, _ = EXTENDED.unpack(body[:EXTENDED.size])
    end = len(body) - meta_header - meta_body
    if ext < EXTENDED.size or end < ext:
        raise ValueError(f"a version-2 body whose extended header ({ext} bytes) and metadata ({meta_header} + "
                         f"{meta_body} bytes) do not fit its {len(body)} bytes")
    return body[ext:end]


def read_transform(content: bytes) -> np.ndarray:
    """A TRANSFORM's 4x4 matrix (float64) from its 48 bytes (12 big-endian float32: the rotation's
    columns, then the translation); ValueError for any other size."""
    if len(content) != 48:
        raise ValueError(f"a TRANSFORM body of {len(content)} bytes (48 expected: 12 float32)")
    v = np.frombuffer(content, dtype=">f4").astype(np.float64)
    M = np.eye(4)
    M[:3, :4] = v.reshape(4, 3).T
    return M


def read_string(content: bytes, limit: int = 65535) -> str:
    """A STRING's text (US-ASCII or UTF-8, at most ``limit`` bytes); ValueError otherwise."""
    if len(content) < 4:
        raise ValueError(f"a STRING body of {len(content)} bytes (at least 4)")
    encoding, length = struct.unpack(">HH", content[:4])
    if length != len(content) - 4:
        raise ValueError(f"a STRING saying {length} bytes with {len(content) - 4} after its header")
    if length > limit:
        raise ValueError(f"a STRING of {length} bytes (at most {limit} here)")
    codec = {3: "ascii", 106: "utf-8"}.get(encoding)
    if codec is None:
        raise ValueError(f"a STRING in character set {encoding} (3, US-ASCII, or 106, UTF-8, are read)")
    try:
        return content[4:].decode(codec)
    except UnicodeDecodeError:
        raise ValueError(f"a STRING that is not {codec}") from None


def pack(kind: str, name: str, content: bytes, timestamp: float | None = None) -> bytes:
    """A version-1 message: the header (CRC-64 of the content) and the content."""
    t = time.time() if timestamp is None else float(timestamp)
    sec = int(t)
    frac = min(int((t - sec) * 2.0**32), 0xFFFFFFFF)
    return HEADER.pack(1, kind.encode("ascii"), name.encode("utf-8")[:20], sec & 0xFFFFFFFF, frac, len(content),
                       crc64(content)) + content


def transform_body(M) -> bytes:
    """A TRANSFORM's content from a 4x4 (or 3x4) matrix."""
    return np.ascontiguousarray(np.asarray(M, dtype=float)[:3, :4].T, dtype=">f4").tobytes()


def string_body(text: str) -> bytes:
    """A STRING's content (US-ASCII when it can be, else UTF-8; cut to 65535 bytes)."""
    try:
        data, encoding = text.encode("ascii"), 3
    except UnicodeEncodeError:
        data, encoding = text.encode("utf-8"), 106
    data = data[:65535]
    return struct.pack(">HH", encoding, len(data)) + data


def polydata_body(points, polygons: bytes, n_polygons: int) -> bytes:
    """A POLYDATA's content: ``points`` (n, 3) as float32 and ``polygons`` (the cells' big-endian
    uint32 bytes, each cell its size then its points) of ``n_polygons`` cells; no vertices, lines,
    strips or attributes (the layout pyigtl's PolyDataMessage writes)."""
    P = np.ascontiguousarray(points, dtype=">f4")
    head = struct.pack(">10I", len(P), 0, 0, 0, 0, n_polygons, len(polygons), 0, 0, 0)
    return head + P.tobytes() + polygons
