"""The extension package: manifest validation, zip build, install into headless Blender."""

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "headless_scripts"))

import build_extension  # noqa: E402


def blender_ext(*args):
    return subprocess.run([sys.executable, str(build_extension.blender_ext_cli()), *map(str, args)],
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="session")
def extension_zip(tmp_path_factory):
    """The linux-x64 extension with its bundled wheels (pip fetches them once)."""
    return build_extension.build(["linux-x64"], tmp_path_factory.mktemp("dist") / "pgt_blender.zip")


def test_manifest_validates(tmp_path):
    build_extension.stage(tmp_path / "pkg", ["linux-x64"], wheels=[])
    result = blender_ext("validate", tmp_path / "pkg")
    assert result.returncode == 0, result.stdout + result.stderr


def test_invalid_manifest_is_refused(tmp_path):
    build_extension.stage(tmp_path / "pkg", ["linux-x64"], wheels=[])
    manifest = tmp_path / "pkg" / "blender_manifest.toml"
    manifest.write_text(manifest.read_text().replace('blender_version_min = "4.2.0"', 'blender_version_min = "4.x"'))
    assert blender_ext("validate", tmp_path / "pkg").returncode != 0


def test_bundled_wheels_are_the_runtime_dependencies(extension_zip):
    import zipfile

    names = zipfile.ZipFile(extension_zip).namelist()
    wheels = sorted(Path(n).name.split("-")[0] for n in names if n.endswith(".whl"))
    assert wheels == ["embreex", "manifold3d", "pillow", "pycolmap", "pyyaml", "scipy", "trimesh"]  # numpy comes with Blender
    assert "blender_manifest.toml" in names and "__init__.py" in names
    assert "models/heading_pointnet.pt" in names  # the shipped heading classifier
    assert not any("__pycache__" in n for n in names)
    assert "dev.py" not in names and "cli.py" in names  # nothing benchmark-only ships


# Runs in a fresh interpreter with HOME in a temporary folder (Blender's user config
# lives there). The venv's own copies of the bundled packages are hidden, so the
# import below can only succeed from the wheels the extension installed.
INSTALL_SCRIPT = textwrap.dedent("""
    import importlib, importlib.abc, importlib.machinery, os, sys
    site = {p for p in sys.path if p.endswith("site-packages")}
    class HideVenvCopies(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] not in ("pycolmap", "trimesh", "manifold3d", "scipy", "yaml", "embreex") \\
                    or path is not None:
                return None
            spec = importlib.machinery.PathFinder.find_spec(name, [p for p in sys.path if p not in site])
            if spec is None:
                raise ModuleNotFoundError(name)
            return spec
    sys.meta_path.insert(0, HideVenvCopies())

    import bpy
    zip_path, statue, calibration, module = sys.argv[1:4] + ["bl_ext.user_default.pgt_blender"]
    assert bpy.ops.extensions.package_install_files(
        filepath=zip_path, repo="user_default", enable_on_install=True) == {"FINISHED"}
    assert module in bpy.context.preferences.addons
    assert hasattr(bpy.types.Object, "pgt") and hasattr(bpy.types, "VIEW3D_PT_pgt_import")
    for name in ("pgt_colmap", "pgt_gaussian_splat", "pgt_point_cloud", "pgt_mesh"):
        assert hasattr(bpy.ops.import_scene, name)
    assert bpy.ops.import_scene.pgt_colmap(directory=statue) == {"FINISHED"}
    import pycolmap
    assert "extensions" in pycolmap.__file__, pycolmap.__file__
    assert len(bpy.context.active_object.data.vertices) == 1816
    assert bpy.ops.object.pgt_align() == {"FINISHED"}  # scipy's KD-tree, from the bundled wheel
    import scipy
    assert "extensions" in scipy.__file__, scipy.__file__
    sensors = importlib.import_module(module + ".core.scan.sensors")  # reads YAML with the bundled PyYAML
    assert len(sensors.read_velodyne_calibration(calibration)["elevations_deg"]) == 32
    import yaml
    assert "extensions" in yaml.__file__, yaml.__file__
    bpy.context.scene.pgt_scan.distance = 10.0
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}  # the default engine: Embree, from the bundled wheel
    import embreex
    assert "extensions" in embreex.__file__, embreex.__file__
    bpy.ops.preferences.addon_disable(module=module)
    assert not hasattr(bpy.types.Object, "pgt") and not hasattr(bpy.types, "VIEW3D_PT_pgt_import")
    bpy.ops.preferences.addon_enable(module=module)
    assert hasattr(bpy.types.Object, "pgt")
    bpy.ops.preferences.addon_disable(module=module)
    repos = bpy.context.preferences.extensions.repos
    index = next(i for i, repo in enumerate(repos) if repo.module == "user_default")
    assert bpy.ops.extensions.package_uninstall(repo_index=index, pkg_id="pgt_blender") == {"FINISHED"}
    assert not os.path.exists(os.path.join(repos[index].directory, "pgt_blender"))
    print("EXTENSION-OK", flush=True)
    if bpy.app.version < (4, 5, 0):  # 4.2 crashes at exit after an add-on's callbacks (see cli.exit),
        os._exit(0)                  # which this process cannot import: the venv copy is hidden
""")


def test_install_enable_disable_remove(extension_zip, tmp_path, shared_data):
    statue = shared_data / "colmap_statue" / "sparse" / "0"
    env = {"HOME": str(tmp_path), "PATH": "/usr/bin:/bin"}
    calibration = shared_data / "velodyne_calibrations" / "32db.yaml"
    result = subprocess.run([sys.executable, "-c", INSTALL_SCRIPT, str(extension_zip), str(statue), str(calibration)],
                            capture_output=True, text=True, timeout=600, env=env)
    assert "EXTENSION-OK" in result.stdout, result.stdout[-3000:] + result.stderr[-3000:]
    assert result.returncode == 0
