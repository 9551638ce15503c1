"""``.npz`` archives (numpy's format: a zip of ``.npy`` members), written uncompressed
member by member, each large array straight from its memory.

``np.savez`` writes the same archive but passes every array through 16 MiB ``tobytes``
copies; here a C-contiguous numeric array goes to its zip member as one buffer (zipfile
computes its CRC-32 as it writes), so writing the frames of a clip costs the CRC and the
write, no copy of them. ``np.load`` reads the result.
"""
from __future__ import annotations

import zipfile
from typing import BinaryIO, Mapping

import numpy as np

__all__ = ["write_npz"]


def write_npz(fh: BinaryIO, arrays: Mapping[str, np.ndarray]) -> None:
    """Write ``arrays`` (name -> array; no object arrays) to the binary file ``fh`` as an
    uncompressed ``.npz`` with members ``<name>.npy`` in the mapping's order."""
    with zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, value in arrays.items():
            arr = np.asanyarray(value)
            with zf.open(f"{name}.npy", "w", force_zip64=True) as member:
                if arr.flags.c_contiguous and arr.dtype.kind in "biuf" and arr.nbytes:
                    write_header(member, arr)
                    member.write(memoryview(arr.reshape(-1)).cast("B"))
                else:
                    np.lib.format.write_array(member, arr, allow_pickle=False)


def write_header(member, arr: np.ndarray) -> None:
    """The ``.npy`` header of ``arr`` (the format version ``np.save`` would choose)."""
    d = np.lib.format.header_data_from_array_1_0(arr)
    try:
        np.lib.format.write_array_header_1_0(member, d)
    except ValueError:            # a header too long for version 1.0
        np.lib.format.write_array_header_2_0(member, d)
