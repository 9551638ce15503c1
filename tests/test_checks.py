"""nrpose.checks: the one validator of user arrays (vertices, handles, triangles)."""
import numpy as np
import pytest

from nrpose.checks import real_rows, triangles, within_float32
from nrpose.errors import HandleError, InputError


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int32, np.int64, np.uint16])
def test_real_rows_accepts_real_dtypes_as_float64(dtype):
    rng = np.random.default_rng(7)
    a = (rng.random((11, 3)) * 100).astype(dtype)
    got = real_rows(a, "points")
    assert got.dtype == np.float64 and got.shape == (11, 3)
    np.testing.assert_array_equal(got, a.astype(np.float64))


def test_real_rows_keeps_float64_without_copy_and_reads_lists():
    a = np.zeros((4, 2, 3))
    assert real_rows(a, "segments", (2, 3)) is a
    assert real_rows([[1, 2, 3]], "points").tolist() == [[1.0, 2.0, 3.0]]
    assert real_rows(np.array([[1, 2, 3]], dtype=object), "points").dtype == np.float64


@pytest.mark.parametrize("value, match", [
    (np.zeros((3, 2)), r"points: expected shape \(N, 3\), got \(3, 2\)"),
    (np.zeros(3), r"points: expected shape \(N, 3\), got \(3,\)"),
    (np.zeros((2, 3, 1)), r"expected shape \(N, 3\), got \(2, 3, 1\)"),
    (np.zeros((0, 3)), r"points: empty; expected shape \(N, 3\) with N >= 1"),
    (np.ones((2, 3), dtype=bool), "expected real numbers of shape .* got dtype bool"),
    (np.ones((2, 3), dtype=complex), "got dtype complex128"),
    (np.array([["a", "b", "c"]]), "got dtype <U1"),
    ([[1, 2, 3], [4, 5]], "points: expected real numbers of shape \\(N, 3\\); got list"),
    (np.array([[1, 2, "x"]], dtype=object), "expected real numbers"),
])
def test_real_rows_names_the_problem(value, match):
    with pytest.raises(InputError, match=match):
        real_rows(value, "points")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_real_rows_reports_non_finite_rows(bad):
    rng = np.random.default_rng(3)
    a = rng.random((50, 3))
    rows = np.sort(rng.choice(50, size=4, replace=False))
    a[rows, rng.integers(0, 3, size=4)] = bad
    with pytest.raises(InputError, match=rf"v: 4 of 50 rows have NaN or infinite values \(first: row {rows[0]}\)"):
        real_rows(a, "v")
    seg = np.zeros((3, 2, 3))
    seg[2, 1, 0] = bad               # one bad entry deep inside a row counts its row once
    with pytest.raises(InputError, match=r"1 of 3 rows .* \(first: row 2\)"):
        real_rows(seg, "s", (2, 3))


def test_real_rows_error_class_and_empty():
    with pytest.raises(HandleError):
        real_rows(np.zeros((2, 2)), "handles", error=HandleError)
    for empty in ((), [], np.zeros((0, 3)), np.zeros(0)):
        got = real_rows(empty, "handles", (2, 3), HandleError, allow_empty=True)
        assert got.shape == (0, 2, 3) and got.dtype == np.float64
    with pytest.raises(HandleError, match=r"expected shape \(N, 2, 3\), got \(1, 3\)"):
        real_rows([[0, 0, 0]], "handles", (2, 3), HandleError, allow_empty=True)   # not empty: checked
    with pytest.raises(HandleError, match="1 of 1 rows have NaN or infinite values .*; repair them"):
        real_rows([[0, 0, np.nan]], "handles", error=HandleError, fix="repair them")


@pytest.mark.parametrize("dtype", [np.int32, np.int64, np.uint32, np.float64, object])
def test_triangles_accepts_integer_indices(dtype):
    F = np.array([[0, 1, 2], [2, 1, 3]], dtype=dtype)      # whole-number floats too
    got = triangles(F, 4)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, F)


@pytest.mark.parametrize("faces, match", [
    (np.zeros((2, 4), int), r"faces: expected triangles of shape \(F, 3\) with F >= 1, got \(2, 4\)"),
    (np.zeros((0, 3), int), r"got \(0, 3\)"),
    (np.zeros(3, int), r"got \(3,\)"),
    (np.array([[0.0, 1.0, 2.0], [0.0, 1.5, 2.0], [np.nan, 1, 2]]),
     r"faces: 2 of 3 faces hold vertex indices that are not whole numbers \(first: face 1 = \[0\.0, 1\.5, 2\.0\]\)"),
    (np.ones((1, 3), dtype=bool), "faces: expected integer vertex indices, got dtype bool"),
    ([[0, 1, 2], [1, 2]], r"faces: expected triangles of shape \(F, 3\); got list that is not a numeric array"),
    (np.array([[0, 1, 2], [1, 2, 4], [4, 5, 0]]), r"faces: 2 of 3 faces index vertices outside 0\.\.3 "
                                                  r"\(first: face 1 = \[1, 2, 4\]\); drop those faces"),
    (np.array([[0, 1, 2], [-1, 2, 3]]), r"1 of 2 faces index vertices outside 0\.\.3 \(first: face 1 = \[-1, 2, 3\]\)"),
    (np.array([[0, 1, 2**63 + 5]], np.uint64), r"outside 0\.\.3 \(first: face 0 = \[0, 1, 9223372036854775813\]\)"),
])
def test_triangles_names_the_problem(faces, match):
    with pytest.raises(InputError, match=match):
        triangles(faces, 4)


def test_triangles_error_class_and_fix():
    from nrpose.errors import FileFormatError
    with pytest.raises(FileFormatError, match=r"m\.obj: faces: .*; re-export it"):
        triangles([[0, 1, 7]], 4, "m.obj: faces", FileFormatError, "re-export it")


def test_within_float32_refuses_what_a_float32_file_would_hold_as_infinity():
    within_float32(np.array([[3.4e38, -3.4e38, 0.0]]), "v")
    within_float32(np.zeros((0, 3)), "v")
    with pytest.raises(InputError, match=r"v: a value of magnitude 1e\+39 does not fit the file's float32"):
        within_float32(np.array([[0.0, -1e39, 0.0]]), "v")
