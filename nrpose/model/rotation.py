"""Rotation algebra and the project's conventions, stated once.

Conventions (followed everywhere in nrpose):

* Points are rows: an array of N points has shape ``(N, 3)``.
* Rotation matrices act on column vectors: ``x' = R @ x``; for an ``(N, 3)``
  array that is ``X @ R.T``. (The seed paper writes row vectors, ``x R``.)
* Quaternions are ``(x, y, z, w)``, scalar last, as in glTF and scipy.
* Rotation vectors are axis × angle in radians.
* Host arithmetic is float64; device arithmetic is float32.
* No axis conversion is ever applied: coordinates stay in the input's frame
  (glTF is Y-up, metres; BVH and OBJ as authored).

Batched conversions on the posing path (quaternion -> matrix, slerp) are plain numpy
here; other rotation algebra goes through :class:`scipy.spatial.transform.Rotation`,
reached as :data:`Rotation`, which imports scipy.spatial (~0.3 s) on first use only.
"""
from __future__ import annotations

import numpy as np

from ..errors import InputError

__all__ = ["Rotation", "quat_matrices", "matrix_quats", "quat_slerp", "unit_quaternions", "minimal_rotvec", "minimal_quat", "quat_multiply", "kabsch", "covariance_rotation",
           "relative_rotvec_table"]


class LazyRotation:
    """Stands for :class:`scipy.spatial.transform.Rotation`: attribute access (``Rotation.from_quat``)
    imports scipy.spatial then, so that a module using it only off the posing path does not
    import it at start."""

    def __getattr__(self, name):
        from scipy.spatial.transform import Rotation as scipy_rotation
        return getattr(scipy_rotation, name)


Rotation = LazyRotation()


