"""Apply a trained intensity estimator to a scan preview made by the Scan section.

The preview ("<name> Scan") holds the returns in the sensor frame, its ``face`` column
naming the source's polygon (meshes) or vertex (point clouds) each return hit. The
estimator wants each return in the source's *box frame* (box centre at the origin,
+x forward, m) with the sRGB colour of what it hit: points go sensor -> object frame by
``inverse(source.matrix_world) @ preview.matrix_world`` (the preview is placed by
``source.matrix_world @ inverse(sensor_from_object)``), then minus the box centre.
"""

import functools
from pathlib import Path

import bpy
import numpy as np

from ..core.errors import InputError
from ..core.intensity.estimator import IntensityEstimator
from ..core.scan.physical_intensity import dataset_intensity
from ..core.scan.sensors import INTENSITY_MAX
from ..core.scan.targets import srgb_from_linear
from . import scanning
from .authoring import positions

GREY = (0.5, 0.5, 0.5)


def load(path) -> IntensityEstimator:
    """The estimator at ``path``, loaded once and kept while the file is unchanged."""
    status = Path(path).stat() if Path(path).is_file() else None
    return _load(str(path), status and (status.st_mtime_ns, status.st_size))


@functools.lru_cache(maxsize=2)
def _load(path: str, stamp) -> IntensityEstimator:
    return IntensityEstimator.load(path)


def source_of(preview: bpy.types.Object):
    """The object a scan preview was made of, or None."""
    name = preview.get(scanning.SOURCE_TAG)
    return bpy.data.objects.get(name) if name and preview.type == "MESH" and scanning.DATASET_TAG in preview else None


def element_rgb(source: bpy.types.Object) -> np.ndarray:
    """(E, 3) float32 sRGB per polygon (meshes) or per vertex (point clouds): the colour
    attribute (averaged over a polygon's corners), else the material's base colour,
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


def apply_estimator(preview: bpy.types.Object, estimator: IntensityEstimator, class_name: str, settings) -> float:
    """Overwrite the preview's ``intensity`` attribute (and its colours when the scan
    ``settings``, ``Scene.pgt_scan``, show intensity) with ``estimator``'s values for
    ``class_name``; returns points per second."""
    source = source_of(preview)
    dataset = preview[scanning.DATASET_TAG]
    if estimator.dataset != dataset:
        raise InputError(estimator.path, f"trained on {estimator.dataset} intensities, the scan is {dataset}'s")
    target = scanning.scan_target(source, settings.surfel_scale)
    mesh = preview.data
    faces = scanning.read(mesh.attributes["face"].data, "value", len(mesh.vertices), np.int32)
    to_object = np.array(source.matrix_world.inverted() @ preview.matrix_world)
    local = positions(preview).astype(np.float64) @ to_object[:3, :3].T + to_object[:3, 3]
    box = local - target.bounds.mean(axis=0)
    relative = estimator.predict(box, target.size, element_rgb(source)[faces], class_name, source.name)
    values = dataset_intensity(relative, dataset)
    mesh.attributes["intensity"].data.foreach_set("value", values)
    if settings.colour_by == "INTENSITY":
        mesh.color_attributes["color"].data.foreach_set("color", scanning.ramp(values / INTENSITY_MAX[dataset]).ravel())
    mesh.update()
    return estimator.last_rate
