"""Apply a trained intensity estimator to a scan preview made by the Scan section.

The preview ("<name> Scan") holds the returns in the sensor frame, its ``face`` column
naming the source's polygon (meshes) or vertex (point clouds) each return hit. The
estimator wants each return in the source's *box frame* (box centre at the origin,
+x forward, m) with the sRGB color of what it hit: points go sensor -> object frame by
``inverse(source.matrix_world) @ preview.matrix_world`` (the preview is placed by
``source.matrix_world @ inverse(sensor_from_object)``), then minus the box centre.
"""

import bpy
import numpy as np

from ..core.intensity.estimator import cached_estimator, scan_intensity
from ..core.scan.returns import RETURN_DTYPE, Scan
from ..core.scan.sensors import INTENSITY_MAX
from ..core.scan.targets import srgb_from_linear
from . import scanning
from .authoring import object_from_world, positions

GREY = (0.5, 0.5, 0.5)


def source_of(preview: bpy.types.Object):
    """The object a scan preview was made of, or None."""
    name = preview.get(scanning.SOURCE_TAG)
    return bpy.data.objects.get(name) if name and preview.type == "MESH" and scanning.DATASET_TAG in preview else None


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
    sensor frame, the ``face`` each hit, and the pose sensor_from_object the two objects'
    matrices imply (see the module docstring)."""
    mesh = preview.data
    count = len(mesh.vertices)
    rows = np.zeros(count, RETURN_DTYPE)
    rows["x"], rows["y"], rows["z"] = positions(preview).astype(np.float64).T
    rows["face"] = scanning.read(mesh.attributes["face"].data, "value", count, np.int32)
    rows["intensity"] = scanning.read(mesh.attributes["intensity"].data, "value", count, np.float32)
    object_from_sensor = np.array(object_from_world(source) @ preview.matrix_world)
    return Scan(rows, np.zeros(9), count, 0.0, preview[scanning.DATASET_TAG], [np.linalg.inv(object_from_sensor)])


def apply_estimator(preview: bpy.types.Object, checkpoint, class_name: str, settings) -> float:
    """Overwrite the preview's ``intensity`` attribute (and its colors when the scan
    ``settings``, ``Scene.pgt_scan``, show intensity) with the estimator at
    ``checkpoint`` (intensity/estimator.scan_intensity); ``class_name`` "" takes the
    checkpoint's only class. Returns points per second; InputError as the core's."""
    source = source_of(preview)
    estimator = cached_estimator(checkpoint)
    class_name = class_name or (estimator.classes[0] if len(estimator.classes) == 1 else "")
    scan = preview_scan(preview, source)
    bounds = scanning.scan_target(source, settings.surfel_scale).bounds
    values, _ = scan_intensity(scan, bounds, element_rgb(source), class_name, estimator, name=source.name)
    mesh = preview.data
    mesh.attributes["intensity"].data.foreach_set("value", values)
    if settings.color_by == "INTENSITY":
        mesh.color_attributes["color"].data.foreach_set("color", scanning.ramp(values / INTENSITY_MAX[scan.dataset]).ravel())
    mesh.update()
    return estimator.last_rate
