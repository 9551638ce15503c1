"""Benchmark: binding with topological weights, what top-k sparsity costs, weight maps.

Three parts, one record (``bench/results/bind.json``, written atomically):

* ``bind``: bind time = distances (:func:`nrpose.bind.distances.distance_matrix`)
  + weights (:func:`nrpose.weights.dense_weights`, then the poser's top-k),
  uncached, median of ``--repeat`` runs (default 3):

  - Mannequin (15,882 vertices, 77 bones from 65 joints; welded to 14,442
    positions, one surface): heat, graph, euclidean; also the whole
    ``CharacterPoser(weights="heat")`` bind (distances, weights and the
    OpenCL deformer) with an empty cache and with a warm one. Target: heat
    bind under 3 s.
  - Mannequin ``exact``: one MMP solve per bone (igl.exact_geodesic) takes
    seconds on 14k vertices, so all 77 would take minutes per run; the
    sources are computed for all bones, ``--exact-bones`` bones (evenly
    spaced, default 4) are solved and timed, and the full bind is
    extrapolated (sources + 77 × mean per-bone time). Marked
    ``"estimated": true``.
  - Stanford bunny (35,947 vertices, 69,451 faces) with 4 point handles
    placed by farthest-point sampling from the vertex nearest the centroid
    (the rule of ``bench/table1.py``): heat, graph, exact. ``exact`` takes
    minutes per bind: timed ``--exact-repeat`` times (default 1).

* ``sparsity``: nrmls posing (OpenCL) with heat weights keeping the k = 4 and
  k = 8 most influential bones per vertex vs dense weights (all bones), for
  α = 1 (the default) and α = 2, on Fox (clips Survey, Walk, Run at 1/4, 1/2,
  3/4 and the end of each), Mannequin and Ely. The Mixamo clips of Mannequin
  and Ely are 2-frame T-poses (nothing to measure), so they also get two test
  poses built from world-axis joint rotations: ``arms_down_fists`` (upper
  arms lowered 75° to the hips, every finger joint curled 50°) and
  ``crouch_reach`` (hips flexed 60°, knees 90°, spine 20° forward, elbows
  90°). Reported: the max and RMS over vertices and poses of
  ``|x_k − x_dense|``, divided by the character's height (rest bounding-box
  extent along Y); for scale, the same distances of the sparse and dense
  results to linear blend skinning with the file's authored weights.

* ``figure2``: the palm-and-two-fingers shape (``rigs/fingers.py``), finger
  A's bone bent 45° about its base: the largest displacement of finger B's
  tip with heat / exact / graph / kNN (point cloud) distances, as a fraction
  of what Euclidean distances give.

* PNG weight maps (``--maps``, default on): ``weights_fox.png`` (the Fox's
  left front lower leg, ``b_LeftForeArm_010``: its front legs are close
  together) and ``weights_mannequin.png`` (Mannequin with its arms lowered to
  the hips by its own skin, then bound in that pose: the left forearm bone),
  Euclidean vs heat, colour scale γ = 0.5.

Usage: ``.venv/bin/python bench/bench_bind.py [--repeat 3] [--exact-repeat 1]
[--exact-bones 4] [--skip-exact] [--no-maps] [--data DIR] [--out DIR]``.
A full run takes about 5 minutes, 3 of them the bunny's exact geodesics.
Not a test; the machine is a shared 2-core box.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import subprocess
import sys
import tempfile
import time
import warnings

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent
PROJECT = ROOT.parent
if str(PROJECT) not in sys.path:
    sys.path.insert(0, str(PROJECT))

from nrpose import device  # noqa: E402
from nrpose.io import load_character  # noqa: E402
from nrpose.bind.distances import distance_matrix, handle_sources, weld_vertices  # noqa: E402
from nrpose.io.files import atomic_path  # noqa: E402
from nrpose.io.meshes import read_geometry  # noqa: E402
from nrpose.model.rotation import Rotation  # noqa: E402
from nrpose.model.skeleton import LocalPose  # noqa: E402
from table1 import fps_handles  # noqa: E402  (bench/ is on sys.path as the script's folder)
from nrpose.bind.weights import dense_weights, deviation, keep_top_k  # noqa: E402

SKELETON_K = 8


# ---------------------------------------------------------------------------- utilities
def git_commit() -> str:
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=PROJECT, capture_output=True, text=True,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", "nrpose", "kernels", "rigs"],
                               cwd=PROJECT, capture_output=True, text=True).stdout.strip()
        return sha + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def environment() -> dict:
    import igl
    import scipy

    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {"python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
            "libigl": getattr(igl, "__version__", None), "processor": cpu, "cpu_count": os.cpu_count(),
            "device": device.describe()}


def timed(fn, repeat: int) -> tuple[dict, object]:
    """Median / min / max seconds of ``repeat`` calls (no warm-up: binds are one-off work)."""
    samples, out = [], None
    for _ in range(max(1, repeat)):
        t = time.perf_counter()
        out = fn()
        samples.append(time.perf_counter() - t)
    return {"median_s": float(np.median(samples)), "min_s": float(min(samples)),
            "max_s": float(max(samples)), "runs": len(samples)}, out


def bind_weights(V, F, P, S, method: str, k: int | None):
    D = distance_matrix(V, F, P, S, method=method)
    return keep_top_k(dense_weights(D), k)


# ---------------------------------------------------------------------------- poses
def world_rotated(skel, pose: LocalPose, turns: list[tuple[str, str, float]]) -> LocalPose:
    """``pose`` with joints turned about world axes at their own position, in order.

    turns: (joint name, axis 'x'|'y'|'z', degrees). A joint's turn is applied
    after its ancestors' (list parents first): ``L' = P⁻¹ R P L`` with ``P``
    the parent's current global rotation.
    """
    rot = pose.rotation.copy()
    for name, axis, deg in turns:
        j = skel.index(name)
        G = skel.forward_kinematics(LocalPose(pose.translation, rot, pose.scale))
        p = skel.parents[j]
        Pm = G[p, :3, :3] if p >= 0 else np.eye(3)
        Pm = Pm / np.cbrt(np.linalg.det(Pm))  # drop uniform scale
        Pr = Rotation.from_matrix(Pm)
        R = Rotation.from_euler(axis, deg, degrees=True)
        rot[j] = (Pr.inv() * R * Pr * Rotation.from_quat(rot[j])).as_quat()
    return LocalPose(pose.translation.copy(), rot, pose.scale.copy())


def mixamo_poses(skel) -> dict[str, LocalPose]:
    """Test poses for a Mixamo T-pose rig (left on +X, Y up, facing +Z)."""
    pre = "mixamorig:"
    rest = skel.rest_pose
    fingers = [n for n in skel.names if n.startswith(pre) and "Hand" in n and n[-1] in "123"
               and "Thumb" not in n]
    arms = [(pre + "LeftArm", "z", -75.0), (pre + "RightArm", "z", 75.0)]
    curl = [(n, "z", -50.0 if "Left" in n else 50.0) for n in fingers]
    crouch = [(pre + "Spine", "x", 20.0),
              (pre + "LeftUpLeg", "x", -60.0), (pre + "RightUpLeg", "x", -60.0),
              (pre + "LeftLeg", "x", 90.0), (pre + "RightLeg", "x", 90.0),
              (pre + "LeftForeArm", "y", -90.0), (pre + "RightForeArm", "y", 90.0)]
    order = {n: i for i, n in enumerate(skel.names)}
    return {"arms_down_fists": world_rotated(skel, rest, sorted(arms + curl, key=lambda t: order[t[0]])),
            "crouch_reach": world_rotated(skel, rest, sorted(crouch, key=lambda t: order[t[0]]))}


def stack_poses(poses: list[LocalPose]) -> LocalPose:
    return LocalPose(*(np.stack([getattr(p, f) for p in poses]) for f in ("translation", "rotation", "scale")))


# ---------------------------------------------------------------------------- parts
def bench_bind(data: pathlib.Path, repeat: int, exact_repeat: int, exact_bones: int, skip_exact: bool) -> dict:
    from nrpose.bind import distances as dm
    from nrpose.pose.poser import CharacterPoser

    out: dict = {}
    # -- Mannequin
    ch = load_character(data / "gltf" / "Mannequin.glb")
    mesh = ch.meshes[0]
    bones = ch.skeleton.bones()
    V, F, S = mesh.vertices, mesh.faces, bones.segments
    B = len(bones)
    k = SKELETON_K if B > SKELETON_K else None
    rec = {"vertices": int(len(V)), "welded_vertices": int(len(weld_vertices(V)[0])), "faces": int(len(F)),
           "joints": ch.skeleton.num_joints, "bones": B, "k": k, "methods": {}}
    for method in ("heat", "graph", "euclidean"):
        stats, _ = timed(lambda: bind_weights(V, F, None, S, method, k), repeat)
        rec["methods"][method] = stats
        print(f"Mannequin {method:9s} bind {stats['median_s']:.2f} s (median of {stats['runs']})", flush=True)
    if not skip_exact:
        Vw, inv = weld_vertices(V)
        Fw = inv[F]
        t = time.perf_counter()
        src = handle_sources(Vw, Fw, None, S)
        t_src = time.perf_counter() - t
        pick = np.unique(np.linspace(0, B - 1, max(1, exact_bones)).round().astype(int))
        per = []
        for j in pick:
            t = time.perf_counter()
            dm.exact_component(Vw, Fw, [(int(j), src[j][0], src[j][1])])
            per.append(time.perf_counter() - t)
        rec["methods"]["exact"] = {
            "estimated": True, "median_s": float(t_src + B * np.mean(per)),
            "sources_s": t_src, "per_bone_s": {bones.names[j]: s for j, s in zip(pick, per)},
            "why": f"exact (MMP) needs one solve per bone, {np.mean(per):.1f} s each on "
                   f"{len(Vw)} vertices: {B} bones would take minutes per run, so {len(pick)} bones "
                   f"were solved and the bind is sources + {B} x their mean"}
        print(f"Mannequin exact     bind ≈ {rec['methods']['exact']['median_s']:.0f} s (estimated from "
              f"{len(pick)} bones, {np.mean(per):.1f} s each)", flush=True)
    # the whole poser bind, cold and warm cache
    cold = []
    with tempfile.TemporaryDirectory(prefix="nrpose-bench-cache-") as tmp:
        old = os.environ.get("NRPOSE_CACHE_DIR")
        try:
            for r in range(max(1, repeat)):
                os.environ["NRPOSE_CACHE_DIR"] = os.path.join(tmp, f"cold{r}")
                t = time.perf_counter()
                CharacterPoser(ch, weights="heat")
                cold.append(time.perf_counter() - t)
            warm = []
            for _ in range(max(1, repeat)):
                t = time.perf_counter()
                CharacterPoser(ch, weights="heat")
                warm.append(time.perf_counter() - t)
        finally:
            if old is None:
                os.environ.pop("NRPOSE_CACHE_DIR", None)
            else:
                os.environ["NRPOSE_CACHE_DIR"] = old
    rec["poser_heat_cold_cache_s"] = float(np.median(cold))
    rec["poser_heat_warm_cache_s"] = float(np.median(warm))
    rec["target_heat_bind_s"] = 3.0
    rec["heat_under_target"] = bool(rec["methods"]["heat"]["median_s"] < 3.0 and np.median(cold) < 3.0)
    print(f"Mannequin CharacterPoser(weights='heat') bind: cold cache {np.median(cold):.2f} s, "
          f"warm cache {np.median(warm):.2f} s (target < 3 s)", flush=True)
    out["Mannequin"] = rec

    # -- bunny with 4 point handles
    g = read_geometry(data / "meshes" / "stanford-bunny.obj")
    V, F = g.vertices, g.faces
    P = fps_handles(V, 4).points   # bench/table1.py's placement rule
    rec = {"vertices": int(len(V)), "faces": int(len(F)), "point_handles": P.tolist(), "methods": {}}
    for method in ("heat", "graph", "euclidean") + (() if skip_exact else ("exact",)):
        n = exact_repeat if method == "exact" else repeat
        stats, _ = timed(lambda: bind_weights(V, F, P, None, method, None), n)
        rec["methods"][method] = stats
        print(f"bunny     {method:9s} bind {stats['median_s']:.2f} s (median of {stats['runs']})", flush=True)
    if skip_exact:
        rec["methods"]["exact"] = {"skipped": True, "why": "--skip-exact"}
    elif exact_repeat < 3:
        rec["methods"]["exact"]["why"] = (f"exact takes minutes per bind on 36k vertices: "
                                          f"{exact_repeat} run(s) (--exact-repeat)")
    out["bunny"] = rec
    return out


def bench_sparsity(data: pathlib.Path, ks=(4, 8), alphas=(1.0, 2.0)) -> dict:
    from nrpose.pose.poser import CharacterPoser

    out = {}
    with tempfile.TemporaryDirectory(prefix="nrpose-bench-cache-") as tmp:
        old = os.environ.get("NRPOSE_CACHE_DIR")
        os.environ["NRPOSE_CACHE_DIR"] = tmp
        try:
            for name in ("Fox", "Mannequin", "Ely"):
                ch = load_character(data / "gltf" / f"{name}.glb")
                skel = ch.skeleton
                labels, poses = [], []
                for clip in ch.clips:
                    times = np.unique(np.round(clip.duration * np.array([0.25, 0.5, 0.75, 1.0]), 9))
                    for t in times:
                        labels.append(f"{clip.name}@{t:.3f}s")
                        poses.append(clip.sample(t))
                if name != "Fox":
                    for label, p in mixamo_poses(skel).items():
                        labels.append(label)
                        poses.append(p)
                local = stack_poses(poses)
                rest = np.concatenate([m.vertices for m in ch.meshes])
                height = float(np.ptp(rest[:, 1]))
                B = len(skel.bones())
                lbs = CharacterPoser(ch, method="lbs", weights="authored").pose(local).positions
                rec = {"vertices": int(len(rest)), "bones": B, "height": height, "poses": labels,
                       "weights": "heat", "alpha": {}}

                def stats(a, b):
                    d = np.linalg.norm(a.astype(np.float64) - b, axis=2) / height
                    return d, {"max_rel": float(d.max()), "rms_rel": float(np.sqrt(np.mean(d * d)))}

                for alpha in alphas:
                    dense = CharacterPoser(ch, weights="heat", alpha=alpha, k=B).pose(local).positions
                    arec = {"dense_vs_authored_lbs": stats(dense, lbs)[1], "k": {}}
                    for k in ks:
                        sparse = CharacterPoser(ch, weights="heat", alpha=alpha, k=k).pose(local).positions
                        d, st = stats(sparse, dense)
                        st["per_pose"] = {lab: {"max_rel": float(d[f].max()),
                                                "rms_rel": float(np.sqrt(np.mean(d[f] ** 2)))}
                                          for f, lab in enumerate(labels)}
                        st["vs_authored_lbs"] = stats(sparse, lbs)[1]
                        arec["k"][str(k)] = st
                        worst = labels[int(np.argmax(d.max(axis=1)))]
                        print(f"sparsity {name:9s} α={alpha:g} k={k}: vs dense max {100 * st['max_rel']:.2f} % "
                              f"of height (worst {worst}), RMS {100 * st['rms_rel']:.3f} %; vs authored LBS "
                              f"RMS {100 * st['vs_authored_lbs']['rms_rel']:.2f} % (dense "
                              f"{100 * arec['dense_vs_authored_lbs']['rms_rel']:.2f} %)", flush=True)
                    rec["alpha"][f"{alpha:g}"] = arec
                out[name] = rec
        finally:
            if old is None:
                os.environ.pop("NRPOSE_CACHE_DIR", None)
            else:
                os.environ["NRPOSE_CACHE_DIR"] = old
    return out


def bench_figure2() -> dict:
    from nrpose import Deformer, HandleSet, Pose
    from nrpose.rigs.fingers import fingers_shape

    s = fingers_shape()
    V, F = s.vertices, s.faces
    a = s.bone_names.index("finger_a")
    rest = HandleSet.make(segments=s.bones)
    R = Rotation.from_euler("z", 45, degrees=True).as_matrix()
    segs, rots = s.bones.copy(), np.stack([np.eye(3)] * len(s.bones))
    segs[a] = (segs[a] - segs[a, 0]) @ R.T + segs[a, 0]
    rots[a] = R
    pose = Pose.make(rest, segments=segs, rotations=rots)
    tip_b = (V[:, 0] > 0.5 * s.finger_gap) & (V[:, 1] > s.finger_length - 2 * s.finger_radius)
    res = {}
    for method, faces in (("euclidean", F), ("heat", F), ("exact", F), ("graph", F), ("knn", None)):
        D = distance_matrix(V, faces, None, s.bones, method=method)
        P = Deformer(V, rest, distances=D).pose(pose)
        res[method] = float(np.linalg.norm(P - V, axis=1)[tip_b].max())
    out = {"vertices": int(len(V)), "finger_gap": s.finger_gap, "finger_length": s.finger_length,
           "tip_displacement": res,
           "ratio_to_euclidean": {m: res[m] / res["euclidean"] for m in res if m != "euclidean"}}
    print("figure 2: finger B tip displacement / Euclidean: "
          + ", ".join(f"{m} {r:.3f}" for m, r in out["ratio_to_euclidean"].items()), flush=True)
    return out


# ---------------------------------------------------------------------------- weight maps
SIDE_VIEWS = (("left side", 0.0, 0.0), ("right side", 0.0, 180.0), ("rear 3/4", 10.0, 120.0))
FRONT_VIEWS = (("front", 0.0, -90.0), ("left side", 0.0, 0.0), ("oblique", 15.0, -60.0))


def _map_columns(V, F, bones, b: int, other: np.ndarray, other_label: str) -> dict:
    cols = {}
    for method in ("euclidean", "heat"):
        w = dense_weights(distance_matrix(V, F, None, bones, method=method))[:, b]
        cols[f"{method}: max on {other_label} {w[other].max():.3f}"] = w
    return cols


def _rel(path: pathlib.Path) -> str:
    try:
        return str(path.resolve().relative_to(PROJECT))
    except ValueError:
        return str(path)


def weight_maps(data: pathlib.Path, out_dir: pathlib.Path) -> dict:
    from nrpose.pose.poser import CharacterPoser
    from nrpose.render.weightmap import save_weight_maps

    info = {}
    # Fox: left front lower leg; the right front leg is the vertices whose dominant authored joint is on it
    ch = load_character(data / "gltf" / "Fox.glb")
    m, skel = ch.meshes[0], ch.skeleton
    bones = skel.bones()
    b = bones.names.index("b_LeftForeArm_010->b_LeftHand_011")
    dom = m.joints[np.arange(len(m.vertices)), np.argmax(m.weights, axis=1)]
    other = np.isin(dom, [skel.index(n) for n in ("b_RightUpperArm_06", "b_RightForeArm_07", "b_RightHand_08")])
    cols = _map_columns(m.vertices, m.faces, bones.segments, b, other, "right front leg")
    path = out_dir / "weights_fox.png"
    with atomic_path(path) as tmp:
        save_weight_maps(m.vertices, m.faces, cols, tmp, f"Fox: weight of bone {bones.names[b]} (α=1)",
                         vmax=1.0, gamma=0.5, views=SIDE_VIEWS, up="y")
    info["fox"] = {"path": _rel(path), "bone": bones.names[b], "columns": list(cols)}

    # Mannequin: arms lowered to the hips by its own skin (LBS, authored weights), bound in that pose
    ch = load_character(data / "gltf" / "Mannequin.glb")
    m, skel = ch.meshes[0], ch.skeleton
    pre = "mixamorig:"
    local = world_rotated(skel, skel.rest_pose, [(pre + "LeftArm", "z", -75.0), (pre + "RightArm", "z", 75.0)])
    V = CharacterPoser(ch, method="lbs", weights="authored").pose(local).positions[0].astype(np.float64)
    posed_bones, _ = skel.bones().pose(skel.forward_kinematics(local))
    bones = skel.bones()
    b = bones.names.index(pre + "LeftForeArm->" + pre + "LeftHand")
    dom = m.joints[np.arange(len(V)), np.argmax(m.weights, axis=1)]
    hips = np.isin(dom, [skel.index(pre + n) for n in ("Hips", "LeftUpLeg", "Spine")])
    cols = _map_columns(V, m.faces, posed_bones, b, hips, "hips + left thigh")
    path = out_dir / "weights_mannequin.png"
    with atomic_path(path) as tmp:
        save_weight_maps(V, m.faces, cols, tmp,
                         f"Mannequin, arms lowered 75° and bound there: weight of {bones.names[b]} (α=1)",
                         vmax=1.0, gamma=0.5, views=FRONT_VIEWS, up="y")
    info["mannequin"] = {"path": _rel(path), "bone": bones.names[b], "columns": list(cols),
                         "pose": "LeftArm/RightArm turned 75° down about +Z/-Z (world), LBS with authored weights"}
    for v in info.values():
        print(f"map {v['path']}: {v['bone']}: " + "; ".join(v["columns"]), flush=True)
    return info


# ---------------------------------------------------------------------------- main

def fingers_figure(path=ROOT / "results" / "fingers_weights.png", alpha: float = 1.0) -> dict:
    """Figure 2 of the seed paper on the palm-and-two-fingers shape: the blend
    weight of finger A's bone with Euclidean vs heat-geodesic distances.
    Returns a few numbers (max weight of bone A on finger B for both)."""
    from nrpose.bind.distances import distance_matrix
    from nrpose.rigs.fingers import fingers_shape
    from nrpose.render.weightmap import save_weight_maps
    from nrpose.bind.weights import dense_weights

    s = fingers_shape()
    V, F = s.vertices, s.faces
    a = s.bone_names.index("finger_a")
    W = {}
    for method in ("euclidean", "heat"):
        D = distance_matrix(V, F, None, s.bones, method=method)
        W[method] = dense_weights(D, alpha)[:, a]
    on_b = (V[:, 0] > 0.5 * s.finger_gap) & (V[:, 1] > 0.3)  # finger B, above the palm
    stats = {m: float(W[m][on_b].max()) for m in W}
    save_weight_maps(V, F, {f"{m}: max on finger B {stats[m]:.3f}": W[m] for m in W}, path,
                     f"weight of finger A's bone (α={alpha:g}): spatial vs topological distance",
                     gamma=0.5)
    return stats

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3, help="binds timed per configuration (median; default 3)")
    ap.add_argument("--exact-repeat", type=int, default=1, help="runs of the bunny's exact bind (default 1)")
    ap.add_argument("--exact-bones", type=int, default=4, help="Mannequin bones solved exactly (default 4)")
    ap.add_argument("--skip-exact", action="store_true", help="skip exact geodesics")
    ap.add_argument("--no-maps", action="store_true", help="do not draw the PNG weight maps")
    ap.add_argument("--parts", default="figure2,bind,sparsity,maps",
                    help="comma-separated parts to run (default all); the others are kept from an existing bind.json")
    ap.add_argument("--data", default=str(PROJECT.parent / "shared" / "data"), help="asset folder")
    ap.add_argument("--out", default=str(ROOT / "results"), help="output folder (default bench/results)")
    args = ap.parse_args(argv)
    data, out_dir = pathlib.Path(args.data), pathlib.Path(args.out)
    if not data.is_dir():
        print(f"bench_bind: asset folder {data} not found (--data)", file=sys.stderr)
        return 2
    out_dir.mkdir(parents=True, exist_ok=True)
    warnings.simplefilter("default")
    parts = {p.strip() for p in args.parts.split(",") if p.strip()}
    unknown = parts - {"figure2", "bind", "sparsity", "maps"}
    if unknown:
        print(f"bench_bind: unknown part(s) {sorted(unknown)}", file=sys.stderr)
        return 2
    path = out_dir / "bind.json"
    record = {}
    if parts != {"figure2", "bind", "sparsity", "maps"} and path.is_file():
        record = json.loads(path.read_text())
    record.update({"benchmark": "bind (topological weights)", "git_commit": git_commit(),
                   "environment": environment(), "repeat": args.repeat,
                   "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "parts_run_last": sorted(parts)})
    if "figure2" in parts:
        record["figure2"] = bench_figure2()
    if "bind" in parts:
        record["bind"] = bench_bind(data, args.repeat, args.exact_repeat, args.exact_bones, args.skip_exact)
    if "sparsity" in parts:
        record["sparsity"] = bench_sparsity(data)
    if "maps" in parts and not args.no_maps:
        record["maps"] = weight_maps(data, out_dir)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(record, indent=2) + "\n")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
