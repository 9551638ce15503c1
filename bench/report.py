"""Render the committed benchmark results into the docs that quote them.

    python bench/report.py [--table1 results/table1.json] [--suites results/suites.json]
                           [--readme FILE ...]

Each ``--readme`` file (repeatable; default: bench/README.md, the project README
and docs/performance.md) gets every block below whose markers it holds replaced
by tables of the documents' figures, so that the docs quote exactly what the
JSON holds; everything outside the markers is left alone.

* ``<!-- results -->`` / ``<!-- /results -->``: the Table-1 document (bench/README.md);
* ``<!-- suites-results -->``: every suite of the suites document (bench/README.md);
* ``<!-- readme-results -->``: one summary table of the suites document (the user manual), with
  the e2e and fit-skin documents' lines;
* ``<!-- bounds -->``: what bounds each Table-1 row (docs/performance.md).

Writes atomically; exits 2 with one line, writing nothing, on a missing or
malformed document or a file without any of the markers.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import re
import sys

HERE = pathlib.Path(__file__).resolve().parent
if str(HERE.parent) not in sys.path:  # allow `python bench/report.py` from a checkout
    sys.path.insert(0, str(HERE.parent))

from nrpose.io.files import atomic_path  # noqa: E402


def _ms(x: float) -> str:
    return f"{x:.3f}" if x < 10 else f"{x:.1f}"


def _row(cells) -> str:
    return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"


def _table(head: list[str], rows: list[list]) -> str:
    return "\n".join([_row(head), _row(["---"] * len(head))] + [_row(r) for r in rows])


def _header(doc: dict) -> str:
    env = doc.get("environment", {})
    dev = env.get("device", {})
    opts = doc.get("options", {})
    return (f"commit {doc.get('git_commit', '?')[:8]}{' (dirty)' if doc.get('git_dirty') else ''}, "
            f"{doc.get('timestamp', '?')}, `--repeat {opts.get('repeat', '?')}`, "
            f"{dev.get('summary', dev.get('device_version', dev.get('device', '?')))}, {env.get('cpu_count', '?')} CPUs")


def table1_block(doc: dict) -> str:
    """Markdown for one Table-1 document (bench/table1.py)."""
    rows = []
    for r in doc["rows"]:
        cl, b = r["pocl_pose_ms"], r["pocl_batched_per_frame_ms"]
        rows.append([r["model"], r["kind"], f"{r['points']:,} × {r['handles']}", _ms(r["bind_ms"]["median"]),
                     _ms(r["pose_make_ms"]["median"]),
                     f"**{_ms(cl['median'])}** [{_ms(cl['p10'])}–{_ms(cl['p90'])}]",
                     _ms(r["numpy_pose_ms"]["median"]), f"{r['speedup_vs_numpy']:.0f}×",
                     f"{_ms(b['median'])} ({r['batched_speedup_vs_numpy']:.0f}×)",
                     r["paper_ms"], f"{r['paper_over_pocl']:.0f}×", f"{r['max_error_rel_bbox']:.1e}"])
    t = doc["targets"]
    verdict = lambda ok: "met" if ok else "**not met**"  # noqa: E731
    return "\n".join([
        f"`results/table1.json`: {_header(doc)}. Medians in ms (PoCL p10–p90 in brackets); "
        "`Pose.make` is not included in the pose times; batched = one launch posing the "
        f"{doc['rows'][0]['batch_frames']} poses, per frame.", "",
        _table(["row", "kind", "N × h", "bind", "Pose.make", "PoCL pose", "numpy pose", "numpy/PoCL",
                "batched (numpy/batched)", "paper", "paper/PoCL", "max err / diag"], rows), "",
        f"Targets ({t['row']}): pose ≤ {t['pose_ms_max']} ms: {_ms(t['pose_ms'])} ms, "
        f"{verdict(t['pose_ms_met'])}; ≥ {t['speedup_min']:.0f}× faster than the numpy reference: "
        f"{t['speedup']:.0f}×, {verdict(t['speedup_met'])}."])


def suites_block(doc: dict) -> str:
    """Markdown for one suites document (bench/suites.py)."""
    s = doc["suites"]
    steal = doc.get("cpu_steal_percent")
    out = [f"`results/suites.json`: {_header(doc)}, load {doc.get('load_start')} → {doc.get('load_end')}, "
           + ("" if steal is None else f"CPU steal {steal} %, ")
           + f"{doc.get('seconds', 0) / 60:.1f} min, peak RSS {doc.get('peak_rss_gb', 0):.1f} GB.", "",
           "Targets (medians, same run):", ""]
    for t in doc.get("targets", []):
        m = t["measured"]
        shown = "—" if m is None else (f"{m:.3g}" if isinstance(m, float) else m)
        out.append(f"* {t['name']}: **{shown}** ({t.get('where', '')}) → "
                   f"{'met' if t['met'] else '**not met**'}")
    if "table1" in s:
        out += ["", _table(["Table-1 row", "PoCL ms", "into out= ms", "after a pause ms", "batched ms/frame",
                            "numpy ms", "numpy/PoCL", "paper/PoCL"],
                           [[f"{r['model']}/{r['kind']}", _ms(r["pocl_pose_ms"]["median"]),
                             _ms(r["pocl_pose_into_ms"]["median"]) if "pocl_pose_into_ms" in r else "—",
                             _ms(r["pocl_pose_after_pause_ms"]["median"]) if "pocl_pose_after_pause_ms" in r else "—",
                             _ms(r["pocl_batched_per_frame_ms"]["median"]), _ms(r["numpy_pose_ms"]["median"]),
                             f"{r['speedup_vs_numpy']:.0f}×", f"{r['paper_over_pocl']:.0f}×"]
                            for r in s["table1"]["rows"]])]
    if "roofline" in s:
        ro = s["roofline"]
        c = ro["roofs"]
        rule = ro.get("roof_rule", "max")
        standing = c.get("launch_standing") or {}
        out += ["", f"Roofline ceilings (the rows' roofs, `ROOF_RULE` {rule}; medians in brackets): "
                    f"{c['gflops'][rule]:.0f} GFLOP/s arithmetic ({c['gflops']['median']:.0f}), copy "
                    f"{c['dram_gbs'][rule]:.1f} GB/s DRAM ({c['dram_gbs']['median']:.1f}), "
                    f"{c['l3_gbs'][rule]:.1f} GB/s L3-resident ({c['l3_gbs']['median']:.1f}); empty kernel shared with the workers "
                    f"{c['launch']['event_ms'] * 1e3:.1f} µs event, {c['launch']['wall_ms'] * 1e3:.0f} µs "
                    "enqueue+wait"
                    + (f", on the calling thread alone {c['launch_alone']['event_ms'] * 1e3:.1f} µs event, "
                       f"{c['launch_alone']['wall_ms'] * 1e3:.0f} µs enqueue+wait" if "launch_alone" in c else "")
                    + (f", with a standing worker {standing['span_ms'] * 1e3:.1f} µs from publication to end, "
                       if "span_ms" in standing else ", with a standing worker " if standing else "")
                    + (f"{standing['wall_ms'] * 1e3:.0f} µs enqueue+wait" if standing else "")
                    + ".", "", f"Pose kernels timed {ro['method'].get('pose_timing', ro['method']['timing'])}.", "",
                _table(["row", "flop/pt", "B/pt", "pose ms", "kernel ms", "GFLOP/s", "% arith",
                        "% arith net of an empty job",
                        "best round: kernel ms, % arith", "worker woken: kernel ms, % arith",
                        "batched kernel ms/frame", "batched % arith", "bound"],
                       [[f"{r['model']}/{r['kind']}", r["work"]["flops_per_point"], r["work"]["bytes_per_point"],
                         _ms(r["pose_ms"]["median"]), _ms(r["kernel_ms"]["median"]), f"{r['gflops']:.1f}",
                         f"{100 * r['fraction_arithmetic']:.1f}",
                         f"{100 * r['fraction_arithmetic_net_of_launch']:.1f}"
                         if "fraction_arithmetic_net_of_launch" in r else "—",
                         f"{_ms(r['kernel_ms_best_round'])}, {100 * r['fraction_arithmetic_best_round']:.1f}"
                         if "kernel_ms_best_round" in r else "—",
                         f"{_ms(r['kernel_woken_ms']['median'])}, {100 * r['fraction_arithmetic_woken']:.1f}"
                         if "kernel_woken_ms" in r else "—",
                         _ms(r["batched"]["kernel_ms_per_frame"]),
                         f"{100 * r['batched']['fraction_arithmetic']:.1f}", r["kernel_bound"]]
                        for r in ro["rows"]])]
    if "scaling" in s:
        sc = s["scaling"]
        out += ["", "Scaling fits (pose medians):", ""]
        for mode, f in sc["fits"].items():
            if "linear" in f:
                lin, pw = f["linear"], f.get("power", {})
                out.append(f"* {mode}: t = {lin['c0_ms']:.3f} ms + {lin['c1_ns_per_point']:.1f} ns·N + "
                           f"{lin['c2_ns_per_point_handle']:.2f} ns·N·H (R² {lin['r2']:.3f}); "
                           f"t ∝ (N·H)^{pw.get('b', float('nan')):.2f}")
        out += ["", _table(["mode", "N", "H", "bind s", "RSS GB", "pose ms", "kernel ms", "gathered"],
                           [[r["mode"], f"{r['points']:,}", r["handles"], f"{r['bind_ms'] / 1e3:.2f}",
                             f"{r['peak_rss_gb_after_bind']:.1f}", _ms(r["pose_ms"]["median"]),
                             _ms(r["kernel_ms"]["median"]) if "kernel_ms" in r else "—",
                             f"{100 * r['work']['lanes']['gathered_slot_fraction']:.0f} %"]
                            for r in sc["rows"]])]
    if "clips" in s:
        by: dict[tuple, dict] = {}
        for r in s["clips"]["rows"]:
            key = (r["character"], r["clip"], r["weights"], r["vertices"], r["joints"])
            by.setdefault(key, {})[r["method"]] = r
        out += ["", _table(["character (clip, weights)", "V", "J", "nrmls ms/frame", "lbs ms/frame",
                            "dqs ms/frame"],
                           [[f"{ch} ({clip}, {w})", f"{v:,}", j] +
                            [_ms(m[k]["frame_ms"]["median"]) if k in m else "—" for k in ("nrmls", "lbs", "dqs")]
                            for (ch, clip, w, v, j), m in by.items()])]
    return "\n".join(out)


def manual_block(doc: dict, e2e: dict | None = None, fit: dict | None = None,
                 fit_source: str = "bench/results/fit_skin_tracks.json") -> str:
    """Markdown for the user manual: one table of the suites document's Table-1 rows, its
    characters' per-frame times, given the e2e document whole jobs against Blender and, given
    bench/fit_skin.py's document, the fitted skins' errors and sizes."""
    s = doc["suites"]
    env = doc.get("environment", {})
    roof = {f"{r['model']}/{r['kind']}": r for r in s.get("roofline", {}).get("rows", [])}
    rows = []
    for r in s["table1"]["rows"]:
        key = f"{r['model']}/{r['kind']}"
        ro = roof.get(key)
        rows.append([f"{r['model']}, {r['handles']} {r['kind']}", f"{r['points']:,}", f"{r['paper_ms']:g}",
                     f"**{_ms(r['pocl_pose_ms']['median'])}**", _ms(r["pocl_batched_per_frame_ms"]["median"]),
                     _ms(r["numpy_pose_ms"]["median"]), f"{r['speedup_vs_numpy']:.0f}×",
                     f"{r['paper_over_pocl']:.0f}×",
                     "—" if ro is None else f"{100 * ro['fraction_arithmetic']:.0f} %"])
    steal = doc.get("cpu_steal_percent")
    out = [f"`bench/results/suites.json` of {doc.get('timestamp', '?')[:10]}: {env.get('cpu', '?')}, "
           f"{env.get('cpu_count', '?')} CPUs, PoCL {env.get('pocl_version', '?')}"
           + ("" if steal is None else f", CPU steal {steal} %")
           + ". Medians in ms per pose (batched: 20 poses in one launch, per frame); "
           "roof: the pose kernel's share of the measured arithmetic peak.", "",
           _table(["Table-1 row", "points", "paper", "nrpose", "batched", "numpy float64", "numpy / nrpose",
                   "paper / nrpose", "roof"], rows)]
    sc = s.get("scaling", {}).get("target")
    if sc:
        out += ["", f"{sc['points']:,} points × {sc['handles']} bones (k = {sc['k']}): "
                    f"{_ms(sc['measured'])} ms per pose, bound in {sc['bind_ms'] / 1e3:.1f} s."]
    if "clips" in s:
        per = {}
        for r in s["clips"]["rows"]:
            per.setdefault(f"{r['character']} ({r['vertices']:,} vertices)", {})[r["method"]] = r["frame_ms"]["median"]
        out += ["", "Characters, ms per frame NR-MLS / LBS / DQS: " + "; ".join(
            f"{name} {' / '.join(_ms(m[k]) for k in ('nrmls', 'lbs', 'dqs') if k in m)}" for name, m in per.items())
            + "."]
    if e2e:
        out += ["", whole_jobs_line(e2e)]
        glb = glb_jobs_line(e2e)
        if glb:
            out += ["", glb]
    if fit:
        out += ["", fit_skin_line(fit, fit_source)]
    return "\n".join(out)


def fit_skin_line(fit: dict, source: str = "bench/results/fit_skin_tracks.json") -> str:
    """One sentence of bench/fit_skin.py's document (read from ``source``): per character, helper
    count, influences and helper-track mode, the held-out RMS / max (% of the height) and the file
    against a 10 s morph-target bake."""
    cells = [f"{r['character']} {r['helpers']} helpers ({r['influences']} influences, {r['tracks']} tracks) "
             f"{r['rms_pct']:.3f} / {r['max_pct']:.2f}, {r['file_bytes'] / r['bake_10s_bytes']:.3f}"
             for r in fit["rows"] if r["set"] == "held-out"]
    return (f"NR-MLS exported as LBS (`nrpose fit-skin`; `{source}` of {fit.get('created', '?')[:10]}): held-out "
            f"RMS / max % of the height, file / 10 s morph-target bake: " + "; ".join(cells) + ".")


def whole_jobs_line(e2e: dict) -> str:
    """One sentence of the e2e document: warm and cold whole-process medians to .npz per character
    and method, with Blender's of the same run."""
    rows = [r for r in e2e["rows"] if r.get("output", "npz") == "npz" or r["who"] == "floor"]
    parts = []
    for name in dict.fromkeys(r["character"] for r in rows):
        def med(who, mode, method=None):
            for r in rows:
                if r["character"] == name and r["who"] == who and r["mode"] == mode and \
                        (method is None or r.get("method") == method):
                    return r["wall_ms"]["median"]
        cells = []
        for mode in ("warm", "cold"):
            blender = med("blender", mode)
            ours = [(m, med("nrpose", mode, m)) for m in ("nrmls", "lbs", "dqs")]
            ours = [(m, v) for m, v in ours if v is not None]
            if blender is None or not ours:
                continue
            floor = med("floor", mode) if mode == "cold" else None
            cells.append(f"{mode} Blender {blender:.0f}, " + ", ".join(
                f"{ {'nrmls': 'NR-MLS', 'lbs': 'LBS', 'dqs': 'DQS'}[m]} {v:.0f} ({blender / v:.2f}×)" for m, v in ours)
                + (f", the OpenCL floor {floor:.0f} ({blender / floor:.2f}×)" if floor else ""))
        if cells:
            parts.append(f"{name}: " + "; ".join(cells))
    return (f"Whole jobs, `nrpose pose CHARACTER --clip CLIP -o OUT.npz` as processes against Blender 5 "
            f"importing, playing and saving the same clip (`bench/results/e2e.json` of "
            f"{e2e.get('timestamp', '?')[:10]}, ms, medians; the OpenCL floor: a process that only "
            f"imports numpy and pyopencl and builds and runs a one-line kernel on PoCL): " + "; ".join(parts) + ".")


