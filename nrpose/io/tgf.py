"""libigl skeletons (TGF), poses (DMAT) and meshes (OBJ/OFF/PLY/STL, Medit .mesh).

TGF: joint lines ``index x y z ...`` up to a ``#`` line, then bone lines
``parent child ...`` (1-based joint indices, extra columns ignored) up to a
second ``#``; anything after it is ignored.

libigl's handles are the *bones* (edges), not the joints: weights, poses and
forward kinematics (``igl::forward_kinematics``) are per bone, each bone
rotating about its first endpoint. So the :class:`~nrpose.model.skeleton.Skeleton`
made from a TGF has **one joint per bone**, named ``bone<e>`` where ``e`` is
the bone's 0-based line order in the file (= DMAT pose and weight column
order). A joint sits at its bone's first endpoint with identity rest rotation,
its parent is the bone ending where it starts, and its tip is the bone's
other endpoint (so ``bones()`` gives back exactly the TGF segments).

DMAT pose (libigl tutorial 403, ``hand-pose.dmat``): a column of 4·B values,
one quaternion per bone in file order, ``(x, y, z, w)`` (``igl::column_to_quats``).
Each is the bone's rotation relative to its parent in rest coordinates
(``vQ[b] = vQ[p] * dQ[b]``), which with identity rest rotations is exactly
this skeleton's local rotation.

DMAT weights (``arm-weights.dmat``, :func:`read_dmat_weights`): a #V × #B
matrix, one row per mesh vertex (file order), one column per bone in TGF
order, as ``igl::lbs_matrix`` takes them. Values must be finite and not
negative (down to -1e-9 is taken as 0), every row needs a positive entry;
rows are normalised to sum to 1.

DMAT animation (libigl tutorial 408_DirectDeltaMush, ``elephant-anim.dmat``,
:func:`read_dmat_animation`): a (#B·4·3) × #frames matrix, one column per
frame. The tutorial maps column ``f`` onto a column-major (4·#B) × 3 matrix
``Tf`` (``Map<MatrixXd>(T.data() + f * T.rows(), 4 * B, 3)``) and poses with
``U = M * Tf``, ``M = igl::lbs_matrix(V, W)``: rows ``4e .. 4e+3`` of ``Tf``
are bone e's affine transform transposed, ``[R | t]ᵀ`` (4 × 3), taking rest
positions to posed positions in world space. Because the data are read
column-major, the same values stored as one column of 12·#B·#frames
numbers are the same animation; the size must be a multiple of 12·#B.
nrpose poses rigid bones: each R must be a rotation (orthonormal to 1e-4,
positive determinant); bone e's joint gets the local transform
``G_parent⁻¹ · T_e · G_rest`` (translation and rotation), so forward kinematics
gives back exactly the file's transforms, and frame f is the time ``f / fps``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..checks import coordinates, triangles
from ..errors import FileFormatError, InputError
from ..model.character import Clip, Track
from ..model.rotation import Rotation, unit_quaternions
from ..model.skeleton import LocalPose, Skeleton, polar_rotation
from ..model.timing import check_frame_count
from ..native import quiet_native
from . import MESH_SUFFIXES
from .files import read_input, read_input_text

__all__ = ["read_tgf", "read_dmat_pose", "read_dmat_weights", "read_dmat_animation", "dmat_is_pose", "bone_joints",
           "read_mesh", "MESH_SUFFIXES"]


def _tgf_sections(path: Path) -> tuple[list[tuple[int, list[str]]], list[tuple[int, list[str]]]]:
    """Joint and bone lines as (line number, fields)."""
    text = read_input_text(path, "TGF file")
    sections: list[list[tuple[int, list[str]]]] = [[]]
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        if fields[0] == "#":
            sections.append([])
            if len(sections) == 3:
                break
            continue
        sections[-1].append((number, fields))
    if len(sections) < 2:
        raise FileFormatError(f"{path}: TGF has no '#' line separating joints from bones")
    return sections[0], sections[1]


def read_tgf(path: str | Path) -> Skeleton:
    """Skeleton with one joint per TGF bone (see the module docstring)."""
    path = Path(path)
    joint_lines, bone_lines = _tgf_sections(path)
    C = np.empty((len(joint_lines), 3))
    for row, (number, fields) in enumerate(joint_lines):
        try:
            C[row] = [float(v) for v in fields[1:4]]
        except ValueError:
            raise FileFormatError(f"{path}:{number}: joint line needs 'index x y z', "
                                  f"got {' '.join(fields)!r}") from None
        if not np.isfinite(C[row]).all():
            raise FileFormatError(f"{path}:{number}: joint coordinates contain NaN or infinity")
    edges = []
    for number, fields in bone_lines:
        try:
            a, b = int(fields[0]), int(fields[1])
        except (ValueError, IndexError):
            raise FileFormatError(f"{path}:{number}: bone line needs 'parent child' joint indices, "
                                  f"got {' '.join(fields)!r}") from None
        if not (1 <= a <= len(C) and 1 <= b <= len(C)) or a == b:
            raise FileFormatError(f"{path}:{number}: bone {a} {b} must join two different joints "
                                  f"among 1..{len(C)}")
        edges.append((a - 1, b - 1))
    if not edges:
        raise FileFormatError(f"{path}: TGF has no bones (point handles are not supported)")
    BE = np.array(edges, dtype=np.int64)
    heads = np.bincount(BE[:, 1], minlength=len(C))
    if (heads > 1).any():
        raise FileFormatError(f"{path}: joint {int(np.argmax(heads)) + 1} ends several bones; "
                              "the bones must form a forest")
    parent_bone = np.full(len(C), -1, np.int64)
    parent_bone[BE[:, 1]] = np.arange(len(BE))
    bone_parent = parent_bone[BE[:, 0]]  # parent bone of each bone, -1 for roots
    order, stack = [], [int(e) for e in np.flatnonzero(bone_parent < 0)[::-1]]
    while stack:
        e = stack.pop()
        order.append(e)
        stack.extend(int(c) for c in np.flatnonzero(bone_parent == e)[::-1])
    if len(order) != len(BE):
        raise FileFormatError(f"{path}: TGF bones contain a cycle")
    order = np.array(order, dtype=np.int64)
    position = np.empty(len(BE), np.int64)
    position[order] = np.arange(len(BE))
    parents = np.where(bone_parent[order] < 0, -1, position[np.maximum(bone_parent[order], 0)])
    start = C[BE[order, 0]]
    translation = start - np.where(parents[:, None] < 0, 0.0, start[np.maximum(parents, 0)])
    J = len(order)
    return Skeleton(names=tuple(f"bone{e}" for e in order), parents=parents, translation=translation,
                    rotation=np.tile([0.0, 0.0, 0.0, 1.0], (J, 1)), scale=np.ones((J, 3)),
                    tips=C[BE[order, 1]] - start)


def _dmat_header(path: Path, line: bytes) -> tuple[int, int]:
    """(columns, rows) of a DMAT header line: two non-negative decimal integers."""
    fields = line.split()
    if len(fields) != 2 or not all(f.isdigit() for f in fields):
        raise FileFormatError(f"{path}: not a DMAT matrix (the header {line[:40]!r} is not "
                              f"'COLUMNS ROWS')")
    return int(fields[0]), int(fields[1])


def _read_dmat(path: Path) -> np.ndarray:
    """A libigl DMAT matrix (rows, cols) float64, ASCII or binary.

    Parsed here rather than by ``igl.readDMAT``, which allocates whatever its header says
    (``2147483648 4`` aborts the process) and prints its errors on stderr: the header's size
    is checked against the values the file holds before anything is allocated. ASCII: a line
    ``COLUMNS ROWS`` then the values column by column; binary: a line ``0 0``, a line
    ``COLUMNS ROWS``, then the float64 values (little-endian) column by column.
    """
    if not path.exists():
        raise FileFormatError(f"{path}: no such DMAT file")
    data = read_input(path, "DMAT file")
    first, _, rest = data.partition(b"\n")
    cols, rows = _dmat_header(path, first)
    if cols == rows == 0:
        second, _, body = rest.partition(b"\n")
        cols, rows = _dmat_header(path, second)
        if len(body) != 8 * rows * cols:
            raise FileFormatError(f"{path}: binary DMAT header says {rows} x {cols} values "
                                  f"({8 * rows * cols} bytes), the file holds {len(body)} bytes")
        values = np.frombuffer(body, "<f8").astype(np.float64)
    else:
        tokens = rest.split()
        if len(tokens) != rows * cols:
            raise FileFormatError(f"{path}: DMAT header says {rows} x {cols} values, the file holds "
                                  f"{len(tokens)}")
        try:
            values = np.array([float(t) for t in tokens], dtype=np.float64)
        except ValueError:
            raise FileFormatError(f"{path}: not a DMAT matrix (a value is not a number)") from None
    return values.reshape(cols, rows).T


def read_dmat_pose(path: str | Path, skeleton: Skeleton) -> LocalPose:
    """Local pose (J, ...) from a libigl per-bone quaternion DMAT for a TGF skeleton.

    Bone e's quaternion drives joint ``bone<e>``; translations and scales stay at rest.
    """
    path = Path(path)
    Q = _read_dmat(path)
    J = skeleton.num_joints
    if Q.size != 4 * J or not (1 in Q.shape or Q.shape == (J, 4)):
        raise FileFormatError(f"{path}: expected {J} quaternions (a column of {4 * J} values), "
                              f"got a {Q.shape} matrix")
    quats = Q.reshape(J, 4)
    if not np.isfinite(quats).all():
        raise FileFormatError(f"{path}: quaternions must be finite")
    quats = unit_quaternions(quats, [f"{path}: quaternion {k}" for k in range(J)], FileFormatError)
    pose = skeleton.rest_pose
    pose.rotation[bone_joints(skeleton, "a DMAT pose")] = quats
    return pose


def dmat_is_pose(path: str | Path, skeleton: Skeleton) -> bool:
    """Whether a DMAT holds one pose (4·#B values: :func:`read_dmat_pose`) rather than an
    animation (a multiple of 12·#B: :func:`read_dmat_animation`); the two never share a size."""
    return _read_dmat(Path(path)).size == 4 * skeleton.num_joints


def bone_joints(skeleton: Skeleton, what: str) -> np.ndarray:
    """Joint index (B,) int64 of each TGF bone in file order (joint ``bone<e>`` for bone e).

    InputError naming ``what`` when the skeleton was not read from a TGF file.
    """
    J = skeleton.num_joints
    index = {n: j for j, n in enumerate(skeleton.names)}
    joints = [index.get(f"bone{e}") for e in range(J)]
    if None in joints:
        raise InputError(f"{what} needs a skeleton read from TGF (joints named bone0, bone1, ...)")
    return np.array(joints, dtype=np.int64)


def read_dmat_weights(path: str | Path, skeleton: Skeleton, n_vertices: int) -> np.ndarray:
    """Skin weights (n_vertices, J) float64 on the skeleton's joints from a libigl weight DMAT.

    The file is #V × #B (module docstring); rows are normalised to sum to 1. FileFormatError
    for a wrong shape, non-finite or negative values, or a row without weight.
    """
    path = Path(path)
    joints = bone_joints(skeleton, "a DMAT weight file")
    B = len(joints)
    W = _read_dmat(path)
    if W.shape != (n_vertices, B):
        hint = " (transposed? rows are vertices, columns bones)" if W.shape == (B, n_vertices) else ""
        raise FileFormatError(f"{path}: expected {n_vertices} rows (one per vertex) × {B} columns (one per TGF "
                              f"bone), got {W.shape[0]} × {W.shape[1] if W.ndim > 1 else 1}{hint}")
    if not np.isfinite(W).all():
        row = int(np.flatnonzero(~np.isfinite(W).all(axis=1))[0])
        raise FileFormatError(f"{path}: weights of vertex {row} contain NaN or infinity")
    if (W < -1e-9).any():
        row, col = np.argwhere(W < -1e-9)[0]
        raise FileFormatError(f"{path}: weight of vertex {row} on bone {col} is negative ({W[row, col]:.3g}); "
                              "skin weights must be >= 0")
    W = np.maximum(W, 0.0)
    sums = W.sum(axis=1)
    if not (sums > 0).all():
        row = int(np.flatnonzero(~(sums > 0))[0])
        raise FileFormatError(f"{path}: vertex {row} has no weight (an all-zero row); every vertex needs "
                              "a positive weight on some bone")
    out = np.zeros((n_vertices, skeleton.num_joints))
    out[:, joints] = W / sums[:, None]
    return out


def read_dmat_animation(path: str | Path, skeleton: Skeleton, fps: float = 30.0, name: str | None = None) -> Clip:
    """A clip (LINEAR translation and rotation tracks on every joint, frame f at ``f / fps``)
    from a libigl animation DMAT of per-bone affine transforms (module docstring).

    FileFormatError when the size is not a multiple of 12·#B, for non-finite values, or when
    a transform is not rigid.
    """
    path = Path(path)
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"fps must be a positive number, got {fps}")
    joints = bone_joints(skeleton, "a DMAT animation")
    B = len(joints)
    T = _read_dmat(path)
    per_frame = 12 * B
    if T.size == 0 or T.size % per_frame:
        raise FileFormatError(f"{path}: {T.size} values do not divide into frames of {B} bones × 12 "
                              f"(a (12·{B}) × frames matrix, one stacked 4×3 transform per bone per frame; "
                              f"a pose of this skeleton is {4 * B} values)")
    F = T.size // per_frame
    check_frame_count(F, str(path))
    if not np.isfinite(T).all():
        raise FileFormatError(f"{path}: the transforms contain NaN or infinity")
    # column-major frames of (4B, 3); bone e's rows 4e..4e+3 are [R | t] transposed
    Tf = T.ravel(order="F").reshape(F, 3, 4 * B).transpose(0, 2, 1).reshape(F, B, 4, 3)
    A = np.zeros((F, B, 4, 4))
    A[..., :3, :] = np.swapaxes(Tf, -1, -2)
    A[..., 3, 3] = 1.0
    R = A[..., :3, :3]
    gram = np.swapaxes(R, -1, -2) @ R - np.eye(3)
    bad = (np.abs(gram).max(axis=(-1, -2)) > 1e-4) | (np.linalg.det(R) <= 0)
    if bad.any():
        f, e = np.argwhere(bad)[0]
        raise FileFormatError(f"{path}: frame {f}, bone {e}: the 3×3 part is not a rotation (scale, shear or "
                              "reflection); nrpose poses rigid bones")
    A[..., :3, :3] = polar_rotation(R)
    G = np.empty((F, skeleton.num_joints, 4, 4))
    G[:, joints] = A @ skeleton.rest_globals()[joints]
    parents = skeleton.parents
    local = G.copy()
    child = np.flatnonzero(parents >= 0)
    local[:, child] = np.linalg.inv(G[:, parents[child]]) @ G[:, child]
    local = np.linalg.inv(skeleton.pre)[None] @ local
    times = np.arange(F) / fps
    rotation = Rotation.from_matrix(polar_rotation(local[..., :3, :3]).reshape(-1, 3, 3)).as_quat()
    rotation = rotation.reshape(F, -1, 4)
    tracks = []
    for j in range(skeleton.num_joints):
        tracks.append(Track(j, "translation", times, local[:, j, :3, 3]))
        tracks.append(Track(j, "rotation", times, rotation[:, j]))
    return Clip(name or path.stem, float(times[-1]), skeleton.rest_pose, tuple(tracks))


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Triangle mesh: vertices (N, 3) float64 and faces (M, 3) int64.

    OBJ/OFF/PLY/STL through :func:`nrpose.io.meshes.read_geometry` (order-preserving;
    ``igl.read_triangle_mesh`` can abort the interpreter on some PLYs). A tetrahedral Medit
    ``.mesh`` gives its boundary triangles (``igl.boundary_facets``, oriented
    like the tets) and only the vertices they use, in file order; other
    formats keep every vertex (so per-vertex data such as DMAT weights align).
    """
    import igl

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise FileFormatError(f"{path}: unknown mesh extension {suffix!r}; use one of {', '.join(MESH_SUFFIXES)}")
    if not path.is_file():
        raise FileFormatError(f"{path}: no such mesh file")
    try:
        if suffix == ".mesh":
            with quiet_native():
                V, T, F = igl.readMESH(str(path))
                if len(T):
                    F = igl.boundary_facets(np.ascontiguousarray(T, dtype=np.int64))[0]
        else:
            from .meshes import read_geometry
            V, F = read_geometry(path)
    except RuntimeError as exc:
        raise FileFormatError(f"{path}: cannot read mesh ({exc})") from None
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0 or F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise FileFormatError(f"{path}: no triangles read (vertices {V.shape}, faces {F.shape})")
    V = coordinates(V, f"{path}: vertices", error=FileFormatError, fix="fix or remove them")
    F = triangles(F, len(V), f"{path}: faces", FileFormatError, "the file is inconsistent, re-export it")
    used = np.unique(F)
    if suffix == ".mesh" and len(used) < len(V):
        remap = np.full(len(V), -1, np.int64)
        remap[used] = np.arange(len(used))
        V, F = V[used], remap[F]
    return V, F
