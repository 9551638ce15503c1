"""Clips suite: frames per second posing characters through their animation clips.

Characters (each with nrmls, lbs and dqs through :class:`nrpose.pose.poser.CharacterPoser`):

* the shared glTF characters ``gltf/Fox.glb`` (clip ``Walk``), ``gltf/Mannequin.glb`` and
  ``gltf/Ely.glb`` (their single Mixamo clip) with their authored skin weights;
* ``bvh``: a point cloud around the bones of ``bvh/131_03.bvh`` (CMU mocap, 31 joints),
  posed by that file's motion clip with euclidean weights (no faces: a point cloud).
  Points: per bone, a capsule of radius 0.18 x the median bone length around it, points
  uniform in the capsule's cylinder part, in proportion to bone length (seeded);
* ``humanoid``: the embedded capsule humanoid (``nrpose.rigs.humanoid``) and its walk,
  authored weights.

Frames: ``FRAMES`` (60) times evenly spaced over the clip (the Mixamo clips are 2-3 keys
long: their frames interpolate). Per round, every (character, method) poses all frames
in one ``CharacterPoser.pose(local_batch)`` call, methods taking turns. Reported:
``frame_ms`` -- the poser's own per-frame time (device pose + per-frame host work,
``Frames.frame_ms``), median over all frames of all rounds, and ``fps`` = 1000 / that;
``batch_fps`` -- frames / wall time of the whole ``pose`` call (forward kinematics,
bone poses and the output array included).
"""
from __future__ import annotations

import pathlib
import time

import numpy as np

import common
from nrpose.io import load_character
from nrpose.model.character import Character, Mesh
from nrpose.pose.poser import CharacterPoser

METHODS = ("nrmls", "lbs", "dqs")
FRAMES = 60
BVH_POINTS = 20_000
GLTF = (("fox", "gltf/Fox.glb", "Walk"), ("mannequin", "gltf/Mannequin.glb", None),
        ("ely", "gltf/Ely.glb", None))


def bvh_cloud(path: pathlib.Path, n: int, seed: int = 0) -> Character:
    """The BVH skeleton with a point cloud of n points around its bones, and its clip."""
    base = load_character(path)
    segs = base.skeleton.bones().segments
    length = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1)
    radius = 0.18 * float(np.median(length))
    rng = np.random.default_rng(seed)
    b = rng.choice(len(segs), n, p=length / length.sum())
    t = rng.random(n)[:, None]
    axis = segs[b, 1] - segs[b, 0]
    off = rng.normal(size=(n, 3))
    off -= np.sum(off * axis, 1, keepdims=True) * axis / np.sum(axis * axis, 1, keepdims=True)
    off *= (radius * np.sqrt(rng.random(n)) / np.maximum(np.linalg.norm(off, axis=1), 1e-12))[:, None]
    pts = segs[b, 0] + t * axis + off
    mesh = Mesh("bvh-cloud", pts, np.zeros((0, 3), np.int64))
    return Character(base.skeleton, (mesh,), base.clips)


def characters(data: pathlib.Path, quick: bool):
    """[(name, character, clip, weights, source)] of the available characters."""
    out = []
    for name, rel, clip in GLTF[:1] if quick else GLTF:
        path = data / rel
        if path.exists():
            ch = load_character(path)
            out.append((name, ch, ch.clip(clip) if clip else ch.clips[0], "authored", rel))
    bvh = data / "bvh" / "131_03.bvh"
    if bvh.exists():
        ch = bvh_cloud(bvh, 1_000 if quick else BVH_POINTS)
        out.append(("bvh", ch, ch.clips[0], "euclidean", "bvh/131_03.bvh + point cloud around its bones"))
    try:
        from nrpose.rigs import humanoid
    except ImportError:
        humanoid = None
    if humanoid is not None and not quick:
        ch = humanoid.humanoid()
        out.append(("humanoid", ch, ch.clips[0], "authored", "nrpose.rigs.humanoid (procedural walk)"))
    return out


def run(repeat: int = 5, quick: bool = False, data=None, log=None) -> dict:
    data = pathlib.Path(data) if data is not None else common.table1.DEFAULT_DATA
    frames = 6 if quick else FRAMES
    rounds = 1 if quick else max(repeat, 1)
    rows = []
    for name, ch, clip, weights, source in characters(data, quick):
        local = clip.sample(np.linspace(0.0, clip.duration, frames))
        posers, bind = {}, {}
        for m in METHODS:
            t = time.perf_counter()
            posers[m] = CharacterPoser(ch, method=m, weights=weights)
            bind[m] = (time.perf_counter() - t) * 1e3
            posers[m].pose(clip.sample(0.0))    # warm-up
        frame_ms = {m: [] for m in METHODS}
        batch = {m: [] for m in METHODS}
        for _ in range(rounds):
            for m in METHODS:                   # methods take turns
                t = time.perf_counter()
                fr = posers[m].pose(local)
                batch[m].append(time.perf_counter() - t)
                frame_ms[m].extend((fr.frame_ms * 1e-3).tolist())
                if not np.isfinite(fr.positions).all():
                    raise RuntimeError(f"clips {name}/{m}: non-finite positions")
        p0 = posers["nrmls"]
        for m in METHODS:
            st = common.stats(frame_ms[m])
            bt = common.stats(batch[m])
            rows.append({"character": name, "method": m, "weights": weights, "source": source,
                         "clip": clip.name, "clip_duration_s": float(clip.duration), "frames": frames,
                         "rounds": rounds, "vertices": int(p0.n), "joints": int(ch.skeleton.num_joints),
                         "bones": int(len(p0.bones)), "nrmls_slots": getattr(p0.deformer, "slots", None),
                         "bind_ms": bind[m], "frame_ms": st, "fps": 1e3 / st["median"],
                         "batch_ms": bt, "batch_fps": frames / (bt["median"] * 1e-3), "load": common.load()})
            if log:
                r = rows[-1]
                log(f"clips {name:9s} {m:5s} V={r['vertices']:6d} J={r['joints']:3d}  frame "
                    f"{st['median']:7.3f} ms  {r['fps']:8.0f} fps  (batch {r['batch_fps']:7.0f} fps)")
        del posers
    return {"rows": rows, "methods": list(METHODS), "frames_per_clip": frames, "rounds": rounds,
            "measure": "frame_ms: CharacterPoser's per-frame time (Frames.frame_ms); fps = 1000 / its "
                       "median; batch_fps: frames / median wall time of one pose(all frames) call"}
