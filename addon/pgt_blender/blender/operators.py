"""Operators: each reads with the core, then builds Blender data with ``objects``."""

import bpy
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from ..core.classes import MINORITY_CLASSES
from ..core.errors import InputError
from ..core.importing import load_reconstruction
from . import objects


def _select_only(context, obj):
    for other in context.selected_objects:
        other.select_set(False)
    obj.select_set(True)
    context.view_layer.objects.active = obj


class _ImportReconstruction:
    """Shared execute of the importers: core read, then one bulk object build.
    Bad input is reported as an ERROR and leaves the scene untouched."""

    bl_options = {"REGISTER", "UNDO"}
    source_kind = "auto"
    with_cameras = False

    def input_path(self) -> str:
        return self.filepath

    def execute(self, context):
        try:
            recon = load_reconstruction(self.input_path(), kind=self.source_kind,
                                        with_cameras=self.with_cameras)
            obj = objects.add_reconstruction(context.scene, recon, self.with_cameras, context.collection)
        except InputError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        _select_only(context, obj)
        summary = recon.summary()
        self.report({"INFO"}, f"Imported {obj.name}: {summary['points']} points, "
                              f"{summary['faces']} faces, {len(obj.children)} cameras")
        return {"FINISHED"}


class IMPORT_SCENE_OT_pgt_colmap(_ImportReconstruction, bpy.types.Operator):
    """Import a COLMAP sparse model folder (points with colour, track length and error)"""

    bl_idname = "import_scene.pgt_colmap"
    bl_label = "Import COLMAP Model"
    source_kind = "colmap"

    directory: StringProperty(name="Model folder", subtype="DIR_PATH",
                              description="Folder with cameras, images and points3D (.bin or .txt)")
    filter_folder: BoolProperty(default=True, options={"HIDDEN"})
    with_cameras: BoolProperty(name="Cameras", default=True,
                               description="Add the registered photos as cameras, children of the points")

    def input_path(self) -> str:
        return self.directory

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}


class IMPORT_SCENE_OT_pgt_gaussian_splat(ImportHelper, _ImportReconstruction, bpy.types.Operator):
    """Import a 3D Gaussian Splatting PLY (opacity, scale and rotation as attributes)"""

    bl_idname = "import_scene.pgt_gaussian_splat"
    bl_label = "Import Gaussian Splats"
    source_kind = "gaussian_splat"
    filename_ext = ".ply"
    filter_glob: StringProperty(default="*.ply", options={"HIDDEN"})


class IMPORT_SCENE_OT_pgt_point_cloud(ImportHelper, _ImportReconstruction, bpy.types.Operator):
    """Import a point-cloud PLY (binary or ASCII, optional colours and normals)"""

    bl_idname = "import_scene.pgt_point_cloud"
    bl_label = "Import Point Cloud"
    source_kind = "point_ply"
    filename_ext = ".ply"
    filter_glob: StringProperty(default="*.ply", options={"HIDDEN"})


class IMPORT_SCENE_OT_pgt_mesh(ImportHelper, _ImportReconstruction, bpy.types.Operator):
    """Import a reconstructed mesh (OBJ, PLY, GLB/GLTF, STL) through trimesh"""

    bl_idname = "import_scene.pgt_mesh"
    bl_label = "Import Reconstructed Mesh"
    source_kind = "mesh"
    filter_glob: StringProperty(default="*.obj;*.ply;*.glb;*.gltf;*.stl", options={"HIDDEN"})


class OBJECT_OT_pgt_add_sample(bpy.types.Operator):
    """Add a built-in synthetic reconstruction of a parametric vehicle (noisy, posed, scaled)"""

    bl_idname = "object.pgt_add_sample"
    bl_label = "Add Sample Reconstruction"
    bl_options = {"REGISTER", "UNDO"}

    class_name: EnumProperty(name="Class", items=[(c, c.replace("_", " ").title(), "") for c in MINORITY_CLASSES])
    seed: IntProperty(name="Seed", default=0, min=0)
    points: IntProperty(name="Points", default=20000, min=100, max=5_000_000)

    def execute(self, context):
        from ..core.samples import synthetic_reconstruction

        sample = synthetic_reconstruction(self.class_name, seed=self.seed, points=self.points)
        obj = objects.add_reconstruction(context.scene, sample.to_reconstruction(), collection=context.collection)
        _select_only(context, obj)
        return {"FINISHED"}


IMPORTERS = (IMPORT_SCENE_OT_pgt_colmap, IMPORT_SCENE_OT_pgt_gaussian_splat,
             IMPORT_SCENE_OT_pgt_point_cloud, IMPORT_SCENE_OT_pgt_mesh)
classes = IMPORTERS + (OBJECT_OT_pgt_add_sample,)
