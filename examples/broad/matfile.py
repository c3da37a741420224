"""A Matlab v5 ``.mat`` file from outside, read with bounded memory.

``scipy.io.loadmat`` decompresses a variable whole before anything can look at it, and even
``scipy.io.whosmat`` decompresses all of a compressed variable (its integrity check) or at least
its first 128 KiB of compressed data, up to about a thousand times that: a 1 MB file that claims
5e7 samples, or claims 10 and holds 5e7, expands to gigabytes before any check. Here:

1. :func:`check_regular_file`: the path is an existing regular file (a folder, a FIFO that would
   block the read, a device are refused by name);
2. :func:`variables`: each variable's header, ``{name: (shape, class)}``, parsed here from at
   most :data:`HEADER_BYTES` decompressed bytes per variable (no data), for the caller to check
   against its limits;
3. :func:`read_variables`: only the variables asked for, each decompressed at most to the size
   its header's shape and class allow (a little more for its own header; twice for a complex
   array), so a variable that holds more than it claims is refused before it is expanded. The
   other variables are skipped unread. scipy then parses the few bounded bytes.

Errors are :class:`MatFileError` naming the file, the variable and the fix.
"""

from __future__ import annotations

import io
import math
import os
import stat
import struct
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np

__all__ = [
    "HEADER_BYTES", "MatFileError", "NUMERIC_CLASSES", "Variable", "check_regular_file", "variables",
    "read_variables",
]

#: Bytes per element of the numeric classes ``whosmat`` names (``logical`` is stored as bytes).
NUMERIC_CLASSES = {
    "double": 8, "single": 4, "int8": 1, "uint8": 1, "int16": 2, "uint16": 2, "int32": 4,
    "uint32": 4, "int64": 8, "uint64": 8, "logical": 1,
}
#: The most decompressed bytes a variable's header (flags, dimensions, name) may take.
HEADER_BYTES = 1 << 16

_CLASSES = {1: "cell", 2: "struct", 3: "object", 4: "char", 5: "sparse", 6: "double",
            7: "single", 8: "int8", 9: "uint8", 10: "int16", 11: "uint16", 12: "int32",
            13: "uint32", 14: "int64", 15: "uint64", 16: "function", 17: "opaque"}  # fmt: skip
_MI_MATRIX, _MI_COMPRESSED = 14, 15
#: Bytes per element of the numeric data types a numeric variable's data may be stored as.
_DATA_TYPES = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 9: 8, 12: 8, 13: 8}
_CHUNK = 1 << 20


class MatFileError(ValueError):
    """A ``.mat`` file is unreadable, or holds more than it may; the message names the fix."""


