"""Markdown report of a fuzz summary: the totals by command and input kind
(:func:`totals_table`) and the distinct defects, grouped by root cause.

    python -m tests.fuzzing.report SUMMARY.json > DEFECTS.md

The root-cause classes are issue 32's: nesting/recursion, glTF field types, sizes vs
bytes, work/output budget, float32 ranges, libigl guards and prints, outputs committed
together, broken pipe (and "other" for the rest). A defect's class is chosen from its
contract class, exception, message and mutation; the module where the fix belongs is its
last nrpose frame, mapped to the package layout of issue 29.
"""
from __future__ import annotations

import json
import re
import sys

__all__ = ["root_cause", "markdown", "normalise", "totals_table", "NEW_HOME"]

ROOTS = {
    "nesting": "Nesting / recursion (one bounded, iterative reader for nested structures)",
    "gltf-types": "glTF field types (every index, count, offset, enum type-checked)",
    "sizes": "Sizes vs bytes (counts checked against the bytes that exist before allocating)",
    "budget": "Work / output budget (frames x vertices, files written; checked before work)",
    "float32": "Float32 ranges (values that overflow the kernels refused where they enter)",
    "libigl": "libigl guards and its stdout/stderr prints (and other multi-line stderr)",
    "commit": "Outputs committed together (all outputs checked writable first, nothing left behind)",
    "pipe": "Broken pipe",
    "other": "Other",
}

#: where a module of the old layout lives after issue 29 (file to fix)
NEW_HOME = {
    "nrpose/formats/gltf.py": "nrpose/io/gltf_read.py", "nrpose/jsonfile.py": "nrpose/io/jsonfile.py",
    "nrpose/formats/bvh.py": "nrpose/io/bvh_read.py", "nrpose/formats/bvh_write.py": "nrpose/io/bvh_write.py",
    "nrpose/meshio.py": "nrpose/io/meshes.py", "nrpose/formats/tgf.py": "nrpose/io/tgf.py",
    "nrpose/handles.py": "nrpose/io/poses.py (parse) / nrpose/model/handles.py",
    "nrpose/character.py": "nrpose/io/poses.py (load_pose) / nrpose/model/character.py",
    "nrpose/retargetcli.py": "nrpose/cli/retarget.py + nrpose/io/gltf_write.py",
    "nrpose/cli.py": "nrpose/cli/*.py", "nrpose/posing.py": "nrpose/pose/poser.py",
    "nrpose/distances.py": "nrpose/bind/distances.py", "nrpose/bindcache.py": "nrpose/bind/cache.py",
    "nrpose/retarget.py": "nrpose/pose/retarget.py", "nrpose/weightcli.py": "nrpose/cli/weights.py",
    "nrpose/gltf_export.py": "nrpose/io/gltf_write.py", "nrpose/skeleton.py": "nrpose/model/skeleton.py",
    "nrpose/rotation.py": "nrpose/model/rotation.py", "nrpose/weights.py": "nrpose/bind/weights.py",
    "nrpose/engine.py": "nrpose/pose/mls.py", "nrpose/skinning.py": "nrpose/pose/skinning.py",
}


def root_cause(d: dict) -> str:
    cls, where = d["class"], d["where"]
    text = " ".join(d.get("stderr_tail", [])) + " " + where
    mutation = d.get("mutation", "")
    if cls == "broken-pipe" or "BrokenPipe" in text:
        return "pipe"
    if cls == "leftover":
        return "commit"
    if "RecursionError" in text or "nested" in mutation and cls == "traceback":
        return "nesting"
    if cls == "hang":
        return "nesting" if "children" in mutation else "budget"
    if cls in ("nonfinite", "bad-option-accepted"):
        return "float32"
    if cls in ("memory",) or "MemoryError" in text or "bad_alloc" in text:
        return "budget" if re.search(r"--(fps|frames|time)", mutation) else "sizes"
    if cls == "crash":
        return "libigl"
    if cls == "multiline-stderr":
        return "libigl"
    if cls == "invalid-output":
        return "sizes"
    if cls == "traceback" and ("gltf" in where or "retargetcli" in where or d["input_kind"] in
                               ("glb", "gltf_embedded", "gltf_external", "bin")):
        return "gltf-types"
    return "other"


