"""Roofline of the NR-MLS pose kernel on this device, measured in the same run.

Two device ceilings, measured with OpenCL profiling events on private queues, each
kernel launched as the pose kernels are (:func:`nrpose.device.launch_shared`: PoCL's
worker threads and the calling thread take blocks of one job from a mailbox; the
time of a launch is from the first device's start to the last one's end):

* **arithmetic**: ``peak_flops`` -- every block runs ``ACCS`` independent
  ``float8`` accumulators through ``a = a*m + c`` (plain multiply and add, no
  ``fma()``/``mad()``: those are ~10x slower on PoCL), ``ITERS`` times. FLOPs
  counted: 2 per lane per update (a multiply and an add).
* **bandwidth**: ``copy8`` -- ``dst[i] = src[i]`` over ``float8`` elements.
  Bytes counted: read + written (no write-allocate traffic). Measured twice:
  over a buffer far larger than the last-level cache (DRAM), and over one that
  fits in it (L3), since the Table-1 pose kernels' working sets (2-8 MB) fit
  in this CPU's 32 MB L3.

The pose kernel's work is counted from ``kernels/nrmls.cl`` (:func:`pose_flops`,
:func:`pose_bytes`); its time is that of the ``nrmls_pose`` launch of a bound
:class:`nrpose.Deformer`, re-run as a frame loop runs it
(:func:`nrpose.diagnostics.time_launch`), or on the private queues
(:func:`nrpose.diagnostics.relaunch`), shared or not as the deformer decides.
"""
from __future__ import annotations

import time

import numpy as np

import ablation
from nrpose import device, diagnostics
from nrpose.pose.mls import levers_stored

ACCS = 8          # independent float8 accumulators per work-item
#: a kernel near the copy bandwidth is called memory bound only if taking its memory
#: traffic away (ablation.py "memory") saves at least this share of its time
MEMORY_BOUND_SHARE = 0.3
#: ... and launch bound if its time is within this factor of an empty kernel's (the
#: launch is then at least half of it)
LAUNCH_BOUND_RATIO = 2
#: ... and held under the target by the host's slow phases if its median is at least this
#: factor over its best round's and that round reached the target (in a slow phase of a
#: shared VM every part of a launch runs slower for hundreds of ms)
PHASE_RATIO = 1.25
ITERS = 2048      # updates of each accumulator
PEAK_ITEMS = 4096  # work-items of the arithmetic kernel (many work-groups for both cores)
COPY_DRAM_MB = 256
COPY_L3_MB = 4

#: the ceilings the kernels are held against: the best of the ceiling kernels' samples. On
#: this VM one of the two vCPUs is now and then away for a while (seen: every arithmetic
#: sample after one run's rows at 102 GFLOP/s, half the 185-195 of the samples before),
#: and such samples pulled the median ceiling down (146 GFLOP/s), flattering every fraction;
#: a ceiling is what the device can do, so the best sample (about 2-4 % over the median of
#: an undisturbed measurement), which errs against the kernels
ROOF_RULE = "max"
#: the rows are timed in repeat x ROW_ROUNDS rounds over all rows, each turn of a row
#: starting with ROW_WARM_S of posing (the warm-up ends within ~10 ms, Table 1's
#: pocl_pose_warmup_ms)
ROW_ROUNDS = 2
ROW_WARM_S = 0.05
COPY_BLOCK = 4096  # float8 elements (128 KB) per block of the copy kernel
STANDING_EMPTY_BLOCKS = 2   # empty blocks of the job timed with a standing worker polling
#: how the pose kernels are timed (Roofs.timing): as a frame loop runs them, or (where PoCL's
#: event clock is not the host's, so that a span cannot start at the job's publication) on
#: the profiling queues with the workers woken for each launch
TIMING_STANDING = ("as a frame loop runs them (diagnostics.time_launch): a standing worker serving, from "
                   "the job's publication to the end of the calling thread's kernel, which returns "
                   "once every block is done")
TIMING_WOKEN = ("OpenCL profiling events on private queues, PoCL's worker woken for each launch, first "
                "start to last end")

