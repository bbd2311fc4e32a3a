"""Operators: each reads with the core, then builds Blender data with ``objects``."""

import json
import warnings
from contextlib import contextmanager
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper

from ..core.authoring import prepare
from ..core.bank.config import config_toml
from ..core.bank.folder import WORK
from ..core.capture import CaptureOptions
from ..core.classes import MINORITY_CLASSES
from ..core.errors import InputError, one_line, printable
from ..core.files import apart_from_inputs, atomic_output, output_path, regular_file
from ..core.importing import SUPPORTED, find_reconstructions, load_reconstruction
from . import authoring, bank, intensity, objects, placement, properties, scanning

# What an operator reports as one ERROR line and CANCELLED, never a traceback: bad input,
# or a read or write that failed (a name too long, a full disk, no permission).
REPORTED = (InputError, OSError)


@contextmanager
def progress(context, total: int):
    """Blender's progress indicator over ``total`` items: yields ``advance(item) -> item``."""
    manager, done = context.window_manager, [0]
    manager.progress_begin(0, max(total, 1))

    def advance(item):
        done[0] += 1
        manager.progress_update(done[0])
        return item
    try:
        yield advance
    finally:
        manager.progress_end()


def _select_only(context, obj):
    for other in context.selected_objects:
        other.select_set(False)
    obj.select_set(True)
    context.view_layer.objects.active = obj


def _nothing_chosen(operator, path: str, noun: str) -> bool:
    """True, with "<label>: no <noun> chosen" reported, when ``path`` is empty: the
    operator ran without its file browser (a script, Redo with nothing picked)."""
    if path:
        return False
    operator.report({"ERROR"}, f"{operator.bl_label}: no {noun} chosen")
    return True


class _ImportReconstruction:
    """Shared execute of the importers: core read, then one bulk object build.
    Bad input is reported as an ERROR and leaves the scene untouched."""

    bl_options = {"REGISTER", "UNDO"}
    source_kind = "auto"
    input_noun = "file"
    with_cameras = False

    def input_path(self) -> str:
        return self.filepath

    def capture_options(self) -> CaptureOptions | None:
        """What the capture settings ask for (``_CaptureSettings``), None without them."""
        return None

    def cameras_path(self):
        return None

    def execute(self, context):
        if _nothing_chosen(self, self.input_path(), self.input_noun):
            return {"CANCELLED"}
        try:
            capture = self.capture_options()
            recon = load_reconstruction(self.input_path(), kind=self.source_kind, with_cameras=self.with_cameras,
                                        cameras=self.cameras_path(), capture=capture)
            obj = objects.add_reconstruction(context.scene, recon, self.with_cameras, context.collection)
        except REPORTED as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        _select_only(context, obj)
        summary = recon.summary()
        if recon.capture:
            obj["pgt_capture"] = json.dumps(recon.capture)
        self.report({"INFO"}, f"Imported {obj.name}: {summary['points']} points, "
                              f"{summary['faces']} faces, {len(obj.children)} cameras{_capture_note(recon.capture)}")
        return {"FINISHED"}


def _capture_note(report: dict) -> str:
    """The capture report in a few words for the status bar."""
    note = ""
    if "view_color" in report:
        color = report["view_color"]
        note += f"; view color: {color['hit_share']:.0%} hit in {report['cameras']} views"
    if "foreground" in report:
        note += f"; foreground: kept {report['foreground']['kept']} of {report['foreground']['elements']}"
    return note


