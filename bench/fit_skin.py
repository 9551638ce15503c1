"""NR-MLS fitted as LBS (``nrpose fit-skin``): error table, fit time and file size per character.

Cases (issue 35's targets): Fox trained on Walk + Survey, Run held out; Mannequin and Ely
trained on their own clip + the range of motion, CMU 131_03 retargeted onto them
(``nrpose retarget``, in a temporary folder) held out. ``--only hand arm``: libigl's hand
(heat weights) and arm (its weight file), meshes with a TGF skeleton, trained on 48 random
poses + the range of motion, 48 others held out (:data:`MESH_CASES`). Each case is fitted with the given
influences (default 4), helper-joint counts (default 0, 8, 16; per character with
``--helpers NAME=N``) and ``--helper-tracks`` modes
(``--tracks``, default rule); the held-out motion is also exported into the file
(``--export``), so the file size includes it. Output: the reports of ``nrpose fit-skin
--report`` in one JSON (``results/fit_skin.json``), a table on stdout (RMS / max as % of the
height), and per case a map of the held-out error (rule mode: 4-influence fits,
``results/fit_skin_<name>_h<N>.png``; fitted tracks: ``fit_skin_<name>_k<k>_h<N>_tracks.png``;
per-vertex RMS over the held-out frames, colour scale 0 to 1 % of the height), evaluated by
loading the written file (helpers move by the animation channels it holds). ``--curve PNG``
plots the held-out errors and the size ratio against the helper count instead of the maps.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import tempfile

import numpy as np

import common
import table1
from nrpose.cli import main as nrpose
from nrpose.cli.common import character_with_weights
from nrpose.cli.fit_skin import motion
from nrpose.fit.character_skin import character_height, nrmls_targets
from nrpose.io import load_character
from nrpose.io.bvh_write import write_bvh
from nrpose.model.rotation import Rotation
from nrpose.model.skeleton import LocalPose
from nrpose.model.timing import sample_times
from nrpose.pose.poser import CharacterPoser
from nrpose.render.weightmap import save_weight_maps

MAP_SCALE = 0.01     # error map colour scale: 0 .. 1 % of the height

CASES = (("Fox", ["Walk", "Survey"], "Run"),
         ("Mannequin", ["Armature|mixamo.com|Layer0"], "131_03"),
         ("Ely", ["Armature|mixamo.com|Layer0"], "131_03"))
#: libigl characters, a mesh with a TGF skeleton (no glTF: the fitted file is a new one):
#: (name, mesh, skeleton, libigl weight file or None for heat weights) in libigl/; trained on
#: RANDOM_POSES random poses, another RANDOM_POSES held out (:func:`random_motion`)
MESH_CASES = (("hand", "hand.mesh", "hand.tgf", None), ("arm", "arm.obj", "arm.tgf", "arm-weights.dmat"))
RANDOM_POSES, RANDOM_DEGREES = 48, 40.0


def random_motion(mesh: pathlib.Path, skeleton: pathlib.Path, out: pathlib.Path, seed: int) -> str:
    """A BVH on the TGF skeleton (its joint names) of RANDOM_POSES poses, each joint turned by up to
    RANDOM_DEGREES about a random axis (seeded); its path (written once per run)."""
    if out.exists():
        return str(out)
    skel = load_character(mesh, skeleton).skeleton
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(RANDOM_POSES, skel.num_joints, 3))
    angles = np.radians(RANDOM_DEGREES) * rng.uniform(size=(RANDOM_POSES, skel.num_joints, 1))
    rest = skel.rest_pose
    pose = LocalPose(np.tile(rest.translation, (RANDOM_POSES, 1, 1)),
                     Rotation.from_rotvec((angles * axes / np.linalg.norm(axes, axis=2, keepdims=True))
                                          .reshape(-1, 3)).as_quat().reshape(RANDOM_POSES, -1, 4),
                     np.tile(rest.scale, (RANDOM_POSES, 1, 1)))
    write_bvh(out, skel, pose, 1 / 30)
    return str(out)


def run_case(data: pathlib.Path, tmp: pathlib.Path, name: str, train, holdout: str, k: int, helpers: int,
             tracks: str = "rule", maps: bool = True) -> dict:
    mesh = {c[0]: c[1:] for c in MESH_CASES}.get(name)
    if mesh is None:
        source = [str(data / "gltf" / f"{name}.glb")]
    else:
        files = [data / "libigl" / f for f in mesh[:2]]
        source = [str(files[0]), "--skeleton", str(files[1])] + \
            (["--weights-file", str(data / "libigl" / mesh[2])] if mesh[2] else [])
        train = [random_motion(*files, tmp / f"{name}_train.bvh", seed=1)]
        holdout = random_motion(*files, tmp / f"{name}_holdout.bvh", seed=2)
    if holdout == "131_03":
        motion = tmp / f"{name}_131_03.glb"
        if not motion.exists() and nrpose(["retarget", str(data / "bvh" / "131_03.bvh"), source[0],
                                           "-o", str(motion)]):
            raise SystemExit(2)
        holdout = str(motion)
    tag = f"{name}_{k}_{helpers}" + ("_tracks" if tracks == "fitted" else "")
    report, out = tmp / f"{tag}.json", tmp / f"{tag}.glb"
    if nrpose(["fit-skin", *source, "--train", *train, "--holdout", holdout, "--export", holdout,
               "--influences", str(k), "--helpers", str(helpers), "--helper-tracks", tracks,
               "-o", str(out), "--report", str(report)]):
        raise SystemExit(2)
    r = json.loads(report.read_text())
    if maps and (k == 4 or tracks == "fitted"):
        png = f"fit_skin_{name}_h{helpers}.png" if tracks == "rule" else f"fit_skin_{name}_k{k}_h{helpers}_tracks.png"
        error_map(source, r["weights"], out, holdout, pathlib.Path(__file__).with_name("results") / png)
    return r


def error_map(source: list, weights: str, fitted_file: pathlib.Path, holdout: str, png: pathlib.Path) -> None:
    """Per-vertex RMS over the held-out frames of the fitted file's LBS vs NR-MLS, drawn at rest.

    The file's LBS: its exported held-out animation (the last) played by nrpose's LBS, helpers
    moved by their channels; NR-MLS (with ``weights``) of the same motion on the source
    character (``source``: fit-skin's arguments naming it)."""
    src = pathlib.Path(source[0])
    given = dict(zip(source[1::2], source[2::2]))
    character = character_with_weights(source[0], given.get("--skeleton"), given.get("--weights-file"))
    back = load_character(fitted_file)
    clip = back.clips[-1]
    times = sample_times(clip.duration, 30.0)
    lbs = CharacterPoser(back, method="lbs", backend="numpy").pose(clip.sample(times)).positions
    _, local, _ = motion(character, holdout, 30.0, pose_ok=False)
    _, targets = nrmls_targets(CharacterPoser(character, method="nrmls", weights=weights), local)
    rms = np.sqrt(((lbs - targets) ** 2).sum(axis=2).mean(axis=0))
    V = np.concatenate([m.vertices for m in character.meshes])
    offsets = np.cumsum([0] + [len(m.vertices) for m in character.meshes])
    F = np.concatenate([m.faces + o for m, o in zip(character.meshes, offsets)])
    scaled = np.clip(rms / (MAP_SCALE * character_height(character)), 0, 1)
    save_weight_maps(V, F, {"held-out RMS / 1 % of height": scaled}, png, vmax=1.0,
                     title=f"{src.stem}: fitted LBS vs NR-MLS on {pathlib.Path(holdout).name} (yellow >= 1 %)",
                     scale_label="held-out RMS, % of height")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="bench/fit_skin.py", description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(table1.DEFAULT_DATA), help="shared data folder (gltf/, bvh/)")
    ap.add_argument("--json", default=str(pathlib.Path(__file__).with_name("results") / "fit_skin.json"))
    ap.add_argument("--influences", type=int, nargs="+", default=[4], choices=(4, 8))
    ap.add_argument("--helpers", nargs="+", default=["0", "8", "16"],
                    help="helper counts: N for every character, NAME=N for one (Fox=44 Ely=64)")
    ap.add_argument("--tracks", nargs="+", default=["rule"], choices=("rule", "fitted"),
                    help="fit-skin --helper-tracks modes to run (default rule)")
    ap.add_argument("--curve", help="a PNG of held-out RMS / max and file size against the helper count (no maps)")
    ap.add_argument("--only", nargs="+", choices=[c[0] for c in CASES + MESH_CASES],
                    help="characters to run (default: the glTF ones, Fox, Mannequin, Ely)")
    a = ap.parse_args(argv)
    data = pathlib.Path(a.data)
    meshes = [c[0] for c in MESH_CASES]
    folders = {"libigl" if name in meshes else "gltf" for name in a.only or [c[0] for c in CASES]}
    for folder in sorted(folders):
        if not (data / folder).is_dir():
            print(f"bench/fit_skin.py: error: no {folder}/ folder in {data}", file=sys.stderr)
            return 2
    counts = {name: [] for name, *_ in CASES + MESH_CASES}
    for item in a.helpers:
        name, _, n = item.rpartition("=")
        if not n.isdigit() or (name and name not in counts):
            print(f"bench/fit_skin.py: error: --helpers {item}: expected N or NAME=N with NAME one of "
                  f"{', '.join(counts)}", file=sys.stderr)
            return 2
        for key in [name] if name else counts:
            counts[key].append(int(n))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, train, holdout in CASES + tuple((c[0], [], "") for c in MESH_CASES):
            if (name not in a.only) if a.only else (name not in [c[0] for c in CASES]):
                continue
            for k, n, mode in [(k, n, m) for k in a.influences for n in counts[name] for m in a.tracks]:
                r = run_case(data, pathlib.Path(tmp), name, train, holdout, k, n, mode, maps=not a.curve)
                for label, e in r["errors"].items():
                    rows.append({"character": name, "influences": k, "helpers": r["helpers"], "tracks": mode,
                                 "set": "training" if label == "training" else "held-out",
                                 "rms_pct": 100 * e["rms_fraction"], "max_pct": 100 * e["max_fraction"],
                                 "authored_rms_pct": 100 * r["authored_lbs_errors"][label]["rms_fraction"],
                                 "fit_seconds": r["fit_seconds"], "file_bytes": r["size"]["file_bytes"],
                                 "bake_10s_bytes": r["size"]["morph_bake_bytes_10s"], "report": r})
    print(f"{'character':10} {'k':>2} {'h':>2} {'tracks':6} {'set':9} {'RMS %':>7} {'max %':>7} {'authored RMS %':>15} "
          f"{'fit s':>6} {'file / bake10s':>15}")
    for row in rows:
        print(f"{row['character']:10} {row['influences']:2d} {row['helpers']:2d} {row['tracks']:6} {row['set']:9} {row['rms_pct']:7.3f} "
              f"{row['max_pct']:7.3f} {row['authored_rms_pct']:15.3f} {row['fit_seconds']:6.1f} "
              f"{row['file_bytes'] / row['bake_10s_bytes']:15.4f}")
    common.write_record({"created": common.now(), "environment": common.environment(), "rows": rows}, a.json)
    if a.curve:
        helper_curve(rows, pathlib.Path(a.curve))
    return 0


