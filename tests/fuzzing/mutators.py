"""Mutations of seed files and of command-line options.

Every mutator takes the bytes of a file, its kind (see :mod:`tests.fuzzing.seeds`)
and a :class:`random.Random`, and returns ``(new bytes, description)``; the
description (e.g. ``"number->1e308 @line 3"``) goes into reproducers.
:func:`mutate_file` picks a mutator suited to the kind:

* bytes: flips, truncation, duplicated / deleted chunks, special bytes inserted;
* text tokens: a number replaced by an extreme (:data:`EXTREMES`: 0, -1, 1e308, nan,
  inf, 2^31, 2^64, a 400-digit integer, a 5,000-character string, ...), a word
  replaced, lines duplicated, deleted, swapped or repeated 1,000 times;
* headers and counts: the numbers of a file's header (PLY ``element``, OFF counts,
  DMAT sizes, BVH ``Frames:``, binary STL triangle count, GLB lengths) tampered;
* JSON structure (handles, pose, map and glTF, also inside a .glb, which is re-packed
  with correct chunk lengths): values of the wrong type, null, extreme numbers,
  ``Infinity``, missing and extra keys, lists emptied or repeated, nesting 100 to
  100,000 levels deep; for glTF also node cycles and odd buffer URIs;
* BVH structure: a hierarchy nested thousands of joints deep;
* bake JOBS files (:func:`mutate_jobs`): a job key set to a value chosen for that key (paths
  outside the folder or of the wrong kind, outputs that collide or leave OUTDIR, huge frame
  counts and numbers, two motion keys or none), jobs repeated.

Option mutations: :data:`BAD_VALUES` for numbers and names, :data:`PATH_KINDS` for paths
(a directory, a FIFO, a read-only folder, a missing folder, an empty string, a name of
300 characters or with a newline, a path under a regular file); the runner builds them.
"""
from __future__ import annotations

import json
import random
import re
import struct

from .seeds import glb_bytes, glb_parts

__all__ = ["EXTREMES", "BAD_VALUES", "PATH_KINDS", "mutate_file", "JSON_KINDS", "TEXT_KINDS"]

EXTREMES = ["0", "-1", "1", "-0", "0.5", "1e308", "-1e308", "1e-320", "nan", "NaN", "inf", "-inf",
            "Infinity", "1e20", "1e39", "3.5e38", "-3.5e38", "1e200", "2147483647", "2147483648",
            "4294967295", "4294967296", "268435456", "18446744073709551616", "9" * 400, "-" + "9" * 30,
            "1e", "", "0x10", "1_000", "a" * 5000, "\u00e9", "1,5", "+-1"]

#: bad option values for numbers, names and choices
BAD_VALUES = ["", " ", "nan", "NaN", "inf", "-inf", "-1", "0", "-0", "1e308", "1e5", "100000", "2147483648",
              "18446744073709551616", "9" * 400, "abc", "1e-320", "0.000001", "a" * 5000, "\n", "x\ny",
              "-", "--", "all", "bone0", "Spine", "Hips->Spine", "0:100000000", "0:5:0", "5:1", "1:2:3:4",
              "-5:5", "0:0", "0:10"]

#: how a path argument can be replaced (built by the runner in the case's directory)
PATH_KINDS = ["dir", "fifo", "readonly", "missing_dir", "empty", "long", "newline", "under_file",
              "existing_input", "dotdot"]

JSON_KINDS = {"handles", "pose_json", "map_json", "gltf_embedded", "gltf_external", "jobs_json", "manifest"}
TEXT_KINDS = {"obj", "off", "ply_ascii", "stl_ascii", "xyz", "tgf", "dmat_ascii", "bvh"} | JSON_KINDS
NUMBER = re.compile(rb"-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?")
SPECIAL_BYTES = [b"\0", b"\xff", b"\n", b"\r", b"\xef\xbb\xbf", b"\xc3\x28", b"#", b"{", b"}", b"[", b"\"",
                 b" ", b"\t", b"-", b"e", b"\x00" * 64, b"\xff" * 64, b"9" * 400]


