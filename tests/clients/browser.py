"""three.js's GLTFLoader in headless Chromium, as a test client for nrpose's glTF outputs.

``probe(path, times)`` serves the file's folder, three.js (Debian's ``libjs-three``) and
``probe.html`` on 127.0.0.1 only, loads the file in headless Chromium and returns the page's
report: animations, meshes (attributes, materials, morph targets), console errors and
warnings, and every mesh's world-space vertex positions at each time, computed from
three.js's own animation mixer, morph influences and skeleton matrices. ``screenshot``
renders one frame to a PNG. ``available()`` says why the client cannot run, or None.
"""
from __future__ import annotations

import functools
import html
import http.server
import json
import os
import re
import shutil
import subprocess
import tempfile
import threading
import urllib.parse
from contextlib import contextmanager
from pathlib import Path

import numpy as np

THREE = Path("/usr/share/javascript/three")
PAGE = Path(__file__).with_name("probe.html")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = ["--headless", "--no-sandbox", "--disable-dev-shm-usage", "--no-first-run",
         "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--hide-scrollbars",
         "--disable-background-networking", "--virtual-time-budget=60000"]


def available() -> str | None:
    """None when Chromium and three.js are installed, else the reason they cannot be used."""
    if CHROMIUM is None:
        return "chromium not installed (Debian package chromium)"
    if not (THREE / "examples/jsm/loaders/GLTFLoader.js").is_file():
        return "three.js not installed (Debian package libjs-three)"
    return None


class _Handler(http.server.SimpleHTTPRequestHandler):
    """/three/... from three.js, /probe.html, /files/... from the served folder."""

    def __init__(self, *args, folder: Path, **kwargs):
        self.folder = folder
        super().__init__(*args, directory=str(folder), **kwargs)

    def translate_path(self, path):
        path = urllib.parse.unquote(urllib.parse.urlsplit(path).path)
        if path.startswith("/three/"):
            return str(THREE / path[len("/three/"):])
        if path == "/probe.html":
            return str(PAGE)
        if path.startswith("/files/"):
            return str(self.folder / path[len("/files/"):])
        return str(self.folder / "__nothing__")

    def log_message(self, *args):  # quiet
        pass


@contextmanager
def _server(folder: Path):
    handler = functools.partial(_Handler, folder=folder)
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()


def _chromium(args: list[str], timeout: float) -> str:
    with tempfile.TemporaryDirectory(prefix="nrpose-chromium-") as profile:
        run = subprocess.run([CHROMIUM, *FLAGS, f"--user-data-dir={profile}", *args], capture_output=True,
                             text=True, timeout=timeout, env={**os.environ, "HOME": profile})
    if run.returncode != 0:
        raise RuntimeError(f"chromium exited {run.returncode}: {run.stderr[-2000:]}")
    return run.stdout


def _url(base: str, path: Path, times, clip: str | None, shot: float | None) -> str:
    query = {"file": path.name, "times": json.dumps([float(t) for t in times])}
    if clip is not None:
        query["clip"] = clip
    if shot is not None:
        query["shot"] = repr(float(shot))
    return f"{base}/probe.html?{urllib.parse.urlencode(query)}"


def probe(path, times=(), clip: str | None = None, timeout: float = 300) -> dict:
    """The page's report for glTF file ``path`` (its folder is served: external buffers and
    images load). ``samples[i]["meshes"][m]["positions"]`` become (V, 3) float64 arrays."""
    path = Path(path).resolve()
    with _server(path.parent) as base:
        dom = _chromium(["--dump-dom", _url(base, path, times, clip, None)], timeout)
    found = re.search(r'<pre id="result"[^>]*>(.*?)</pre>', dom, re.S)
    if not found or not found.group(1).strip():
        raise RuntimeError(f"the probe page did not finish: {dom[-2000:]}")
    report = json.loads(html.unescape(found.group(1)))
    for sample in report.get("samples", []):
        for mesh in sample["meshes"]:
            mesh["positions"] = np.asarray(mesh["positions"], dtype=np.float64).reshape(-1, 3)
    return report


def screenshot(path, png, time: float = 0.0, clip: str | None = None, size=(960, 720), timeout: float = 300) -> Path:
    """Render ``path`` at ``time`` to ``png`` (lit, textured as the file says); returns ``png``."""
    path, png = Path(path).resolve(), Path(png).resolve()
    with _server(path.parent) as base:
        _chromium([f"--screenshot={png}", f"--window-size={size[0]},{size[1]}",
                   _url(base, path, (), clip, time)], timeout)
    if not png.is_file():
        raise RuntimeError(f"chromium wrote no screenshot to {png}")
    return png
