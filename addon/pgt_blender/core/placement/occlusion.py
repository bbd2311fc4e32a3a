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

from ..scan.range_view import cells_of_points
from ..scan.sensors import Sensor


def occlude(sensor: Sensor, scene: np.ndarray, inserted: np.ndarray, owner: np.ndarray) -> tuple:
    """(N,) bool scene points kept and (M,) bool inserted points kept, for (N, >= 3)
    scene and (M, >= 3) inserted sensor-frame points; ``owner`` (M,) int the inserted
    object each inserted point belongs to."""
    scene_cells, scene_range = cells_of_points(sensor, np.asarray(scene, np.float64)[:, :3])
    inserted_cells, inserted_range = cells_of_points(sensor, np.asarray(inserted, np.float64)[:, :3])
    count = sensor.beams * sensor.columns
    in_scene, in_inserted = scene_cells >= 0, inserted_cells >= 0
    nearest_inserted = _nearest(count, inserted_cells[in_inserted], inserted_range[in_inserted])
    scene_kept = ~in_scene | (scene_range <= nearest_inserted[np.maximum(scene_cells, 0)])
    remaining = in_scene & scene_kept
    nearest_scene = _nearest(count, scene_cells[remaining], scene_range[remaining])
    inserted_kept = ~in_inserted | (inserted_range <= nearest_scene[np.maximum(inserted_cells, 0)])
    # the nearest inserted point per cell, and whose: other objects' farther points are hidden
    order = np.lexsort((inserted_range[in_inserted], inserted_cells[in_inserted]))
    cells = inserted_cells[in_inserted][order]
    first = np.concatenate([[True], cells[1:] != cells[:-1]]) if len(cells) else np.zeros(0, bool)
    nearest_owner = np.full(count, -1, np.int64)
    nearest_owner[cells[first]] = np.asarray(owner)[in_inserted][order][first]
    cell_of = np.maximum(inserted_cells, 0)
    behind_other = in_inserted & (nearest_owner[cell_of] != owner) & (inserted_range > nearest_inserted[cell_of])
    return scene_kept, inserted_kept & ~behind_other


def _nearest(count: int, cells: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """(count,) the smallest range per cell (inf where none)."""
    nearest = np.full(count, np.inf)
    np.minimum.at(nearest, cells, ranges)
    return nearest
