"""The defects issue 32 lists, as explicit cases over the seeds (regression cases).

:func:`known_cases` returns ``{name: Case}``; each must keep the contract once the
fixes land (exit 0 with a valid output, or exit 2 with one line and nothing left).
``python -m tests.fuzzing.known`` runs them all and prints each outcome.
"""
from __future__ import annotations

import base64
import json
import sys

import numpy as np

from .cases import Case
from .seeds import BAKE_INPUTS, Seed, glb_bytes, gltf_document, make_seeds

__all__ = ["known_cases", "bake_files", "MUST_REJECT"]

#: cases whose exit 0 is itself the defect (the input is invalid)
MUST_REJECT = {"glTF -Infinity in an unread field (retarget)", "pose --alpha nan (authored)", "pose --alpha -1 (authored)", "glTF index as a string",
               "glTF POSITION index as a string", "pose -o '' (empty output name)",
               "glTF clip not played past its bufferView (posed copy)"}


def _gltf(mutate, blob_mutate=None, kind: str = "glb") -> dict:
    """Files of a (mutated) seed glTF at ``in/c/body.glb`` (or .gltf, buffer embedded)."""
    doc, blob = gltf_document(None)
    blob = bytearray(blob)
    if blob_mutate:
        blob_mutate(doc, blob)
    mutate(doc)
    if kind == "glb":
        return {"in/c/body.glb": glb_bytes(None, bytes(blob), json.dumps(doc, allow_nan=True))}
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(bytes(blob)).decode()
    return {"in/c/body.gltf": json.dumps(doc, allow_nan=True).encode()}


def _set(path, value):
    def apply(doc):
        node = doc
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value
    return apply


def _zero_view(view):
    def apply(doc, blob):
        v = doc["bufferViews"][view]
        blob[v["byteOffset"]:v["byteOffset"] + v["byteLength"]] = bytes(v["byteLength"])
    return apply


def _case(name, argv, files, **kw) -> Case:
    return Case(index=0, command=argv[0], template=f"known:{name}", argv=argv, files=files, **kw)


