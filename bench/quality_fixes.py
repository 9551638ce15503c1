"""Figures of the three NR-MLS weaknesses and their prototype fixes (float64 references).

    python bench/quality_fixes.py [--json OUT.json] [--png-dir DIR] [--quick]

1. Rigid parts: the cylinder with a rigid joint sleeve (rigs/sleeve.py), weight splits
   0.4/0.6, 0.5/0.5, 0.9/0.1, bends 90°/135°: largest in-sleeve edge strain, body strain
   p99.9 and volume, for the relative blend as is and with the segment parameters taken at
   the weight group's centroid (``group-t``) or at the CoR center (``center-t``).
2. Continuity: the Y-junction probe line (spacing 1e-4) and mesh, both spread families,
   spreads 30°–179°: largest continuity ratio of the relative, quaternion, tree-signed and
   eigen (Markley) blends, and the tree blend's derived bound (nrpose/blend_variants.py).
3. Leakage: palm-and-two-fingers shapes (rigs/fingers.py; finger length 1, radii 0.06/0.09/0.15,
   gaps 0.05–0.3, two marching-cubes resolutions), finger A bent 45°, α = 1: finger B's tip
   motion over the Euclidean-weight one, with heat distances, heat + arrival parameters,
   bone heat weights, plain kNN (point cloud) and normal-pruned kNN + arrival parameters.
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

from quality_adapter import HandleSet, Pose, Rotation, blend, cor, cylinder, distance_matrix  # noqa: E402
from quality_adapter import blend_variants as bv, deformation_metrics as dm, topological_fixes as tf  # noqa: E402
from quality_adapter import fingers_shape, handle_sources, sleeve, yjunction  # noqa: E402

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
        terms = {"as is": blend.rest_terms(V, rest, weights=W),
                 "group-t": bv.center_parameters(V, rest, W, bv.group_centers(V, dm.weight_groups(W))),
                 "center-t": bv.center_parameters(V, rest, W, cor.centers(V, F, np.tile([0, 1], (len(V), 1)), W))}
        for deg in (90, 135):
            pose = cylinder.bend_pose(deg)
            for name, T in terms.items():
                P = blend.pose_reference(T, rest, pose)
                rows.append({"split": list(split), "bend": deg, "variant": name,
                             "sleeve_strain_max": float(dm.group_rigidity(V, P, E, cap)),
                             "body_p99.9": float(np.percentile(dm.edge_strain(V[:nb], P[:nb], body_E), 99.9)),
                             "body_volume": float(dm.signed_volume(P[:nb], body_F) / dm.signed_volume(V[:nb], body_F))})
    return rows


def edge_bound(T, pose, pts, pairs, Q, signs) -> np.ndarray:
    """The tree blend's bound per pair (nrpose/blend_variants.py, finite-difference form)."""
    q_star = np.einsum("nh,nhk->nk", T.weights, blend.handle_points(pose.handles, T.t))
    a = T.lever @ (signs[:, None] * Q)
    i, j = pairs.T
    delta = np.linalg.norm(pts[i] - pts[j], axis=1)
    amax = np.maximum(np.linalg.norm(a[i], axis=1), np.linalg.norm(a[j], axis=1))
    return 2 + (np.linalg.norm(T.p_star[i] - T.p_star[j], axis=1) + np.linalg.norm(q_star[i] - q_star[j], axis=1)
                + 4 * np.linalg.norm(T.u[i], axis=1) * np.abs(T.lever[i] - T.lever[j]).sum(axis=1) / amax) / delta


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
            Q = bv.segment_quats(rest, pose)
            for where, (pts, pairs) in sets.items():
                T = blend.rest_terms(pts, rest)
                tree = bv.coinfluence_tree(T)
                signs = bv.tree_signs(Q, *tree)
                outs = {b: blend.pose_reference(T, rest, pose, b) for b in ("relative", "quaternion")}
                outs["tree"] = bv.pose_variant(T, rest, pose, "tree", tree)
                outs["eigen"] = bv.pose_variant(T, rest, pose, "eigen")
                row = {"family": family, "spread": s, "where": where,
                       "bound_tree": float(edge_bound(T, pose, pts, pairs, Q, signs).max()),
                       "a_min": float(bv.signed_quaternion_rotations(T, Q, signs)[1].min())}
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
    import igl

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
                T = blend.rest_terms(V, rest, distances=distance_matrix(V, F, None, s.bones, method="heat"))
                arrive = bv.arrival_parameters(V, F, s.bones, handle_sources(V, F, None, s.bones))
                Dk = tf.graph_bone_distances(tf.normal_knn_graph(V, igl.per_vertex_normals(V, F)), V, s.bones)
                Tk = blend.rest_terms(V, rest, distances=Dk)
                cloud_arrive = bv.arrival_parameters(V, None, s.bones, handle_sources(V, None, None, s.bones))
                variants = {
                    "heat": T,
                    "heat+arrival": bv.with_parameters(T, V, rest, arrive),
                    "bone heat": blend.rest_terms(V, rest, weights=tf.bone_heat_weights(V, F, s.bones)),
                    "knn (cloud)": blend.rest_terms(V, rest, distances=distance_matrix(V, None, None, s.bones, method="knn")),
                    "normal-knn+arrival (cloud)": bv.with_parameters(Tk, V, rest, cloud_arrive)}
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
        for b, style in (("relative", "o-"), ("quaternion", "s-"), ("eigen", "^-"), ("tree", "D-"), ("bound_tree", "k--")):
            ax.semilogy(x, [r[b] for r in rows], style, label=b if b != "bound_tree" else "tree: derived bound")
        ax.set_xlabel("rotation spread (°)")
        ax.set_ylabel("max |Δ displacement| / rest spacing (probe, 1e-4)")
        ax.set_title(f"Y-junction, {family} axes")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png_dir / "fix_continuity.png", dpi=90)
    plt.close(fig)

    rows = doc["leakage"]
    names = [k for k in rows[0] if isinstance(rows[0][k], dict)]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), sharey=True)
    for ax, r in zip(axes, sorted({row["radius"] for row in rows})):
        sub = [row for row in rows if row["radius"] == r]
        for n, style, colour in zip(names, ("o-", "s-", "^-", "x:", "D-"), ("C0", "C1", "C2", "C3", "C4")):
            for grid, dash in (("fine", "-"), ("coarse", ":")):
                pts = sorted((row["gap"], row[n]["leak"]) for row in sub if row["grid"] == grid)
                ax.plot(*zip(*pts), style[0] + dash, color=colour, label=f"{n} ({grid} grid)")
        ax.axhline(0.10, color="k", lw=0.8, ls="--")
        ax.set_yscale("symlog", linthresh=0.01)
        ax.set_xlabel("gap / finger length")
        ax.set_title(f"finger radius {r}")
    axes[0].set_ylabel("finger B tip motion / Euclidean")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png_dir / "fix_leakage.png", dpi=90)
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