def glb_jobs_line(e2e: dict) -> str:
    """One sentence of the e2e document's ``.glb`` rows (morph targets with normals; Blender has
    no such job in the suite): warm and cold medians per character and method; "" without them."""
    rows = [r for r in e2e["rows"] if r.get("output") == "glb" and r["who"] == "nrpose"]
    parts = []
    for name in dict.fromkeys(r["character"] for r in rows):
        cells = []
        for mode in ("warm", "cold"):
            got = [f"{ {'nrmls': 'NR-MLS', 'lbs': 'LBS', 'dqs': 'DQS'}[r['method']]} {r['wall_ms']['median']:.0f}"
                   for r in rows if r["character"] == name and r["mode"] == mode]
            if got:
                cells.append(f"{mode} " + ", ".join(got))
        parts.append(f"{name}: " + "; ".join(cells))
    if not parts:
        return ""
    return ("The same jobs into `OUT.glb` (every frame a morph target with positions and normals), ms, "
            "medians: " + "; ".join(parts) + ".")


def bounds_block(doc: dict) -> str:
    """Markdown for docs/performance.md: what bounds each Table-1 row (the roofline suite)."""
    ro = doc["suites"]["roofline"]
    c, rule = ro["roofs"], ro.get("roof_rule", "max")
    standing = c.get("launch_standing") or {}

    def share(r, name):
        a = r.get("ablation", {}).get(name)
        return "—" if a is None else f"{100 * max(a['share'], 0.0):.0f} %"

    rows = [[f"{r['model']}/{r['kind']}", r["work"]["flops_per_point"], r["work"]["bytes_per_point"],
             _ms(r["kernel_ms"]["median"]), f"{100 * r['fraction_arithmetic']:.1f} %",
             f"{100 * r['fraction_arithmetic_net_of_launch']:.1f} %" if "fraction_arithmetic_net_of_launch" in r
             else "—", share(r, "memory"), share(r, "stores"), f"{100 * r['outside_kernel_fraction']:.0f} %",
             r["kernel_bound"]] for r in ro["rows"]]
    return "\n".join([
        f"`bench/results/suites.json` of {doc.get('timestamp', '?')[:10]}. Roofs: {c['gflops'][rule]:.0f} GFLOP/s "
        f"arithmetic, {c['l3_gbs'][rule]:.1f} GB/s L3-resident copy, {c['dram_gbs'][rule]:.1f} GB/s DRAM copy "
        "(best samples)" + (f"; an empty job with a standing worker spans {standing['span_ms'] * 1e3:.1f} µs"
                            if "span_ms" in standing else "") + ".", "",
        _table(["row", "flop/point", "bytes/point", "kernel ms", "of the arithmetic roof", "net of an empty job",
                "waiting for memory", "scattered stores", "pose wall outside the kernel", "bound"], rows)])


