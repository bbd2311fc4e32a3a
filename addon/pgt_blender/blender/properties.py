"""Data pgt_blender stores on Blender objects (``Object.pgt``), the authoring settings
(``Scene.pgt_authoring``), the scan settings (``Scene.pgt_scan``) and the bank settings
(``Scene.pgt_bank``) of the scene: all saved with the .blend."""

import math

import bpy
from bpy.app.handlers import persistent
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, FloatVectorProperty, IntProperty,
                       PointerProperty, StringProperty)

from ..core.authoring.prepare import UP_CHOICES
from ..core.bank.config import MAX_SWEEPS, BankConfig
from ..core.classes import CLASS_SIZES
from ..core.errors import InputError
from ..core.reconstruction import SOURCE_KINDS
from ..core.scan.sensors import PRESETS

_KIND_LABELS = {
    "colmap": "COLMAP model", "gaussian_splat": "Gaussian splats", "plenoxels": "Plenoxels grid",
    "point_ply": "Point cloud", "mesh": "Mesh",
}
_IDENTITY = ((1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1))
UI_UP_CHOICES = ("cursor", "face")  # up choices only the UI has (the CLI has no cursor or selection)
_UP_LABELS = {"auto": ("Auto", "Cameras' mean up when the object has cameras, else the PCA minor axis"),
              "cameras": ("Cameras", "Mean up vector of the reconstruction's cameras"),
              "pca": ("PCA", "Minor principal axis: right for objects lower than they are wide"),
              "cursor": ("3D Cursor", "From the middle of the points towards the 3D cursor"),
              "face": ("Selected Faces", "Mean normal of the mesh's selected faces (pick them in Edit Mode)")}
_LABELS = {"nuscenes": "nuScenes", "kitti": "KITTI", "lyft": "Lyft", "vlp16": "VLP-16"}
# "//" (relative to the .blend) is a supported file-path form; 4.5 warns about it
# unless the property says so, and 4.2 does not know the option.
PATH_OPTIONS = {"PATH_SUPPORTS_BLEND_RELATIVE"} if bpy.app.version >= (4, 5, 0) else set()


def label(name: str) -> str:
    """How the UI writes a dataset or sensor preset (nuScenes for nuscenes); other names as they are."""
    return _LABELS.get(name, name)


def _class_search(settings, context, text):
    """The chosen dataset's classes for the Class field's search list."""
    return [name for name in CLASS_SIZES.get(settings.dataset, ()) if text.lower() in name]


def class_problem(settings) -> str:
    """Why ``settings.class_name`` cannot be used with ``settings.dataset``, or ""."""
    if settings.dataset not in CLASS_SIZES:  # "": a stored index this version has no item for
        return "no dataset chosen: choose one in the Size panel"
    dataset = label(settings.dataset)
    if not settings.class_name:
        return f"no class chosen: choose a {dataset} class"
    if settings.class_name not in CLASS_SIZES[settings.dataset]:
        return (f"'{settings.class_name}' is not a {dataset} class "
                f"(have: {', '.join(CLASS_SIZES[settings.dataset])})")
    return ""


def _check_class(settings, context):
    """Clear a class the chosen dataset does not have, keeping why for the Size panel:
    the class is stored by name, so a dataset switch never turns it into another class."""
    problem = class_problem(settings)
    if settings.class_name and problem:
        settings.class_note = f"Cleared: {problem}"
        settings.class_name = ""
    elif settings.class_name:
        settings.class_note = ""


class PGT_PG_object(bpy.types.PropertyGroup):
    """Where an object came from and what the authoring steps did to it (``Object.pgt``)."""

    source_path: StringProperty(name="Source", subtype="FILE_PATH", options=PATH_OPTIONS,
                                description="File or COLMAP folder the object was imported from")
    source_kind: EnumProperty(
        name="Kind", description="What the object was imported from",
        items=[("none", "None", "Not imported by pgt_blender")]
        + [(kind, _KIND_LABELS[kind], f"Imported from a {_KIND_LABELS[kind].lower()}") for kind in SOURCE_KINDS],
        default="none",
    )
    source_sha256: StringProperty(name="Checksum", description="sha256 of the source file(s) content")
    class_name: StringProperty(name="Class", description="Dataset class; empty until the size is set")
    dataset: StringProperty(name="Dataset", description="Dataset whose class sizes were used")
    # The authoring record: the 4x4 from the source file's frame to the object frame
    # (the mesh data holds object-frame coordinates), the box and what is done.
    object_from_source: FloatVectorProperty(name="Object from source", size=(4, 4),
                                            subtype="MATRIX", default=_IDENTITY,
                                            description="4x4 from the source file's frame to the object "
                                                        "frame: the product of the authoring steps (float32; "
                                                        "each step's float64 transform is in Steps)")
    dims: FloatVectorProperty(name="Box", size=3, subtype="XYZ",
                              description="Box length, width, height in the object frame, m (a Blender unit each, "
                                          "whatever the scene's Unit Scale)")
    steps_json: StringProperty(name="Steps", description="JSON list of the authoring steps applied; "
                                                         "what is done and left is read off it")


