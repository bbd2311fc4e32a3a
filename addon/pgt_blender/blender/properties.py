"""Data pgt_blender stores on Blender objects."""

import bpy
from bpy.props import EnumProperty, FloatVectorProperty, StringProperty

from ..core.reconstruction import SOURCE_KINDS

_KIND_LABELS = {
    "colmap": "COLMAP model", "gaussian_splat": "Gaussian splats",
    "point_ply": "Point cloud", "mesh": "Mesh",
}
_IDENTITY = ((1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1))


class PGT_PG_object(bpy.types.PropertyGroup):
    """Where an object came from and what the authoring steps did to it (``Object.pgt``)."""

    source_path: StringProperty(name="Source", subtype="FILE_PATH",
                                description="File or COLMAP folder the object was imported from")
    source_kind: EnumProperty(
        name="Kind",
        items=[("none", "None", "Not imported by pgt_blender")]
        + [(kind, _KIND_LABELS[kind], "") for kind in SOURCE_KINDS],
        default="none",
    )
    source_sha256: StringProperty(name="Checksum", description="sha256 of the source file(s) content")
    class_name: StringProperty(name="Class", description="Dataset class; empty until set")
    # Filled by the authoring steps: the 4x4 from the source file's frame to the object frame.
    object_from_source: FloatVectorProperty(name="Object from source", size=(4, 4),
                                            subtype="MATRIX", default=_IDENTITY)


classes = (PGT_PG_object,)


def register():
    bpy.types.Object.pgt = bpy.props.PointerProperty(type=PGT_PG_object)


def unregister():
    del bpy.types.Object.pgt
