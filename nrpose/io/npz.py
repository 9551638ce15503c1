"""``.npz`` archives (numpy's format: a zip of ``.npy`` members), written uncompressed
member by member, each large array straight from its memory, and read back without
numpy's chunked copies.

``np.savez`` writes the same archive but passes every array through 16 MiB ``tobytes``
copies (and a non-contiguous one through a buffered iterator); here each C-contiguous
block of an array goes to its zip member as one buffer (zipfile computes its CRC-32 as it
writes), so writing the frames of a clip costs the CRC and the write, no copy of them. A
member may also be :class:`Streamed`: its header is written first and its data as they
arrive (frames as they come back from the device), so the whole array never exists.
``np.load`` reads the result; :func:`read_npz` reads an uncompressed archive with one read
per member, checking each member's CRC-32.
"""
from __future__ import annotations

import io
import struct
import zipfile
import zlib
from dataclasses import dataclass
from typing import BinaryIO, Iterable, Mapping

import numpy as np

from ..errors import FileFormatError, InputError

__all__ = ["Streamed", "write_npz", "read_npz"]

#: a zip local file header: signature, then 22 bytes, then the name's and the extra field's lengths
_LOCAL_HEADER = struct.Struct("<4s22sHH")
_LOCAL_SIGNATURE = b"PK\x03\x04"
#: sub-arrays at least this large are written from their own memory (smaller ones are copied in blocks)
DIRECT_MIN_BYTES = 1 << 16
#: bytes copied at a time from an array that is not C-contiguous (np.save's buffer size)
COPY_BLOCK_BYTES = 1 << 24
#: the largest ``.npy`` header read (numpy's own limit in ``np.load``)
MAX_HEADER_SIZE = 10000


@dataclass(frozen=True)
class Streamed:
    """An archive member whose data arrive in pieces: an array of ``shape`` and ``dtype``
    whose elements in C order are those of the ``chunks`` (arrays of that dtype, any
    shapes), one after the other. :func:`write_npz` writes the header, then each chunk as
    it comes (consuming the iterable once), and refuses (InputError) chunks that do not
    add up to the shape."""

    shape: tuple[int, ...]
    dtype: np.dtype
    chunks: Iterable[np.ndarray]


def write_npz(fh: BinaryIO, arrays: Mapping[str, np.ndarray | Streamed]) -> None:
    """Write ``arrays`` (name -> array or :class:`Streamed`; no object arrays) to the binary
    file ``fh`` as an uncompressed ``.npz`` with members ``<name>.npy`` in the mapping's order."""
    with zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, value in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as member:
                if isinstance(value, Streamed):
                    write_streamed(member, value)
                    continue
                arr = np.asanyarray(value)
                if arr.dtype.kind in "biuf" and arr.size:
                    write_header(member, {"descr": np.lib.format.dtype_to_descr(arr.dtype),
                                          "fortran_order": False, "shape": arr.shape})
                    write_blocks(member, arr)
                else:
                    np.lib.format.write_array(member, arr, allow_pickle=False)


def write_streamed(member, value: Streamed) -> None:
    """The ``.npy`` header of ``value``, then its chunks as they arrive."""
    dtype = np.dtype(value.dtype)
    shape = tuple(int(s) for s in value.shape)
    write_header(member, {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False, "shape": shape})
    expected, written = int(np.prod(shape, dtype=np.int64)), 0
    for chunk in value.chunks:
        chunk = np.asanyarray(chunk)
        if chunk.dtype != dtype:
            raise InputError(f"streamed member: a chunk of {chunk.dtype}, the member is {dtype}")
        written += chunk.size
        if written > expected:
            raise InputError(f"streamed member: more than the {expected} elements of shape {shape}")
        write_blocks(member, chunk)
    if written != expected:
        raise InputError(f"streamed member: {written} elements arrived, shape {shape} holds {expected}")


