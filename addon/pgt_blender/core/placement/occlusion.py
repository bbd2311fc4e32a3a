"""Range-view ray tracing between a scene and the objects put into it (the paper's
supplement, "Ray tracing"): a rotating LiDAR returns the first surface along each ray,
so cell by cell of the sensor's (ring, column) grid (scan.range_view.cells_of_points,
ranges measured from each cell's laser):

- a scene point farther than the nearest inserted point of its cell is in that
  object's shadow: removed;
- an inserted point farther than the nearest remaining scene point of its cell is
  hidden behind it: removed;
- an inserted point farther than the nearest point of another inserted object in its
  cell is hidden behind that object: removed.

Ties keep both (strictly farther is hidden). Points outside the sensor's beam table
(no cell) are left alone. Multi-sweep scans are traced from the key frame's sensor
pose: earlier sweeps' points, taken a few metres back, fall into nearly the same
cells, so a few of them near an inserted object's outline may be judged wrongly.
"""

import numpy as np

from ..scan.range_view import cells_of_points, columns_of
from ..scan.sensors import Sensor


def occlude(sensor: Sensor, scene: np.ndarray, inserted: np.ndarray, owner: np.ndarray) -> tuple:
    """(N,) bool scene points kept and (M,) bool inserted points kept, for (N, >= 3)
    scene and (M, >= 3) inserted sensor-frame points; ``owner`` (M,) int the inserted
    object each inserted point belongs to."""
    inserted_cells, inserted_range = cells_of_points(sensor, np.asarray(inserted, np.float64)[:, :3])
    valid = np.flatnonzero(inserted_cells >= 0)
    cells, slot = np.unique(inserted_cells[valid], return_inverse=True)  # the cells inserted points fall in
    scene = np.asarray(scene[:, :3], np.float64)
    near = _in_columns(sensor, scene, cells % sensor.columns)
    scene_cells, scene_range = cells_of_points(sensor, scene[near])
    position = np.minimum(np.searchsorted(cells, scene_cells), max(len(cells) - 1, 0))
    shared = (scene_cells >= 0) & (cells[position] == scene_cells) if len(cells) else np.zeros(len(near), bool)
    near, position, scene_range = near[shared], position[shared], scene_range[shared]
    nearest_inserted = _nearest(len(cells), slot, inserted_range[valid])
    shadowed = scene_range > nearest_inserted[position]
    scene_kept = np.ones(len(scene), bool)
    scene_kept[near[shadowed]] = False
    nearest_scene = _nearest(len(cells), position[~shadowed], scene_range[~shadowed])
    # the nearest inserted point per cell, and whose: other objects' farther points are hidden
    order = np.lexsort((inserted_range[valid], slot))
    first = order[np.concatenate([[True], slot[order][1:] != slot[order][:-1]])] if len(order) else order
    nearest_owner = np.empty(len(cells), np.int64)
    nearest_owner[slot[first]] = np.asarray(owner)[valid][first]
    hidden = (inserted_range[valid] > nearest_scene[slot]) | \
        ((nearest_owner[slot] != np.asarray(owner)[valid]) & (inserted_range[valid] > nearest_inserted[slot]))
    inserted_kept = np.ones(len(inserted_cells), bool)
    inserted_kept[valid[hidden]] = False
    return scene_kept, inserted_kept


def _nearest(count: int, slots: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """(count,) the smallest range per slot (inf where none)."""
    nearest = np.full(count, np.inf)
    np.minimum.at(nearest, slots, ranges)
    return nearest


def _in_columns(sensor: Sensor, points: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """(N,) indices of the (N, 3) points whose azimuth falls in one of ``columns``, or
    within the beams' largest azimuth offset plus a column of one: only those can share
    a cell with points in those columns."""
    touched = np.zeros(sensor.columns, bool)
    touched[columns] = True
    reach = int(np.ceil(np.abs(sensor.azimuth_offsets_deg).max(initial=0.0) / sensor.azimuth_step_deg)) + 1
    touched = np.logical_or.reduce([np.roll(touched, shift) for shift in range(-reach, reach + 1)])
    return np.flatnonzero(touched[columns_of(sensor, np.degrees(np.arctan2(points[:, 1], points[:, 0])))])