def normalise(summary: dict) -> dict:
    """Re-class tracebacks the runner's current rules class otherwise (a MemoryError of any
    kind is ``memory``, a BrokenPipeError is ``broken-pipe``), counts moved with them."""
    by = dict(summary.get("by_outcome", {}))
    for d in summary["defects"]:
        last = d["stderr_tail"][-1] if d["stderr_tail"] else ""
        new = ("memory" if "MemoryError" in last.split(":")[0] else
               "broken-pipe" if "BrokenPipe" in last else d["class"]) if d["class"] == "traceback" else d["class"]
        if new != d["class"]:
            by[d["class"]] -= d["count"]
            by[new] = by.get(new, 0) + d["count"]
            d["class"] = new
    summary["by_outcome"] = {k: v for k, v in by.items() if v}
    return summary


def _home(frame: str) -> str:
    path = frame.split(":")[0]
    return NEW_HOME.get(path, path) + (":" + frame.split(":")[-1] if ":" in frame else "")


def totals_table(summary: dict) -> str:
    """Markdown table of the cases by command and input kind: cases, accepted, rejected,
    partial (a bake's accounted exit 1), then one column per contract violation class that
    occurred, a total row per command and one for the run."""
    from .runner import CLASSES, GOOD

    totals = summary["totals"]
    seen = {k for kinds in totals.values() for outcomes in kinds.values() for k in outcomes}
    columns = [c for c in GOOD if c in seen or c != "partial"] + [c for c in CLASSES if c in seen]
    out = ["| command | input kind | cases | " + " | ".join(columns) + " |",
           "|---|---|---:|" + "---:|" * len(columns)]

    def row(cmd, kind, counts, bold=False):
        cells = [f"{sum(counts.values()):,}"] + [f"{counts.get(c, 0):,}" for c in columns]
        if bold:
            cells = [f"**{c}**" for c in cells]
        out.append(f"| {cmd} | {kind} | " + " | ".join(cells) + " |")

    grand: dict = {}
    for cmd in sorted(totals):
        sub: dict = {}
        for kind in sorted(totals[cmd]):
            row(cmd, kind, totals[cmd][kind])
            for k, n in totals[cmd][kind].items():
                sub[k] = sub.get(k, 0) + n
                grand[k] = grand.get(k, 0) + n
        row(cmd, "all", sub, bold=True)
    row("all", "all", grand, bold=True)
    return "\n".join(out)


def markdown(summary: dict) -> str:
    out = [f"Fuzz run: {summary['cases']:,} cases, seed {summary.get('seed')}, "
           f"{summary.get('elapsed_s', 0):.0f} s, {summary.get('cases_per_s', 0)} cases/s; "
           f"{summary['violations']:,} violations, {summary['distinct']} distinct (command, class, where).", ""]
    out.append("| outcome | cases |")
    out.append("|---|---:|")
    for k, v in sorted(summary.get("by_outcome", {}).items(), key=lambda kv: -kv[1]):
        out.append(f"| {k} | {v:,} |")
    out += ["", totals_table(summary), ""]
    groups: dict = {}
    for d in summary["defects"]:
        groups.setdefault(root_cause(d), []).append(d)
    for key, title in ROOTS.items():
        ds = groups.get(key, [])
        if not ds:
            continue
        out += [f"## {title}: {len(ds)} distinct, {sum(d['count'] for d in ds)} cases", ""]
        for d in sorted(ds, key=lambda d: -d["count"]):
            argv = " ".join(repr(a) if (not a or " " in a or "\n" in a) else a for a in d["argv"])
            last = d["stderr_tail"][-1] if d["stderr_tail"] else ""
            out.append(f"- **{d['class']}** `{d['command']}` ({d['template']}, input {d['input_kind']}) "
                       f"x{d['count']}: {d['where'][:140]}")
            out.append(f"  - repro: `nrpose {argv[:300]}` with mutation *{d['mutation'][:120]}*"
                       + (f" ({d['repro']})" if d.get("repro") else ""))
            out.append(f"  - last stderr line: `{last[:200]}`")
            if d.get("nrpose_frame"):
                out.append(f"  - last nrpose frame: `{d['nrpose_frame']}` -> fix in `{_home(d['nrpose_frame'])}`")
            if d.get("problems"):
                out.append(f"  - problems: {'; '.join(map(str, d['problems']))[:200]}")
        out.append("")
    return "\n".join(out)


if __name__ == "__main__":
    print(markdown(normalise(json.loads(open(sys.argv[1]).read()))))
