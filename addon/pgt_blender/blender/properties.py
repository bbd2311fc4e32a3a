"""Data pgt_blender stores on Blender objects (``Object.pgt``), the authoring settings
(``Scene.pgt_authoring``) and the scan settings (``Scene.pgt_scan``) of the scene."""

import math

import bpy
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, FloatVectorProperty, IntProperty,
                       PointerProperty, StringProperty)

from ..core.authoring.prepare import UP_CHOICES
from ..core.classes import CLASS_SIZES
from ..core.reconstruction import SOURCE_KINDS
from ..core.scan.sensors import PRESETS

_KIND_LABELS = {
    "colmap": "COLMAP model", "gaussian_splat": "Gaussian splats",
    "point_ply": "Point cloud", "mesh": "Mesh",
}
_IDENTITY = ((1, 0, 0, 0), (0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1))
_UP_LABELS = {"auto": ("Auto", "Cameras' mean up when the object has cameras, else the PCA minor axis"),
              "cameras": ("Cameras", "Mean up vector of the reconstruction's cameras"),
              "pca": ("PCA", "Minor principal axis: right for objects lower than they are wide")}
_SENSOR_LABELS = {"nuscenes": "nuScenes", "kitti": "KITTI", "lyft": "Lyft", "vlp16": "VLP-16"}
# Enum items must outlive the callback that returns them (Blender keeps raw pointers).
_CLASS_ITEMS = {dataset: [(name, name.replace("_", " ").title(), f"{dataset} {name}: mean size "
                           + " x ".join(f"{v:.2f}" for v in dims) + " m") for name, dims in sizes.items()]
                for dataset, sizes in CLASS_SIZES.items()}


def _class_items(settings, context):
    return _CLASS_ITEMS[settings.dataset]


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
    class_name: StringProperty(name="Class", description="Dataset class; empty until the size is set")
    dataset: StringProperty(name="Dataset", description="Dataset whose class sizes were used")
    # The authoring record: the 4x4 from the source file's frame to the object frame
    # (the mesh data holds object-frame coordinates), the box and what is done.
    object_from_source: FloatVectorProperty(name="Object from source", size=(4, 4),
                                            subtype="MATRIX", default=_IDENTITY)
    dims: FloatVectorProperty(name="Box", size=3, subtype="XYZ", unit="LENGTH",
                              description="Box length, width, height in the object frame")
    steps_json: StringProperty(name="Steps", description="JSON list of the authoring steps applied; "
                                                         "what is done and left is read off it")


class PGT_PG_authoring(bpy.types.PropertyGroup):
    """Settings of the Align, Heading and Size sections (``Scene.pgt_authoring``)."""

    up: EnumProperty(name="Up", default="auto", items=[
        (choice, *_UP_LABELS.get(choice, (f"Source {choice.upper()}", f"The source frame's {choice} axis")))
        for choice in UP_CHOICES])
    heading_method: EnumProperty(name="Method", default="classifier", items=[
        ("classifier", "Classifier", "PointNet front/back classifier (needs torch)"),
        ("baseline", "Baseline", "Geometric rule: the lower end is the front")])
    checkpoint: StringProperty(name="Checkpoint", subtype="FILE_PATH",
                               description="Heading classifier checkpoint; empty: the one shipped with pgt_blender")
    dataset: EnumProperty(name="Dataset", default="nuscenes",
                          items=[(d, {"nuscenes": "nuScenes", "kitti": "KITTI", "lyft": "Lyft"}[d], "")
                                 for d in CLASS_SIZES])
    class_name: EnumProperty(name="Class", items=_class_items)
    size_mode: EnumProperty(name="Size", default="class", items=[
        ("class", "Class", "Class mean with Gaussian noise (sigma 10 %, clipped at 1 sigma)"),
        ("exact", "Exact", "The size given below"),
        ("keep", "Keep", "The source is already metric")])
    uniform: BoolProperty(name="Uniform", description="One scale factor for all axes (keeps the proportions)")
    seed: IntProperty(name="Seed", min=0, description="Seed of the size noise")
    exact_dims: FloatVectorProperty(name="Exact size", size=3, default=(4.0, 2.0, 1.5), min=0.001,
                                    subtype="XYZ", unit="LENGTH")


class PGT_PG_scan(bpy.types.PropertyGroup):
    """Settings of the Scan section (``Scene.pgt_scan``) and the last scan's statistics.
    Azimuth and heading are stored in radians (shown in degrees, as Blender angles are)."""

    sensor: EnumProperty(name="Sensor", default="nuscenes", items=[
        (name, _SENSOR_LABELS.get(name, name), sensor.note) for name, sensor in PRESETS.items()]
        + [("CUSTOM", "Custom", "A sensor TOML file: Sensor fields, or base = a preset and what differs")])
    sensor_file: StringProperty(name="Sensor file", subtype="FILE_PATH", description="Custom sensor .toml")
    distance: FloatProperty(name="Distance", default=15.0, min=0.0, soft_max=100.0, unit="LENGTH",
                            description="Ground distance from the sensor to the object's origin")
    azimuth: FloatProperty(name="Azimuth", default=0.0, subtype="ANGLE",
                           description="Direction of the object seen from the sensor, from +x counter-clockwise")
    heading: FloatProperty(name="Heading", default=math.radians(90.0), subtype="ANGLE",
                           description="Direction the object's front (+x) faces in the sensor frame")
    colour_by: EnumProperty(name="Colour", default="INTENSITY", items=[
        ("INTENSITY", "Intensity", "Colour the returns by intensity"),
        ("RING", "Ring", "Colour the returns by beam")])
    surfel_scale: FloatProperty(name="Surfel scale", default=1.0, min=0.01, soft_max=5.0,
                                description="Point clouds: surfel radius in units of the point spacing")
    stats: StringProperty(name="Statistics", description="Points, rays and time of the last scan")


# The add-on's own module name: "pgt_blender", or "bl_ext.<repo>.pgt_blender" as an extension.
ADDON = __package__.rpartition(".")[0]


class PGTPreferences(bpy.types.AddonPreferences):
    """Edit > Preferences > Add-ons > PGT Blender."""

    bl_idname = ADDON

    intensity_checkpoint: StringProperty(
        name="Intensity checkpoint", subtype="FILE_PATH",
        description="intensity.pt written by headless_scripts/train_intensity.py, used by Apply Intensity Model")

    def draw(self, context):
        self.layout.prop(self, "intensity_checkpoint")


def preferences(context):
    """The add-on's preferences, or None when it runs without an add-on entry (a script
    that called register() itself)."""
    addon = context.preferences.addons.get(ADDON)
    return addon.preferences if addon is not None else None


classes = (PGT_PG_object, PGT_PG_authoring, PGT_PG_scan, PGTPreferences)


def register():
    bpy.types.Object.pgt = PointerProperty(type=PGT_PG_object)
    bpy.types.Scene.pgt_authoring = PointerProperty(type=PGT_PG_authoring)
    bpy.types.Scene.pgt_scan = PointerProperty(type=PGT_PG_scan)


def unregister():
    del bpy.types.Scene.pgt_scan
    del bpy.types.Scene.pgt_authoring
    del bpy.types.Object.pgt