def check_regular_file(path: Path) -> None:
    """``MatFileError`` unless ``path`` is an existing regular file that can be opened."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise MatFileError(f"{path}: no such file; check the path.") from None
    except OSError as err:
        raise MatFileError(f"{path}: cannot be read ({type(err).__name__}: {err.strerror}).") from None
    if stat.S_ISDIR(mode):
        raise MatFileError(f"{path}: is a folder, not a .mat file; give the path of a .mat file.")
    if not stat.S_ISREG(mode):
        raise MatFileError(
            f"{path}: is not a regular file (a FIFO, socket or device); give the path of a "
            ".mat file on disk."
        )
    if not os.access(path, os.R_OK):
        raise MatFileError(f"{path}: cannot be read (no read permission).")


def _unreadable(path, err) -> MatFileError:
    return MatFileError(
        f"{path}: not a readable Matlab v5 file ({type(err).__name__}: {err}); save it with "
        "Matlab's save -v7 (or scipy.io.savemat)."
    )


def _sub(buf: bytes, pos: int, e: str):
    """``(type, data, next position)`` of the sub-element at ``pos``; ``None`` past ``buf``."""
    if pos + 8 > len(buf):
        return None
    (first,) = struct.unpack_from(e + "I", buf, pos)
    if first >> 16:  # the small format: byte count and type in one word, data in the next
        return first & 0xFFFF, buf[pos + 4 : pos + 4 + (first >> 16)], pos + 8
    mdtype, n = struct.unpack_from(e + "II", buf, pos)
    if pos + 8 + n > len(buf):
        return None
    return mdtype, buf[pos + 8 : pos + 8 + n], pos + 8 + (n + 7) // 8 * 8


def _header(element: bytes, e: str):
    """``(name, shape, class, complex)`` from the start of a variable's element (its tag, array
    flags, dimensions, name); ``None`` while ``element`` is too short to hold them."""
    flags = _sub(element, 8, e)
    dims = flags and _sub(element, flags[2], e)
    name = dims and _sub(element, dims[2], e)
    if not name:
        return None
    (word,) = struct.unpack_from(e + "I", flags[1])
    shape = struct.unpack(e + f"{len(dims[1]) // 4}i", dims[1][: len(dims[1]) // 4 * 4])
    cls = "logical" if word & 0x200 else _CLASSES.get(word & 0xFF, "unknown")
    return name[1].decode("latin1"), tuple(shape), cls, bool(word & 0x800)


def _head_of(f, path, nbytes: int, compressed: bool) -> bytes:
    """The first :data:`HEADER_BYTES` (or fewer) bytes of the element at ``f``'s position."""
    if not compressed:
        return f.read(min(nbytes, HEADER_BYTES))
    inflater, out, left = zlib.decompressobj(), b"", nbytes
    while len(out) < HEADER_BYTES and not inflater.eof:
        if inflater.unconsumed_tail:
            piece = inflater.unconsumed_tail
        elif left:
            piece = f.read(min(left, 1 << 12))
            left -= len(piece)
            if not piece:
                break
        else:
            break
        try:
            out += inflater.decompress(piece, HEADER_BYTES - len(out))
        except zlib.error as err:
            raise _unreadable(path, err) from None
    return out


class Variable(NamedTuple):
    """A variable's header: ``shape``, ``cls`` (``whosmat``'s class names: ``double``,
    ``logical``, ``cell``, ...), ``complex``, and where its element lies in the file."""

    shape: tuple[int, ...]
    cls: str
    complex: bool
    compressed: bool
    offset: int
    nbytes: int


def variables(path: Path) -> dict[str, Variable]:
    """``{name: Variable}`` of the file's variables, in file order; no data is read."""
    import scipy.io

    try:
        version = scipy.io.matlab.matfile_version(str(path))
    except Exception as err:  # noqa: BLE001 - any failure of the parser is a format error
        raise _unreadable(path, err) from None
    if version[0] != 1:
        raise _unreadable(path, ValueError(f"Matlab format version {version}, not v5/v7 (1, 0)"))
    out = {}
    with open(path, "rb") as f:
        head = f.read(128)
        e = ">" if head[126:128] == b"MI" else "<"
        size = os.fstat(f.fileno()).st_size
        while f.tell() < size:
            offset = f.tell()
            tag = f.read(8)
            if len(tag) < 8:
                raise _unreadable(path, EOFError(f"a cut tag at byte {offset}"))
            mdtype, nbytes = struct.unpack(e + "II", tag)
            if mdtype not in (_MI_MATRIX, _MI_COMPRESSED) or offset + 8 + nbytes > size:
                raise _unreadable(path, ValueError(f"a damaged variable at byte {offset}"))
            compressed = mdtype == _MI_COMPRESSED
            element = _head_of(f, path, nbytes, compressed)
            try:
                found = _header(element if compressed else tag + element, e)
            except (struct.error, UnicodeDecodeError) as err:
                raise _unreadable(path, err) from None
            if found is None:
                raise MatFileError(f"{path}: the variable at byte {offset} has a damaged or "
                                   f"oversized header (over {HEADER_BYTES} bytes); re-export it.")
            name, shape, cls, cplx = found
            if name in out:
                raise MatFileError(f"{path}: variable {name!r} is stored twice; keep one.")
            if any(n < 0 for n in shape):
                raise MatFileError(f"{path}: variable {name!r} has negative sizes {shape}.")
            out[name] = Variable(shape, cls, cplx, compressed, offset, nbytes)
            f.seek(offset + 8 + nbytes)
    return out