# --------------------------------------------------------------------------- bytes

def flip_bytes(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    if not data:
        return b"\xff", "flip on empty"
    b = bytearray(data)
    n = rng.choice([1, 1, 2, 4, 16])
    for _ in range(n):
        i = rng.randrange(len(b))
        b[i] = rng.choice([b[i] ^ (1 << rng.randrange(8)), rng.randrange(256), 0, 255])
    return bytes(b), f"flip {n} bytes"


def truncate(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    cut = rng.choice([0, 1, 4, 12, 20, 84, rng.randrange(len(data) + 1), len(data) // 2, len(data) - 1])
    cut = max(0, min(cut, len(data)))
    return data[:cut], f"truncate at {cut}"


def duplicate_chunk(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    if not data:
        return data * 2, "duplicate empty"
    i = rng.randrange(len(data))
    j = min(len(data), i + rng.choice([1, 8, 64, 512, 4096]))
    times = rng.choice([1, 2, 10, 1000])
    return data[:j] + data[i:j] * times + data[j:], f"duplicate bytes {i}:{j} x{times}"


def delete_chunk(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    if not data:
        return data, "delete on empty"
    i = rng.randrange(len(data))
    j = min(len(data), i + rng.choice([1, 4, 64, 1024]))
    return data[:i] + data[j:], f"delete bytes {i}:{j}"


def insert_special(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    i = rng.randrange(len(data) + 1)
    s = rng.choice(SPECIAL_BYTES)
    return data[:i] + s + data[i:], f"insert {s[:8]!r} at {i}"


BYTE_MUTATORS = [flip_bytes, truncate, duplicate_chunk, delete_chunk, insert_special]


# --------------------------------------------------------------------------- text tokens

def _lines(data: bytes) -> list[bytes]:
    return data.split(b"\n")


def replace_number(data: bytes, rng: random.Random, region: int | None = None) -> tuple[bytes, str]:
    """One number (or every number of one line, or a tenth of all) becomes an extreme.

    ``region``: only numbers in the first ``region`` bytes (a header)."""
    matches = [m for m in NUMBER.finditer(data) if region is None or m.start() < region]
    if not matches:
        return insert_special(data, rng)
    value = rng.choice(EXTREMES).encode()
    how = rng.choice(["one", "one", "one", "line", "tenth"])
    if how == "one":
        chosen = [rng.choice(matches)]
    elif how == "line":
        m = rng.choice(matches)
        lo, hi = data.rfind(b"\n", 0, m.start()), data.find(b"\n", m.end())
        hi = len(data) if hi < 0 else hi
        chosen = [x for x in matches if lo < x.start() < hi]
    else:
        chosen = [m for m in matches if rng.random() < 0.1] or [matches[0]]
    out, last = [], 0
    for m in chosen:
        out += [data[last:m.start()], value]
        last = m.end()
    out.append(data[last:])
    line = data.count(b"\n", 0, chosen[0].start()) + 1
    return b"".join(out), f"number->{value[:20].decode(errors='replace')!r} ({how}) @line {line}"


def replace_word(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    words = list(re.finditer(rb"[A-Za-z_][A-Za-z_0-9]*", data))
    if not words:
        return replace_number(data, rng)
    m = rng.choice(words)
    new = rng.choice([b"", b"x", b"ROOT", b"JOINT", b"End", b"{", b"}", b"element", b"vertex", b"face",
                      b"property", b"list", b"binary_big_endian", b"facet", b"v", b"f", b"#", b"nan",
                      b"a" * 5000, b"Hips", b"Spine", b"CHANNELS", b"MOTION", b"null", b"true", b"float",
                      b"double", b"uchar", b"int", b"uint", b"char", b"ascii", b"binary_little_endian",
                      b"Xrotation", b"Xposition", b"OFFSET", b"Site", b"solid", b"endloop", b"vertex_indices"])
    return data[:m.start()] + new + data[m.end():], f"word {m.group()[:20]!r}->{new[:20]!r}"


def line_edit(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    lines = _lines(data)
    i = rng.randrange(len(lines))
    op = rng.choice(["dup", "del", "swap", "repeat", "empty"])
    if op == "dup":
        lines.insert(i, lines[i])
    elif op == "del":
        del lines[i]
    elif op == "swap":
        j = rng.randrange(len(lines))
        lines[i], lines[j] = lines[j], lines[i]
    elif op == "repeat":
        lines[i:i + 1] = [lines[i]] * 1000
    else:
        lines[i] = b""
    return b"\n".join(lines), f"line {i + 1} {op}"


def scale_numbers(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """Every real number of the file times a factor (coordinates near float32's limit or beyond)."""
    factor = rng.choice([1e-30, 1e20, 1e38, 1e39, 1e200, -1e38])

    def scaled(m):
        try:
            return repr(float(m.group()) * factor).encode() if b"." in m.group() or b"e" in m.group() else m.group()
        except (ValueError, OverflowError):
            return m.group()
    return NUMBER.sub(scaled, data), f"reals x{factor:g}"


TEXT_MUTATORS = [replace_number, replace_number, replace_number, replace_word, line_edit, scale_numbers]


# --------------------------------------------------------------------------- headers and counts

def tamper_header(data: bytes, kind: str, rng: random.Random) -> tuple[bytes, str]:
    """A number of the file's header (its counts and sizes) becomes an extreme."""
    if kind == "stl_binary" and len(data) >= 84:
        n = rng.choice([0, 1, 2 ** 31, 2 ** 32 - 1, 2 ** 28, (struct.unpack_from("<I", data, 80)[0] + 1) % 2 ** 32])
        return data[:80] + struct.pack("<I", n) + data[84:], f"STL triangle count {n}"
    if kind == "glb" and len(data) >= 20:
        field = rng.choice([8, 12])
        n = rng.choice([0, 1, 12, 2 ** 31, 2 ** 32 - 1, len(data) + 4, len(data) - 4])
        return data[:field] + struct.pack("<I", n) + data[field + 4:], f"GLB u32 at {field} = {n}"
    if kind == "dmat_binary" or kind == "dmat_ascii":
        head = data.split(b"\n", 2)
        k = 1 if kind == "dmat_binary" and len(head) > 1 else 0
        cols = rng.choice([b"0", b"1", b"4", b"-1", b"4294967296", b"2147483648", b"100000", b"20"])
        rows = rng.choice([b"0", b"1", b"4", b"20", b"4294967296", b"100000", b"-3"])
        head[k] = cols + b" " + rows
        return b"\n".join(head), f"DMAT header line {k + 1} -> {cols.decode()} {rows.decode()}"
    end = {"ply_ascii": data.find(b"end_header"), "ply_binary": data.find(b"end_header"),
           "off": len(b"\n".join(_lines(data)[:2])), "bvh": len(data)}.get(kind)
    if kind == "bvh":
        frames = re.search(rb"Frames:\s*(\d+)", data)
        if frames and rng.random() < 0.7:
            v = rng.choice(EXTREMES).encode()
            return data[:frames.start(1)] + v + data[frames.end(1):], f"BVH Frames: {v[:20]!r}"
        ft = re.search(rb"Frame Time:\s*(\S+)", data)
        if ft:
            v = rng.choice(EXTREMES).encode()
            return data[:ft.start(1)] + v + data[ft.end(1):], f"BVH Frame Time: {v[:20]!r}"
    if end is None or end < 0:
        end = min(len(data), 200)
    return replace_number(data, rng, region=end)


# --------------------------------------------------------------------------- JSON structure

WRONG_VALUES = [None, True, False, "0", "x", "", -1, 0, 1, 1.5, 2 ** 28, 2 ** 31, 2 ** 32, 2 ** 64, 10 ** 400,
                1e30, 1e308, -1e308, float("inf"), float("-inf"), float("nan"), [], {}, [0], [None],
                [1e308, 0, 0, 1], [0, 0, 0, 0], [1e20, 1e20, 1e20], {"a": 1}, "a" * 5000, "%00", "../x.bin",
                "/", "data:,", "data:application/octet-stream;base64,!!!"]


def _paths(doc, prefix=()):
    """Every (path, value) in a JSON document, depth first."""
    yield prefix, doc
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:64]):
            yield from _paths(v, prefix + (i,))


def _set(doc, path, value):
    if not path:
        return value
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    parent[path[-1]] = value
    return doc


def _get(doc, path):
    for k in path:
        doc = doc[k]
    return doc


NEST = "\u2063NEST\u2063"


def mutate_json_doc(doc, kind: str, rng: random.Random) -> tuple[object, str, int]:
    """A structurally mutated copy of ``doc``, a description and a nesting depth (0 or
    the depth of nested lists to put where the placeholder string :data:`NEST` is)."""
    doc = json.loads(json.dumps(doc))
    paths = list(_paths(doc))
    path, value = rng.choice(paths[1:] or paths)
    op = rng.choice(["wrong", "wrong", "wrong", "delete", "extra", "nest", "empty", "repeat", "root"]
                    + (["cycle", "index", "index", "nobuffer"] if kind.startswith("gltf") or kind == "glb" else []))
    where = "/".join(map(str, path))
    if op == "wrong":
        new = rng.choice(WRONG_VALUES)
        return _set(doc, path, new), f"{where} = {str(new)[:30]}", 0
    if op == "delete" and path:
        parent = _get(doc, path[:-1])
        del parent[path[-1]]
        return doc, f"delete {where}", 0
    containers = [v for _, v in paths if isinstance(v, (dict, list))]
    if op == "extra" and containers:
        target = rng.choice(containers)
        if isinstance(target, dict):
            target[rng.choice(["extra", "", "alpha", "points", "rotations", "uri", "extensions", "extras"])] = \
                rng.choice(WRONG_VALUES)
        else:
            target.append(rng.choice(WRONG_VALUES))
        return doc, "extra key/element", 0
    if op == "nest":
        depth = rng.choice([100, 1000, 3000, 100000])
        return _set(doc, path, NEST), f"{where} nested {depth} deep", depth
    if op == "empty":
        return _set(doc, path, [] if isinstance(value, list) else {}), f"{where} emptied", 0
    if op == "repeat":
        lists = [(p, v) for p, v in paths if isinstance(v, list) and v]
        if lists:
            p, v = rng.choice(lists)
            times = rng.choice([2, 100, 10000])
            return _set(doc, p, v * times), f"{'/'.join(map(str, p))} repeated x{times}", 0
    if op == "root":
        new = rng.choice([[], "x", 1, None, [doc], {"": doc}])
        return new, f"root = {str(new)[:30]}", 0
    if op == "cycle" and isinstance(doc, dict) and isinstance(doc.get("nodes"), list) and doc["nodes"]:
        nodes = doc["nodes"]
        a, b = rng.randrange(len(nodes)), rng.randrange(len(nodes))
        if isinstance(nodes[a], dict):
            nodes[a]["children"] = [b]
        return doc, f"nodes/{a}/children = [{b}]", 0
    if op == "nobuffer" and isinstance(doc, dict) and isinstance(doc.get("accessors"), list) and doc["accessors"]:
        a = rng.randrange(len(doc["accessors"]))
        acc = doc["accessors"][a]
        if isinstance(acc, dict):
            acc.pop("bufferView", None)
            acc["count"] = rng.choice([2 ** 20, 2 ** 28, 2 ** 31, 2 ** 32 - 1])
        return doc, f"accessors/{a}: no bufferView, count {acc.get('count') if isinstance(acc, dict) else '?'}", 0
    if op == "index":
        ints = [(p, v) for p, v in paths if isinstance(v, int) and not isinstance(v, bool)]
        if ints:
            p, v = rng.choice(ints)
            new = rng.choice([-1, v + 1, v + 1000, 2 ** 28, 2 ** 30, 2 ** 31, 2 ** 32, 2 ** 63, 1e30, float("inf"),
                              str(v), None, [v], True, 5124, 5130, 0])
            return _set(doc, p, new), f"{'/'.join(map(str, p))}: {v} -> {str(new)[:30]}", 0
    new = rng.choice(WRONG_VALUES)
    return _set(doc, path, new), f"{where} = {str(new)[:30]}", 0


def json_text(doc, depth: int) -> str:
    text = json.dumps(doc, allow_nan=True)
    if depth:
        text = text.replace(json.dumps(NEST), "[" * depth + "0" + "]" * depth, 1)
    return text


def mutate_json(data: bytes, kind: str, rng: random.Random) -> tuple[bytes, str]:
    try:
        doc = json.loads(data)
    except (ValueError, RecursionError):
        return rng.choice(TEXT_MUTATORS)(data, rng)
    if kind == "jobs_json" and rng.random() < 0.6:
        new, what = mutate_jobs(doc, rng)
        return json.dumps(new, allow_nan=True).encode(), "jobs: " + what
    new, what, depth = mutate_json_doc(doc, kind, rng)
    return json_text(new, depth).encode(), "json: " + what


def mutate_glb(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    parts = glb_parts(data)
    r = rng.random()
    if parts is None or r < 0.25:
        return rng.choice(BYTE_MUTATORS + [lambda d, g: tamper_header(d, "glb", g)])(data, rng)
    text, blob = parts
    if r < 0.4 and blob:
        new_blob, what = rng.choice([flip_bytes, truncate, delete_chunk])(blob, rng)
        return glb_bytes(None, new_blob, text), "BIN chunk: " + what
    if r < 0.45:
        return glb_bytes(None, None, text), "BIN chunk dropped"
    try:
        doc = json.loads(text)
    except (ValueError, RecursionError):
        return rng.choice(BYTE_MUTATORS)(data, rng)
    new, what, depth = mutate_json_doc(doc, "glb", rng)
    return glb_bytes(None, blob, json_text(new, depth)), "glb json: " + what


# --------------------------------------------------------------------------- BVH structure

def deep_bvh(rng: random.Random) -> tuple[bytes, str]:
    depth = rng.choice([100, 1000, 3000, 20000])
    head = ["HIERARCHY", "ROOT Hips", "{", "OFFSET 0 0 0",
            "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"]
    body = [f"JOINT j{i}\n{{\nOFFSET 0 0.01 0\nCHANNELS 3 Zrotation Xrotation Yrotation" for i in range(depth)]
    tail = ["End Site", "{", "OFFSET 0 0.01 0", "}"] + ["}"] * (depth + 1)
    motion = ["MOTION", "Frames: 1", "Frame Time: 0.1", " ".join(["0"] * (6 + 3 * depth))]
    return "\n".join(head + body + tail + motion).encode(), f"BVH nested {depth} joints deep"


# --------------------------------------------------------------------------- bake JOBS files

#: values a job key may get, by key (the other keys of :data:`JOB_VALUES` and WRONG_VALUES too)
JOB_VALUES = {
    "output": ["../x.npz", "/tmp/nrpose-fuzz-abs.npz", "manifest.json", ".bake-tmp/x.npz", "A/BEND.NPZ", "a",
               "a/bend.npz/x.npz", "b.glb/x", "", ".", "x.txt", "x.NPZ", "a\nb.npz", "a" * 300 + ".npz",
               "dir/", "c/frames/frame_0000.ply", "./rest.npz", "a//bend.npz", "é.npz", "nul\u0000.npz"],
    "character": ["missing.glb", "/dev/null", ".", "rig.bvh", "pose.json", "jobs.json", "body.obj", "../jobs/body.glb",
                  "/", "map.json"],
    "skeleton": ["rig.bvh", "rig.tgf", "body.glb", "missing.tgf", "pose.json"],
    "clip": ["nope", "", "bend ", "BEND", "a" * 5000],
    "motion": ["rig.bvh", "pose.dmat", "pose.json", "body.glb", "missing.bvh", "jobs.json"],
    "pose": ["pose.json", "pose.dmat", "rig.bvh", "map.json", "missing.json"],
    "rest": [True, False, 1, "true"],
    "retarget": [{"source": "rig.bvh"}, {"source": "body.glb"}, {"source": "rig.bvh", "in_place": True, "root": "keep"},
                 {"source": "rig.bvh", "map": "pose.json"}, {"source": "rig.bvh", "source_clip": "nope"},
                 {"source": "rig.tgf"}, {"source": "rig.bvh", "root": "in-place", "force": True}, {}, "rig.bvh"],
    "time": [1e308, -1, [0, 1e308], [], [0.5, 0.1], list(range(0, 20000)), [float("nan")], 1e6, 1e-300],
    "frames": ["0:100000000", "0:3:0", "5:1", "0:2:1:1", "-1:2", "0:999999", "0:20000", "a:b", "0:" + "9" * 400],
    "fps": [1e5, 1e6, 1e308, 0, -5, 1e-300, 2000, 10 ** 400, True],
    "method": ["cor", "nrmls", "x", None],
    "weights": ["heat", "exact", "authored", "x"],
    "alpha": [0, -1, 1e308, 50, float("nan")],
    "blend": ["paper", "relative", "x"],
    "backend": ["opencl", "cuda"],
    "format": ["obj", "stl", None],
    "quantize": [True, 1],
}


def mutate_jobs(doc, rng: random.Random) -> tuple[object, str]:
    """A bake JOBS document with one job (or the defaults) changed as a bake user might get it
    wrong (:data:`JOB_VALUES`), or its jobs repeated / made to collide."""
    doc = json.loads(json.dumps(doc))
    jobs = doc.get("jobs") if isinstance(doc, dict) else None
    if not isinstance(jobs, list) or not jobs:
        return doc, "jobs: unchanged (no jobs)"
    op = rng.random()
    if op < 0.1:
        times = rng.choice([2, 50, 5000])
        doc["jobs"] = jobs * times
        return doc, f"jobs repeated x{times}"
    if op < 0.2:
        i = rng.randrange(len(jobs))
        job = dict(jobs[i]) if isinstance(jobs[i], dict) else {}
        first = str(jobs[0].get("output", "x")) if isinstance(jobs[0], dict) else "x"
        job["output"] = rng.choice([first, first.upper(), first + "/inner.npz"])
        jobs.append(job)
        return doc, f"jobs[{len(jobs) - 1}]: a copy of jobs[{i}] writing {str(job['output'])[:40]!r}"
    target = doc.setdefault("defaults", {}) if op < 0.3 else rng.choice(jobs)
    where = "defaults" if op < 0.3 else f"jobs[{jobs.index(target)}]"
    if not isinstance(target, dict):
        return doc, f"{where}: unchanged (not an object)"
    key = rng.choice(list(JOB_VALUES))
    value = rng.choice(JOB_VALUES[key] + [rng.choice(WRONG_VALUES)])
    target[key] = value
    return doc, f"{where}/{key} = {str(value)[:40]}"


# --------------------------------------------------------------------------- dispatch

def mutate_file(data: bytes, kind: str, rng: random.Random) -> tuple[bytes, str]:
    """One mutation of ``data`` (a file of ``kind``) chosen for its kind."""
    r = rng.random()
    if kind == "glb":
        return mutate_glb(data, rng)
    if kind in JSON_KINDS and r < 0.6:
        return mutate_json(data, kind, rng)
    if kind == "bvh" and r < 0.08:
        return deep_bvh(rng)
    if r < 0.75 and (kind in TEXT_KINDS or kind == "ply_binary"):
        if rng.random() < 0.3:
            return tamper_header(data, kind, rng)
        return rng.choice(TEXT_MUTATORS)(data, rng)
    if r < 0.85 and kind in ("stl_binary", "dmat_binary", "dmat_ascii", "ply_binary"):
        return tamper_header(data, kind, rng)
    return rng.choice(BYTE_MUTATORS)(data, rng)