def known_cases(seeds: dict[str, Seed] | None = None) -> dict[str, Case]:
    S = seeds or make_seeds()
    obj, xyz, handles = S["obj"].data, S["xyz"].data, S["handles"].data
    tgf, bvh, glb = S["tgf"].data, S["bvh"].data, S["glb"].data
    mesh_h = {"in/m/body.obj": obj, "in/h/handles.json": handles}
    deform = ["deform", "in/m/body.obj", "-H", "in/h/handles.json", "-o", "out/o.ply"]
    pose_glb = ["pose", "in/c/body.glb", "--clip", "bend", "--fps", "5", "-o", "out/o.npz", "--backend", "numpy"]
    retarget = ["retarget", "in/s/rig.bvh", "in/c/body.glb", "--fps", "5", "-o", "out/r.glb"]
    deep = lambda d: ("[" * d + "0" + "]" * d)  # noqa: E731
    scaled = lambda data, f: b"\n".join(  # noqa: E731
        b" ".join(repr(float(t) * f).encode() if i and line.startswith(b"v ") else t
                  for i, t in enumerate(line.split())) for line in data.split(b"\n"))
    far = json.loads(handles)
    for seg in far["segments"]:
        seg["rest"] = (np.asarray(seg["rest"]) * 1e20).tolist()
        seg["pose"] = (np.asarray(seg["pose"]) * 1e20).tolist()
    far_pts = dict(far, segments=[], points=[{"rest": [1e20, 0, 0], "pose": [1e20, 1, 0]}])
    obj_lines = obj.decode().splitlines()
    faces = [ln for ln in obj_lines if ln.startswith("f ")]
    c = {
        "empty --clip": _case("empty-clip", ["pose", "in/c/body.glb", "--clip", "", "-o", "out/o.npz"],
                              {"in/c/body.glb": glb}),
        "handles JSON nested 100000 deep": _case("deep-handles", deform, {"in/m/body.obj": obj,
                                                 "in/h/handles.json": deep(100000).encode()}),
        "pose JSON nested 5000 deep": _case("deep-pose", ["pose", "in/c/body.glb", "--pose", "in/p/pose.json",
                                            "-o", "out/o.npz"], {"in/c/body.glb": glb,
                                            "in/p/pose.json": ('{"rotations": ' + deep(5000) + "}").encode()}),
        "map JSON nested 5000 deep": _case("deep-map", retarget + ["--map", "in/m/map.json"],
                                           {"in/s/rig.bvh": bvh, "in/c/body.glb": glb,
                                            "in/m/map.json": deep(5000).encode()}),
        "glTF nested 5000 deep": _case("deep-gltf", ["info", "in/c/body.glb"],
                                       {"in/c/body.glb": glb_bytes(None, None, '{"asset": ' + deep(5000) + "}")}),
        "BVH 3000 nested joints": _case("deep-bvh", ["info", "in/s/rig.bvh"], {"in/s/rig.bvh": _deep_bvh(3000)}),
        "glTF bufferView.buffer null": _case("view-buffer-null", pose_glb,
                                             _gltf(_set(("bufferViews", 0, "buffer"), None))),
        "glTF channel sampler null": _case("sampler-null", pose_glb,
                                           _gltf(_set(("animations", 0, "channels", 0, "sampler"), None))),
        "glTF index as a string": _case("index-string", pose_glb, _gltf(_set(("accessors", 0, "bufferView"), "0"))),
        "glTF -Infinity in an unread field (retarget)": _case("extra-infinity", retarget, {
            "in/s/rig.bvh": bvh, **_gltf(_set(("bufferViews", 0, "extensions"), float("-inf")))}),
        "glTF POSITION without min/max (retarget)": _case("no-min-max", retarget, {
            "in/s/rig.bvh": bvh, **_gltf(lambda d: [a.pop(k, None) for a in d["accessors"] for k in ("min", "max")])}),
        "glTF POSITION index as a string": _case("position-string", pose_glb, _gltf(
            _set(("meshes", 0, "primitives", 0, "attributes", "POSITION"), "0"))),
        "glTF count true": _case("count-true", pose_glb, _gltf(_set(("accessors", 0, "count"), True))),
        "glTF Infinity in an integer field": _case("count-inf", pose_glb,
                                                   _gltf(_set(("accessors", 1, "count"), float("inf")))),
        "glTF skin joint 1e30": _case("joint-1e30", pose_glb, _gltf(_set(("skins", 0, "joints", 1), 1e30))),
        "glTF node rotation [1e308, 0, 0, 1]": _case("rotation-1e308", pose_glb,
                                                     _gltf(_set(("nodes", 1, "rotation"), [1e308, 0, 0, 1]))),
        "glTF joint scale 1e-320 (nrmls, numpy)": _case("scale-subnormal", [
            "pose", "in/c/body.gltf", "--rest", "--weights", "authored", "-o", "out/o.npz", "--backend", "numpy",
            "--method", "nrmls"], _gltf(_set(("nodes", 1, "scale"), [1e-320, 1, 1]), kind="gltf")),
        "glTF zero animation keys": _case("zero-keys", pose_glb, _gltf(lambda d: None, _zero_view(6))),
        "glTF clip not played past its bufferView (posed copy)": _case("unplayed-clip-range", [
            "pose", "in/c/body.glb", "--rest", "-o", "out/o.glb", "--backend", "numpy"],
            _gltf(_set(("accessors", 5, "count"), 1011))),
        "glTF buffer URI with %00": _case("uri-nul", ["info", "in/c/body.gltf"],
                                          {"in/c/body.gltf": json.dumps(_doc_with(("buffers", 0, "uri"),
                                                                                  "body%00.bin")).encode(),
                                           "in/c/body.bin": bytes(gltf_document(None)[1])}),
        "PLY property list float int": _case("ply-list-float", ["deform", "in/m/body.ply", "-H", "in/h/handles.json",
                                                                "-o", "out/o.ply"],
                                             {"in/m/body.ply": S["ply_ascii"].data.replace(b"list uchar int",
                                                                                           b"list float int"),
                                              "in/h/handles.json": handles}),
        "binary PLY property list float int": _case("plyb-list-float", ["deform", "in/m/body.ply", "-H",
                                                                        "in/h/handles.json", "-o", "out/o.ply"],
                                                    {"in/m/body.ply": S["ply_binary"].data.replace(b"list uchar int",
                                                                                                   b"list float int"),
                                                     "in/h/handles.json": handles}),
        "knn weights on a cloud x1e200": _case("knn-1e200", ["deform", "in/m/cloud.xyz", "-H", "in/h/handles.json",
                                                            "-o", "out/o.xyz", "--weights", "knn"],
                                               {"in/m/cloud.xyz": b"\n".join(
                                                   b" ".join(repr(float(t) * 1e200).encode() for t in ln.split())
                                                   for ln in xyz.strip().split(b"\n")), "in/h/handles.json": handles}),
        "far handles with heat weights": _case("heat-far", deform + ["--weights", "heat", "--backend", "numpy"],
                                               {"in/m/body.obj": obj,
                                                "in/h/handles.json": json.dumps(far_pts).encode()}),
        "BVH huge motion values (retarget)": _case("bvh-huge-motion", retarget,
                                                   {"in/s/rig.bvh": _bvh_motion(bvh, "1e300"), "in/c/body.glb": glb}),
        "handles at 1e20 (opencl)": _case("handles-1e20", deform + ["--backend", "opencl"],
                                          {"in/m/body.obj": obj, "in/h/handles.json": json.dumps(far).encode()}),
        "vertices x1e38 (opencl)": _case("vertices-1e38", deform + ["--backend", "opencl"],
                                         {"in/m/body.obj": scaled(obj, 1e38), "in/h/handles.json": handles}),
        "pose translation 1e308": _case("pose-translation-1e308",
                                        ["pose", "in/c/body.glb", "--pose", "in/p/pose.json", "-o", "out/o.npz"],
                                        {"in/c/body.glb": glb, "in/p/pose.json":
                                         b'{"translations": {"Spine": [1e308, 0, 0]}}'}),
        "pose --alpha nan (authored)": _case("alpha-nan", pose_glb + ["--alpha", "nan"], {"in/c/body.glb": glb}),
        "pose --alpha -1 (authored)": _case("alpha-neg", pose_glb + ["--alpha", "-1"], {"in/c/body.glb": glb}),
        "exact weights, repeated face": _case("exact-repeated-face", deform + ["--weights", "exact"],
                                              {"in/m/body.obj": (obj.decode() + faces[0] + "\n").encode(),
                                               "in/h/handles.json": handles}),
        "exact weights, degenerate face": _case("exact-degenerate-face", deform + ["--weights", "exact"],
                                                {"in/m/body.obj": (obj.decode() + "f 1 1 2\n").encode(),
                                                 "in/h/handles.json": handles}),
        "DMAT header 4294967296 0": _case("dmat-4g", ["pose", "in/m/body.obj", "--skeleton", "in/s/rig.tgf", "--pose",
                                                      "in/p/pose.dmat", "--weights", "euclidean", "-o", "out/o.npz"],
                                          {"in/m/body.obj": obj, "in/s/rig.tgf": tgf,
                                           "in/p/pose.dmat": b"4294967296 0\n0\n"}),
        "DMAT not numbers (libigl prints)": _case("dmat-text", ["pose", "in/m/body.obj", "--skeleton", "in/s/rig.tgf",
                                                                "--pose", "in/p/pose.dmat", "--weights", "euclidean",
                                                                "-o", "out/o.npz"],
                                                  {"in/m/body.obj": obj, "in/s/rig.tgf": tgf,
                                                   "in/p/pose.dmat": b"1 20\nabc\n"}),
        "accessor without bufferView, count 2^28": _case("count-2^28", pose_glb, _gltf(_no_view(5, 2 ** 28))),
        "accessor without bufferView, count 2^31": _case("count-2^31", pose_glb, _gltf(_no_view(0, 2 ** 31))),
        "pose --fps 1e5 -o x.glb": _case("fps-1e5-glb", ["pose", "in/c/body.glb", "--clip", "bend", "--fps", "1e5",
                                                         "-o", "out/x.glb", "--backend", "numpy"],
                                         {"in/c/body.glb": glb}),
        "pose --fps 1e5 -o frames/": _case("fps-1e5-dir", ["pose", "in/c/body.glb", "--clip", "bend", "--fps", "1e5",
                                                           "-o", "out/frames", "--backend", "numpy"],
                                           {"in/c/body.glb": glb}),
        "skin joints in a cycle with the node tree": _case("joint-cycle", pose_glb,
                                                           _gltf(_set(("nodes", 3, "children"), [0]))),
        "pose -o '' (empty output name)": _case("empty-output", ["pose", "in/c/body.glb", "--rest", "-o", "",
                                                                 "--backend", "numpy"], {"in/c/body.glb": glb}),
        "--png into a read-only folder": _case("png-readonly", deform + ["--png", "ro/p.png"], dict(mesh_h),
                                               specials={"ro/p.png": "readonly"}),
        "pose frames with a full disk": _case("frames-full-disk", ["pose", "in/c/body.glb", "--clip", "bend", "--fps",
                                                                   "5", "-o", "out/frames", "--backend", "numpy"],
                                              {"in/c/body.glb": glb}, fsize=100),
        "retarget: bufferView 1 GB past its buffer": _case("view-1gb", ["retarget", "in/s/rig.bvh", "in/c/body.glb",
                                                                        "--fps", "5", "-o", "out/r.glb"],
                                                           {"in/s/rig.bvh": bvh, **_gltf(_extra_view(2 ** 30))}),
        "heat weights on a clean seed mesh": _case("heat-clean", deform + ["--weights", "heat", "--backend", "numpy"],
                                                   dict(mesh_h)),
        "heat weights on the STL seed": _case("heat-stl", ["deform", "in/m/body.stl", "-H", "in/h/handles.json",
                                                           "-o", "out/o.ply", "--weights", "heat"],
                                              {"in/m/body.stl": S["stl_binary"].data, "in/h/handles.json": handles}),
        "handles with 20,000 segments (opencl)": _case("segments-20000", deform + ["--backend", "opencl"],
                                                       {"in/m/body.obj": obj, "in/h/handles.json": json.dumps(
                                                           dict(json.loads(handles), segments=json.loads(handles)[
                                                               "segments"] * 10000)).encode()}),
        "exact weights, an edge in three faces": _case("exact-nonmanifold", deform + ["--weights", "exact"],
                                                       {"in/m/body.obj": (obj.decode() + _fin(
                                                            faces[0], obj.count(b"\nv ") + 1)).encode(),
                                                        "in/h/handles.json": handles}),
        "exact weights, a sliver triangle": _case("exact-sliver", deform + ["--weights", "exact"],
                                                  {"in/m/body.obj": _sliver(obj), "in/h/handles.json": handles}),
        "exact weights on a mesh x1e-30": _case("exact-tiny", deform + ["--weights", "exact"],
                                                {"in/m/body.obj": scaled(obj, 1e-30), "in/h/handles.json": handles}),
        "glTF primitives repeated 10000 times": _case("primitives-x10000", ["pose", "in/c/body.glb", "--rest",
                                                                             "--weights", "heat", "-o", "out/o.glb"],
                                                      _gltf(lambda d: d["meshes"][0].update(
                                                          primitives=d["meshes"][0]["primitives"] * 10000))),
        "glTF skin joints a number": _case("skin-joints-number", retarget, {"in/s/rig.bvh": bvh,
                                           **_gltf(_set(("skins", 0, "joints"), 1.5))}),
        "bake JOBS file a FIFO": _case("bake-fifo", ["bake", "out/jobs.json", "-o", "out/bake", "--workers", "1"],
                                       {}, specials={"out/jobs.json": "fifo"}),
        "bake job of 100,001 frames": _case("bake-fps-1e5", ["bake", "in/j/jobs.json", "-o", "out/bake", "--workers",
                                                             "1"], bake_files(S, {"fps": 100000})),
        "bake with a full disk": _case("bake-full-disk", ["bake", "in/j/jobs.json", "-o", "out/bake", "--workers", "1"],
                                       bake_files(S, {}), fsize=0),
        "bake JOBS file nested 3000 deep": _case("bake-deep", ["bake", "in/j/jobs.json", "-o", "out/bake"],
                                                 {"in/j/jobs.json": ('{"jobs": ' + deep(3000) + "}").encode()}),
        "bake job time of 400 digits": _case("bake-time-400", ["bake", "in/j/jobs.json", "-o", "out/bake"],
                                             bake_files(S, {"time": [0, int("9" * 400)]})),
        "bake --resume, a manifest nested 100000 deep": _case(
            "bake-deep-manifest", ["bake", "in/j/jobs.json", "-o", "in/j", "--workers", "1", "--resume"],
            dict(bake_files(S, {}), **{"in/j/manifest.json": ('{"outputs": ' + deep(100000) + "}").encode()})),
        "bake --resume, a manifest entry a number": _case(
            "bake-manifest-entry", ["bake", "in/j/jobs.json", "-o", "in/j", "--workers", "1", "--resume"],
            dict(bake_files(S, {}), **{"in/j/manifest.json": b'{"outputs": {"a.npz": 1}}'})),
        "demo --frames of 400 digits": _case("demo-frames-400", ["demo", "--out", "out/d", "--frames", "9" * 400], {}),
        "demo --repeat 100000": _case("demo-repeat", ["demo", "--out", "out/d", "--frames", "1", "--repeat",
                                                      "100000"], {}),
        "demo --frames 20000": _case("demo-frames", ["demo", "--out", "out/d", "--frames", "20000"], {}),
        "info | head (broken pipe)": _case("broken-pipe", ["info", "in/c/body.glb"], {"in/c/body.glb": glb},
                                           broken_pipe=True),
    }
    return c


