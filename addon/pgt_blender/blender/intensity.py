"""Apply a trained intensity estimator to a scan preview made by the Scan section.

The preview ("<name> Scan") holds the returns in the sensor frame, its ``face`` column
naming the source's polygon (meshes) or vertex (point clouds) each return hit. The
estimator wants each return in the source's *box frame* (box centre at the origin,
+x forward, m) with the sRGB color of what it hit: points go sensor -> object frame by
the scan's pose ``sensor_from_object``, stamped on the preview (scanning.POSE_TAG), so
moving the source or the preview since changes nothing; then minus the box centre. A
preview made before the stamp takes the pose its placement implies, ``inverse(
source.matrix_world) @ preview.matrix_world`` (the preview is placed by
``source.matrix_world @ inverse(sensor_from_object)``).
"""

import bpy
import numpy as np

from ..core.errors import InputError
from ..core.intensity.estimator import cached_estimator, scan_intensity
from ..core.scan.returns import RETURN_DTYPE, Scan
from ..core.scan.sensors import INTENSITY_MAX
from ..core.scan.targets import srgb_from_linear
from . import scanning
from .authoring import authored_bounds, object_from_world, positions

GREY = (0.5, 0.5, 0.5)


def source_of(preview: bpy.types.Object):
    """The mesh object a scan preview was made of, or None."""
    name = preview.get(scanning.SOURCE_TAG)
    if not (isinstance(name, str) and name and preview.type == "MESH" and scanning.DATASET_TAG in preview):
        return None
    source = bpy.data.objects.get(name)
    return source if source is not None and source.type == "MESH" else None


def element_rgb(source: bpy.types.Object) -> np.ndarray:
    """(E, 3) float32 sRGB per polygon (meshes) or per vertex (point clouds): the color
    attribute (averaged over a polygon's corners), else the material's base color,
    else grey."""
    mesh = source.data
    attribute = scanning.color_attribute(mesh)
    polygons = len(mesh.polygons)
    if attribute is not None:
        rgb = scanning.srgb(attribute)[:, :3]
        if not polygons:
            return rgb if attribute.domain == "POINT" else np.tile(GREY, (len(mesh.vertices), 1)).astype(np.float32)
        corners = scanning.read(mesh.loops, "vertex_index", len(mesh.loops), np.int32) \
            if attribute.domain == "POINT" else np.arange(len(mesh.loops))
        owner = np.repeat(np.arange(polygons), scanning.read(mesh.polygons, "loop_total", polygons, np.int32))
        sums = np.zeros((polygons, 3))
        np.add.at(sums, owner, rgb[corners])
        return (sums / np.bincount(owner, minlength=polygons)[:, None]).astype(np.float32)
    if not polygons:
        return np.tile(GREY, (len(mesh.vertices), 1)).astype(np.float32)
    slots = [slot.material for slot in source.material_slots]
    per_slot = np.array([srgb_from_linear(np.array([scanning.base_color(m)]))[0] if m else GREY for m in slots]
                        or [GREY], np.float32)
    index = scanning.read(mesh.polygons, "material_index", polygons, np.int32)
    return per_slot[np.clip(index, 0, len(per_slot) - 1)]


