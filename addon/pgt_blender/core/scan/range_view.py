"""The paper's range-view mode (sec. 3.2, "view-dependent points filtering and
rearrangement") for dense point input, without rays:

1. place the object's points in the sensor frame and project each to its
   (beam, column) cell: the beam of nearest elevation (points beyond half a beam gap
   outside the table are dropped), the column whose azimuth span holds it; with lasers
   off the sensor origin (sensors.py) the elevation is seen from the height of the
   beam's cone apex (offset / cos elevation), refined twice, and the range is measured
   from the cell's laser;
2. keep the nearest point per cell (what the sensor would see first);
3. move each kept point to its cell's centre angles (phi', theta') at its own range.

The output has the ray-cast scan's columns (returns.py); ``face`` is the input point's
index, ``rays`` counts the points projected.
"""

import time

import numpy as np

from .raycast import ScanOptions, build_returns, placed_box
from .returns import Scan
from .sensors import Sensor


def columns_of(sensor: Sensor, azimuth_deg: np.ndarray) -> np.ndarray:
    """(N,) int64 column whose azimuth span holds each (N,) azimuth (degrees, the beam's
    azimuth offset already taken off)."""
    step = sensor.direction * (np.asarray(azimuth_deg) - sensor.start_azimuth_deg) / sensor.azimuth_step_deg
    return np.floor(step).astype(np.int64) % sensor.columns


def cells_of_points(sensor: Sensor, points: np.ndarray):
    """(M,) flat cell index and (M,) range from the cell's laser for (M, 3) sensor-frame
    points; -1 for points outside the beam table's span."""
    table = np.asarray(sensor.elevations_deg)
    gaps = np.diff(table)
    edges = np.concatenate([[table[0] - (gaps[0] if len(gaps) else 1.0) / 2], table[:-1] + gaps / 2,
                            [table[-1] + (gaps[-1] if len(gaps) else 1.0) / 2]])
    apex_of_ring = np.asarray(sensor.vertical_offsets_m) / np.cos(np.radians(table))
    distance, apex = np.linalg.norm(points[:, :2], axis=1), 0.0
    for _ in range(3 if sensor.cell_origins is not None else 1):
        elevation = np.degrees(np.arctan2(points[:, 2] - apex, distance))
        rings = np.searchsorted(edges, elevation, side="right") - 1
        apex = apex_of_ring[np.clip(rings, 0, sensor.beams - 1)]
    inside = (rings >= 0) & (rings < sensor.beams)
    rings = np.clip(rings, 0, sensor.beams - 1)
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0])) - np.asarray(sensor.azimuth_offsets_deg)[rings]
    cells = rings * sensor.columns + columns_of(sensor, azimuth)
    origins = 0.0 if sensor.cell_origins is None else sensor.cell_origins[cells]
    return np.where(inside, cells, -1), np.linalg.norm(points - origins, axis=1)


def range_view_scan(positions: np.ndarray, sensor: Sensor, sensor_from_object: np.ndarray,
                    bounds: np.ndarray, reflectivity: np.ndarray | None = None, normals: np.ndarray | None = None,
                    options: ScanOptions = ScanOptions(), sweep: int = 0, velocity=(0.0, 0.0)) -> Scan:
    """Range-view scan of (N, 3) object-frame points placed by ``sensor_from_object``.

    reflectivity: (N,) in [0, 1] (default 0.5), taken relative to the object's mean as
    targets do (targets.relative_reflectivity); normals: (N, 3) object frame for the
    incidence term (default: local PCA normals). ``bounds`` (2, 3) is the object's box.
    """
    from .targets import DEFAULT_REFLECTIVITY, local_frames, relative_reflectivity

    start = time.perf_counter()
    positions = np.asarray(positions, np.float64)
    rotation, translation = sensor_from_object[:3, :3], sensor_from_object[:3, 3]
    points = positions @ rotation.T + translation
    cells, ranges = cells_of_points(sensor, points)
    candidates = np.flatnonzero((cells >= 0) & (ranges >= sensor.min_range) & (ranges <= sensor.max_range))
    order = candidates[np.lexsort((ranges[candidates], cells[candidates]))]
    first = np.concatenate([[True], cells[order][1:] != cells[order][:-1]]) if len(order) else np.zeros(0, bool)
    kept = order[first]
    if normals is None:
        normals = local_frames(positions)[0] if len(positions) > 3 else np.tile([0.0, 0.0, 1.0], (len(positions), 1))
    surface_normals = np.asarray(normals, np.float64)[kept] @ rotation.T
    surface_normals /= np.maximum(np.linalg.norm(surface_normals, axis=1, keepdims=True), 1e-12)
    directions = sensor.directions[cells[kept]]
    cos_incidence = np.einsum("ij,ij->i", surface_normals, directions)
    reflectivity = (np.full(len(positions), DEFAULT_REFLECTIVITY, np.float32) if reflectivity is None
                    else relative_reflectivity(reflectivity, np.ones(len(positions))))
    returns, _ = build_returns(sensor, cells[kept], ranges[kept], reflectivity[kept], cos_incidence,
                               kept.astype(np.int32), options, sweep)
    return Scan(returns, placed_box(bounds, sensor_from_object, velocity), len(positions),
                time.perf_counter() - start, sensor.dataset, [sensor_from_object])