def _fin(face: str, vertices: int) -> str:
    """An OBJ face line on the first edge of ``face`` and the last vertex (that edge then in three faces)."""
    a, b, _ = face.split()[1:]
    return f"f {a} {b} {vertices}\n"


def _sliver(obj: bytes) -> bytes:
    """The OBJ with the first vertex of its first face moved next to the middle of that face's other
    two vertices (a sliver triangle, its height 1e-14 of its longest edge)."""
    lines = obj.decode().splitlines()
    verts = [i for i, ln in enumerate(lines) if ln.startswith("v ")]
    a, b, c = (int(t) - 1 for t in next(ln for ln in lines if ln.startswith("f ")).split()[1:])
    pb, pc = (np.array(lines[verts[k]].split()[1:], float) for k in (b, c))
    mid = (pb + pc) / 2 + 1e-14 * np.linalg.norm(pc - pb) * np.array([0.6, 0.0, 0.8])
    lines[verts[a]] = "v " + " ".join(repr(float(x)) for x in mid)
    return ("\n".join(lines) + "\n").encode()


def bake_files(S, defaults: dict, jobs: list | None = None) -> dict:
    """A JOBS file at ``in/j/jobs.json`` (``jobs``, default two jobs writing .npz and .glb of the
    seed clip, over the seed defaults updated with ``defaults``) and the seed files jobs read."""
    jobs = jobs or [{"clip": "bend", "output": "a.npz"}, {"clip": "bend", "output": "b.glb"}]
    doc = {"defaults": dict({"character": "body.glb", "fps": 5, "backend": "numpy"}, **defaults), "jobs": jobs}
    return {"in/j/jobs.json": json.dumps(doc).encode(),
            **{f"in/j/{name}": S[kind].data for name, kind in BAKE_INPUTS.items()}}