class PGT_PG_authoring(bpy.types.PropertyGroup):
    """Settings of the Align, Heading and Size sections (``Scene.pgt_authoring``)."""

    up: EnumProperty(name="Up", default="auto", description="Which direction Align Axes takes as up", items=[
        (choice, *_UP_LABELS.get(choice, (f"Source {choice.upper()}", f"The source frame's {choice} axis")))
        for choice in (*UP_CHOICES, *UI_UP_CHOICES)])
    refine: BoolProperty(name="Refine from Geometry", default=True,
                         description="Turn the chosen up and the yaw onto the object's own flat faces (sides, "
                                     "roof, floor); without a prior, find up from them")
    heading_method: EnumProperty(name="Method", default="classifier",
                                 description="How Detect Front decides which end is the front", items=[
        ("classifier", "Classifier", "PointNet front/back classifier (needs torch); where it is unsure, the "
                                     "geometric rule decides, and for a trailer its running gear"),
        ("baseline", "Baseline", "Geometric rule: the lower end is the front; a trailer's front is ahead of "
                                 "its wheels")])
    checkpoint: StringProperty(name="Checkpoint", subtype="FILE_PATH", options=PATH_OPTIONS,
                               description="Heading classifier checkpoint; empty: the one shipped with pgt_blender")
    dataset: EnumProperty(name="Dataset", default="nuscenes", update=_check_class,
                          description="Dataset whose class mean sizes Set Size uses",
                          items=[(d, label(d), f"{label(d)} classes and mean sizes")
                                 for d in CLASS_SIZES])
    # A string searched in the dataset's classes, not an enum: an enum stores a position
    # in its list (a dataset switch turned truck into pedestrian), and an enum whose items
    # come from a callback crashes Blender 4.2 at exit.
    class_name: StringProperty(name="Class", search=_class_search, update=_check_class,
                               description="Class of the chosen dataset: Set Size samples its mean size; Detect "
                                           "Front heads a trailer by its running gear")
    class_note: StringProperty(name="Class note",
                               description="Why the class was cleared (shown in the Size panel until one is chosen)")
    size_mode: EnumProperty(name="Size", default="class", description="How Set Size scales the object", items=[
        ("class", "Class", "Class mean with Gaussian noise (sigma 10 %, clipped at 1 sigma)"),
        ("exact", "Exact", "The size given below"),
        ("keep", "Keep", "The source is already metric")])
    uniform: BoolProperty(name="Uniform", description="One scale factor for all axes (keeps the proportions)")
    seed: IntProperty(name="Seed", min=0, description="Seed of the size noise")
    exact_dims: FloatVectorProperty(name="Exact size", size=3, default=(4.0, 2.0, 1.5), min=0.001, max=1000.0,
                                    subtype="XYZ", description="Length, width, height the Exact mode scales the "
                                                               "box to, m")