ROOF_SOURCE = r"""
#include "share.h"

__kernel void peak_flops(__global float8 *out, const float m, const float c, const int iters,
                         volatile __global int *jobs, const int role)
{
    FOR_EACH_JOB(jobs, role) FOR_EACH_BLOCK(g, jobs) {
        float8 a0 = (float8)(g), a1 = a0 + 1.0f, a2 = a0 + 2.0f, a3 = a0 + 3.0f,
               a4 = a0 + 4.0f, a5 = a0 + 5.0f, a6 = a0 + 6.0f, a7 = a0 + 7.0f;
        for (int i = 0; i < iters; ++i) {
            a0 = a0 * m + c; a1 = a1 * m + c; a2 = a2 * m + c; a3 = a3 * m + c;
            a4 = a4 * m + c; a5 = a5 * m + c; a6 = a6 * m + c; a7 = a7 * m + c;
        }
        out[g] = a0 + a1 + a2 + a3 + a4 + a5 + a6 + a7;
    }
}

__kernel void copy8(__global const float8 *src, __global float8 *dst,
                    volatile __global int *jobs, const int role)
{
    FOR_EACH_JOB(jobs, role) FOR_EACH_BLOCK(b, jobs) {
        for (int i = b * COPY_BLOCK; i < (b + 1) * COPY_BLOCK; ++i)
            dst[i] = src[i];
    }
}

__kernel void empty(volatile __global int *jobs, const int role)
{
    FOR_EACH_JOB(jobs, role) FOR_EACH_BLOCK(b, jobs) {}
}
"""

# --------------------------------------------------------------------------- counting

#: flops per point of ``nrmls_pose`` (DERIVED_LEVER build, the default lever rule), by
#: section, as (per point handle, per segment slot, fixed, once if P > 0). Multiplies, adds and
#: subtractions are 1 each; constants folded by the compiler (-1.0f/6 ...) are not
#: counted; integer index arithmetic, comparisons and select() are not counted.
#: Calls and divisions (each counted as 1 flop in the totals) are listed apart.
FLOP_COUNT = {
    "point handle, q* term (3 mul + 3 add)": (6, 0, 0, 0),
    "segment slot: q* += w*a + wt*d (3 x (2 mul + 2 add))": (0, 12, 0, 0),
    "segment slot: r += w*table' (3 x (1 mul + 1 add); the lever factor len2 is in the per-pose "
    "table)": (0, 6, 0, 0),
    "point handles: Y* = R_ref^T q* (3 x (3 mul + 2 add)), once per point": (0, 0, 0, 15),
    "point handle: y = R_ref^T q_p - Y* (3 sub; R_ref^T q_p is per-pose table data)": (3, 0, 0, 0),
    "point handle: c = phat x y (3 x (2 mul + 1 sub))": (9, 0, 0, 0),
    "point handle: |c|^2 (3 mul + 2 add)": (5, 0, 0, 0),
    "point handle: phat.y (3 mul + 2 add)": (5, 0, 0, 0),
    "point handle: angle / |c| = atan2(|c|, phat.y) / |c| by angle_per_sine: (phat.y)^2 (1 mul), 1/h "
    "(1 div), t and B (2 mul), t^2 and t^4 (2 mul), degree-7 polynomial in t by Estrin's scheme (7 mul "
    "+ 7 add), A/|c| by rsqrt8_normal_twice as built on x86 with AVX (the rsqrtps estimate 1, its "
    "Newton step with A/2 taken in, (A/2) y (3 - |c|^2 y^2), 4 mul + 1 sub; the portable build's "
    "bit-trick seed + 3 Newton steps would be 15), + B p (1 mul + 1 add)": (28, 0, 0, 0),
    "point handle: lever coef*|phat|^2, *k (3 mul + 2 add + 1 mul + 1 mul)": (7, 0, 0, 0),
    "point handle: r += l*c (3 x (1 mul + 1 add))": (6, 0, 0, 0),
    "normalise r: times the bound 1/lever sum (3 mul)": (0, 0, 3, 0),
    "Rodrigues: x = |h|^2, h = r/2 (the levers bound halved) (3 mul + 2 add)": (0, 0, 5, 0),
    "Rodrigues: x^2, x^4 for Estrin's scheme (2 mul)": (0, 0, 2, 0),
    "Rodrigues: sqrt2 sinc, degree 4 in x by Estrin's scheme (4 mul + 4 add)": (0, 0, 8, 0),
    "Rodrigues: sqrt2 cos, degree 5 in x by Estrin's scheme (5 mul + 5 add)": (0, 0, 10, 0),
    "Rodrigues: A = S*C, B = S*S (2 mul)": (0, 0, 2, 0),
    "Rodrigues: k = h x u, j = h x k (2 x 3 x (2 mul + 1 sub))": (0, 0, 18, 0),
    "Rodrigues: w = u + A k + B j (3 x (2 mul + 2 add))": (0, 0, 12, 0),
    "output: R_ref w + q* (3 x (3 mul + 3 add); segments only: e = R_ref u, e + q* before the rotation, as many)": (0, 0, 18, 0),
}
#: of the totals above: divisions (counted 1 each; the kernel makes no out-of-line calls)
DIVISIONS = {"1 / h in angle_per_sine": (1, 0, 0, 0)}
#: what a build reading the levers from the bound record (not DERIVED_LEVER: the "paper"
#: rule, and rigs without segments, nrpose.pose.mls.levers_stored) does not count above
STORED_LEVERS_SKIP = {"point handle: lever coef*|phat|^2 (3 mul + 2 add + 1 mul; the *k remains)": (6, 0, 0, 0),
                      "normalise r: 3 mul": (0, 0, 3, 0)}


