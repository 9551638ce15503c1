"""Where a pose kernel's time goes, measured by taking one cost away (the roofline suite's
``bound_by``).

Each ablation is the shipped ``kernels/nrmls.cl`` with one edit, built with the bound
deformer's options (:func:`nrpose.diagnostics.kernel_variant`) and launched in
turn with the shipped kernel on the calling thread alone
(:func:`kernel_ab.paired_launches`; both built as variants, by the same path), so that
both see the same machine. Its ``share`` is
1 - (its time / the shipped kernel's), the median over side-by-side launch pairs: the
fraction of the kernel's time that the removed cost takes.

* ``memory``: every chunk of points reads its bound records (and writes its output rows)
  within a window of ``WINDOW`` chunks, which stays in the L1 cache: the time spent
  waiting for memory (bound data streamed from L2/L3, output lines written back).
* ``stores``: each chunk's output written with three vector stores at the chunk's
  position instead of, for chunks whose rows are not one run (lanes.h STORE_CHUNKV), 8-byte
  (x, y) and 4-byte z stores per row: the points of rigs with segments are stored sorted
  by reference rotation, so their rows are scattered. Not run on rigs without segments,
  which already store so.

Their outputs are wrong by design and not checked. The time neither takes is the
kernel's instructions: arithmetic, the loads of the rows it needs, dependency chains.
"""
from __future__ import annotations

import numpy as np

import common
import kernel_ab
from nrpose import device, diagnostics
from nrpose.errors import NrposeError

WINDOW = 16       # chunks whose records the memory ablation cycles through
LAUNCHES = 60     # launch pairs per ablation (quick: 5)

ABLATIONS = {
    "memory": [("((frec) + (size_t)(g) * FREC(P, K))", f"((frec) + (size_t)((g) % {WINDOW}) * FREC(P, K))"),
               ("((irec) + (size_t)(g) * IREC(K))", f"((irec) + (size_t)((g) % {WINDOW}) * IREC(K))")],
    "stores": [("STORE_CHUNKV(ox, oy, oz, out, ints + VW);", "STORE_XYZV(ox, oy, oz, out + 3 * VW * (size_t)g);")],
}


def variant_source(name: str) -> str:
    """The shipped pose kernel's source with ablation ``name``'s edits; NrposeError if
    an edit no longer finds its text (the kernel changed: the ablation must follow)."""
    source = device.kernel_source("nrmls.cl")
    for old, new in ABLATIONS[name]:
        if source.count(old) != 1:
            raise NrposeError(f"ablation {name!r}: {old!r} is not in kernels/nrmls.cl exactly once; "
                              f"update bench/ablation.py ABLATIONS to the kernel")
        source = source.replace(old, new)
    return source


def measure(deformer, launches: int = LAUNCHES) -> dict:
    """Each applicable ablation of ``deformer``'s pose kernel (its last posing relaunched):
    {name: {"share": ..., "paired_ratio": {median, p10, p90} of variant/shipped time,
    "shipped_ms", "variant_ms" (medians)}}."""
    names = [n for n in ABLATIONS if n != "stores" or len(deformer.rest.segments)]
    # the shipped source built as a variant too, so that both sides come from the same build
    # path (a variant's arguments are bound again only after they change)
    kernels = {"shipped": diagnostics.kernel_variant(deformer, device.kernel_source("nrmls.cl")),
               **{n: diagnostics.kernel_variant(deformer, variant_source(n)) for n in names}}
    times = kernel_ab.paired_launches(deformer, kernels, launches)
    out = {}
    for n in names:
        ratio = np.divide(times[n], times["shipped"])
        out[n] = {"share": float(1 - np.median(ratio)),
                  "paired_ratio": common.quantiles(ratio),
                  "shipped_ms": float(np.median(times["shipped"]) * 1e3),
                  "variant_ms": float(np.median(times[n]) * 1e3)}
    diagnostics.relaunch(deformer)       # the shipped kernel's output back in place
    return out
