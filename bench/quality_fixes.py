"""Figures of the three NR-MLS weaknesses and their fixes (float64 references; the device
runs the same blend, tests/test_quality_fixes.py).

    python bench/quality_fixes.py [--json OUT.json] [--png-dir DIR] [--quick]

1. Rigid parts: the cylinder with a rigid joint sleeve (rigs/sleeve.py), weight splits
   0.4/0.6, 0.5/0.5, 0.9/0.1, bends 90°/135°: largest in-sleeve edge strain, body strain
   p99.9 and volume, for the default blend with the closest-point parameters (``as is``)
   and with the segment parameters taken at the weight group's centroid (``group-t``, what
   nrpose.bind.bone_weights gives authored weights).
2. Continuity: the Y-junction probe line (spacing 1e-4) and mesh, both spread families,
   spreads 30°–179°: largest continuity ratio of the default (tree-signed quaternion),
   relative and paper blends, and the default's derived bound (nrpose/pose/blend.py).
3. Leakage: palm-and-two-fingers shapes (rigs/fingers.py; finger length 1, radii 0.06/0.09/0.15,
   gaps 0.05–0.3, two marching-cubes resolutions), finger A bent 45°, α = 1: finger B's tip
   motion over the Euclidean-weight one, with heat distances, heat + arrival parameters
   (nrpose.bind.distances.arrival_parameters), and the vertices as a point cloud: kNN
   distances, kNN + arrival parameters.
Not a test: no assertions.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

from quality_adapter import HandleSet, Pose, Rotation, blend, cylinder, distance_matrix  # noqa: E402
from quality_adapter import arrival_parameters, deformation_metrics as dm, group_centers, segment_parameters  # noqa: E402
from quality_adapter import continuity_bound, fingers_shape, sleeve, yjunction  # noqa: E402

SPREADS = (30, 60, 90, 120, 150, 170, 179)


def rigid_parts() -> list:
    rows = []
    rest = cylinder.rest_handles()
    for split in ((0.4, 0.6), (0.5, 0.5), (0.9, 0.1)):
        V, F, W, nb = sleeve.sleeve_rig(split)
        E = dm.mesh_edges(F, len(V))
        body_E = E[(E < nb).all(axis=1)]
        body_F = F[(F < nb).all(axis=1)]
        cap = np.where(np.arange(len(V)) >= nb, 0, -1)
        t = segment_parameters(group_centers(V, dm.weight_groups(W)), rest.segments)
        terms = {"as is": blend.rest_terms(V, rest, weights=W), "group-t": blend.rest_terms(V, rest, weights=W, t=t)}
        for deg in (90, 135):
            pose = cylinder.bend_pose(deg)
            for name, T in terms.items():
                P = blend.pose_reference(T, rest, pose)
                rows.append({"split": list(split), "bend": deg, "variant": name,
                             "sleeve_strain_max": float(dm.group_rigidity(V, P, E, cap)),
                             "body_p99.9": float(np.percentile(dm.edge_strain(V[:nb], P[:nb], body_E), 99.9)),
                             "body_volume": float(dm.signed_volume(P[:nb], body_F) / dm.signed_volume(V[:nb], body_F))})
    return rows


def continuity(spreads) -> list:
    rows = []
    rest = yjunction.rest_handles()
    line = yjunction.probe_line()
    YV, YF = yjunction.yjunction_mesh()
    sets = {"probe": (line, np.stack([np.arange(len(line) - 1), np.arange(1, len(line))], 1)),
            "mesh": (YV, dm.measurable_edges(YV, dm.mesh_edges(YF, len(YV))))}
    for family, make in (("spread", yjunction.spread_pose), ("opposed", yjunction.opposed_pose)):
        for s in spreads:
            pose = make(s)
            for where, (pts, pairs) in sets.items():
                T = blend.rest_terms(pts, rest)
                outs = {b: blend.pose_reference(T, rest, pose, b) for b in blend.BLENDS}
                bound, a = continuity_bound(pts, rest, pose, pairs)
                row = {"family": family, "spread": s, "where": where, "bound": float(bound.max()),
                       "a_min": float(a.min())}
                row.update({b: float(dm.continuity_ratio(pts, o, pairs).max()) for b, o in outs.items()})
                rows.append(row)
    return rows


def fingers_pose(s):
    a = s.bone_names.index("finger_a")
    rest = HandleSet.make(segments=s.bones)
    R = Rotation.from_euler("z", 45, degrees=True).as_matrix()
    segs = s.bones.copy()
    segs[a] = (segs[a] - segs[a, 0]) @ R.T + segs[a, 0]
    rots = np.stack([np.eye(3)] * len(s.bones))
    rots[a] = R
    return rest, Pose.make(rest, segments=segs, rotations=rots)


def leakage(radii, gaps, resolutions) -> list:
    rows = []
    for r in radii:
        for g in gaps:
            for k, res in enumerate(resolutions(r, g)):
                s = fingers_shape(resolution=res, finger_radius=r, finger_spacing=g + 2 * r, finger_length=1.0)
                V, F = s.vertices, s.faces
                tip_b = (V[:, 1] > s.finger_length - 2 * r) & (V[:, 0] > 0.5 * s.finger_gap)
                rest, pose = fingers_pose(s)
                E = dm.measurable_edges(V, dm.mesh_edges(F, len(V)))

                def measure(T):
                    P = blend.pose_reference(T, rest, pose)
                    return (float(np.linalg.norm(P - V, axis=1)[tip_b].max()),
                            float(np.percentile(dm.edge_strain(V, P, E), 99.9)), float(dm.continuity_ratio(V, P, E).max()))

                euclid = measure(blend.rest_terms(V, rest))[0]
                D = distance_matrix(V, F, None, s.bones, method="heat")
                Dk = distance_matrix(V, None, None, s.bones, method="knn")
                variants = {
                    "heat": blend.rest_terms(V, rest, distances=D),
                    "heat+arrival": blend.rest_terms(V, rest, distances=D, t=arrival_parameters(V, F, s.bones)),
                    "knn (cloud)": blend.rest_terms(V, rest, distances=Dk),
                    "knn+arrival (cloud)": blend.rest_terms(V, rest, distances=Dk, t=arrival_parameters(V, None, s.bones))}
                row = {"radius": r, "gap": g, "grid": ("coarse", "fine")[k], "resolution": round(res, 4), "vertices": len(V), "euclid_tip": euclid}
                for name, TT in variants.items():
                    tip, p999, cont = measure(TT)
                    row[name] = {"leak": tip / euclid, "p99.9": p999, "continuity": cont}
                rows.append(row)
                print(f"  r {r} gap {g} res {res:.3f}: " + " ".join(f"{n} {row[n]['leak']:.3f}" for n in variants), flush=True)
    return rows


def figures(doc: dict, png_dir: pathlib.Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    for ax, family in zip(axes, ("spread", "opposed")):
        rows = [r for r in doc["continuity"] if r["family"] == family and r["where"] == "probe"]
        x = [r["spread"] for r in rows]
        for b, style in (("relative", "o-"), ("paper", "^-"), ("quaternion", "D-"), ("bound", "k--")):
            ax.semilogy(x, [r[b] for r in rows], style,
                        label={"bound": "quaternion: derived bound", "quaternion": "quaternion (default)"}.get(b, b))
        ax.set_xlabel("rotation spread (°)")
        ax.set_ylabel("max |Δ displacement| / rest spacing (probe, 1e-4)")
        ax.set_title(f"Y-junction, {family} axes")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png_dir / "fix_continuity.png", dpi=70)
    plt.close(fig)

    rows = doc["leakage"]
    names = [k for k in rows[0] if isinstance(rows[0][k], dict)]
    radii = sorted({row["radius"] for row in rows})
    fig, axes = plt.subplots(1, len(radii), figsize=(5 * len(radii), 4.2), sharey=True, squeeze=False)
    axes = axes[0]
    for ax, r in zip(axes, radii):
        sub = [row for row in rows if row["radius"] == r]
        for n, style, colour in zip(names, ("o-", "s-", "x:", "D-"), ("C0", "C1", "C3", "C4")):
            for grid, dash in (("fine", "-"), ("coarse", ":")):
                pts = sorted((row["gap"], row[n]["leak"]) for row in sub if row["grid"] == grid)
                ax.plot(*zip(*pts), style[0] + dash, color=colour, label=f"{n} ({grid} grid)")
        ax.axhline(0.10, color="k", lw=0.8, ls="--")
        ax.set_yscale("log")
        ax.set_ylim(1e-3, 1.5)
        ax.set_xlabel("gap / finger length")
        ax.set_title(f"finger radius {r}")
    axes[0].set_ylabel("finger B tip motion / Euclidean")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png_dir / "fix_leakage.png", dpi=70)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=pathlib.Path, default=HERE / "results" / "quality_fixes.json")
    ap.add_argument("--png-dir", type=pathlib.Path, default=HERE / "results" / "quality")
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    args.png_dir.mkdir(parents=True, exist_ok=True)
    radii, gaps = ((0.09,), (0.05, 0.3)) if args.quick else ((0.06, 0.09, 0.15), (0.05, 0.1, 0.2, 0.3))
    # the grid must resolve the gap (a coarser one glues the fingers together)
    # the finer grid resolves the gap well; the coarser one (at most 0.05) barely (the kNN graph of
    # its vertices then bridges the gap)
    resolutions = (lambda r, g: (min(r / 2, g / 1.1, 0.05), min(r / 3, g / 3)))
    doc = {"schema": "nrpose-bench-quality-fixes/1", "rigid_parts": rigid_parts(),
           "continuity": continuity(SPREADS[::3] if args.quick else SPREADS),
           "leakage": leakage(radii, gaps, resolutions)}
    args.json.write_text(json.dumps(doc, indent=1))
    figures(doc, args.png_dir)
    print(f"wrote {args.json} and {args.png_dir}/fix_*.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