class _CaptureSettings:
    """Capture options of the importers whose inputs come with training cameras."""

    view_color: BoolProperty(
        name="View-Agnostic Color", default=False,
        description="Replace each splat's or voxel's color by its mean spherical-harmonic color over the training "
                    "views whose rays hit it; never hit: DC color, view_hit attribute False")
    foreground: EnumProperty(
        name="Foreground", default="none", description="Keep only the captured object",
        items=[("none", "Everything", "Keep every element"),
               ("masks", "Masks", "Keep elements inside the per-image masks in enough of the views that see them"),
               ("plane", "Remove Support Plane",
                "Remove the support plane (table, turntable, ground) and keep the connected object at the centre "
                "of the camera orbit")])
    masks_directory: StringProperty(name="Masks", subtype="DIR_PATH", options=properties.PATH_OPTIONS,
                                    description="Folder of per-image masks named after the images (IMG_1.png for "
                                                "IMG_1.jpg): white or opaque is the object")
    mask_share: FloatProperty(name="Mask Share", default=0.5, min=0.0, max=1.0, subtype="FACTOR",
                              description="Share of the views seeing an element that must put it inside the mask")
    seed: IntProperty(name="Seed", default=0, min=0, description="Seed of the foreground's random draws")

    def capture_options(self) -> CaptureOptions | None:
        if self.foreground == "masks" and not self.masks_directory:
            raise InputError(self.input_path(), "Foreground Masks needs a masks folder")
        options = CaptureOptions(view_color=self.view_color, foreground=self.foreground,
                                 masks=bpy.path.abspath(self.masks_directory) if self.masks_directory else None,
                                 mask_share=self.mask_share, seed=self.seed)
        return options if options.needs_cameras else None


class _CameraFile:
    """The training cameras of a splat or Plenoxels file, when they are not beside it."""

    cameras_file: StringProperty(name="Cameras", subtype="FILE_PATH", options=properties.PATH_OPTIONS,
                                 description="Training cameras in the input's frame (3DGS cameras.json or a COLMAP "
                                             "model folder); empty: the run's own or a cameras.json beside the file")
    with_cameras: BoolProperty(name="Add Cameras", default=False,
                               description="Also add the training cameras to the scene, children of the points: "
                                           "Align's Up Auto then takes their mean up")

    def cameras_path(self):
        return bpy.path.abspath(self.cameras_file) if self.cameras_file else None


