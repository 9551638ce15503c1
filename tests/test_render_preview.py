"""PNG previews: valid images, shared bounds across panels, handles, bad input, speed."""
from __future__ import annotations


import numpy as np
import pytest

from nrpose.errors import InputError
from nrpose.render.preview import MAX_FACES, _front_faces, render_figure, save_preview

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def sphere(n_lat=12, n_lon=16, radius=1.0, center=(0, 0, 0)):
    """UV sphere with outward-oriented (counter-clockwise seen from outside) triangles."""
    lat = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    ring = np.stack([np.outer(np.sin(lat), np.cos(lon)), np.outer(np.sin(lat), np.sin(lon)),
                     np.repeat(np.cos(lat)[:, None], n_lon, axis=1)], axis=-1).reshape(-1, 3)
    V = np.vstack([[0, 0, 1], ring, [0, 0, -1]]) * radius + np.asarray(center, float)
    idx = 1 + np.arange(len(lat) * n_lon).reshape(len(lat), n_lon)
    nxt = np.roll(idx, -1, axis=1)
    F = [np.stack([np.zeros(n_lon, int), idx[0], nxt[0]], 1)]
    for i in range(len(lat) - 1):
        F.append(np.stack([idx[i], idx[i + 1], nxt[i + 1]], 1))
        F.append(np.stack([idx[i], nxt[i + 1], nxt[i]], 1))
    F.append(np.stack([np.full(n_lon, len(V) - 1), nxt[-1], idx[-1]], 1))
    return V, np.vstack(F)


def read_png(path):
    import matplotlib.image as mpimg
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC
    return mpimg.imread(path)


def test_mesh_and_cloud_panels_with_handles(tmp_path):
    V, F = sphere()
    W = V * [1.0, 1.5, 1.0] + [0.5, 0, 0]
    pts = np.array([[0, -1.2, 0], [0, 1.2, 0]])
    segs = pts[None]
    out = tmp_path / "p.png"
    save_preview(out, [("before", V, F), ("after", W, F), ("points", W, None)],
                 handles=[(pts, segs), (pts * 1.5, segs * 1.5), None], dpi=50)
    img = read_png(out)
    assert img.shape[:2] == (200, 600)                 # 4 in x 50 dpi per panel
    assert img[..., :3].std() > 0.05                   # something was drawn
    red = (img[..., 0] > 0.7) & (img[..., 1] < 0.3) & (img[..., 2] < 0.3)
    assert red[:, :200].sum() > 20 and red[:, 200:400].sum() > 20   # handle segments
    assert red[:, 400:].sum() == 0                      # no handles in the third panel
    assert [p.name for p in tmp_path.iterdir()] == ["p.png"]


def test_panels_share_one_bounding_box_with_equal_scale():
    V, F = sphere()
    far = V * 0.2 + [5, 0, 0]
    fig = render_figure([("a", V, F), ("b", far, None)], handles=[([[0, 3, 0]], None), None])
    axes = fig.axes
    limits = [(ax.get_xlim3d(), ax.get_ylim3d(), ax.get_zlim3d()) for ax in axes]
    assert limits[0] == limits[1]
    (x0, x1), (y0, y1), (z0, z1) = limits[0]
    # data y is up (plot z), data z goes to plot -y; everything (handle point too) is inside
    assert x0 < -1 and x1 > 5.2 and z0 < -1 and z1 > 3 and y0 < -1 and y1 > 1
    aspect = axes[0].get_box_aspect()
    ext = np.array([x1 - x0, y1 - y0, z1 - z0])
    np.testing.assert_allclose(aspect / aspect.max(), ext / ext.max(), rtol=1e-6)


def test_up_axis_is_a_relabelling():
    V = np.array([[0, 0, 0], [1, 2, 3.0]])
    for up, want in [("y", (1, 3, 2)), ("z", (1, 2, 3)), ("x", (2, 3, 1))]:
        ax = render_figure([("t", V, None)], up=up).axes[0]
        ext = np.array([np.ptp(lim) for lim in (ax.get_xlim3d(), ax.get_ylim3d(),
                                                  ax.get_zlim3d())])
        ext -= 2 * 0.04 * 3.0                            # the 4 % margin on each side
        np.testing.assert_allclose(ext, want, rtol=1e-6)