def quat_matrices(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) float64 of quaternions q (n, 4) (x, y, z, w), normalised first
    (scipy's ``Rotation.from_quat(q).as_matrix()`` to round-off)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    xx, yy, zz, ww = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = xx - yy - zz + ww
    out[..., 1, 0] = 2 * (xy + zw)
    out[..., 2, 0] = 2 * (xz - yw)
    out[..., 0, 1] = 2 * (xy - zw)
    out[..., 1, 1] = -xx + yy - zz + ww
    out[..., 2, 1] = 2 * (yz + xw)
    out[..., 0, 2] = 2 * (xz + yw)
    out[..., 1, 2] = 2 * (yz - xw)
    out[..., 2, 2] = -xx - yy + zz + ww
    return out


def matrix_quats(m: np.ndarray) -> np.ndarray:
    """Quaternions (n, 4) (x, y, z, w), unit, of rotation matrices m (n, 3, 3) taken as exact
    rotations (scipy's ``Rotation.from_matrix(m, assume_valid=True).as_quat()``: the same
    branch on the largest of the diagonal and the trace, so the same sign)."""
    m = np.asarray(m, dtype=np.float64)
    n = len(m)
    diag = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    trace = diag.sum(axis=1)
    choice = np.argmax(np.concatenate([diag, trace[:, None]], axis=1), axis=1)
    q = np.empty((n, 4))
    rows = np.arange(n)
    for i in range(3):
        sel = rows[choice == i]
        j, k = (i + 1) % 3, (i + 2) % 3
        q[sel, i] = 1.0 - trace[sel] + 2.0 * m[sel, i, i]
        q[sel, j] = m[sel, j, i] + m[sel, i, j]
        q[sel, k] = m[sel, k, i] + m[sel, i, k]
        q[sel, 3] = m[sel, k, j] - m[sel, j, k]
    sel = rows[choice == 3]
    q[sel, 0] = m[sel, 2, 1] - m[sel, 1, 2]
    q[sel, 1] = m[sel, 0, 2] - m[sel, 2, 0]
    q[sel, 2] = m[sel, 1, 0] - m[sel, 0, 1]
    q[sel, 3] = 1.0 + trace[sel]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quat_slerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Spherical interpolation (n, 4) from unit quaternions q0 to q1 (n, 4) (x, y, z, w) at
    fractions s (n, 1), along the shorter arc; as scipy's ``r0 * Rotation.from_rotvec(s *
    (r0.inv() * r1).as_rotvec())`` (the same quaternion sign)."""
    q0, q1 = np.asarray(q0, dtype=np.float64), np.asarray(q1, dtype=np.float64)
    q0 = q0 / np.linalg.norm(q0, axis=1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=1, keepdims=True)
    d = quat_multiply(q0 * [-1.0, -1.0, -1.0, 1.0], q1)          # r0^-1 r1
    d = np.where(d[:, 3:] < 0, -d, d)                             # shorter arc
    v = d[:, :3]
    sv = np.linalg.norm(v, axis=1, keepdims=True)
    half = np.arctan2(sv, d[:, 3:]) * s                           # half angle of the step
    small = sv < 1e-12
    axis = np.where(small, 0.0, v / np.where(small, 1.0, sv))
    step = np.concatenate([np.where(small, v * s, axis * np.sin(half)), np.cos(half)], axis=1)
    return quat_multiply(q0, step)


def unit_quaternions(q: np.ndarray, labels, error: type[InputError] = InputError) -> np.ndarray:
    """Finite quaternions q (n, 4) scaled to unit length, float64 (n, 4), a new array.

    Each row is divided by its largest |entry| before its norm is taken, so that entries
    near the float64 limit (1e308) do not overflow. labels: n names for the message
    (``labels[i]`` is a zero quaternion) raised as ``error`` where a norm is under 1e-12.
    """
    q = np.asarray(q, dtype=np.float64)
    big = np.abs(q).max(axis=1, initial=0.0)
    scaled = q / np.where(big > 0, big, 1.0)[:, None]
    n = np.linalg.norm(scaled, axis=1)                    # in [1, 2] unless the row is zero
    zero = big * n < 1e-12
    if zero.any():
        raise error(f"{labels[int(np.argmax(zero))]} is a zero quaternion; give a unit (or non-zero) quaternion")
    return scaled / n[:, None]


def minimal_rotvec(a: np.ndarray, b: np.ndarray, opposite: str = "zero") -> np.ndarray:
    """Rotation vectors of the smallest rotations taking direction ``a`` to ``b``.

    a, b: (..., 3) float64, any non-zero length. Returns (..., 3) float64 with
    angle ``atan2(|a×b|, a·b)`` about ``a×b``. Zero vectors give a zero rotation.
    Exactly opposite directions (angle π, axis undefined) give a zero rotation
    vector with ``opposite="zero"`` (the blend's convention, matched by the
    kernels), or a half turn about an axis perpendicular to ``a`` with
    ``opposite="half_turn"``.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    cross = np.cross(a, b)
    s = np.linalg.norm(cross, axis=-1)
    c = np.sum(a * b, axis=-1)
    angle = np.arctan2(s, c)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(s > 0, angle / np.where(s > 0, s, 1.0), 0.0)
    out = cross * scale[..., None]
    if opposite == "half_turn":
        flip = (s <= 1e-12 * np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1)) & (c < 0)
        if np.any(flip):
            helper = np.where(np.abs(a[..., :1]) < 0.9 * np.linalg.norm(a, axis=-1, keepdims=True),
                              np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
            perp = np.cross(a, helper)
            perp = np.pi * perp / np.linalg.norm(perp, axis=-1, keepdims=True)
            out = np.where(flip[..., None], perp, out)
    return out


def minimal_quat(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4), (x, y, z, w) with w >= 0, of the smallest rotations
    taking direction ``a`` to ``b`` (..., 3): ``(a×b, |a||b| + a·b)`` normalised, the
    half-angle form of :func:`minimal_rotvec`. Zero vectors and exactly opposite
    directions give the identity (as ``minimal_rotvec(opposite="zero")``)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    w = np.sqrt(np.sum(a * a, axis=-1) * np.sum(b * b, axis=-1)) + np.sum(a * b, axis=-1)
    q = np.concatenate([np.cross(a, b), w[..., None]], axis=-1)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    identity = np.broadcast_to(np.array([0.0, 0.0, 0.0, 1.0]), q.shape)
    return np.where(n > 0, q / np.where(n > 0, n, 1.0), identity)


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton products p ⊗ q of (..., 4) quaternions (x, y, z, w), broadcasting."""
    p = np.asarray(p, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    pv, pw, qv, qw = p[..., :3], p[..., 3:], q[..., :3], q[..., 3:]
    return np.concatenate([pw * qv + qw * pv + np.cross(pv, qv), pw * qw - np.sum(pv * qv, -1, keepdims=True)],
                          axis=-1)


def kabsch(P: np.ndarray, Q: np.ndarray, centre: bool = True) -> np.ndarray:
    """Best rotation R (3,3) with ``R @ (p - p̄) ≈ (q - q̄)`` for the rows of P, Q (M,3)
    (``centre=False``: ``R @ p ≈ q``, e.g. for directions).

    Unweighted least squares (Kabsch), solved by :func:`covariance_rotation`.
    Where the fit is not unique (a single point, collinear points: the
    covariance is rank-deficient) it takes, among the optimal rotations (to
    1e-9 relative), the one closest to the identity (for collinear points, the
    minimal rotation between the two lines). The result is equivariant
    (R -> G R when Q -> G Q) whenever the fit is unique.
    """
    P = np.asarray(P, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    Pc = P - P.mean(axis=0) if centre else P
    Qc = Q - Q.mean(axis=0) if centre else Q
    return covariance_rotation(Qc.T @ Pc, np.abs(Pc).max() ** 2)


def covariance_rotation(C: np.ndarray, p_scale2: float) -> np.ndarray:
    """The rotation R (3, 3) maximising trace(Rᵀ C) for a covariance C = Σ q pᵀ
    (3, 3) of point pairs with R p ≈ q: the Kabsch step of :func:`kabsch`, for
    callers that keep the centred p side. p_scale2: max |p|² component of the
    (centred) p; with max |C| it sets the scale of the tie tolerance.

    Solved as Horn's quaternion eigenproblem: trace(R(q)ᵀ C) = qᵀ N q for unit
    q = (w, x, y, z) and a symmetric 4×4 N built from C, so the best proper
    rotations are the top eigenvectors of N (no reflection case to repair, unlike
    an SVD of C). Ties: eigenvalues within 1e-9 of the scale of the top one
    count as optimal (collinear pairs leave a circle of optimal rotations, one
    pair a sphere), and the one nearest the identity is taken: the identity
    quaternion projected onto their eigenspace (when all of them are half turns,
    the one whose axis is nearest x, else y, else z). That is exact, where a
    regularised SVD (C + εI) resolves it only to ~1e-5, and one 4×4 ``eigh`` costs
    less than an SVD and two determinants.
    kernels/global_fit.h is its device twin for the OpenCL deformer's R_g.
    """
    if not np.isfinite(C).all():
        return np.full((3, 3), np.nan)    # eigh cannot take it; the caller's non-finite check names it
    scale = max(np.abs(C).max(), p_scale2, 1e-300)
    (xx, xy, xz), (yx, yy, yz), (zx, zy, zz) = C.tolist()
    N = np.array([[xx + yy + zz, zy - yz, xz - zx, yx - xy],
                  [zy - yz, xx - yy - zz, yx + xy, xz + zx],
                  [xz - zx, yx + xy, yy - xx - zz, zy + yz],
                  [yx - xy, xz + zx, zy + yz, zz - xx - yy]])
    vals, vecs = np.linalg.eigh(N)                    # ascending
    best = vecs[:, vals >= vals[3] - 1e-9 * scale]
    q = best @ best[0]                                 # identity quaternion (1, 0, 0, 0) projected
    norm = float(np.linalg.norm(q))
    if norm <= 1e-6:
        # every optimal rotation a half turn (w = 0: e.g. collinear pairs reversed): the
        # one whose axis is nearest x (the half turn about x, (0, 1, 0, 0), projected), or
        # where that projection is shorter than 1/2 (every optimal axis more than 60° from
        # x) y, else z; the longest of the three is at least 1/sqrt(3). A rule rather than
        # eigh's arbitrary pick, so that the device's fit (kernels/global_fit.h) agrees.
        for axis in (1, 2, 3):
            q = best @ best[axis]
            norm = float(np.linalg.norm(q))
            if norm >= 0.5:
                break
    w, x, y, z = (q / norm).tolist()
    # the matrix of (w, x, y, z) written out: scipy's from_quat(...).as_matrix() gives the
    # same to 1e-16 but costs ~27 µs against ~3.5 µs
    return np.array([[w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z]])


def relative_rotvec_table(quats: np.ndarray) -> np.ndarray:
    """Table T[j, i] = log(R_j⁻¹ R_i) as rotation vectors, shape (M, M, 3) float64.

    quats: (M, 4) unit quaternions (x, y, z, w). Plain numpy quaternion
    algebra (this runs once per pose for every pair: scipy's per-object
    overhead would dominate). Angles are taken in [0, π]; the table is made
    exactly antisymmetric (T[i, j] = -T[j, i]) so that at an angle of exactly
    π, where the log is ambiguous, the blends seen from either handle agree.
    """
    q = np.asarray(quats, dtype=np.float64)
    m = len(q)
    jj, ii = np.triu_indices(m, k=1)
    T = np.zeros((m, m, 3))
    if len(jj):
        a, b = q[jj], q[ii]                       # conj(a) ⊗ b
        w = np.sum(a * b, axis=1)
        v = a[:, 3:] * b[:, :3] - b[:, 3:] * a[:, :3] - np.cross(a[:, :3], b[:, :3])
        sign = np.where(w < 0, -1.0, 1.0)         # shortest rotation
        w, v = w * sign, v * sign[:, None]
        s = np.linalg.norm(v, axis=1)
        angle = 2.0 * np.arctan2(s, w)
        scale = np.where(s > 1e-12, angle / np.where(s > 1e-12, s, 1.0), 2.0 / np.maximum(w, 1e-300))
        upper = v * scale[:, None]
        T[jj, ii] = upper
        T[ii, jj] = -upper
    return T
