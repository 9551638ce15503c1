"""Progress of a bake: a bar on a terminal (jobs and frames), the final line, the summary JSON."""
from __future__ import annotations

import sys
import time

from .jobs import Job


class Progress:
    """Counts finished jobs and frames; draws a bar on ``stream`` when it is a terminal."""

    def __init__(self, total: int, stream=None):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.total, self.done, self.failed, self.frames = total, 0, 0, 0
        self.t0 = time.perf_counter()

    @property
    def seconds(self) -> float:
        return time.perf_counter() - self.t0

    def update(self, record: dict) -> None:
        if record["status"] == "done":
            self.done += 1
            self.frames += record["frames"]
        else:
            self.failed += 1
        if self.tty:
            n, width = self.done + self.failed, 30
            fill = width * n // max(self.total, 1)
            print(f"\r[{'#' * fill}{'.' * (width - fill)}] {n}/{self.total} jobs, {self.frames} frames"
                  f"{f', {self.failed} failed' if self.failed else ''}", end="", file=self.stream, flush=True)
            if n == self.total:
                print(file=self.stream)

    def final_line(self, skipped: int) -> str:
        """``bake: N jobs (D done, F failed, S already done) in T s: X jobs/s, Y frames/s``."""
        s = max(self.seconds, 1e-9)
        ran = self.done + self.failed
        return (f"bake: {ran + skipped} jobs ({self.done} done, {self.failed} failed, {skipped} already done) "
                f"in {s:.1f} s: {ran / s:.2f} jobs/s, {self.frames / s:.0f} frames/s")


def summary(jobs: list[Job], records: dict[int, dict], skipped: set[int], progress: Progress, runner: str,
            workers: int | None) -> dict:
    """The summary document: totals and each job's status, frames, seconds, worker and node.

    status: "done", "failed", "already done" (resumed: output in the manifest), "not run" (interrupted);
    attempts: runs of the job (more than 1 after a lost worker; None where the runner does not count).
    """
    rows = []
    for job in jobs:
        r = records.get(job.index)
        if r is not None:
            row = {k: r[k] for k in ("index", "output", "status", "error", "frames", "seconds",
                                     "load_seconds", "bind_seconds", "worker", "node")}
            rows.append(dict(row, attempts=r.get("attempts")))
        else:
            rows.append({"index": job.index, "output": job.output,
                         "status": "already done" if job.index in skipped else "not run", "error": None,
                         "frames": 0, "seconds": 0.0, "load_seconds": 0.0, "bind_seconds": 0.0,
                         "worker": None, "node": None, "attempts": 0})
    s = max(progress.seconds, 1e-9)
    return {"runner": runner, "workers": workers, "seconds": s, "jobs": len(jobs), "done": progress.done,
            "failed": progress.failed, "already_done": len(skipped), "frames": progress.frames,
            "jobs_per_second": (progress.done + progress.failed) / s, "frames_per_second": progress.frames / s,
            "records": rows}

