"""Gather a scene's authored objects as the bank's inputs (core/bank/inputs.py), in bulk.

An object's mesh data is its object frame (authoring wrote it so); its box is the last
authoring step's dims. Meshes give their triangles, point objects their points; colors
come from the per-point color attribute (sRGB), as the prepared-object route reads them
from the PLY, so the same objects by either route make the same bank.
"""

from pathlib import Path

import bpy
import numpy as np

from ..core.bank.inputs import BankObject, incomplete_reason
from ..core.reconstruction import Reconstruction
from .authoring import current_dims, is_reconstruction, status
from .scanning import mesh_triangles, mesh_vertices, point_colors


def scene_bank_objects(scene: bpy.types.Scene) -> tuple[list, list]:
    """(BankObjects of the complete reconstructions in ``scene`` by name, incomplete
    ones as (name, reason))."""
    objects, incomplete = [], []
    for obj in sorted(scene.objects, key=lambda o: o.name):
        if not is_reconstruction(obj):
            continue
        reason = incomplete_reason(obj.pgt.class_name, bool(status(obj)["size"]))
        if reason:
            incomplete.append((obj.name, reason))
            continue
        mesh = obj.data
        faces = mesh_triangles(mesh)[0] if len(mesh.polygons) else np.zeros((0, 3), np.int32)
        geometry = Reconstruction(mesh_vertices(mesh), "mesh" if len(faces) else "point_ply",
                                  Path(bpy.data.filepath or "scene") / obj.name, obj.pgt.source_sha256,
                                  faces=faces, colors=point_colors(mesh))
        objects.append(BankObject(obj.name, obj.pgt.class_name, current_dims(obj), geometry))
    return objects, incomplete
