"""Fixtures shared by test modules: the shared Fox character and a binding cache of the test's own."""
from pathlib import Path

import pytest

FOX = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "gltf" / "Fox.glb"


@pytest.fixture
def fox():
    """The Fox of ../shared/data loaded as a Character (skips without the shared assets or pyopencl)."""
    if not FOX.exists():
        pytest.skip(f"shared assets not found at {FOX}")
    pytest.importorskip("pyopencl")
    from nrpose.io import load_character
    return load_character(FOX)


@pytest.fixture
def own_cache(tmp_path, monkeypatch):
    """NRPOSE_CACHE_DIR in the test's temporary folder: binds of other tests and runs are not seen."""
    monkeypatch.setenv("NRPOSE_CACHE_DIR", str(tmp_path / "cache"))