class PGT_PG_scan(bpy.types.PropertyGroup):
    """Settings of the Scan section (``Scene.pgt_scan``) and the last scan's statistics.
    Azimuth and heading are stored in radians (shown in degrees, as Blender angles are)."""

    sensor: EnumProperty(name="Sensor", default="nuscenes", description="LiDAR the Scan simulates", items=[
        (name, label(name), sensor.note) for name, sensor in PRESETS.items()]
        + [("CUSTOM", "Custom", "A sensor TOML file: Sensor fields, or base = a preset and what differs")])
    sensor_file: StringProperty(name="Sensor file", subtype="FILE_PATH", options=PATH_OPTIONS,
                                description="Custom sensor .toml")
    distance: FloatProperty(name="Distance", default=15.0, min=0.0, max=1e4, soft_max=100.0,
                            description="Ground distance from the sensor to the object's origin, m")
    azimuth: FloatProperty(name="Azimuth", default=0.0, subtype="ANGLE",
                           description="Direction of the object seen from the sensor, from +x counter-clockwise")
    heading: FloatProperty(name="Heading", default=math.radians(90.0), subtype="ANGLE",
                           description="Direction the object's front (+x) faces in the sensor frame")
    color_by: EnumProperty(name="Color", default="INTENSITY", description="What the scan preview's colors show", items=[
        ("INTENSITY", "Intensity", "Color the returns by intensity"),
        ("RING", "Ring", "Color the returns by beam")])
    surfel_scale: FloatProperty(name="Surfel scale", default=1.0, min=0.01, soft_max=5.0,
                                description="Point clouds: surfel radius in units of the point spacing")
    stats: StringProperty(name="Statistics", description="Points, rays and time of the last scan")
    stats_of: StringProperty(name="Statistics of", description="The object and distance of the last scan")


_BANK_DEFAULTS = BankConfig()


class PGT_PG_bank(bpy.types.PropertyGroup):
    """Settings of the Bank section (``Scene.pgt_bank``): the bank config's main keys (every
    other key keeps core/bank/config.py's default), or a config file instead of them;
    where the bank goes; the state of the export running in the background."""

    config_file: StringProperty(name="Config file", subtype="FILE_PATH", options=PATH_OPTIONS,
                                description="A bank .toml (export_bank --config): when set, the export uses it "
                                            "instead of the fields below")
    dataset: EnumProperty(name="Dataset", default="nuscenes", description="Dataset the bank is made for: its grid, "
                          "sensor, sweeps, intensity scale and class names",
                          items=[(d, label(d), f"A {label(d)} bank") for d in CLASS_SIZES])
    sensor: EnumProperty(name="Sensor", default="DATASET", description="LiDAR the bank is scanned with", items=[
        ("DATASET", "Dataset's", "The chosen dataset's own LiDAR")]
        + [(name, label(name), sensor.note) for name, sensor in PRESETS.items()])
    sweeps: IntProperty(name="Sweeps", default=0, min=0, max=MAX_SWEEPS, soft_max=20,
                        description="Sweeps merged per entry; 0: the dataset's (nuScenes, Lyft 10; KITTI 1)")
    heading_step: FloatProperty(name="Heading step", default=math.radians(_BANK_DEFAULTS.headings_deg[2]),
                                min=math.radians(1.0), max=math.radians(360.0), subtype="ANGLE",
                                description="Headings from -180 to 180 degrees every this many")
    grid_step: FloatProperty(name="Grid step", default=5.0, min=0.5, soft_max=50.0,
                             description="Box centres every this many metres over the dataset's x and y range")
    openpcdet: BoolProperty(name="OpenPCDet", default=True, description="Write the OpenPCDet ground-truth database")
    mmdet3d: BoolProperty(name="mmdetection3d", default=True,
                          description="Write the mmdetection3d ground-truth database")
    engine: EnumProperty(name="Engine", default=_BANK_DEFAULTS.engine, description="Ray engine of the scans", items=[
        ("auto", "Auto", "Embree where it runs (the extension ships it), else BVH"),
        ("bvh", "BVH", "Blender's BVHTree: exact, everywhere"),
        ("embree", "Embree", "embreex: several times faster, when installed")])
    seed: IntProperty(name="Seed", default=0, min=0, description="Seed of every draw of the bank")
    chunk_size: IntProperty(name="Chunk size", default=2, min=1, soft_max=256,
                            description="Entries per unit of work: what a background step writes before the "
                                        "interface answers again, and what Resume redoes at most")
    skip_incomplete: BoolProperty(name="Skip incomplete", description="Leave out objects whose class or size is "
                                                                      "not set instead of refusing to export")
    output: StringProperty(name="Output folder", subtype="DIR_PATH", options=PATH_OPTIONS,
                           description="Folder the bank is written to (OpenPCDet and mmdetection3d layouts inside)")
    real_database: StringProperty(name="Real database", subtype="FILE_PATH", options=PATH_OPTIONS,
                                  description="A real ground-truth info pickle (*_dbinfos_*.pkl): the bank report "
                                              "sets its statistics beside the bank's and scores the bank against it "
                                              "per class (score_bank.py's quality table)")
    real_convention: EnumProperty(name="Real points", default="AUTO", description="How the real database "
                                  "stores each object's points", items=[
        ("AUTO", "From the file", "Read from the database's infos: mmdetection3d writes a group_id in each, "
                                  "OpenPCDet in none"),
        ("openpcdet", "About the box centre", "OpenPCDet's ground-truth database"),
        ("mmdet3d", "About the box bottom", "mmdetection3d's ground-truth database")])
    existing: EnumProperty(name="If it exists", default="REFUSE", description="What to do with a non-empty output "
                           "folder", items=[
        ("REFUSE", "Refuse", "Stop with an error: nothing is overwritten"),
        ("RESUME", "Resume", "Continue a stopped export of the same objects and settings"),
        ("OVERWRITE", "Overwrite", "Delete the folder's bank and export anew")])
    preview_count: IntProperty(name="Entries", default=12, min=1, soft_max=100,
                               description="Bank entries Preview Bank loads, spread evenly over the bank")
    status: StringProperty(name="Status", description="What the last export or preview did")
    progress: FloatProperty(name="Progress", min=0.0, max=1.0, subtype="FACTOR",
                            description="Share of the running export's entries written")
    running: BoolProperty(name="Running", description="An export runs in the background (Esc or Stop ends it)")
    stop_requested: BoolProperty(name="Stop requested", description="Set by Stop: the running export ends after "
                                                                    "its current chunk, resumable")