class _ChoosesFolder:
    """Opens the file browser on folders for the operator's ``directory`` (as ImportHelper
    does for a file)."""

    filter_folder: BoolProperty(default=True, options={"HIDDEN"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}


class IMPORT_SCENE_OT_pgt_colmap(_ChoosesFolder, _CaptureSettings, _ImportReconstruction, bpy.types.Operator):
    """Import a COLMAP sparse model folder (points with color, track length and error)"""

    bl_idname = "import_scene.pgt_colmap"
    bl_label = "Import COLMAP Model"
    source_kind = "colmap"
    input_noun = "model folder"

    directory: StringProperty(name="Model folder", subtype="DIR_PATH", options=properties.PATH_OPTIONS,
                              description="Folder with cameras, images and points3D (.bin or .txt)")
    with_cameras: BoolProperty(name="Cameras", default=True,
                               description="Add the registered photos as cameras, children of the points: Align's Up "
                                           "Auto takes their mean up (without them, the PCA minor axis)")

    def input_path(self) -> str:
        return self.directory


class IMPORT_SCENE_OT_pgt_gaussian_splat(ImportHelper, _CaptureSettings, _CameraFile, _ImportReconstruction,
                                         bpy.types.Operator):
    """Import a Gaussian-splat PLY: 3DGS (point_cloud.ply of an output folder, with its cameras) or nerfstudio splatfacto"""

    bl_idname = "import_scene.pgt_gaussian_splat"
    bl_label = "Import Gaussian Splats"
    source_kind = "gaussian_splat"
    filename_ext = ".ply"
    filter_glob: StringProperty(default="*.ply", options={"HIDDEN"})


class IMPORT_SCENE_OT_pgt_plenoxels(ImportHelper, _CaptureSettings, _CameraFile, _ImportReconstruction,
                                    bpy.types.Operator):
    """Import a Plenoxels (svox2) checkpoint .npz: occupied voxels as points with density, opacity and SH color"""

    bl_idname = "import_scene.pgt_plenoxels"
    bl_label = "Import Plenoxels Grid"
    source_kind = "plenoxels"
    filename_ext = ".npz"
    filter_glob: StringProperty(default="*.npz", options={"HIDDEN"})


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


class IMPORT_SCENE_OT_pgt_folder(_ChoosesFolder, bpy.types.Operator):
    """Import every reconstruction in a folder (files, 3DGS output folders, COLMAP model folders); one bad file imports none"""

    bl_idname = "import_scene.pgt_folder"
    bl_label = "Import Folder"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(name="Folder", subtype="DIR_PATH", options=properties.PATH_OPTIONS,
                              description="Folder whose reconstructions are imported")

    def execute(self, context):
        if _nothing_chosen(self, self.directory, "folder"):
            return {"CANCELLED"}
        folder = Path(bpy.path.abspath(self.directory))
        built = []
        try:  # every file is read before any Blender data is made, and one that Blender refuses (an
            # attribute name it keeps for itself) takes back the others: the scene stays as it was
            found = find_reconstructions(folder)
            if not found:
                raise InputError(folder, f"no reconstructions found (supported: {SUPPORTED})")
            with progress(context, len(found)) as advance:
                recons = [advance(load_reconstruction(path)) for path in found]
            made = [objects.add_reconstruction(context.scene, recon, collection=context.collection, made=built)
                    for recon in recons]
        except REPORTED as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        for other in context.selected_objects:
            other.select_set(False)
        for obj in made:
            obj.select_set(True)
        context.view_layer.objects.active = made[0]
        self.report({"INFO"}, printable(f"Imported {len(made)} reconstructions from {folder}"))
        return {"FINISHED"}


class IMPORT_SCENE_OT_pgt_placed_scene(_ChoosesFolder, bpy.types.Operator):
    """Load a placement folder (place_objects.py --out): the scene's points, each inserted object's points and every box"""

    bl_idname = "import_scene.pgt_placed_scene"
    bl_label = "Import Placed Scene"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(name="Placement folder", subtype="DIR_PATH", options=properties.PATH_OPTIONS,
                              description="Folder with scan.bin and boxes.json, as place_objects.py writes it")

    def execute(self, context):
        if _nothing_chosen(self, self.directory, "placement folder"):
            return {"CANCELLED"}
        try:
            collection, shown = placement.load_placement(context.scene, bpy.path.abspath(self.directory))
        except REPORTED as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        inserted = sum(1 for obj in shown if obj.type == "MESH") - 1
        self.report({"INFO"}, f"Loaded {inserted} placed objects and the scene into '{collection.name}'")
        return {"FINISHED"}


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
        self.report({"INFO"}, f"Added {obj.name}: {self.points:,} points of a sample {self.class_name.replace('_', ' ')}, "
                              f"{int(sample.is_outlier.sum()):,} of them floaters")
        return {"FINISHED"}


@contextmanager
def warnings_reported(operator):
    """Report each of the core's warnings (UserWarning) raised inside as a WARNING line, in
    the status bar where a panel user looks, not only the console; numpy's RuntimeWarnings
    are not the user's."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            yield
        finally:
            for warning in caught:
                if warning.category is UserWarning:
                    operator.report({"WARNING"}, one_line(str(warning.message)))


def align(context, obj, settings) -> prepare.Step:
    """The Align Axes step of ``obj`` with the scene's authoring ``settings``."""
    source = obj.pgt.source_path or obj.name
    points = authoring.positions(obj)
    if settings.up == "cursor":
        up = np.array(authoring.object_from_world(obj) @ context.scene.cursor.location) - np.median(points, axis=0)
        if not np.linalg.norm(up):
            raise InputError(obj.name, "the 3D cursor is at the points' median: put it above the object "
                                       "(up points from the median to the cursor)")
    elif settings.up == "face":
        up = authoring.selected_face_normal(obj)
    else:
        up = prepare.up_vector(settings.up, authoring.camera_poses(obj), source)
    return prepare.align_step(points, authoring.weights(obj), up, source, settings.refine, authoring.triangles(obj))


def heading_checkpoint(settings) -> str | None:
    """The Heading section's classifier checkpoint, absolute; None: the shipped one."""
    return bpy.path.abspath(settings.checkpoint) if settings.checkpoint else None


def detect_front(context, obj, settings) -> prepare.Step:
    """The Detect Front step of ``obj``."""
    return prepare.automatic_heading_step(authoring.positions(obj), authoring.current_dims(obj),
                                          settings.heading_method, heading_checkpoint(settings),
                                          obj.pgt.source_path or obj.name, settings.class_name)


def set_size(context, obj, settings, seed: int | None = None) -> prepare.Step:
    """The Set Size step of ``obj`` (``seed``: the size noise's, default the settings')."""
    problem = properties.class_problem(settings) if settings.size_mode == "class" else ""
    if problem:
        raise InputError(obj.name, problem)
    scale = scanning.unapplied_scale(obj)
    if scale:
        warnings.warn(printable(f"{obj.name}: {scale} is not part of the size, which is its mesh data's: apply it "
                                f"(Object > Apply > Scale) to see in the viewport the size the bank takes"),
                      stacklevel=2)
    return prepare.size_step(authoring.current_dims(obj), settings.size_mode, settings.dataset, settings.class_name,
                             settings.seed if seed is None else seed, settings.uniform, tuple(settings.exact_dims),
                             obj.name)


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
        problem = authoring.record_problem(obj)
        if problem:
            cls.poll_message_set(f"{obj.name}: {problem}")
            return False
        if cls.needs_alignment and not authoring.status(obj)["aligned"]:
            cls.poll_message_set("Align the axes first")
            return False
        return True

    def execute(self, context):
        obj = context.active_object
        with authoring.object_mode(obj):
            try:
                authoring.require_authorable(obj)
                with warnings_reported(self):
                    step = self.step(context, obj, context.scene.pgt_authoring)
            except REPORTED as error:
                self.report({"ERROR"}, str(error))
                return {"CANCELLED"}
            authoring.apply_step(obj, step)
        unit = " m" if authoring.status(obj)["size"] else " (source units)"  # metres once sized
        self.report({"INFO"}, one_line(f"{obj.name}: {self.bl_label.lower()}"
                                        f"{self.outcome(step, context.scene.pgt_authoring)}, box "
                                        + " x ".join(f"{d:.4g}" for d in obj.pgt.dims) + unit))
        return {"FINISHED"}

    def outcome(self, step, settings) -> str:
        """What the INFO report says about how ``step`` came about (after the label)."""
        return ""


class OBJECT_OT_pgt_align(_AuthoringStep, bpy.types.Operator):
    """Rotate the principal axes onto x (length), y (width), z (up) and centre the box"""

    bl_idname = "object.pgt_align"
    bl_label = "Align Axes"
    needs_alignment = False

    def step(self, context, obj, settings):
        return align(context, obj, settings)

    def outcome(self, step, settings) -> str:
        return f" (up from {step.details['up_from']})"


class OBJECT_OT_pgt_turn(_AuthoringStep, bpy.types.Operator):
    """Turn the object about its up axis by quarter turns (2: swap front and back)"""

    bl_idname = "object.pgt_turn"
    bl_label = "Turn"

    turns: IntProperty(name="Quarter turns", default=2, min=-3, max=3,
                       description="Counter-clockwise quarter turns seen from above")

    def step(self, context, obj, settings):
        if not self.turns:  # would record a manual heading that nobody decided
            raise InputError(obj.name, "0 quarter turns: nothing to turn")
        return prepare.turn_step(self.turns, authoring.current_dims(obj))

    def outcome(self, step, settings) -> str:
        return f" by {self.turns} quarter turn{'s' * (abs(self.turns) != 1)}"


class OBJECT_OT_pgt_front_from_cursor(_AuthoringStep, bpy.types.Operator):
    """Make the box side facing the 3D cursor the front (+x)"""

    bl_idname = "object.pgt_front_from_cursor"
    bl_label = "Front from Cursor"

    def step(self, context, obj, settings):
        cursor = np.array(authoring.object_from_world(obj) @ context.scene.cursor.location)
        return prepare.front_step(tuple(cursor), authoring.current_dims(obj), obj.name)


class OBJECT_OT_pgt_auto_heading(_AuthoringStep, bpy.types.Operator):
    """Decide front and back automatically (PointNet classifier or geometric baseline; a trailer by its running gear)"""

    bl_idname = "object.pgt_auto_heading"
    bl_label = "Detect Front"

    def step(self, context, obj, settings):
        return detect_front(context, obj, settings)

    def outcome(self, step, settings) -> str:
        """The deciding rule, the class it headed the object as (a trailer's running gear),
        its score and whether the object turned."""
        details = step.details
        measure = "front probability" if details["decided_by"] == "classifier" else "score"
        as_class = f" as {details['class']}" if details["class"] else ""
        turned = "turned 180" if details["turns"] == 2 else "front kept"
        return f" by {prepare.heading_label(details)}{as_class} ({measure} {details['score']:.3g}; {turned})"


class OBJECT_OT_pgt_set_size(_AuthoringStep, bpy.types.Operator):
    """Scale the object to a class size (with the paper's noise), an exact size, or keep it"""

    bl_idname = "object.pgt_set_size"
    bl_label = "Set Size"

    def step(self, context, obj, settings):
        return set_size(context, obj, settings)

    def outcome(self, step, settings) -> str:
        """How the size came about: kept, exact, or drawn for the dataset's class (seed)."""
        details = step.details
        seed = f", seed {details['seed']}" if "seed" in details else ""
        return f" ({details['mode']}: {details['dataset']} {details['class'] or '(no class)'}{seed})"


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
        with authoring.object_mode(obj):
            try:
                with warnings_reported(self):  # the core's own: dropped faces
                    result, sensor, sensor_from_object = scanning.scan(obj, settings, authoring.authored_bounds(obj))
            except REPORTED as error:
                self.report({"ERROR"}, str(error))
                return {"CANCELLED"}
            if not result.hits:  # legal but empty: say why, and leave the scene as it was
                self.report({"WARNING"}, f"{obj.name}: no returns at this pose, out of the "
                                         f"{properties.label(sensor.name)} sensor's range or view; no scan preview made")
                return {"CANCELLED"}
            inside = result.inside_warning(obj.name)
            if inside:
                self.report({"WARNING"}, one_line(inside))
            learned = self.learned_intensity(context, obj, result, settings)
        scanning.show_scan(context.scene, obj, result, sensor, sensor_from_object, settings)
        settings.stats, settings.stats_of = scanning.stats_text(result), f"{obj.name} at {settings.distance:g} m"
        self.report({"INFO"}, one_line(f"{obj.name}: {settings.stats}{learned}"))
        return {"FINISHED"}

    def learned_intensity(self, context, source, result, settings) -> str:
        """With a checkpoint in the preferences the scan takes the learned intensities, as
        the bank and scan_object.py do; a checkpoint that cannot serve this scan (no torch,
        another dataset, no such class) is reported and the physical law kept."""
        preferences = properties.preferences(context)
        checkpoint = bpy.path.abspath(preferences.intensity_checkpoint) if preferences else ""
        if not checkpoint:
            return ""
        try:
            result.returns["intensity"], rate = intensity.learned_intensity(result, source, checkpoint, settings)
        except REPORTED as error:
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
        try:
            with authoring.object_mode(preview):
                rate = intensity.apply_estimator(preview, checkpoint, context.scene.pgt_scan)
        except REPORTED as error:  # no torch, bad checkpoint, other dataset or class, a changed source
            self.report({"ERROR"}, f"{error} (the scan keeps its physical intensities)")
            return {"CANCELLED"}
        self.report({"INFO"}, printable(f"{len(preview.data.vertices)} intensities from {checkpoint} "
                                        f"({rate:,.0f} points/s)"))
        return {"FINISHED"}


class _BackgroundSteps:
    """An operator whose work is a run of short steps: ``steps(context)`` is a generator
    that checks its inputs (InputError: nothing done), yields 0.0, then yields the share
    done after each step. ``execute`` (scripts, ``blender -b``) runs every step at once;
    ``invoke`` (the panels) runs one step per timer event under Blender's progress
    indicator, so the interface answers between steps, and Esc (or ``stop_requested``)
    ends the run between two steps. ``finished`` and ``stopped`` say what was done."""

    _run = None
    _timer = None

    def execute(self, context):
        try:
            for _ in self.steps(context):
                pass
        except Exception as error:
            return self._failure(context, error)
        return self.finished(context)

    def invoke(self, context, event):
        self._run = self.steps(context)
        try:
            next(self._run)
        except Exception as error:
            return self._failure(context, error)
        manager = context.window_manager
        manager.progress_begin(0, 1)
        self._timer = manager.event_timer_add(0.01, window=context.window)
        manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "ESC" or self.stop_requested(context):
            self._end(context)
            return self.stopped(context)
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        try:
            share = next(self._run, None)
        except Exception as error:  # a full disk, a folder gone: what is done stays done
            self._end(context)
            return self._failure(context, error)
        if share is None:
            self._end(context)
            return self.finished(context)
        context.window_manager.progress_update(share)
        for area in context.screen.areas if context.screen else ():
            area.tag_redraw()
        return {"RUNNING_MODAL"}

    def _end(self, context):
        self._run.close()
        manager = context.window_manager
        manager.event_timer_remove(self._timer)
        manager.progress_end()

    def _failure(self, context, error):
        """The result after ``error`` ended the steps: InputError and OSError are reported;
        anything else (a defect) leaves the settings as any failure does (not "running")
        and goes on to Blender, which prints its traceback."""
        result = self.failed(context, error)
        if not isinstance(error, REPORTED):
            raise error
        self.report({"ERROR"}, str(error))
        return result

    def stop_requested(self, context) -> bool:
        return False

    def failed(self, context, error):
        return {"CANCELLED"}


class OBJECT_OT_pgt_author_selected(_BackgroundSteps, bpy.types.Operator):
    """Align, detect the front and set the size of every selected reconstruction, doing only the steps each has left (Esc stops between objects)"""

    bl_idname = "object.pgt_author_selected"
    bl_label = "Author Selected"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if not any(authoring.is_reconstruction(obj) for obj in context.selected_objects):
            cls.poll_message_set("Select imported reconstructions")
            return False
        if context.mode != "OBJECT":
            cls.poll_message_set("Author Selected works in Object Mode")
            return False
        return True

    def steps(self, context):
        """One object's remaining steps per step; object i by name sizes with seed + i.
        What concerns every object (the class, the heading checkpoint) is checked before
        any changes."""
        settings = context.scene.pgt_authoring
        chosen = sorted((obj for obj in context.selected_objects if authoring.is_reconstruction(obj)),
                        key=lambda obj: obj.name)
        problem = properties.class_problem(settings) if settings.size_mode == "class" else ""
        if problem:  # checked once, before any object changes
            raise InputError("Author Selected", problem)
        for obj in chosen:
            authoring.require_authorable(obj)
        if settings.heading_method == "classifier" and not all(authoring.status(obj)["heading"] for obj in chosen):
            from ..core.authoring.heading_classifier import DEFAULT_CHECKPOINT, load_checkpoint

            load_checkpoint(heading_checkpoint(settings) or DEFAULT_CHECKPOINT)
        self.objects, self.applied = len(chosen), 0
        yield 0.0
        for index, obj in enumerate(chosen):  # each step applies whole: an error stops between steps
            for done, make in (("aligned", align), ("heading", detect_front), ("size", None)):
                if not authoring.status(obj)[done]:
                    with warnings_reported(self):
                        step = make(context, obj, settings) if make else set_size(context, obj, settings,
                                                                                  seed=settings.seed + index)
                    authoring.apply_step(obj, step)
                    self.applied += 1
            yield (index + 1) / len(chosen)

    def finished(self, context):
        seed = context.scene.pgt_authoring.seed
        self.report({"INFO"}, f"Authored {self.objects} objects: {self.applied} steps applied "
                              f"(size seeds {seed} to {seed + self.objects - 1} by name)")
        return {"FINISHED"}

    def stopped(self, context):
        self.report({"WARNING"}, f"Author Selected stopped: {self.applied} steps applied")
        return {"FINISHED"}  # what was applied stays, and undo reverts it

    def failed(self, context, error):  # after some steps: keep them undoable
        return {"FINISHED"} if getattr(self, "applied", 0) else {"CANCELLED"}


def _checkpoint(context) -> str:
    """The preferences' intensity checkpoint (absolute), or ""."""
    preferences = properties.preferences(context)
    return bpy.path.abspath(preferences.intensity_checkpoint) if preferences and preferences.intensity_checkpoint else ""


class _OnBankFolder:
    """An operator on the Bank section's output folder: greyed out until one is chosen."""

    @classmethod
    def poll(cls, context):
        if not context.scene.pgt_bank.output:
            cls.poll_message_set("Choose the bank's output folder first")
            return False
        return True


class SCENE_OT_pgt_export_bank(_BackgroundSteps, _OnBankFolder, bpy.types.Operator):
    """Export the scene's authored objects as an object bank; from the panel it runs in the background with progress (Esc or Stop ends it, resumable)"""

    bl_idname = "scene.pgt_export_bank"
    bl_label = "Export Bank"

    @classmethod
    def poll(cls, context):
        if context.scene.pgt_bank.running:
            cls.poll_message_set("An export is running")
            return False
        if context.mode != "OBJECT":  # an object in Edit Mode holds its mesh in an edit mesh
            cls.poll_message_set("Export Bank works in Object Mode")
            return False
        return super().poll(context)

    def steps(self, context):
        """One chunk of entries per step (the Bank section's chunk size), then the assembly
        and the report."""
        settings = context.scene.pgt_bank
        with warnings_reported(self):  # what the bank leaves out of an object
            self.bank_run = run = bank.BankRun(context.scene, settings, _checkpoint(context))
        settings.running, settings.stop_requested, settings.progress = True, False, 0.0
        settings.status = printable(f"exporting {run.total:,} entries to {run.out}")
        try:
            yield 0.0
            while run.step():
                settings.progress = run.done / max(run.total, 1)
                yield settings.progress
            self.report_path = run.finish()
        finally:  # done, stopped or failed: the folder is a bank or resumable
            run.stop()
            settings.running = False

    def stop_requested(self, context) -> bool:
        return context.scene.pgt_bank.stop_requested

    def finished(self, context):
        settings, run = context.scene.pgt_bank, self.bank_run
        settings.progress = 1.0
        settings.status = printable(f"{run.summary()}; report: {self.report_path}")
        self.report({"INFO"}, settings.status)
        return {"FINISHED"}

    def stopped(self, context):
        settings, run = context.scene.pgt_bank, self.bank_run
        settings.status = (f"stopped after {run.done:,} of {run.total:,} entries: choose 'Resume' and export again "
                           "to finish")
        self.report({"WARNING"}, settings.status)
        return {"CANCELLED"}

    def failed(self, context, error):
        run = getattr(self, "bank_run", None)
        if run is None:  # refused before it started: the status must not read as the last export's
            status = f"refused, nothing written: {error}"
        elif (run.out / WORK).is_dir():
            status = "failed: the written chunks stay; 'Resume' continues"
        else:  # a bank that kept no entry is removed: nothing is left to resume
            status = "failed: nothing written stays (the error says why)"
        context.scene.pgt_bank.status = printable(status)
        return {"CANCELLED"}


class SCENE_OT_pgt_stop_bank(bpy.types.Operator):
    """Stop the running bank export after its current chunk; Resume continues it"""

    bl_idname = "scene.pgt_stop_bank"
    bl_label = "Stop"

    def execute(self, context):
        context.scene.pgt_bank.stop_requested = True
        return {"FINISHED"}


class SCENE_OT_pgt_save_bank_config(bpy.types.Operator, ExportHelper):
    """Write the Bank section's settings as a bank .toml, the config file export_bank --config reads"""

    bl_idname = "scene.pgt_save_bank_config"
    bl_label = "Save Config"
    filename_ext = ".toml"
    filter_glob: StringProperty(default="*.toml", options={"HIDDEN"})

    def execute(self, context):
        if _nothing_chosen(self, self.filepath, "file"):
            return {"CANCELLED"}
        scene, checkpoint = context.scene, _checkpoint(context)
        try:  # a .toml, not over a file the scene reads (its own config file is written back the same)
            out = output_path(properties.field_path(self.filepath), False, (".toml",))
            apart_from_inputs(out, [bpy.data.filepath, checkpoint] + [
                bpy.path.abspath(path) for path in (scene.pgt_scan.sensor_file, scene.pgt_bank.real_database) if path])
            config = bank.bank_config(scene.pgt_bank, checkpoint)
            with atomic_output(out) as stream:
                stream.write(config_toml(config).encode())
        except InputError as error:  # names the config file or field at fault
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        except OSError as error:
            self.report({"ERROR"}, printable(f"{self.filepath}: {error.strerror or error}"))
            return {"CANCELLED"}
        self.report({"INFO"}, printable(f"Wrote {self.filepath}"))
        return {"FINISHED"}


def _same_file(blender_path: str, path: Path) -> bool:
    """Whether ``blender_path`` (maybe "//"-relative to the .blend) is the file ``path``."""
    return Path(bpy.path.abspath(blender_path)).resolve() == path.resolve()


class SCENE_OT_pgt_open_bank_report(_OnBankFolder, bpy.types.Operator):
    """Open the bank's report.md as a text (shown in a Text Editor area when there is one); with a Real database set, the report is first written anew beside it, with the bank's quality score"""

    bl_idname = "scene.pgt_open_bank_report"
    bl_label = "Open Report"
    bl_options = {"REGISTER", "UNDO"}  # it adds or replaces a text

    def execute(self, context):
        settings = context.scene.pgt_bank
        out = Path(bpy.path.abspath(settings.output))
        path = out / "report.md"
        real = bank.real_database(settings)
        try:
            if not (path.exists() or path.is_symlink()):  # a dangling link is named as such below
                raise InputError(path, "no report yet: export the bank first")
            regular_file(path)
            if real is not None:  # set after the export, or changed since: the report follows it
                bank.write_bank_report(out, real)
        except REPORTED as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        for old in [text for text in bpy.data.texts
                    if text.filepath and _same_file(text.filepath, path) and objects.made_here(text)]:
            bpy.data.texts.remove(old)  # this report, opened before; a text of the same name or a copy is the user's
        text = bpy.data.texts.load(str(path))
        objects.mark_made(text)
        for area in context.screen.areas if context.screen else ():
            if area.type == "TEXT_EDITOR":
                area.spaces.active.text = text
        self.report({"INFO"}, printable(f"Opened {path} as the text '{text.name}'"))
        return {"FINISHED"}


class SCENE_OT_pgt_preview_bank(_OnBankFolder, bpy.types.Operator):
    """Load entries of the bank in the output folder as point objects colored by intensity, with their boxes"""

    bl_idname = "scene.pgt_preview_bank"
    bl_label = "Preview Bank"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        settings = context.scene.pgt_bank
        try:
            collection, shown = bank.preview_bank(context.scene, bpy.path.abspath(settings.output),
                                                  settings.preview_count)
        except REPORTED as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        settings.status = f"previewing {len(shown)} entries in the '{collection.name}' collection"
        self.report({"INFO"}, settings.status)
        return {"FINISHED"}


AUTHORING = (OBJECT_OT_pgt_align, OBJECT_OT_pgt_turn, OBJECT_OT_pgt_front_from_cursor,
             OBJECT_OT_pgt_auto_heading, OBJECT_OT_pgt_set_size)
IMPORTERS = (IMPORT_SCENE_OT_pgt_colmap, IMPORT_SCENE_OT_pgt_gaussian_splat, IMPORT_SCENE_OT_pgt_plenoxels,
             IMPORT_SCENE_OT_pgt_point_cloud, IMPORT_SCENE_OT_pgt_mesh, IMPORT_SCENE_OT_pgt_folder,
             IMPORT_SCENE_OT_pgt_placed_scene)
BANK = (SCENE_OT_pgt_export_bank, SCENE_OT_pgt_stop_bank, SCENE_OT_pgt_save_bank_config,
        SCENE_OT_pgt_open_bank_report, SCENE_OT_pgt_preview_bank)
classes = (IMPORTERS + (OBJECT_OT_pgt_add_sample,) + AUTHORING + (OBJECT_OT_pgt_author_selected, OBJECT_OT_pgt_scan,
                                                                 OBJECT_OT_pgt_apply_intensity) + BANK)
