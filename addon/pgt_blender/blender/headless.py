"""What headless_scripts/ that use Blender need: the add-on registered in a bpy module
process as Blender would register it (arguments and exit codes: ../cli.py)."""

import atexit
import os
import sys
import tempfile

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
    cannot write it. Blender's own lines are held back while it saves: "Info: Saved as
    ..." would break a command's --json output on standard output, so it goes to standard
    error; a failure's line names Blender's ``path@`` temporary, so the InputError alone
    reports it."""
    path = os.path.abspath(path)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    sys.stdout.flush()
    sys.stderr.flush()
    originals = os.dup(1), os.dup(2)
    with tempfile.TemporaryFile() as said:
        os.dup2(said.fileno(), 1)
        os.dup2(said.fileno(), 2)
        try:
            bpy.ops.wm.save_as_mainfile(filepath=path)
        except RuntimeError as error:  # Blender reports a failed write as a RuntimeError
            raise InputError(path, f"cannot write the .blend: {str(error).strip().splitlines()[-1]}") from None
        finally:
            for stream, original in zip((1, 2), originals):
                os.dup2(original, stream)
                os.close(original)
        said.seek(0)
        sys.stderr.write(said.read().decode(errors="replace"))


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
