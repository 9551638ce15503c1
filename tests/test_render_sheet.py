"""Contact sheets (PNG grids of animation frames)."""
import struct

import numpy as np
import pytest

from nrpose.errors import InputError
from nrpose.render.sheet import save_contact_sheet, view_matrix


def png_size(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


@pytest.fixture(scope="module")
def walk():
    from nrpose.rigs.humanoid import humanoid

    c = humanoid()
    m = c.meshes[0]
    clip = c.clip("walk")
    t = np.linspace(0.0, clip.duration, 20)
    G = c.skeleton.forward_kinematics(clip.sample(t))
    K = c.skin_matrices(G)
    M = np.einsum("nk,fnkab->fnab", m.weights, K[:, m.joints])
    P = np.einsum("fnab,nb->fna", M, np.c_[m.vertices, np.ones(len(m.vertices))])[..., :3]
    segs, _ = c.skeleton.bones().pose(G)
    return P, m.faces, t, list(segs)


def test_mesh_sheet(tmp_path, walk):
    P, F, t, segs = walk
    out = tmp_path / "sheet.png"
    frames = save_contact_sheet(out, P, F, t, "walk", 12, segs)
    assert frames[0] == 0 and frames[-1] == len(P) - 1 and len(frames) == 12
    assert frames == sorted(set(frames))
    w, h = png_size(out)
    assert w > 600 and h > 300
    assert [p.name for p in tmp_path.iterdir()] == ["sheet.png"]


def test_points_and_few_frames(tmp_path):
    rng = np.random.default_rng(0)
    P = rng.normal(size=(3, 200, 3))
    out = tmp_path / "points.png"
    assert save_contact_sheet(out, P, None, [0.0, 0.1, 0.2], "points") == [0, 1, 2]
    png_size(out)
    out2 = tmp_path / "numbers.png"
    assert save_contact_sheet(out2, P[:1], None, None, "", up="z") == [0]
    png_size(out2)


def test_view_matrix_is_a_rotation():
    for up in "xyz":
        M = view_matrix(up, 20.0, -35.0)
        assert np.allclose(M @ M.T, np.eye(3)) and np.isclose(np.linalg.det(M), 1.0)
    # default camera: the data's up axis (y) points up on screen
    assert view_matrix("y", 0.0, -60.0)[1] @ [0, 1, 0] == pytest.approx(1.0)


@pytest.mark.parametrize("kwargs, message", [
    (dict(positions=np.zeros((2, 4))), "positions"),
    (dict(positions=np.full((2, 4, 3), np.nan)), "NaN"),
    (dict(faces=np.array([[0, 1, 9]])), "faces"),
    (dict(faces=np.array([[0.5, 1.0, 2.0]])), "faces: 1 of 1 faces hold vertex indices that are not whole"),
    (dict(times=[0.0]), "times"),
    (dict(handles_per_frame=[None]), "handles_per_frame"),
    (dict(handles_per_frame=[np.zeros((1, 3, 3)), None]), r"handles_per_frame\[0\] segments: expected shape \(N, 2, 3\)"),
    (dict(max_panels=0), "max_panels"),
])
def test_bad_input(tmp_path, kwargs, message):
    args = dict(positions=np.zeros((2, 4, 3)) + np.arange(4)[:, None], faces=np.array([[0, 1, 2]]),
                times=[0.0, 1.0], title="x")
    args.update(kwargs)
    out = tmp_path / "bad.png"
    with pytest.raises(InputError, match=message):
        save_contact_sheet(out, **args)
    assert not list(tmp_path.iterdir())


def test_rasterize_square():
    from nrpose.render.sheet import rasterize

    # a closed, outward tetrahedron-like "pillow": two triangles facing the viewer, two away
    V = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, -0.5]])
    front = [[0, 1, 2], [0, 2, 3]]
    back = [[0, 4, 1], [1, 4, 2], [2, 4, 3], [3, 4, 0]]
    img, drawn = rasterize(V, np.array(front + back), np.array([0.0, 0.0, 1.0]), (-1, 2, -1, 2), (30, 30))
    assert img.shape == (30, 30, 4)
    covered = img[..., 3] > 0
    assert covered.sum() == 100                     # the unit square: 10 x 10 pixels of 0.1
    assert np.allclose(img[covered, :3], img[covered, :3][0])   # flat, facing the light
    assert drawn == 2                               # the pyramid's faces point away
