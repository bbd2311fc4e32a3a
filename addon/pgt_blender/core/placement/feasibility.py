"""Where a class may stand: the paper's fusion of the estimated ground and the map.

"We use the map's value for pixels where the density of LiDAR points is low;
otherwise, we use the estimated ground's value" (§3.4). Density here is what the
scan actually saw, measured along its rays rather than per pixel (ground returns
are rings metres apart at range, so any per-pixel count is low between them):

- **seen free**: along each azimuth bin (``azimuth_bins`` per turn), the ground out to
  the farthest ground return that lies before the bin's first obstacle return;
- **occupied**: a cell (``occupancy_cell`` m) holding an obstacle return (``OBSTACLE_BAND``
  above the ground: a parked car, a wall, a pole);
- the rest (behind obstacles, beyond the last ground return, inside buildings) is
  **unseen**.

Where the scan saw (seen free or occupied) the ground decides: seen free is allowed,
occupied is not. Where it is unseen the map decides: the class's layers
(maps.class_layers); with no map, unseen is not allowed (ground-only placement).
With ``map_bounds_ground`` (default) a map also bounds the seen-free part, so a bus
never lands on a sidewalk next to the sensor; False keeps the paper's rule as written.
"""

from dataclasses import dataclass

import numpy as np

from .ground import GROUND_TOLERANCE, OBSTACLE_BAND, Ground
from .maps import MapRaster, class_layers, square_cells

AZIMUTH_BINS = 720  # 0.5 deg
OCCUPANCY_CELL = 0.5  # m


@dataclass
class Feasibility:
    """What the scan saw around the sensor, and the map: ``free_range`` (B,) m per
    azimuth bin (bin k spans azimuth -pi + [k, k + 1) * 2 pi / B), ``occupied`` (n, n)
    bool cells of ``cell`` m from -``radius`` (row = y, column = x)."""

    ground: Ground
    free_range: np.ndarray
    occupied: np.ndarray
    cell: float
    radius: float
    map: MapRaster | None = None
    map_bounds_ground: bool = True
    class_layers: dict | None = None

    def seen(self, xy: np.ndarray) -> tuple:
        """(N,) bool seen free and (N,) bool occupied, for (N, 2) points."""
        xy = np.asarray(xy, np.float64)
        bins = _azimuth_bins(xy, len(self.free_range))
        free = np.hypot(xy[:, 0], xy[:, 1]) <= self.free_range[bins]
        rows, columns, inside = square_cells(xy, self.radius, self.cell, self.occupied.shape[0])
        occupied = inside & self.occupied[rows, columns]
        return free & ~occupied, occupied

    def allows(self, class_name: str, xy: np.ndarray, map_mask: np.ndarray | None = None) -> np.ndarray:
        """(N,) bool: ``class_name`` may stand at each of (N, 2) points (the module
        docstring's rule). ``map_mask``: the class's map layers, precomputed."""
        free, occupied = self.seen(xy)
        if self.map is None:
            return free
        on_map = self.map.allows(class_layers(class_name, self.class_layers), xy, map_mask)
        return np.where(free | occupied, free & (on_map | (not self.map_bounds_ground)), on_map)

    def map_mask(self, class_name: str) -> np.ndarray | None:
        """The class's map layers as one (H, W) mask (None without a map), for ``allows``."""
        return None if self.map is None else self.map.layer_mask(class_layers(class_name, self.class_layers))


def _azimuth_bins(xy: np.ndarray, bins: int) -> np.ndarray:
    azimuth = np.arctan2(xy[:, 1], xy[:, 0])
    return np.minimum(((azimuth + np.pi) * (bins / (2 * np.pi))).astype(np.int64), bins - 1)


def scene_feasibility(points: np.ndarray, ground: Ground, scene_map: MapRaster | None = None,
                      radius: float = 54.0, cell: float = OCCUPANCY_CELL, azimuth_bins: int = AZIMUTH_BINS,
                      map_bounds_ground: bool = True, layers_by_class: dict | None = None,
                      height_above: np.ndarray | None = None) -> Feasibility:
    """The Feasibility of a scan's (N, >= 3) sensor-frame points over its ``ground``
    (``height_above``: the points' heights over it, when already known)."""
    xyz = np.asarray(points, np.float64)[:, :3]
    height = ground.height_above(xyz) if height_above is None else height_above
    is_ground = np.abs(height) <= GROUND_TOLERANCE
    obstacle = (height > OBSTACLE_BAND[0]) & (height < OBSTACLE_BAND[1])
    distance = np.hypot(xyz[:, 0], xyz[:, 1])
    bins = _azimuth_bins(xyz, azimuth_bins)
    first_obstacle = np.full(azimuth_bins, np.inf)
    np.minimum.at(first_obstacle, bins[obstacle], distance[obstacle])
    before = is_ground & (distance < first_obstacle[bins])
    free_range = np.zeros(azimuth_bins)
    np.maximum.at(free_range, bins[before], distance[before])
    size = int(np.ceil(2 * radius / cell))
    rows, columns, inside = square_cells(xyz[obstacle], radius, cell, size)
    occupied = np.zeros((size, size), bool)
    occupied[rows[inside], columns[inside]] = True
    return Feasibility(ground, free_range, occupied, float(cell), float(radius), scene_map, map_bounds_ground,
                       layers_by_class)