def test_front_faces_for_both_orientations():
    V, F = sphere(24, 32)
    tri = V[F]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    keep = _front_faces(tri, nrm, 15.0, -60.0)
    el, az = np.radians(15.0), np.radians(-60.0)
    eye = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    centres = tri.mean(axis=1)
    assert np.all(centres[keep] @ eye > -0.1)          # the half towards the camera
    assert 0.4 < len(keep) / len(F) < 0.6
    flipped = F[:, ::-1]                               # inward orientation: same faces kept
    tri_f = V[flipped]
    nrm_f = np.cross(tri_f[:, 1] - tri_f[:, 0], tri_f[:, 2] - tri_f[:, 0])
    np.testing.assert_array_equal(_front_faces(tri_f, nrm_f, 15.0, -60.0), keep)


def test_large_inputs_are_drawn(tmp_path):
    """Above MAX_POINTS / MAX_FACES the preview subsamples (timings: ~0.35 s and ~0.8 s measured)."""
    rng = np.random.default_rng(0)
    P = rng.normal(size=(40_000, 3))
    save_preview(tmp_path / "pc.png", [("cloud", P, None)])
    V, F = sphere(160, 240)                            # ~76k faces > MAX_FACES
    assert len(F) > MAX_FACES
    save_preview(tmp_path / "mesh.png", [("mesh", V, F)])
    read_png(tmp_path / "pc.png")
    read_png(tmp_path / "mesh.png")


@pytest.mark.parametrize("panels,handles,match", [
    ([], None, "at least one panel"),
    ([("a", np.zeros((3, 2)), None)], None, r"panel 0 vertices: expected shape \(N, 3\)"),
    ([("a", np.array([[0, 0, np.nan]]), None)], None, "NaN"),
    ([("a", np.eye(3), [[0, 1, 3]])], None, r"outside 0\.\.2"),
    ([("a", np.eye(3), [[0.5, 1.0, 2.0]])], None, "panel 0 faces: 1 of 1 faces hold vertex indices that are not whole"),
    ([("a", np.eye(3))], None, "panel 0 must be"),
    ([("a", np.eye(3), None)], [None, None], "one entry per panel"),
    ([("a", np.eye(3), None)], [(np.eye(3), np.zeros((2, 3)))], r"handles\[0\] segments: expected shape \(N, 2, 3\)"),
    ([("a", np.eye(3), None)], [(np.eye(3),)], r"handles\[0\] must be \(points, segments\)"),
])
def test_bad_input_writes_nothing(tmp_path, panels, handles, match):
    with pytest.raises(InputError, match=match):
        save_preview(tmp_path / "x.png", panels, handles)
    assert list(tmp_path.iterdir()) == []


def test_bad_up_axis(tmp_path):
    with pytest.raises(InputError, match="up must be"):
        save_preview(tmp_path / "x.png", [("a", np.eye(3), None)], up="w")


def spiky_sphere():
    """A sphere with every third vertex moved to the far side: long triangles across the view
    (a mesh with corrupt coordinates), covering it over ten times."""
    V, F = sphere(24, 32)
    V = V.copy()
    V[::3] *= -1.0
    return V, F


def test_a_mesh_covering_the_view_many_times_is_refused_quickly(tmp_path):
    import time

    from nrpose.render.sheet import save_contact_sheet

    V, F = spiky_sphere()
    t0 = time.process_time()
    with pytest.raises(InputError, match=r"cover the view [\d,]+ times over \(at most 8"):
        save_preview(tmp_path / "p.png", [("spiky", V, F)])
    with pytest.raises(InputError, match="times over"):
        save_contact_sheet(tmp_path / "s.png", V[None], F)
    assert time.process_time() - t0 < 5
    assert not list(tmp_path.iterdir())
    # an ordinary closed mesh covers its view about once: drawn
    save_preview(tmp_path / "ok.png", [("sphere", *sphere(24, 32))])
    save_contact_sheet(tmp_path / "ok_sheet.png", sphere(24, 32)[0][None], sphere(24, 32)[1])


def test_cli_picture_of_a_spiky_mesh_is_one_line_and_leaves_nothing(tmp_path, capsys):
    import json

    from nrpose.cli import main
    from nrpose.io.meshes import write_geometry

    V, F = spiky_sphere()
    write_geometry(tmp_path / "m.obj", V, F)
    (tmp_path / "h.json").write_text(json.dumps({"points": [{"rest": [0, 0, 1], "pose": [0, 0.2, 1]},
                                                            {"rest": [0, 0, -1], "pose": [0, 0, -1]}]}))
    out = tmp_path / "out"
    out.mkdir()
    code = main(["deform", str(tmp_path / "m.obj"), "-H", str(tmp_path / "h.json"), "-o", str(out / "o.obj"),
                 "--backend", "numpy", "--png", str(out / "p.png")])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "times over" in err, err
    assert not list(out.iterdir())
