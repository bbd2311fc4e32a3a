"""Operators: each reads with the core, then builds Blender data with ``objects``."""

import warnings

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ImportHelper

from ..core.authoring import prepare
from ..core.classes import MINORITY_CLASSES
from ..core.errors import InputError
from ..core.importing import load_reconstruction
from . import authoring, intensity, objects, properties, scanning


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
    input_noun = "file"
    with_cameras = False

    def input_path(self) -> str:
        return self.filepath

    def execute(self, context):
        if not self.input_path():  # run without the file browser (a script, Redo with nothing picked)
            self.report({"ERROR"}, f"{self.bl_label}: no {self.input_noun} chosen")
            return {"CANCELLED"}
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
    """Import a COLMAP sparse model folder (points with color, track length and error)"""

    bl_idname = "import_scene.pgt_colmap"
    bl_label = "Import COLMAP Model"
    source_kind = "colmap"
    input_noun = "model folder"

    directory: StringProperty(name="Model folder", subtype="DIR_PATH", options=properties.PATH_OPTIONS,
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
    """Import a point-cloud PLY (binary or ASCII, optional colors and normals)"""

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

    class_name: EnumProperty(name="Class", description="Vehicle the sample is a reconstruction of",
                             items=[(c, c.replace("_", " ").title(), f"A parametric nuScenes {c.replace('_', ' ')}")
                                    for c in MINORITY_CLASSES])
    seed: IntProperty(name="Seed", default=0, min=0, description="Seed of the sample's noise, pose and scale")
    points: IntProperty(name="Points", default=20000, min=100, max=5_000_000,
                        description="Number of points the sample reconstruction has")

    def execute(self, context):
        from ..core.samples import synthetic_reconstruction

        sample = synthetic_reconstruction(self.class_name, seed=self.seed, points=self.points)
        obj = objects.add_reconstruction(context.scene, sample.to_reconstruction(), collection=context.collection)
        _select_only(context, obj)
        return {"FINISHED"}


class _AuthoringStep:
    """Shared poll and execute of the authoring operators: one core step on the active
    reconstruction; bad input is reported as an ERROR and changes nothing."""

    bl_options = {"REGISTER", "UNDO"}
    needs_alignment = True

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        if not authoring.is_reconstruction(obj):
            cls.poll_message_set("Select an imported reconstruction")
            return False
        if cls.needs_alignment and not authoring.status(obj)["aligned"]:
            cls.poll_message_set("Align the axes first")
            return False
        return True

    def execute(self, context):
        obj = context.active_object
        try:
            step = self.step(context, obj, context.scene.pgt_authoring)
        except InputError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        authoring.apply_step(obj, step)
        self.report({"INFO"}, f"{obj.name}: {self.bl_label.lower()}, box "
                              + " x ".join(f"{d:.3g}" for d in obj.pgt.dims))
        return {"FINISHED"}


class OBJECT_OT_pgt_align(_AuthoringStep, bpy.types.Operator):
    """Rotate the principal axes onto x (length), y (width), z (up) and centre the box"""

    bl_idname = "object.pgt_align"
    bl_label = "Align Axes"
    needs_alignment = False

    def step(self, context, obj, settings):
        if not len(obj.data.vertices):
            raise InputError(obj.pgt.source_path or obj.name, "has no points to align")
        source = obj.pgt.source_path or obj.name
        points = authoring.positions(obj)
        if settings.up == "cursor":
            up = np.array(obj.matrix_world.inverted() @ context.scene.cursor.location) - np.median(points, axis=0)
        elif settings.up == "face":
            up = authoring.selected_face_normal(obj)
            if up is None:
                raise InputError(source, "has no selected faces to take up from (select them in Edit Mode)")
        else:
            up = prepare.up_vector(settings.up, authoring.camera_poses(obj), source)
        return prepare.align_step(points, authoring.weights(obj), up, source, settings.refine,
                                  authoring.triangles(obj))


class OBJECT_OT_pgt_turn(_AuthoringStep, bpy.types.Operator):
    """Turn the object about its up axis by quarter turns (2: swap front and back)"""

    bl_idname = "object.pgt_turn"
    bl_label = "Turn"

    turns: IntProperty(name="Quarter turns", default=2, min=-3, max=3,
                       description="Counter-clockwise quarter turns seen from above")

    def step(self, context, obj, settings):
        return prepare.turn_step(self.turns, authoring.current_dims(obj))


class OBJECT_OT_pgt_front_from_cursor(_AuthoringStep, bpy.types.Operator):
    """Make the box side facing the 3D cursor the front (+x)"""

    bl_idname = "object.pgt_front_from_cursor"
    bl_label = "Front from Cursor"

    def step(self, context, obj, settings):
        cursor = obj.matrix_world.inverted() @ context.scene.cursor.location
        return prepare.front_step(tuple(cursor), authoring.current_dims(obj), obj.name)


class OBJECT_OT_pgt_auto_heading(_AuthoringStep, bpy.types.Operator):
    """Decide front and back automatically (PointNet classifier or geometric baseline)"""

    bl_idname = "object.pgt_auto_heading"
    bl_label = "Detect Front"

    def step(self, context, obj, settings):
        checkpoint = bpy.path.abspath(settings.checkpoint) if settings.checkpoint else None
        return prepare.automatic_heading_step(authoring.positions(obj), authoring.current_dims(obj),
                                              settings.heading_method, checkpoint, obj.pgt.source_path or obj.name)


class OBJECT_OT_pgt_set_size(_AuthoringStep, bpy.types.Operator):
    """Scale the object to a class size (with the paper's noise), an exact size, or keep it"""

    bl_idname = "object.pgt_set_size"
    bl_label = "Set Size"

    def step(self, context, obj, settings):
        problem = properties.class_problem(settings) if settings.size_mode == "class" else ""
        if problem:
            raise InputError(obj.name, problem)
        return prepare.size_step(authoring.current_dims(obj), settings.size_mode, settings.dataset, settings.class_name,
                                 settings.seed, settings.uniform, tuple(settings.exact_dims), obj.name)


class OBJECT_OT_pgt_scan(bpy.types.Operator):
    """Scan the active mesh or point cloud with the chosen LiDAR, placed on the ground"""

    bl_idname = "object.pgt_scan"
    bl_label = "Scan"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        if obj is None or obj.type != "MESH":
            cls.poll_message_set("Select a mesh or point-cloud object")
            return False
        return True

    def execute(self, context):
        obj, settings = context.active_object, context.scene.pgt_scan
        if obj.mode == "EDIT":
            obj.update_from_editmode()
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                result, sensor, sensor_from_object = scanning.scan(obj, settings)
        except InputError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        for warning in caught:
            self.report({"WARNING"}, str(warning.message))
        if not result.hits:  # legal but empty: say why, and leave the scene as it was
            self.report({"WARNING"}, f"{obj.name}: no returns at this pose, out of the {sensor.name} sensor's "
                                     f"range or view; no scan preview made")
            return {"CANCELLED"}
        preview = scanning.show_scan(context.scene, obj, result, sensor, sensor_from_object, settings)
        settings.stats = scanning.stats_text(result)
        self.report({"INFO"}, f"{obj.name}: {settings.stats}{self.learned_intensity(context, obj, preview, settings)}")
        return {"FINISHED"}

    def learned_intensity(self, context, source, preview, settings) -> str:
        """With a checkpoint in the preferences the scan takes the learned intensities, as
        the bank and scan_object.py do; a checkpoint that cannot serve this scan (no torch,
        another dataset, no such class) is reported and the physical law kept."""
        preferences = properties.preferences(context)
        checkpoint = bpy.path.abspath(preferences.intensity_checkpoint) if preferences else ""
        if not checkpoint:
            return ""
        try:
            rate = intensity.apply_estimator(preview, checkpoint, source.pgt.class_name, settings)
        except InputError as error:
            self.report({"WARNING"}, f"{error} (the scan keeps its physical intensities)")
            return ""
        return f" · learned intensity ({rate:,.0f} points/s)"


class OBJECT_OT_pgt_apply_intensity(bpy.types.Operator):
    """Replace the scan preview's intensities by the trained estimator's (checkpoint in the add-on preferences)"""

    bl_idname = "object.pgt_apply_intensity"
    bl_label = "Apply Intensity Model"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if context.active_object is None or intensity.source_of(context.active_object) is None:
            cls.poll_message_set("Select a scan preview (\"<object> Scan\") whose object still exists")
            return False
        return True

    def execute(self, context):
        settings = properties.preferences(context)
        checkpoint = bpy.path.abspath(settings.intensity_checkpoint) if settings else ""
        if not checkpoint:
            self.report({"ERROR"}, "No intensity checkpoint: set one in Preferences > Add-ons > PGT Blender "
                                   "(the scan keeps its physical intensities)")
            return {"CANCELLED"}
        preview = context.active_object
        source = intensity.source_of(preview)
        try:
            rate = intensity.apply_estimator(preview, checkpoint, source.pgt.class_name, context.scene.pgt_scan)
        except InputError as error:  # no torch, bad checkpoint, other dataset or class
            self.report({"ERROR"}, f"{error} (the scan keeps its physical intensities)")
            return {"CANCELLED"}
        self.report({"INFO"}, f"{len(preview.data.vertices)} intensities from {checkpoint} ({rate:,.0f} points/s)")
        return {"FINISHED"}


AUTHORING = (OBJECT_OT_pgt_align, OBJECT_OT_pgt_turn, OBJECT_OT_pgt_front_from_cursor,
             OBJECT_OT_pgt_auto_heading, OBJECT_OT_pgt_set_size)
IMPORTERS = (IMPORT_SCENE_OT_pgt_colmap, IMPORT_SCENE_OT_pgt_gaussian_splat,
             IMPORT_SCENE_OT_pgt_point_cloud, IMPORT_SCENE_OT_pgt_mesh)
classes = IMPORTERS + (OBJECT_OT_pgt_add_sample,) + AUTHORING + (OBJECT_OT_pgt_scan, OBJECT_OT_pgt_apply_intensity)
