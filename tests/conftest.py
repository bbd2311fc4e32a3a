"""Shared fixtures. Core tests never import bpy; Blender tests ask for ``scene``."""

import os
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data (real third-party data); tests using it skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real test data not found at {SHARED_DATA} (the project's ../shared/data)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def statue(shared_data) -> Path:
    return shared_data / "colmap_statue" / "sparse" / "0"


@pytest.fixture(scope="session")
def donut(shared_data) -> Path:
    return shared_data / "gaussian_splat_donut" / "fused.ply"


@pytest.fixture(scope="session")
def chrono_meshes(shared_data) -> list:
    return sorted((shared_data / "chrono_vehicles").rglob("*.obj"))


@pytest.fixture
def statue_copy(statue, tmp_path) -> Path:
    """A writable copy of the COLMAP model, for breaking it."""
    return Path(shutil.copytree(statue, tmp_path / "sparse0"))


@pytest.fixture(scope="session")
def registered():
    """Headless Blender with the add-on registered for the session."""
    bpy = pytest.importorskip("bpy")
    import pgt_blender

    pgt_blender.register()
    yield bpy
    # The bpy module hangs at exit while Python operators stay registered.
    pgt_blender.unregister()


@pytest.fixture
def scene(registered):
    """An empty factory scene for each Blender test."""
    bpy = registered
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return bpy.context.scene


def datablock_counts(bpy) -> dict:
    """How many objects, meshes, cameras and node groups the file holds (nothing
    half-imported may stay)."""
    return {"objects": len(bpy.data.objects), "meshes": len(bpy.data.meshes),
            "cameras": len(bpy.data.cameras), "node_groups": len(bpy.data.node_groups)}


class CodeOnLoad:
    """Unpickling this runs a shell command that creates ``marker``: what a crafted
    database can do to a plain ``pickle.load``."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)