def _bound(var: Variable, name: str) -> int:
    """The most bytes the element of numeric variable ``var`` may take: its data (twice for a
    complex one) and its own header."""
    data = math.prod(var.shape) * NUMERIC_CLASSES[var.cls] * (2 if var.complex else 1)
    return data + 8 * len(var.shape) + len(name) + 256


def _inflate(f, path, name: str, nbytes: int, bound: int) -> bytes:
    """The ``nbytes`` compressed bytes at ``f``'s position, expanded to at most ``bound``."""
    inflater, out, left = zlib.decompressobj(), bytearray(), nbytes
    while left and not inflater.eof:
        chunk = f.read(min(left, _CHUNK))
        if not chunk:
            raise MatFileError(f"{path}: variable {name!r} is cut short; the file is truncated.")
        left -= len(chunk)
        try:
            out += inflater.decompress(chunk, bound + 1 - len(out))
        except zlib.error as err:
            raise _unreadable(path, err) from None
        if len(out) > bound or inflater.unconsumed_tail:
            raise MatFileError(
                f"{path}: variable {name!r} holds more data than its header's shape and class "
                f"allow (over {bound} bytes); the file is damaged or hostile, re-export it."
            )
    return bytes(out)


def _check_element(path, name: str, element: bytes, e: str, var: Variable) -> bytes:
    """``element`` if it is what its header said, a plain numeric array whose data parts hold
    exactly ``prod(shape)`` values of a known type; else ``MatFileError``. scipy's parser
    trusts these fields (an unknown data type crashed it with a segmentation fault)."""
    def damaged(what: str) -> MatFileError:
        return MatFileError(f"{path}: variable {name!r} is damaged ({what}); re-export the file.")

    try:
        found = _header(element, e)
        (mdtype, nbytes) = struct.unpack_from(e + "II", element)
    except (struct.error, UnicodeDecodeError):
        found = None
    if found is None or found != (name, var.shape, var.cls, var.complex):
        raise damaged("its header differs from the one read first")
    if mdtype != _MI_MATRIX or nbytes != len(element) - 8:
        raise damaged(f"type {mdtype}, {nbytes} bytes for {len(element) - 8}")
    pos = _sub(element, _sub(element, _sub(element, 8, e)[2], e)[2], e)[2]
    for part in ("real", "imaginary")[: 1 + var.complex]:
        sub = _sub(element, pos, e)
        if sub is None or sub[0] not in _DATA_TYPES:
            raise damaged(f"its {part} part has no numeric data")
        if len(sub[1]) != math.prod(var.shape) * _DATA_TYPES[sub[0]]:
            raise damaged(f"its {part} part holds {len(sub[1])} bytes of type {sub[0]}, not "
                          f"{math.prod(var.shape)} values")
        pos = sub[2]
    if pos < len(element) - 7:
        raise damaged("bytes after its data")
    return element


def read_variables(path: Path, header: dict[str, Variable], names) -> dict[str, np.ndarray]:
    """The variables ``names`` (numeric ones of ``header``, from :func:`variables`, checked by
    the caller) as ``scipy.io.loadmat(path, squeeze_me=True)`` gives them, reading nothing
    else."""
    import scipy.io

    parts = []
    with open(path, "rb") as f:
        head = bytearray(f.read(128))
        e = ">" if head[126:128] == b"MI" else "<"
        head[116:124] = bytes(8)  # no subsystem data: its offset would point into this file
        for name in names:
            var = header[name]
            bound = _bound(var, name)
            f.seek(var.offset)
            tag = f.read(8)
            if var.compressed:
                element = _inflate(f, path, name, var.nbytes, bound)
            elif var.nbytes > bound:
                raise MatFileError(
                    f"{path}: variable {name!r} takes {var.nbytes} bytes, more than its "
                    f"header's shape and class allow ({bound}); re-export the file."
                )
            else:
                element = tag + f.read(var.nbytes)
            parts.append(_check_element(path, name, element, e, var))
    try:
        raw = scipy.io.loadmat(io.BytesIO(bytes(head) + b"".join(parts)), squeeze_me=True)
    except Exception as err:  # noqa: BLE001 - the bounded bytes do not parse: a format error
        raise _unreadable(path, err) from None
    return {n: raw[n] for n in names if n in raw}