def _doc_with(path, value) -> dict:
    doc, _ = gltf_document("body.bin")
    _set(path, value)(doc)
    return doc


def _no_view(accessor: int, count: int):
    def apply(doc):
        doc["accessors"][accessor].pop("bufferView")
        doc["accessors"][accessor]["count"] = count
    return apply


def _extra_view(offset: int):
    def apply(doc):
        doc["bufferViews"].append({"buffer": 0, "byteOffset": offset, "byteLength": 4})
    return apply


def _deep_bvh(depth: int) -> bytes:
    head = ["HIERARCHY", "ROOT Hips", "{", "OFFSET 0 0 0",
            "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"]
    body = [f"JOINT j{i}\n{{\nOFFSET 0 0.01 0\nCHANNELS 3 Zrotation Xrotation Yrotation" for i in range(depth)]
    tail = ["End Site", "{", "OFFSET 0 0.01 0", "}"] + ["}"] * (depth + 1)
    motion = ["MOTION", "Frames: 1", "Frame Time: 0.1", " ".join(["0"] * (6 + 3 * depth))]
    return "\n".join(head + body + tail + motion).encode()


def _bvh_motion(bvh: bytes, value: str) -> bytes:
    head, motion = bvh.split(b"MOTION", 1)
    lines = motion.split(b"\n")
    out = []
    for ln in lines:
        parts = ln.split()
        if len(parts) > 6 and not ln.startswith((b"Frame", b"Frames")):
            parts = parts[:3] + [value.encode()] * (len(parts) - 3)
            ln = b" ".join(parts)
        out.append(ln)
    return head + b"MOTION" + b"\n".join(out)


if __name__ == "__main__":
    from .runner import Runner

    runner = Runner()
    try:
        for name, case in known_cases().items():
            if len(sys.argv) > 1 and not any(a in name for a in sys.argv[1:]):
                continue
            o, _ = runner.run(case)
            if name in MUST_REJECT and o.outcome == "accepted":
                o.outcome = "invalid-accepted"
            tail = o.stderr.strip().splitlines()[-1][:110] if o.stderr.strip() else ""
            print(f"{name:<45} {o.outcome:<20} exit {o.exit} {o.seconds:6.2f}s | {tail}"
                  + (f" | {o.problems[0][:80]}" if o.problems else ""), flush=True)
    finally:
        runner.close()