def helper_curve(rows: list[dict], png: pathlib.Path) -> None:
    """Per character and influence count: held-out RMS and max (% of the height, left) and the
    file / 10 s bake ratio (right) against the helper count, with issue 35's targets dashed."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from nrpose.io.files import atomic_path
    held = [r for r in rows if r["set"] == "held-out"]
    groups = list(dict.fromkeys((r["character"], r["influences"], r["tracks"]) for r in held))
    fig, axes = plt.subplots(1, len(groups), figsize=(5.5 * len(groups), 4.4), squeeze=False)
    for ax, (name, k, mode) in zip(axes[0], groups):
        g = sorted((r for r in held if (r["character"], r["influences"], r["tracks"]) == (name, k, mode)),
                   key=lambda r: r["helpers"])
        n = [r["helpers"] for r in g]
        ax.plot(n, [r["max_pct"] for r in g], "o-", color="#d62728", label="held-out max %")
        ax.plot(n, [r["rms_pct"] for r in g], "o-", color="#1f77b4", label="held-out RMS %")
        ax.axhline(1.0, ls="--", color="#d62728", lw=0.8)
        ax.axhline(0.2, ls="--", color="#1f77b4", lw=0.8)
        ax.set_yscale("log")
        ax.set_xlabel("helper joints")
        ax.set_ylabel("% of height")
        size = ax.twinx()
        size.plot(n, [r["file_bytes"] / r["bake_10s_bytes"] for r in g], "s:", color="#2ca02c",
                  label="file / 10 s bake")
        size.axhline(0.05, ls="--", color="#2ca02c", lw=0.8)
        size.set_ylim(0, 1.25 * max([0.05] + [r["file_bytes"] / r["bake_10s_bytes"] for r in g]))
        size.set_ylabel("file / 10 s morph-target bake")
        ax.set_title(f"{name}, {k} influences, {mode} tracks (dashed: targets)", fontsize=9)
        lines = ax.get_legend_handles_labels(), size.get_legend_handles_labels()
        ax.legend(lines[0][0] + lines[1][0], lines[0][1] + lines[1][1], fontsize=8, loc="upper center",
                  bbox_to_anchor=(0.5, -0.16), ncol=3)     # below the axes: never over a curve
    fig.tight_layout()
    with atomic_path(png) as tmp:
        fig.savefig(tmp, format="png", dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