def preview_scan(preview: bpy.types.Object, source: bpy.types.Object) -> Scan:
    """The preview's returns as a one-sweep core Scan: points and intensities in the
    sensor frame, the ``face`` each hit, and the scan's pose sensor_from_object (see the
    module docstring). InputError when the preview lost its ``face`` or ``intensity``
    attribute, its pose stamp is damaged or, unstamped, either object has a zero scale."""
    mesh = preview.data
    count = len(mesh.vertices)
    rows = np.zeros(count, RETURN_DTYPE)
    rows["x"], rows["y"], rows["z"] = positions(preview).astype(np.float64).T
    for column, kind in (("face", "INT"), ("intensity", "FLOAT")):
        attribute = mesh.attributes.get(column)
        if attribute is None or attribute.data_type != kind or attribute.domain != "POINT":
            raise InputError(preview.name, f"has no per-point {kind.lower()} attribute '{column}': "
                                           f"scan {source.name} again")
        rows[column] = scanning.read(attribute.data, "value", count, rows.dtype[column])
    dataset = preview[scanning.DATASET_TAG]
    if dataset not in INTENSITY_MAX:
        raise InputError(preview.name, f"{scanning.DATASET_TAG} = {dataset!r} is not one of "
                                       f"{', '.join(INTENSITY_MAX)}: scan {source.name} again")
    stamp = preview.get(scanning.POSE_TAG)
    if stamp is None:  # a preview made before the stamp
        object_from_world(source)  # a zero scale on either object is named, not a singular pose
        sensor_from_object = np.array(object_from_world(preview) @ source.matrix_world)
    else:
        sensor_from_object = np.array(stamp, np.float64).ravel()
        if sensor_from_object.shape != (16,) or not np.isfinite(sensor_from_object).all():
            raise InputError(preview.name, f"{scanning.POSE_TAG} must be 16 finite numbers: scan {source.name} again")
        sensor_from_object = sensor_from_object.reshape(4, 4)
    return Scan(rows, np.zeros(9), count, 0.0, dataset, [sensor_from_object])


def learned_intensity(scan: Scan, source: bpy.types.Object, checkpoint, settings,
                      scanned: str | None = None) -> tuple[np.ndarray, float]:
    """(values (N,) float32 in the dataset's scale, points per second): the estimator at
    ``checkpoint`` (intensity/estimator.scan_intensity) on the N returns of ``scan``, a
    scan of ``source`` whose ``face`` column names its polygons (meshes) or vertices
    (point clouds); the class is ``source.pgt.class_name``, else the checkpoint's only
    one. InputError as the core's, when ``source``'s geometry differs from ``scanned``
    (scanning.scanned_geometry at the scan; None: not known) and when the scan hit a face
    or point ``source`` no longer has (edited since the scan)."""
    target = scanning.scan_target(source, settings.surfel_scale)  # also what scanned_geometry reads, made now
    bounds = authored_bounds(source)
    bounds = target.bounds if bounds is None else bounds
    if scanned is not None and scanned != scanning.scanned_geometry(source):
        raise InputError(source.name, "changed since the scan (its vertices or faces differ, or another object took "
                                      "its name): scan it again")
    estimator = cached_estimator(checkpoint)
    class_name = source.pgt.class_name or (estimator.classes[0] if len(estimator.classes) == 1 else "")
    rgb = element_rgb(source)
    hit = scan.returns["face"]
    if len(hit) and (hit.min() < 0 or hit.max() >= len(rgb)):
        elements = "faces" if len(source.data.polygons) else "points"
        raise InputError(source.name, f"has {len(rgb)} {elements} but the scan hit number {hit.max()}: "
                                      "it changed since the scan; scan it again")
    values, _ = scan_intensity(scan, bounds, rgb, class_name, estimator, name=source.name)
    return values, estimator.last_rate


def apply_estimator(preview: bpy.types.Object, checkpoint, settings) -> float:
    """Overwrite the preview's ``intensity`` attribute (and its colors when the scan
    ``settings``, ``Scene.pgt_scan``, show intensity) with ``learned_intensity``, given
    the geometry the preview says was scanned. Returns points per second; InputError
    (nothing written) as ``preview_scan`` and ``learned_intensity``, and for a preview
    without its ``color`` attribute."""
    source = source_of(preview)
    mesh = preview.data
    colors = mesh.color_attributes.get("color") if settings.color_by == "INTENSITY" else None
    if settings.color_by == "INTENSITY" and (colors is None or colors.domain != "POINT"):
        raise InputError(preview.name, f"has no per-point color attribute 'color': scan {source.name} again")
    scan = preview_scan(preview, source)
    values, rate = learned_intensity(scan, source, checkpoint, settings, preview.get(scanning.GEOMETRY_TAG))
    mesh.attributes["intensity"].data.foreach_set("value", values)
    if colors is not None:
        colors.data.foreach_set("color", scanning.ramp(values / INTENSITY_MAX[scan.dataset]).ravel())
    mesh.update()
    return rate
