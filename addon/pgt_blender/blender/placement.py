"""A placement folder (place_objects.py --out) in the scene, for inspection: the scene's
points, each inserted object's points and every box, as separate objects in the "PGT
Placed Scene" collection (replacing an earlier one), all in the scan's LiDAR frame."""

from pathlib import Path

import bpy
import numpy as np

from ..core.placement.folder import read_placement
from ..core.scan.sensors import INTENSITY_MAX
from .objects import box_empty, remove_datablocks, replace_collection, suffixed
from .scanning import points_object, ramp

COLLECTION = "PGT Placed Scene"


def load_placement(scene: bpy.types.Scene, folder) -> tuple:
    """Build the objects of the placement in ``folder`` (InputError when it is not one;
    nothing is left behind then) into the collection that replaces the earlier placement
    (objects.replace_collection). Returns the collection and the objects: the scene's
    points first, then each inserted object's points with its box, then the scene's boxes."""
    points, record = read_placement(folder)
    columns = record["columns"]
    intensity_max = INTENSITY_MAX.get(record.get("dataset"), 1.0)
    made = []
    try:
        inserted = [box for box in record["boxes"] if box.get("rows")]
        first_scene_row = max([box["rows"][1] for box in inserted], default=0)
        scene_name = suffixed(Path(record["scan"]).stem, " scene")
        shown = [_points(scene_name, points[first_scene_row:], columns, intensity_max, made)]
        for index, box in enumerate(inserted):
            start, stop = box["rows"]
            name = f"{box['class']} {index} ({box.get('object') or Path(box['entry']).stem})"
            shown += [_points(name, points[start:stop], columns, intensity_max, made),
                      box_empty(name, np.asarray(box["box"]), made)]
        shown += [box_empty(box["class"], np.asarray(box["box"]), made)
                  for box in record["boxes"] if not box.get("rows")]
    except BaseException:
        remove_datablocks(made)
        raise
    return replace_collection(scene, COLLECTION, shown), shown


def _points(name: str, rows: np.ndarray, columns: list, intensity_max: float, made: list) -> bpy.types.Object:
    returns = np.zeros(len(rows), [(column, "f8" if column in ("x", "y", "z") else "f4") for column in columns])
    for index, column in enumerate(columns):
        returns[column] = rows[:, index]
    values = rows[:, columns.index("intensity")] / intensity_max if "intensity" in columns else np.zeros(len(rows))
    return points_object(name, returns, ramp(np.clip(values, 0.0, 1.0)), made)
