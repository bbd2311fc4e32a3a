"""Shared fixtures and markers. Core tests never import bpy; Blender tests ask for ``scene``.

Markers are set here from what a test uses, so ``pytest -m "not blender and not slow"``
(``make test-core``) is a fast loop over the core:

- ``blender``: needs headless bpy (the ``registered`` / ``scene`` fixtures);
- ``data``: reads the shared data (``SHARED_DATA``: $PGT_SHARED_DATA, else ../shared/data; the
  ``shared_data`` fixture, skipped without it);
- ``torch``: trains or loads a network (TORCH_MODULES);
- ``slow``: runs the scripts as subprocesses, builds banks or runs the detectors' code
  (SLOW_MODULES).
"""

import os
import resource
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from pgt_blender.dev import SHARED_DATA  # noqa: F401  (the one setting: $PGT_SHARED_DATA or ../shared/data)

ROOT = Path(__file__).resolve().parents[1]


def file_size_limit(limit: int):
    """A child-process setup that makes writes past ``limit`` bytes fail (EFBIG), as a
    full disk makes them fail (ENOSPC): the same OSError path."""
    def limited():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return limited


def run_script(name: str, *args, check: bool = False, blender_style: bool = False, timeout: float = 600, **kwargs):
    """headless_scripts/<name> as a user runs it, a subprocess of this Python, output
    captured; ``check`` asserts exit status 0. ``blender_style`` runs it the way
    ``blender -b -P script.py -- ARGS`` does: Blender's own arguments before ``--``."""
    script = str(ROOT / "headless_scripts" / name)
    command = [sys.executable, script, *map(str, args)]
    if blender_style:
        code = ("import sys, runpy; script = sys.argv[1]; sys.argv = ['blender', '-b', '-P', script, '--', "
                "*sys.argv[2:]]; runpy.run_path(script, run_name='__main__')")
        command = [sys.executable, "-c", code, *command[1:]]
    result = subprocess.run(command, capture_output=True, text=True, timeout=timeout, **kwargs)
    if check:
        assert result.returncode == 0, result.stderr
    return result


TORCH_MODULES = {"test_intensity_model", "test_heading_classifier", "test_blender_intensity", "test_quality"}
SLOW_MODULES = {"test_scripts", "test_bad_input", "test_detectors", "test_bank", "test_bank_cluster",
                "test_blender_bank", "test_bank_report", "test_authoring", "test_quality"}


def pytest_collection_modifyitems(items):
    for item in items:
        module = item.module.__name__.rsplit(".", 1)[-1]
        if "registered" in item.fixturenames or module.startswith("test_blender"):
            item.add_marker(pytest.mark.blender)
        if "shared_data" in item.fixturenames:
            item.add_marker(pytest.mark.data)
        if module in TORCH_MODULES:
            item.add_marker(pytest.mark.torch)
        if module in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)


def pytest_sessionfinish(session, exitstatus):
    session.config.pgt_exitstatus = int(exitstatus)


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    """On Blender 4.2 the process would crash at exit after the add-on registered and
    lose pytest's status: end it with that status (cli.exit) once pytest is done."""
    bpy = sys.modules.get("bpy")
    if bpy is not None and bpy.app.version < (4, 5, 0):
        from pgt_blender.cli import exit

        exit(getattr(config, "pgt_exitstatus", 1))


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
