"""OUTDIR/manifest.json: every finished output with its size and sha256; publishing outputs.

The manifest is ``{"format": "nrpose-bake-manifest", "version": 1, "outputs":
{OUTPUT: {"spec": sha256 of the job's options, "size": bytes, "sha256": hex,
"frames": F}}}``, keyed by the output's name under OUTDIR, so it lists an
output at most once. Only the driver writes it (at most once a second
while jobs finish, and at the end or on an interrupt), each time through a
temporary file and ``os.replace``: a reader (or a resumed run) never sees
half of it. A directory output's size is the sum of its files' sizes and its
checksum the sha256 over its sorted ``name\\0sha256\\n`` lines.

Outputs are written under ``OUTDIR/.bake-tmp/<unique>/`` and moved to their
deterministic names by :func:`publish` (``os.replace``), so a job run twice
(a retry after a lost worker) leaves one complete output, never two or a
partial one.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
import time
import uuid
from pathlib import Path

from ...io.jsonfile import check_json_size, parse_json
from .jobs import Job

NAME = "manifest.json"
TMP = ".bake-tmp"
#: seconds between manifest saves while jobs finish (one rewrite per job is quadratic in the jobs);
#: an output finished but not yet saved is simply made again by --resume
SAVE_EVERY = 1.0


def digest(path: Path) -> tuple[int, str]:
    """(size in bytes, sha256 hex) of a file or of a directory's files (module docstring)."""
    if path.is_dir():
        lines, size = [], 0
        for f in sorted(p for p in path.iterdir() if p.is_file()):
            s, h = digest(f)
            size += s
            lines.append(f"{f.name}\0{h}\n")
        return size, hashlib.sha256("".join(lines).encode()).hexdigest()
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return path.stat().st_size, h.hexdigest()


def scratch(outdir: Path) -> Path:
    """A new private directory under OUTDIR/.bake-tmp for one attempt at one job."""
    d = outdir / TMP / uuid.uuid4().hex
    d.mkdir(parents=True)
    return d


def publish(tmp: Path, final: Path) -> None:
    """Move a finished output (file or directory) from its scratch name to ``final``."""
    final.parent.mkdir(parents=True, exist_ok=True)
    if tmp.is_dir() and final.exists():
        # a directory cannot replace a non-empty one: move the old one aside first
        old = tmp.parent / (tmp.name + ".old")
        os.replace(final, old)
        os.replace(tmp, final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, final)


def clear_scratch(outdir: Path) -> None:
    """Remove every scratch directory (attempts that died leave theirs)."""
    shutil.rmtree(outdir / TMP, ignore_errors=True)


class Manifest:
    """The manifest of one OUTDIR (module docstring)."""

    def __init__(self, outdir: Path):
        self.path = outdir / NAME
        self.outputs: dict[str, dict] = {}
        self.saved = -math.inf
        if self.path.exists():
            try:
                check_json_size(self.path, "the manifest")
                doc = parse_json(self.path.read_text(), str(self.path), "the manifest")
                self.outputs = dict(doc["outputs"])
            except (OSError, ValueError, KeyError, TypeError):     # NrposeError is a ValueError
                self.outputs = {}       # unreadable: nothing counts as finished

    def finished(self, job: Job, outdir: Path) -> bool:
        """True when the job's output is recorded for these options and the file still matches."""
        entry = self.outputs.get(job.output)
        if not isinstance(entry, dict) or entry.get("spec") != job.spec:
            return False
        out = outdir / job.output
        if not out.exists():
            return False
        return digest(out) == (entry.get("size"), entry.get("sha256"))

    def record(self, job: Job, size: int, sha256: str, frames: int) -> None:
        """Record a finished output; saved at most every :data:`SAVE_EVERY` seconds (and by :meth:`save`)."""
        self.outputs[job.output] = {"spec": job.spec, "size": size, "sha256": sha256, "frames": frames}
        if time.monotonic() - self.saved >= SAVE_EVERY:
            self.save()

    def forget(self, jobs) -> None:
        for job in jobs:
            self.outputs.pop(job.output, None)
        self.save()

    def save(self) -> None:
        doc = {"format": "nrpose-bake-manifest", "version": 1,
               "outputs": dict(sorted(self.outputs.items()))}
        fd, tmp = tempfile.mkstemp(prefix=".manifest-", suffix=".tmp", dir=self.path.parent)
        try:
            with os.fdopen(fd, "w") as fh:
                json.dump(doc, fh, indent=1)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, self.path)
            self.saved = time.monotonic()
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
