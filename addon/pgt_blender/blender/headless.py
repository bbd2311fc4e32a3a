"""What headless_scripts/ that use Blender need: the add-on registered in a bpy module
process as Blender would register it (arguments and exit codes: ../cli.py)."""

import atexit
import os
import sys

import bpy

from ..core.errors import InputError


def ensure_registered() -> None:
    """Register the add-on unless Blender already has it enabled. Unregister at exit:
    the bpy module hangs on exit while Python-defined operators are registered."""
    if hasattr(bpy.types.Object, "pgt"):
        return
    from .. import register, unregister

    register()
    atexit.register(unregister)


def start_scene() -> None:
    """An empty scene, unless a .blend was given on Blender's command line."""
    if not bpy.data.filepath:
        bpy.ops.wm.read_factory_settings(use_empty=True)


def save_blend(path) -> None:
    """Save the open file as ``path`` (its folder made first); InputError when Blender
    cannot write it. Blender prints "Info: Saved as ..." on the process's standard
    output, which would break a command's --json output: it goes to standard error."""
    path = os.path.abspath(path)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    sys.stdout.flush()
    stdout = os.dup(1)
    os.dup2(2, 1)
    try:
        bpy.ops.wm.save_as_mainfile(filepath=path)
    except RuntimeError as error:  # Blender reports a failed write as a RuntimeError
        raise InputError(path, f"cannot write the .blend: {str(error).strip().splitlines()[-1]}") from None
    finally:
        os.dup2(stdout, 1)
        os.close(stdout)


def object_summary(obj: bpy.types.Object) -> dict:
    """What arrived in Blender for an imported object, as JSON-ready values."""
    mesh = obj.data
    return {
        "object": obj.name,
        "kind": obj.pgt.source_kind,
        "path": obj.pgt.source_path,
        "sha256": obj.pgt.source_sha256,
        "points": len(mesh.vertices),
        "faces": len(mesh.polygons),
        "cameras": sum(child.type == "CAMERA" for child in obj.children),
        "attributes": sorted(a.name for a in mesh.attributes
                             if not a.name.startswith(".") and a.name != "position"),
    }