# The add-on's own module name: "pgt_blender", or "bl_ext.<repo>.pgt_blender" as an extension.
ADDON = __package__.rpartition(".")[0]


class PGTPreferences(bpy.types.AddonPreferences):
    """Edit > Preferences > Add-ons > PGT Blender."""

    bl_idname = ADDON

    intensity_checkpoint: StringProperty(
        name="Intensity checkpoint", subtype="FILE_PATH", options=PATH_OPTIONS,
        description="intensity.pt written by headless_scripts/train_intensity.py: every Scan takes its "
                    "learned intensities (Apply Intensity Model redoes a preview)")

    def draw(self, context):
        self.layout.prop(self, "intensity_checkpoint")


def field_path(path: str) -> str:
    """A file or folder field's ``path`` made absolute: a "//" path is relative to the
    .blend (bpy.path.abspath); InputError naming it while the .blend is not saved, where
    Blender would resolve it against whatever folder it was started in."""
    if path.startswith("//") and not bpy.data.filepath:
        raise InputError(path, "is relative to the .blend file, which is not saved yet: save it first or give an "
                               "absolute path")
    return bpy.path.abspath(path)


def preferences(context):
    """The add-on's preferences, or None when it runs without an add-on entry (a script
    that called register() itself)."""
    addon = context.preferences.addons.get(ADDON)
    return addon.preferences if addon is not None else None


classes = (PGT_PG_object, PGT_PG_authoring, PGT_PG_scan, PGT_PG_bank, PGTPreferences)


@persistent
def no_export_running(_filepath) -> None:
    """After a file loads: no export runs in it, though one may have been running when it
    was saved (Ctrl+S or autosave during an export keeps ``running`` set, which would grey
    out Export Bank for good)."""
    for scene in bpy.data.scenes:
        settings = scene.pgt_bank
        if settings.running or settings.stop_requested:
            settings.running = settings.stop_requested = False
            settings.status = "the file was saved during an export: choose 'Resume' and export again to finish it"


def register():
    bpy.types.Object.pgt = PointerProperty(type=PGT_PG_object)
    bpy.types.Scene.pgt_authoring = PointerProperty(type=PGT_PG_authoring)
    bpy.types.Scene.pgt_scan = PointerProperty(type=PGT_PG_scan)
    bpy.types.Scene.pgt_bank = PointerProperty(type=PGT_PG_bank)
    bpy.app.handlers.load_post.append(no_export_running)


def unregister():
    bpy.app.handlers.load_post.remove(no_export_running)
    del bpy.types.Scene.pgt_bank
    del bpy.types.Scene.pgt_scan
    del bpy.types.Scene.pgt_authoring
    del bpy.types.Object.pgt