def _total(table: dict, P: int, K: int) -> int:
    return int(sum(p * P + k * K + f + (g if P else 0) for p, k, f, g in table.values()))


def pose_flops(P: int, K: int, stored_levers: bool = False) -> dict:
    """Floating-point operations per point of ``nrmls_pose`` for P point handles and K
    segment slots (K = S dense, or k sparse): total and how it splits; stored_levers: a
    build that reads the levers (:data:`STORED_LEVERS_SKIP`)."""
    skip = _total(STORED_LEVERS_SKIP, P, K) if stored_levers else 0
    return {"per_point": _total(FLOP_COUNT, P, K) - skip, "stored_levers_skipped": skip,
            "formula": "{} P + {} K + {} (+ {} when P > 0; P point handles, K segment slots)".format(
                *(sum(v[i] for v in FLOP_COUNT.values()) for i in range(4))),
            "divisions_per_point": _total(DIVISIONS, P, K),
            "rule": "mul/add/sub = 1 flop (an FMA is 2); divisions counted as 1 each (listed under "
                    "divisions_per_point); sqrt and atan2 are inline code (rsqrt8, angle_per_sine), counted by "
                    "their operations as the x86 AVX build runs them (the rsqrtps estimate counted 1); "
                    "folded constants, "
                    "integer index work, comparisons and select() not counted; counted per real "
                    "point (padding to a multiple of 8 not counted); the table is the DERIVED_LEVER "
                    "build's (default lever rule on rigs with segments); a build reading stored "
                    "levers skips stored_levers_skipped of it"}


def pose_bytes(P: int, K: int, sparse: bool, derived_levers: bool = True) -> dict:
    """Bytes per point that ``nrmls_pose`` reads from the bound arrays and writes."""
    parts = {"u (3 floats)": 12, "ref (int)": 4, "row (int)": 4,
             "coef ((P + 2K) floats)": 4 * (P + 2 * K), "phat (3P floats)": 12 * P,
             "out (3 floats written)": 12}
    if sparse:
        parts["slot (K ints)"] = 4 * K
    if derived_levers:
        parts["inv (1 float)"] = 4
    else:
        parts["lever ((P + K) floats)"] = 4 * (P + K)
    return {"per_point": int(sum(parts.values())), "parts": parts,
            "rule": "each bound per-point array element read once + the output written once; "
                    "per-pose handle data (posed handles, rotation table: a few KB, cache "
                    "resident) added once per pose in bytes_per_pose"}


def pose_work(deformer) -> dict:
    """Counted flops and bytes of one ``nrmls_pose`` launch of a bound deformer."""
    P, S = len(deformer.rest.points), len(deformer.rest.segments)
    K = deformer.slots
    sparse = K < S
    n = deformer.n
    stored = levers_stored(deformer.lever, S)
    fl = pose_flops(P, K, stored)
    by = pose_bytes(P, K, sparse, not stored)
    # the frame's pose block (positions, rotations, slot) and derived block (refs, table,
    # quats, ploc, dirs), as the deformer lays them out
    per_pose_bytes = diagnostics.frame_bytes(deformer)
    return {"P": P, "S": S, "K": K, "sparse": sparse, "points": n,
            "flops_per_point": fl["per_point"], "bytes_per_point": by["per_point"],
            "flops_per_pose": fl["per_point"] * n,
            "bytes_per_pose": by["per_point"] * n + per_pose_bytes,
            "arithmetic_intensity": fl["per_point"] / by["per_point"],
            "flops": fl, "bytes": by}


# --------------------------------------------------------------------------- measuring