def _shown(path: str) -> str:
    """path relative to the checkout where it lies inside it (as the docs name files), else as given."""
    p = pathlib.Path(path).resolve()
    return str(p.relative_to(HERE.parent)) if p.is_relative_to(HERE.parent) else path


def splice(text: str, tag: str, block: str) -> str:
    """text with the part between <!-- tag --> and <!-- /tag --> replaced by block."""
    pat = re.compile(rf"(<!-- {re.escape(tag)} -->\n).*?(\n<!-- /{re.escape(tag)} -->)", re.S)
    if not pat.search(text):
        raise ValueError(f"markers <!-- {tag} --> ... <!-- /{tag} --> not found")
    return pat.sub(lambda m: m.group(1) + block + m.group(2), text, count=1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--table1", default=str(HERE / "results" / "table1.json"))
    ap.add_argument("--suites", default=str(HERE / "results" / "suites.json"))
    ap.add_argument("--e2e", default=str(HERE / "results" / "e2e.json"))
    ap.add_argument("--fit-skin", default=str(HERE / "results" / "fit_skin_tracks.json"))
    ap.add_argument("--readme", action="append",
                    help="a file to render into (repeatable; default: bench/README.md, README.md, "
                         "docs/performance.md)")
    a = ap.parse_args(argv)
    paths = a.readme or [str(HERE / "README.md"), str(HERE.parent / "README.md"),
                         str(HERE.parent / "docs" / "performance.md")]
    try:
        suites = json.loads(pathlib.Path(a.suites).read_text())
        e2e = json.loads(pathlib.Path(a.e2e).read_text()) if pathlib.Path(a.e2e).exists() else None
        fit = json.loads(pathlib.Path(a.fit_skin).read_text()) if pathlib.Path(a.fit_skin).exists() else None
        blocks = {"results": lambda: table1_block(json.loads(pathlib.Path(a.table1).read_text())),
                  "suites-results": lambda: suites_block(suites),
                  "readme-results": lambda: manual_block(suites, e2e, fit, _shown(a.fit_skin)),
                  "bounds": lambda: bounds_block(suites)}
        rendered = []
        for path in paths:
            text = pathlib.Path(path).read_text()
            tags = [tag for tag in blocks if f"<!-- {tag} -->" in text]
            if not tags:
                raise ValueError(f"{path}: none of the markers <!-- {' -->, <!-- '.join(blocks)} --> found")
            for tag in tags:
                text = splice(text, tag, blocks[tag]())
            rendered.append((path, text))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        print(f"bench/report.py: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2
    for path, text in rendered:
        with atomic_path(path) as tmp:
            tmp.write_text(text)
        print(f"wrote {path}")
    return 0

if __name__ == "__main__":
    sys.exit(main())