def write_blocks(member, arr: np.ndarray) -> None:
    """``arr``'s elements in C order: the whole from its memory where it is C-contiguous,
    else each sub-array along the first axis from its memory where those are C-contiguous
    and large (frames with padding between them), else copied a block at a time."""
    if arr.flags.c_contiguous:
        if arr.size:
            member.write(memoryview(arr.reshape(-1)).cast("B"))
    elif arr.ndim > 1 and arr[0].flags.c_contiguous and arr[0].nbytes >= DIRECT_MIN_BYTES:
        for part in arr:
            member.write(memoryview(part.reshape(-1)).cast("B"))
    else:
        rows = max(1, COPY_BLOCK_BYTES // max(arr[0].nbytes, 1))
        for a in range(0, len(arr), rows):
            member.write(memoryview(np.ascontiguousarray(arr[a:a + rows]).reshape(-1)).cast("B"))


def write_header(member, header: dict) -> None:
    """The ``.npy`` header ``header`` (descr, fortran_order, shape), in the format version
    ``np.save`` would choose."""
    try:
        np.lib.format.write_array_header_1_0(member, header)
    except ValueError:            # a header too long for version 1.0
        np.lib.format.write_array_header_2_0(member, header)


def read_npz(path) -> dict[str, np.ndarray]:
    """The arrays of the ``.npz`` at ``path`` (member ``<name>.npy`` -> name), each read
    with one read into its own writable, aligned memory, its CRC-32 checked. Compressed
    members are read by ``np.load``. FileFormatError for a file that is not such an
    archive, a truncated or corrupt member, or an object array."""
    try:
        with open(path, "rb") as f:
            with zipfile.ZipFile(f) as zf:
                infos = zf.infolist()
            out = {}
            for info in infos:
                if not info.filename.endswith(".npy"):
                    raise FileFormatError(f"{path}: member {info.filename!r} is not a .npy array")
                name = info.filename[:-4]
                if info.compress_type != zipfile.ZIP_STORED:
                    with np.load(path, allow_pickle=False) as z:
                        out[name] = np.array(z[name])
                    continue
                out[name] = _read_member(f, info, path)
            return out
    except (OSError, zipfile.BadZipFile, ValueError, EOFError, struct.error) as exc:
        raise FileFormatError(f"{path}: not a readable .npz archive ({exc})") from None


def _read_member(f, info: zipfile.ZipInfo, path) -> np.ndarray:
    """One stored member's array, read from the open archive ``f``."""
    f.seek(info.header_offset)
    sig, _, name_len, extra_len = _LOCAL_HEADER.unpack(f.read(_LOCAL_HEADER.size))
    if sig != _LOCAL_SIGNATURE:
        raise FileFormatError(f"{path}: member {info.filename!r}: no local header")
    f.seek(info.header_offset + _LOCAL_HEADER.size + name_len + extra_len)
    data = bytearray(info.file_size)        # malloc'd: aligned for every numeric dtype
    if f.readinto(data) != len(data) or zlib.crc32(data) != info.CRC:
        raise FileFormatError(f"{path}: member {info.filename!r} is truncated or corrupt (CRC-32)")
    head = io.BytesIO(data)
    version = np.lib.format.read_magic(head)
    read_header = {(1, 0): np.lib.format.read_array_header_1_0,
                   (2, 0): np.lib.format.read_array_header_2_0}.get(version)
    if read_header is None:
        raise FileFormatError(f"{path}: member {info.filename!r}: .npy format version {version}")
    shape, fortran, dtype = read_header(head, max_header_size=MAX_HEADER_SIZE)
    if dtype.hasobject:
        raise FileFormatError(f"{path}: member {info.filename!r} holds Python objects")
    count = int(np.prod(shape, dtype=np.int64))
    if head.tell() + count * dtype.itemsize != len(data):
        raise FileFormatError(f"{path}: member {info.filename!r}: its size does not match its shape {shape}")
    arr = np.frombuffer(data, dtype, count, offset=head.tell())
    return arr.reshape(shape[::-1]).T if fortran else arr.reshape(shape)