class Roofs:
    """Kernels measuring the device ceilings, on private profiling queues."""

    def __init__(self, quick: bool = False):
        import pyopencl as cl
        self.queues = device.profiling_queues()
        prg = device.build_source(ROOF_SOURCE, (f"-DCOPY_BLOCK={COPY_BLOCK}",))
        self.k_flops = cl.Kernel(prg, "peak_flops")
        self.k_copy = cl.Kernel(prg, "copy8")
        self.k_empty = cl.Kernel(prg, "empty")
        self.jobs = device.Jobs()
        self.quick = quick
        self.items = 512 if quick else PEAK_ITEMS
        self.iters = 256 if quick else ITERS
        self.flops_out = device.HostArray(8 * self.items)
        self.k_flops.set_args(self.flops_out.arg, np.float32(0.999), np.float32(1e-3), np.int32(self.iters),
                              self.jobs.box.arg, np.int32(0))
        self.copy = {}
        for name, mb in (("dram", 8 if quick else COPY_DRAM_MB), ("l3", 1 if quick else COPY_L3_MB)):
            nbytes = mb << 20
            src_, dst = device.HostArray(nbytes // 4), device.HostArray(nbytes // 4)
            src_.host[:] = 1.0
            dst.host[:] = 0.0
            self.copy[name] = (src_, dst, nbytes)
        self.k_empty.set_args(self.jobs.box.arg, np.int32(0))
        self.timing = TIMING_STANDING     # how pose_kernel_once timed the pose kernels

    def _launch_s(self, kernel, blocks: int, workers: bool = True, standing: bool = False) -> tuple[float, float]:
        """(kernel seconds, wall seconds) of one shared launch of ``kernel``, and the
        caller's enqueue-to-return time. Kernel seconds: on the profiling queues (workers
        woken), from the first device's start to the last one's end; ``standing`` (a
        standing worker, as poses in a loop run), from the job's publication to the end of
        the calling thread's kernel (:func:`nrpose.device.published_span_s`; NaN where the
        event clock is not the host's)."""
        t = time.perf_counter()
        events = device.launch_shared(kernel, self.jobs, blocks, queues=None if standing else self.queues,
                                      workers=workers, timed=standing)
        wall = time.perf_counter() - t
        if standing:
            span = device.published_span_s(self.jobs, events[-1])
            return (float("nan") if span is None else span), wall
        return device.events_span_s(events), wall

    def flops(self, n: int) -> list[float]:
        """n samples of the arithmetic kernel's rate, GFLOP/s."""
        work = 2 * 8 * ACCS * self.iters * self.items
        self._launch_s(self.k_flops, self.items)
        return [work / self._launch_s(self.k_flops, self.items)[0] * 1e-9 for _ in range(n)]

    def bandwidth(self, which: str, n: int) -> list[float]:
        """n samples of the copy kernel's read + write rate over buffer ``which``, GB/s."""
        src, dst, nbytes = self.copy[which]
        blocks = nbytes // (32 * COPY_BLOCK)
        self.k_copy.set_args(src.arg, dst.arg, self.jobs.box.arg, np.int32(0))
        self._launch_s(self.k_copy, blocks)
        return [2 * nbytes / self._launch_s(self.k_copy, blocks)[0] * 1e-9 for _ in range(n)]

    def empty_kernel(self, n: int, workers: bool = True) -> dict:
        """Launch floor: an empty job's launch time (events) and its enqueue-to-return wall
        time (ms), shared with workers woken for it or (workers=False) on the calling thread
        alone."""
        ev, wall = zip(*(self._launch_s(self.k_empty, 0, workers) for _ in range(n)))
        return {"event_ms": float(np.median(ev) * 1e3), "wall_ms": float(np.median(wall) * 1e3)}

    def empty_standing(self, n: int) -> dict:
        """Launch floor with a standing worker polling (as poses in a loop run,
        device.standby_s()): the enqueue-to-return wall time (ms) of a job of
        ``STANDING_EMPTY_BLOCKS`` empty blocks on the shared queues (whoever takes them), and
        the share of launches after which the worker still stood; None where standing
        workers are off or there is no worker device."""
        if device.standby_s() <= 0 or device.worker_queue() is None or not self.jobs.box.svm:
            return None
        blocks = STANDING_EMPTY_BLOCKS
        self._launch_s(self.k_empty, blocks, standing=True)     # stands the worker
        span, wall, taken = [], [], 0
        for _ in range(n):
            taken += self.jobs.standing(self.k_empty)
            k, w = self._launch_s(self.k_empty, blocks, standing=True)
            span.append(k)
            wall.append(w)
        device.stop_standing()
        return {"span_ms": float(np.median(span) * 1e3), "wall_ms": float(np.median(wall) * 1e3),
                "blocks": blocks, "stood_fraction": taken / n}

    def measure(self, rounds: int) -> dict:
        """Interleaved rounds of the three ceilings; medians and bests."""
        fl, dram, l3 = [], [], []
        for _ in range(rounds):
            fl += self.flops(3)
            dram += self.bandwidth("dram", 2)
            l3 += self.bandwidth("l3", 5)
        stat = lambda a: {"median": float(np.median(a)), "max": float(np.max(a)),  # noqa: E731
                          "min": float(np.min(a)), "n": len(a)}
        return {"gflops": stat(fl), "dram_gbs": stat(dram), "l3_gbs": stat(l3),
                "launch": self.empty_kernel(5 * rounds),
                "launch_alone": self.empty_kernel(5 * rounds, workers=False),
                "launch_standing": self.empty_standing(5 * rounds)}

    def describe(self) -> dict:
        return {"arithmetic_kernel": f"peak_flops: {self.items} blocks x {ACCS} float8 accumulators x "
                                     f"{self.iters} updates a = a*m + c (no fma/mad); 16 flops per float8 update",
                "copy_kernel": f"copy8: dst[i] = src[i] over float8, blocks of {COPY_BLOCK}; bytes = read + written",
                "copy_buffers_mb": {k: v[2] >> 20 for k, v in self.copy.items()},
                "launch": "every kernel launched as the pose kernels are (nrpose.device.launch_shared): "
                          f"{', '.join(f'{q.device.name} x {n}' for q, n in device.work_items(self.queues))} "
                          "work-items taking blocks of one job (nrpose.device.Jobs)",
                "timing": "ceilings: OpenCL profiling events on private queues, first start to last end over "
                          "the devices of a launch, the best sample (ROOF_RULE); pose kernels: " + self.timing
                          + "; medians",
                "pose_timing": self.timing}

    # ------------------------------------------------------------------ pose kernel
    def pose_kernel_once(self, deformer) -> tuple[float, bool]:
        """(seconds, stood): the pose kernel's time (its prologue, the R_g fit and rotation
        tables, included), re-running the deformer's last posing as a frame loop runs it
        (:func:`nrpose.diagnostics.time_launch`): from the job's publication, where a
        standing worker starts on it, to the end of the calling thread's kernel, which
        returns once every block is done; stood: whether a standing worker served it. Where
        the event clock is not the host's, :meth:`pose_kernel_woken` instead (and
        :attr:`timing` says so)."""
        span, stood = diagnostics.time_launch(deformer)
        if span is None:
            self.timing = TIMING_WOKEN
            return self.pose_kernel_woken(deformer), False
        return span, stood

    def pose_kernel_woken(self, deformer) -> float:
        """The pose kernel's time in seconds re-running the deformer's last posing on the
        profiling queues, PoCL's worker woken for the launch (it starts late): from
        the first device's start to the last one's end."""
        return device.events_span_s(diagnostics.relaunch(deformer, queues=self.queues))

    def launch_floor(self, ceilings: dict) -> dict:
        """An empty kernel's time measured as :meth:`pose_kernel_once` measures the pose
        kernels (``event_ms``; with ``wall_ms``, the woken launch's enqueue + wait): what a
        pose kernel is held against to be called launch bound."""
        standing = ceilings.get("launch_standing")
        if self.timing == TIMING_STANDING and standing and np.isfinite(standing.get("span_ms", np.nan)):
            return {"event_ms": standing["span_ms"], "wall_ms": ceilings["launch"]["wall_ms"],
                    "what": "an empty kernel's span with a standing worker"}
        return {"event_ms": ceilings["launch"]["event_ms"], "wall_ms": ceilings["launch"]["wall_ms"],
                "what": "an empty kernel's event time with workers woken"}



def lane_divergence(deformer) -> dict:
    """How often the pose kernel's lanes disagree, read back from the bound buffers.

    A chunk of points (``deformer.lanes``) whose reference rotations differ, or (sparse) a
    segment slot whose segment indices differ, takes the gathered path (a scalar load per
    lane of each vector value instead of broadcasts)."""
    ref, slots = diagnostics.bound_indices(deformer)
    K = deformer.slots
    chunks = ref.reshape(-1, deformer.lanes)
    uni = (chunks == chunks[:, :1]).all(axis=1)
    out = {"chunks": int(len(chunks)), "ref_uniform_fraction": float(uni.mean())}
    if slots is not None:
        sl = slots.reshape(K, -1, deformer.lanes)
        both = uni[None] & (sl == sl[:, :, :1]).all(axis=2)
        out["gathered_slot_fraction"] = float(1 - both.mean())
    else:
        out["gathered_slot_fraction"] = float(1 - uni.mean()) if K else 0.0
    return out


def assess(work: dict, kernel_ms: float, pose_ms: float, roofs: dict, launch: dict,
           shares: dict | None = None, best_round_ms: float | None = None) -> dict:
    """Achieved rates of one pose kernel against the measured ceilings, and what bounds it:
    launch overhead (the pose wall outside the kernel, or a kernel near an empty one's
    time), memory (at least half the copy bandwidth and, where ablations were measured,
    ``shares`` (:func:`ablation.measure`), at least MEMORY_BOUND_SHARE of the time waiting
    for memory), else the kernel's instructions. ``launch``: the empty kernel's floor
    measured as the pose kernel was (:meth:`Roofs.launch_floor`: ``event_ms``, ``wall_ms``,
    ``what``). ``best_round_ms``: the median of the kernel's best round of poses, where
    measured: a kernel under 30 % whose best round reached it, with its median at least
    PHASE_RATIO over that round's, is held under by the host's slow phases. ``work["lanes"]``
    (lane_divergence), where present, adds the gathered path's share of slot visits."""
    t = kernel_ms * 1e-3
    gflops = work["flops_per_pose"] / t * 1e-9
    gbs = work["bytes_per_pose"] / t * 1e-9
    peak, dram, l3 = (roofs[k][ROOF_RULE] for k in ("gflops", "dram_gbs", "l3_gbs"))
    fits_l3 = work["bytes_per_pose"] < 16 << 20
    bw_roof = l3 if fits_l3 else dram
    f_arith, f_bw = gflops / peak, gbs / bw_roof
    # the roofline ceiling at this arithmetic intensity (against the relevant bandwidth)
    ceiling = min(peak, work["arithmetic_intensity"] * bw_roof)
    outside = max(pose_ms - kernel_ms, 0.0) / pose_ms if pose_ms > 0 else 0.0
    what = launch.get("what", "an empty kernel")
    # the arithmetic rate over the kernel time less an empty job's (0 when no time is left)
    net_s = t - launch["event_ms"] * 1e-3
    f_net = work["flops_per_pose"] / net_s * 1e-9 / peak if net_s > 0 else 0.0
    reasons = []
    if outside >= 0.5:
        floors = (f"an empty job's enqueue + wait {launch['wall_ms']:.3f} ms with workers woken"
                  + (f", {roofs['launch_standing']['wall_ms']:.3f} ms with a standing worker"
                     if roofs.get("launch_standing") else ""))
        reasons.append(f"launch overhead and host work: {100 * outside:.0f} % of the pose wall time is outside "
                       f"the pose kernel ({floors}, packing the pose)")
    if f_arith >= 0.3:
        kernel_bound = "arithmetic"
        reasons.append(f"kernel at {100 * f_arith:.0f} % of the arithmetic roof (compute bound)")
    elif f_bw >= 0.5 and (shares is None or shares["memory"]["share"] >= MEMORY_BOUND_SHARE):
        kernel_bound = "memory"
        reasons.append(f"kernel at {100 * f_bw:.0f} % of the {'L3' if fits_l3 else 'DRAM'} copy bandwidth "
                       f"(memory bound)")
    elif (best_round_ms is not None and kernel_ms >= PHASE_RATIO * best_round_ms
          and f_arith * kernel_ms / best_round_ms >= 0.3):
        kernel_bound = "host phases"
        reasons.append(f"kernel at {100 * f_arith:.0f} % of the arithmetic roof at its median, "
                       f"{100 * f_arith * kernel_ms / best_round_ms:.0f} % in its best round "
                       f"({best_round_ms:.3f} ms); the median is {kernel_ms / best_round_ms:.2f}x that "
                       f"round's: the host's slow phases (a launch's every part ~2x slower for hundreds "
                       f"of ms, not shown as steal; the FMA-only ceiling kernel much less) hold it "
                       f"under 30 %")
    elif kernel_ms < LAUNCH_BOUND_RATIO * launch["event_ms"]:
        kernel_bound = "launch"
        reasons.append(f"kernel time {kernel_ms:.3f} ms is within {LAUNCH_BOUND_RATIO:g}x of "
                       f"{what}, {launch['event_ms']:.3f} ms "
                       f"(publishing the job, thread start, work distribution)")
    elif f_net >= 0.3:
        kernel_bound = "launch"
        reasons.append(f"kernel at {100 * f_arith:.0f} % of the arithmetic roof, {100 * f_net:.0f} % net of "
                       f"{what} ({launch['event_ms']:.3f} ms, "
                       f"{100 * launch['event_ms'] / kernel_ms:.0f} % of it): the launch's fixed cost (publishing "
                       f"the job, the calling thread entering its kernel, the wait for the last block) holds "
                       f"it under 30 %")
    else:
        kernel_bound = "instructions"
        reasons.append(f"kernel at {100 * f_arith:.0f} % of the arithmetic roof and {100 * f_bw:.0f} % of the "
                       f"{'L3' if fits_l3 else 'DRAM'} copy bandwidth, bound by neither: its instructions "
                       f"(dependency chains of the slot and handle loops and the rotation, loads of "
                       f"per-pose rows) on the two cores; {what} is "
                       f"{100 * launch['event_ms'] / kernel_ms:.0f} % of it")
    if shares is not None:
        measured = [f"{100 * shares['memory']['share']:.0f} % of the kernel's time waiting for memory"]
        if "stores" in shares:
            measured.append(f"{100 * shares['stores']['share']:.0f} % in the scattered stores of its output rows")
        reasons.append("measured by ablation: " + ", ".join(measured))
    else:
        reasons.append("no ablation measured (memory: by the copy bandwidth alone)")
    if "lanes" in work:
        reasons.append(f"{100 * work['lanes']['gathered_slot_fraction']:.0f} % of (chunk, slot) visits on the "
                       f"gathered path")
    return {"gflops": gflops, "gbs": gbs, "fraction_arithmetic": f_arith,
            "fraction_arithmetic_net_of_launch": f_net, "launch_floor_ms": launch["event_ms"],
            "fraction_bandwidth": f_bw, "bandwidth_roof": "l3" if fits_l3 else "dram",
            "fraction_bandwidth_dram": gbs / dram, "fraction_bandwidth_l3": gbs / l3,
            "roofline_ceiling_gflops": ceiling, "fraction_of_ceiling": gflops / ceiling,
            "outside_kernel_fraction": outside, "kernel_bound": kernel_bound,
            "pose_bound": "launch+host" if outside >= 0.5 else kernel_bound,
            "bound_by": "; ".join(reasons)}


# --------------------------------------------------------------------------- the suite

def run(repeat: int = 5, quick: bool = False, data=None, roofs: "Roofs | None" = None, log=None) -> dict:
    """Roofline suite: device ceilings, then every Table-1 row's pose kernel against them.

    Rows are table1's (same models, handles and poses; --quick: 500 points). Each
    round poses every pose through ``Deformer.pose`` back to back (wall time), then
    poses each again and re-runs its pose kernel on the profiling queue (event times).
    The ceilings are measured before and after the rows; the rows are held against their
    best samples (:data:`ROOF_RULE`). All rows are bound first, then timed in
    repeat x ROW_ROUNDS rounds over the rows in turn, each row's turn starting with
    ROW_WARM_S of steady posing."""
    import pathlib
    import zlib

    import common
    from common import table1
    from nrpose.pose.mls import Deformer

    data = pathlib.Path(data) if data is not None else table1.DEFAULT_DATA
    roofs = roofs or Roofs(quick)
    rounds = 2 if quick else max(repeat, 3)
    before = roofs.measure(rounds)
    n_poses = 3 if quick else 10
    from nrpose.model.handles import Pose
    bound = []      # (model, kind, points, handles, source, deformer, poses), all bound at once
    for model, count, h, paper_ms, rel in table1.TABLE1:
        v, src = table1.load_model(model, count, rel, data, quick)
        for kind in table1.KINDS:
            rest = table1.chain_handles(v, h) if kind == "segments" else table1.fps_handles(v, h)
            rng = np.random.default_rng(zlib.crc32(f"{model}/{kind}".encode()))
            diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
            poses = [Pose.make(rest, **(table1.chain_pose_args(rest, rng) if kind == "segments"
                                        else table1.point_pose_args(rest, rng, diag))) for _ in range(n_poses)]
            d = Deformer(v, rest, alpha=table1.ALPHA, blend=table1.BLEND, lever=table1.LEVER)
            bound.append((model, kind, int(len(v)), h, src.get("kind"), d, poses))
    wall, kern, woken, stood, batched = ([[] for _ in bound] for _ in range(5))
    # rounds over all rows in turn, so that a slow phase of this VM (one vCPU away for a
    # second or so) costs every row a round rather than one row all its samples
    for _ in range(max(repeat, 1) * ROW_ROUNDS):
        for i, (*_, d, poses) in enumerate(bound):
            # steady posing first: right after another row's or the ceilings' kernels, the first
            # few ms of poses run up to 2x slower (Table 1's pocl_pose_warmup_ms)
            warm_until, j = time.perf_counter() + (0.0 if quick else ROW_WARM_S), 0
            while j < len(poses) or time.perf_counter() < warm_until:
                d.pose(poses[j % len(poses)])
                j += 1
            # the poses back to back as Table 1 times them (a standing worker serves them,
            # each result held until the next is made), then each again with its kernel timed
            # as a frame loop runs it, then on the profiling queues with the worker woken for
            # each launch (which ends the standing worker)
            posed = None
            for p in poses:
                t = time.perf_counter()
                posed = d.pose(p)
                wall[i].append(time.perf_counter() - t)
            del posed
            for p in poses:
                d.pose(p)
                t, s = roofs.pose_kernel_once(d)
                kern[i].append(t)
                stood[i].append(s)
            for p in poses:
                d.pose(p)
                woken[i].append(roofs.pose_kernel_woken(d))
            # the same poses as one launch of F frames (how clips are posed): kernel time per frame
            d.pose_frames(poses)
            batched[i].append(roofs.pose_kernel_once(d)[0] / len(poses))
    rows = []
    for i, (model, kind, n, h, source, d, poses) in enumerate(bound):
        work = pose_work(d)
        work["lanes"] = lane_divergence(d)
        d.pose(poses[0])           # the ablations relaunch a single pose
        shares = ablation.measure(d, 5 if quick else ablation.LAUNCHES)
        rows.append({"model": model, "kind": kind, "points": n, "handles": h, "source": source, "work": work,
                     "pose_ms": common.stats(wall[i]), "kernel_ms": common.stats(kern[i]),
                     "kernel_stood_fraction": float(np.mean(stood[i])),
                     "kernel_woken_ms": common.stats(woken[i]),
                     "batched_kernel_ms_per_frame": common.stats(batched[i]),
                     # the round with the lowest median kernel time: the machine undisturbed
                     "kernel_ms_best_round": 1e3 * float(np.median(np.reshape(kern[i], (-1, len(poses))),
                                                                   axis=1).min()),
                     "batch_frames": len(poses), "ablation": shares, "load": common.load()})
        if log:
            log(f"roofline {model:9s} {kind:8s} pose {rows[-1]['pose_ms']['median']:.3f} ms, "
                f"kernel {rows[-1]['kernel_ms']['median']:.3f} ms")
    del bound, d
    after = roofs.measure(rounds)
    ceilings = merge_roofs(before, after)
    floor = roofs.launch_floor(ceilings)
    for r in rows:
        r.update(assess(r["work"], r["kernel_ms"]["median"], r["pose_ms"]["median"], ceilings,
                        floor, r["ablation"], r["kernel_ms_best_round"]))
        r["fraction_arithmetic_woken"] = r["fraction_arithmetic"] * r["kernel_ms"]["median"] / r["kernel_woken_ms"]["median"]
        r["fraction_arithmetic_best_round"] = r["fraction_arithmetic"] * r["kernel_ms"]["median"] / r["kernel_ms_best_round"]
        r["batched"] = batched_rates(r["work"], r["batched_kernel_ms_per_frame"]["median"], ceilings)
    best = max(rows, key=lambda r: r["fraction_arithmetic"])
    best_batched = max(rows, key=lambda r: r["batched"]["fraction_arithmetic"])
    return {"roofs": ceilings, "roof_rule": ROOF_RULE, "roofs_before": before, "roofs_after": after,
            "method": roofs.describe(),
            "flop_count": {"table": {k: list(v) for k, v in FLOP_COUNT.items()},
                           "columns": ["per point handle", "per segment slot", "fixed", "once per point when P > 0"],
                           "divisions": {k: list(v) for k, v in DIVISIONS.items()},
                           "stored_levers_skip": {k: list(v) for k, v in STORED_LEVERS_SKIP.items()},
                           **{k: v for k, v in pose_flops(1, 1).items() if k in ("formula", "rule")}},
            "rows": rows, "poses_per_round": n_poses, "rounds": max(repeat, 1) * ROW_ROUNDS,
            "best_row": f"{best['model']}/{best['kind']}", "best_fraction_arithmetic": best["fraction_arithmetic"],
            "best_batched_row": f"{best_batched['model']}/{best_batched['kind']}",
            "best_batched_fraction_arithmetic": best_batched["batched"]["fraction_arithmetic"]}


def batched_rates(work: dict, ms_per_frame: float, roofs: dict) -> dict:
    """Achieved rates of a batched launch (F frames), per frame, against the ceilings."""
    t = ms_per_frame * 1e-3
    gflops = work["flops_per_pose"] / t * 1e-9
    fits_l3 = work["bytes_per_pose"] < 16 << 20
    # a batch reads the bound data once for all its frames: bytes per frame are an upper bound
    gbs = work["bytes_per_pose"] / t * 1e-9
    return {"kernel_ms_per_frame": ms_per_frame, "gflops": gflops,
            "fraction_arithmetic": gflops / roofs["gflops"][ROOF_RULE],
            "gbs_upper_bound": gbs,
            "fraction_bandwidth_upper_bound": gbs / roofs["l3_gbs" if fits_l3 else "dram_gbs"][ROOF_RULE]}


def merge_roofs(before: dict, after: dict) -> dict:
    """Ceilings from two measurements: the best sample of either (``max``: the ceiling the
    rows are held against, :data:`ROOF_RULE`), and the median of the two medians."""
    out = {}
    for k in ("gflops", "dram_gbs", "l3_gbs"):
        out[k] = {"median": float(np.median([before[k]["median"], after[k]["median"]])),
                  "max": max(before[k]["max"], after[k]["max"]),
                  "n": before[k]["n"] + after[k]["n"]}
    for k in ("launch", "launch_alone", "launch_standing"):
        if before.get(k) and after.get(k):
            out[k] = {m: float(np.median([before[k][m], after[k][m]])) for m in before[k]}
    out["ridge_flops_per_byte_dram"] = out["gflops"][ROOF_RULE] / out["dram_gbs"][ROOF_RULE]
    out["ridge_flops_per_byte_l3"] = out["gflops"][ROOF_RULE] / out["l3_gbs"][ROOF_RULE]
    return out
