"""io.npz: archives written member by member (whole arrays or streamed in chunks) read back by
np.load as np.savez's are; read_npz reads np.savez's archives as np.load does and refuses
damaged ones."""
from __future__ import annotations

import zipfile

import numpy as np
import pytest

from nrpose.errors import FileFormatError, InputError
from nrpose.io.npz import Streamed, read_npz, write_npz


def sample_arrays() -> dict:
    rng = np.random.default_rng(6)
    padded = np.zeros((5, 9, 3), np.float32)          # frames 9 rows apart, 7 used: a frames_array's layout
    padded[:, :7] = rng.normal(size=(5, 7, 3))
    big = np.zeros((3, 6100, 3), np.float32)           # frames large enough to go out from their own memory
    big[:, :6000] = rng.normal(size=(3, 6000, 3))
    return {"big_padded_frames": big[:, :6000], "positions": rng.normal(size=(5, 7, 3)).astype(np.float32), "faces": np.arange(12).reshape(4, 3),
            "times": np.linspace(0, 1, 5), "mesh_names": np.array(["body", "hat"]),
            "mesh_offsets": np.array([0, 4]), "empty": np.zeros((0, 3), np.float32),
            "strided": np.arange(20.0)[::2], "many_axes": np.zeros((1,) * 30, np.int8),
            "fortran": np.asfortranarray(rng.normal(size=(4, 6))), "padded_frames": padded[:, :7],
            "flags": rng.normal(size=(3, 4)) > 0, "scalar": np.array(3.5), "complex": np.arange(4) * (1 + 2j)}


def assert_same_archives(ours, ref, names) -> None:
    with np.load(ours) as a, np.load(ref) as b:
        assert a.files == b.files == list(names)
        for name in names:
            assert a[name].dtype == b[name].dtype and a[name].shape == b[name].shape, name
            assert a[name].tobytes() == b[name].tobytes(), name


def test_write_npz_reads_back_as_savez(tmp_path):
    arrays = sample_arrays()
    with open(tmp_path / "ours.npz", "wb") as fh:
        write_npz(fh, arrays)
    np.savez(tmp_path / "numpy.npz", **arrays)
    assert_same_archives(tmp_path / "ours.npz", tmp_path / "numpy.npz", arrays)
    with zipfile.ZipFile(tmp_path / "ours.npz") as z:
        assert all(i.compress_type == zipfile.ZIP_STORED for i in z.infolist())
        assert z.testzip() is None                   # every member's CRC-32 holds


@pytest.mark.parametrize("pieces", ["frames", "batches of 2", "one", "rows", "frames of a padded layout"])
def test_streamed_member_equals_the_whole_array(tmp_path, pieces):
    rng = np.random.default_rng(7)
    whole = rng.normal(size=(5, 7, 3)).astype(np.float32)
    padded = np.zeros((5, 9, 3), np.float32)
    padded[:, :7] = whole
    chunks = {"frames": list(whole), "batches of 2": [whole[:2], whole[2:4], whole[4:]], "one": [whole],
              "rows": list(whole.reshape(-1, 3)), "frames of a padded layout": [padded[:3, :7], padded[3:, :7]]}[pieces]
    consumed = []

    def arriving():
        for c in chunks:
            consumed.append(len(consumed))
            yield c
    with open(tmp_path / "ours.npz", "wb") as fh:
        write_npz(fh, {"positions": Streamed(whole.shape, np.float32, arriving()), "times": np.arange(5.0)})
    np.savez(tmp_path / "numpy.npz", positions=whole, times=np.arange(5.0))
    assert_same_archives(tmp_path / "ours.npz", tmp_path / "numpy.npz", ["positions", "times"])
    assert consumed == list(range(len(chunks)))


@pytest.mark.parametrize("chunks, message", [
    ([np.zeros((2, 3), np.float32)], "6 elements arrived"),
    ([np.zeros((4, 3), np.float32), np.zeros((1, 3), np.float32)], "more than the 12"),
    ([np.zeros((4, 3), np.float64)], "a chunk of float64"),
])
def test_streamed_member_refuses_chunks_that_do_not_make_the_shape(tmp_path, chunks, message):
    with open(tmp_path / "o.npz", "wb") as fh:
        with pytest.raises(InputError, match=message):
            write_npz(fh, {"positions": Streamed((4, 3), np.float32, iter(chunks))})


def test_read_npz_equals_np_load(tmp_path):
    arrays = sample_arrays()
    np.savez(tmp_path / "numpy.npz", **arrays)
    with open(tmp_path / "ours.npz", "wb") as fh:
        write_npz(fh, arrays)
    for path in (tmp_path / "numpy.npz", tmp_path / "ours.npz"):
        got = read_npz(path)
        assert list(got) == list(arrays)
        with np.load(path) as ref:
            for name in arrays:
                a = got[name]
                assert a.dtype == ref[name].dtype and a.shape == ref[name].shape, name
                assert np.array_equal(a, ref[name]) and a.tobytes() == ref[name].tobytes(), name
                assert a.flags.writeable and a.flags.aligned, name


def test_read_npz_reads_compressed_members_through_numpy(tmp_path):
    arrays = {"a": np.arange(100.0).reshape(10, 10), "b": np.array(["x", "yz"])}
    np.savez_compressed(tmp_path / "c.npz", **arrays)
    got = read_npz(tmp_path / "c.npz")
    assert list(got) == ["a", "b"] and all(np.array_equal(got[n], arrays[n]) for n in arrays)


def member_data_offset(path, name: str) -> int:
    """Where member ``name``'s data (its .npy header, then the array) starts in the archive."""
    with zipfile.ZipFile(path) as z:
        info = z.getinfo(name)
    raw = path.read_bytes()
    at = info.header_offset
    return at + 30 + int.from_bytes(raw[at + 26:at + 28], "little") + int.from_bytes(raw[at + 28:at + 30], "little")


@pytest.mark.parametrize("damage", ["flipped byte", "truncated", "not a zip", "object array", "missing"])
def test_read_npz_refuses_damaged_archives(tmp_path, damage):
    path = tmp_path / "d.npz"
    np.savez(path, a=np.arange(1000.0), b=np.arange(5))
    raw = bytearray(path.read_bytes())
    if damage == "flipped byte":
        raw[member_data_offset(path, "a.npy") + 500] ^= 0x10
        path.write_bytes(bytes(raw))
    elif damage == "truncated":
        path.write_bytes(bytes(raw[:len(raw) // 2]))
    elif damage == "not a zip":
        path.write_bytes(b"hello" * 100)
    elif damage == "object array":
        np.savez(path, a=np.array([{"x": 1}], dtype=object))
    else:
        path = tmp_path / "missing.npz"
    with pytest.raises(FileFormatError):
        read_npz(path)
