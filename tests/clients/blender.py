"""Blender 5's glTF importer as a test client: ``probe(path, times, clip)`` imports the file in a
separate Python that has ``bpy`` (``pip install bpy``, its own environment: ``make blender``
makes ``.venv-blender``; ``NRPOSE_BLENDER_PYTHON`` names another) and returns its report with
every mesh's evaluated world-space positions (glTF axes) at each time."""
from __future__ import annotations

import json
import os
import subprocess
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = Path(__file__).with_name("blender_probe.py")


def python() -> Path:
    return Path(os.environ.get("NRPOSE_BLENDER_PYTHON", ROOT / ".venv-blender" / "bin" / "python"))


def available() -> str | None:
    """None when a Python with bpy is there, else why not."""
    exe = python()
    if not exe.is_file():
        return f"no Python with bpy at {exe} (run `make blender`)"
    if subprocess.run([exe, "-c", "import bpy"], capture_output=True, timeout=120).returncode != 0:
        return f"{exe} cannot import bpy"
    return None


def probe(path, times, clip: str, timeout: float = 600) -> dict:
    """Blender's import of ``path``: report dict plus ``positions[i][m]`` (V_m, 3) float64 at times[i]."""
    with tempfile.TemporaryDirectory(prefix="nrpose-blender-") as tmp:
        out = Path(tmp) / "probe.npz"
        run = subprocess.run([python(), SCRIPT, str(Path(path).resolve()), str(out), clip,
                              *[repr(float(t)) for t in times]], capture_output=True, text=True, timeout=timeout)
        if run.returncode != 0:
            raise RuntimeError(f"blender probe failed ({run.returncode}): {run.stderr[-3000:]}")
        with np.load(out) as z:
            report = json.loads(str(z["report"]))
            report["positions"] = [[z[f"positions_{i}_{m}"] for m in range(len(report["meshes"]))]
                                   for i in range(len(times))]
    report["stderr"] = run.stderr
    return report
