"""Ray-cast scan of one placed object with its BVH (mathutils), in Blender and headless.

Frames: the object frame of ScanTarget (box on the ground = its lowest point at z = 0
after placement) and the sensor frame of sensors.py. ``sensor_from_object`` (4, 4)
float64 places the object; the geometry never moves: every pose transforms the rays
into the object frame instead, so one BVH serves all poses and the float32 BVH stays
near its origin (accurate for objects far from the sensor).

A return lies exactly on its cell's ray: range x the cell's float64 direction, the
range solved in float64 on the plane of the polygon the BVH hit.

Only the rays a scene needs are cast: the (beam, column) cells inside the object's
angular window, then only those whose ray meets its bounding box (exact float64 slab
test). A full revolution casts every cell; both return the same rows, bit for bit.
"""

import time
from dataclasses import dataclass
from itertools import repeat

import numpy as np

from .physical_intensity import dataset_intensity, relative_intensity
from .returns import RETURN_DTYPE, Scan
from .sensors import Sensor
from .targets import ScanTarget


@dataclass(frozen=True)
class ScanOptions:
    """Sensor effects beyond geometry, all off by default (the exact scan).

    range_noise:       add Gaussian range noise with the sensor's sigma.
    max_incidence_deg: drop returns hitting the surface more obliquely than this.
    min_intensity:     drop returns whose relative intensity (0..1) is below this.
    drop_rate:         drop each remaining return with this probability.
    seed:              the seed of the noise and the random drop.
    window:            cast only cells that can meet the box (False: full revolution).
    """

    range_noise: bool = False
    max_incidence_deg: float = 90.0
    min_intensity: float = 0.0
    drop_rate: float = 0.0
    seed: int = 0
    window: bool = True

    def __post_init__(self):
        if not 0 < self.max_incidence_deg <= 90 or not 0 <= self.min_intensity <= 1 \
                or not 0 <= self.drop_rate < 1:
            raise ValueError("scan options: max_incidence_deg in (0, 90], min_intensity in [0, 1], "
                             "drop_rate in [0, 1)")


def placement(bounds: np.ndarray, sensor: Sensor, x: float, y: float, heading: float) -> np.ndarray:
    """(4, 4) sensor_from_object: the object-frame origin at (x, y) (m, sensor frame),
    turned by ``heading`` (rad, counter-clockwise from +x), its lowest point on the
    ground z = -mounting_height."""
    cos, sin = np.cos(heading), np.sin(heading)
    matrix = np.eye(4)
    matrix[:2, :2] = [[cos, -sin], [sin, cos]]
    matrix[:3, 3] = [x, y, -sensor.mounting_height - bounds[0, 2]]
    return matrix


def placed_box(bounds: np.ndarray, sensor_from_object: np.ndarray, velocity=(0.0, 0.0)) -> np.ndarray:
    """(9,) OpenPCDet box x, y, z, dx, dy, dz, heading, vx, vy of ``bounds`` placed."""
    centre = sensor_from_object[:3, :3] @ bounds.mean(axis=0) + sensor_from_object[:3, 3]
    heading = np.arctan2(sensor_from_object[1, 0], sensor_from_object[0, 0])
    return np.array([*centre, *(bounds[1] - bounds[0]), heading, *velocity])


def _padded(bounds: np.ndarray) -> np.ndarray:
    # The BVH stores float32 corners: pad the float64 box so no hit falls outside it.
    pad = 1e-4 + 1e-5 * np.abs(bounds).max()
    return bounds + np.array([[-pad], [pad]])


def candidate_cells(sensor: Sensor, bounds: np.ndarray, sensor_from_object: np.ndarray) -> np.ndarray:
    """Sorted flat cell indices (ring * columns + column) whose rays' angles fall within
    the angular window of the box ``bounds`` placed by ``sensor_from_object``; a superset
    of the cells whose rays meet the box. A sensor inside the footprint (or a pose that
    tilts the box) opens every azimuth; elevations follow the nearest and farthest
    footprint distance, so overhead and close objects keep all the beams they need."""
    rotation, translation = sensor_from_object[:3, :3], sensor_from_object[:3, 3]
    box = _padded(bounds)
    corners = np.array([[box[i, 0], box[j, 1], box[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    placed = corners @ rotation.T + translation
    upright = np.allclose(rotation[2], [0, 0, 1], atol=1e-12)
    sensor_in_object = rotation.T @ -translation
    nearest = np.clip(sensor_in_object[:2], box[0, :2], box[1, :2])
    r_min = np.linalg.norm(nearest - sensor_in_object[:2]) if upright else 0.0
    r_max = np.linalg.norm(placed[:, :2], axis=1).max()
    z_low, z_high = placed[:, 2].min(), placed[:, 2].max()
    elevation_high = np.arctan2(z_high, r_min if z_high > 0 else r_max)
    elevation_low = np.arctan2(z_low, r_max if z_low > 0 else r_min)
    elevations = np.radians(sensor.elevations_deg)
    rings = np.flatnonzero((elevations >= elevation_low - 1e-9) & (elevations <= elevation_high + 1e-9))
    if r_min == 0.0:
        columns = np.arange(sensor.columns)
    else:
        centre = np.arctan2(*placed[:, :2].mean(axis=0)[::-1])
        offsets = np.angle(np.exp(1j * (np.arctan2(placed[:, 1], placed[:, 0]) - centre)))
        ends = np.degrees(centre + np.array([offsets.min(), offsets.max()]))
        beam_offsets = np.array([min(sensor.azimuth_offsets_deg), max(sensor.azimuth_offsets_deg)])
        steps = sensor.direction * (ends[:, None] - beam_offsets[None, :] - sensor.start_azimuth_deg) \
            / sensor.azimuth_step_deg - 0.5
        first, last = int(np.floor(steps.min())) - 1, int(np.ceil(steps.max())) + 1
        columns = np.arange(first, min(last, first + sensor.columns - 1) + 1) % sensor.columns
    return np.sort((rings[:, None] * sensor.columns + columns[None, :]).ravel())


def _to_object(sensor_from_object: np.ndarray, directions: np.ndarray):
    """The sensor origin and ray directions in the object frame, elementwise (no BLAS),
    so each ray's bits do not depend on how many rays are transformed together."""
    rotation, translation = sensor_from_object[:3, :3], sensor_from_object[:3, 3]
    origin = -(rotation.T @ translation)
    local = [directions[:, 0] * rotation[0, i] + directions[:, 1] * rotation[1, i] + directions[:, 2] * rotation[2, i]
             for i in range(3)]
    return origin, np.column_stack(local)


def _meets_box(origin: np.ndarray, directions: np.ndarray, box: np.ndarray, near: float, far: float) -> np.ndarray:
    """Slab test: (M,) bool, rays from ``origin`` meeting ``box`` between ``near`` and ``far``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (box[0] - origin) / directions
        t1 = (box[1] - origin) / directions
    # fmin/fmax skip the NaN of a ray lying in a slab plane: kept, as a superset must.
    enter = np.fmax.reduce(np.fmin(t0, t1), axis=1)
    leave = np.fmin.reduce(np.fmax(t0, t1), axis=1)
    return ~(leave < np.maximum(enter, near)) & ~(enter > far)


def _refined_ranges(planes: np.ndarray, origin: np.ndarray, directions: np.ndarray, bvh_range: np.ndarray):
    """Ranges of hits solved in float64 on the hit polygon's plane (the BVH's float32
    distance is off by up to a few micrometres at 100 m), and the cosine of incidence.
    Near-grazing hits, where the plane solve is ill-conditioned, keep the BVH's range."""
    # Written out, not BLAS: a ray's bits must not depend on the batch it is in.
    cos_incidence = planes[:, 0] * directions[:, 0] + planes[:, 1] * directions[:, 1] + planes[:, 2] * directions[:, 2]
    height = planes[:, 3] - (planes[:, 0] * origin[0] + planes[:, 1] * origin[1] + planes[:, 2] * origin[2])
    with np.errstate(divide="ignore", invalid="ignore"):
        solved = height / cos_incidence
    usable = (np.abs(cos_incidence) > 1e-3) & (np.abs(solved - bvh_range) < 1e-3 * (1 + bvh_range))
    return np.where(usable, solved, bvh_range), cos_incidence


def cast_rays(target: ScanTarget, sensor: Sensor, sensor_from_object: np.ndarray, options: ScanOptions,
              sweep: int = 0, velocity=(0.0, 0.0)) -> Scan:
    """Scan ``target`` placed by ``sensor_from_object``: one row per return (returns.py)."""
    from mathutils import Vector

    table = sensor.directions  # built once per sensor, outside the timing
    start = time.perf_counter()
    cells = (candidate_cells(sensor, target.bounds, sensor_from_object) if options.window
             else np.arange(sensor.beams * sensor.columns))
    origin, directions = _to_object(sensor_from_object, table[cells])
    if options.window:
        # From range 0, not min_range: a hit inside the blind zone still takes its random
        # draws, as in a full revolution, so both give the same bytes with noise on.
        inside = _meets_box(origin, directions, _padded(target.bounds), 0.0, sensor.max_range)
        cells, directions = cells[inside], directions[inside]
    results = list(map(target.bvh.ray_cast, repeat(Vector(origin), len(cells)), directions.tolist(),
                       repeat(sensor.max_range, len(cells))))
    hit = np.fromiter((result[2] is not None for result in results), bool, len(results))
    hits = [result for result in results if result[2] is not None]
    polygons = np.fromiter((result[2] for result in hits), np.int64, len(hits))
    bvh_range = np.fromiter((result[3] for result in hits), np.float64, len(hits))
    ranges, cos_incidence = _refined_ranges(target.planes[polygons], origin, directions[hit], bvh_range)
    returns = build_returns(sensor, cells[hit], ranges, target.reflectivity[polygons], cos_incidence,
                            target.source_index[polygons], options, sweep)
    box = placed_box(target.bounds, sensor_from_object, velocity)
    return Scan(returns, box, len(cells), time.perf_counter() - start, sensor.dataset)


def build_returns(sensor: Sensor, cells: np.ndarray, ranges: np.ndarray, reflectivity: np.ndarray,
                  cos_incidence: np.ndarray, faces: np.ndarray, options: ScanOptions, sweep: int = 0) -> np.ndarray:
    """Rows of RETURN_DTYPE for returns at ``ranges`` (M,) m along the rays of ``cells``
    (M,), after the min/max range gate and the options' drops and noise. Random draws
    are one per candidate return in cell order, from a generator seeded by (seed, sweep)."""
    rng = np.random.default_rng([options.seed, sweep])
    lost = rng.random(len(cells)) < options.drop_rate
    noise = rng.normal(0.0, sensor.range_noise_sigma, len(cells)) if options.range_noise else 0.0
    relative = relative_intensity(reflectivity, cos_incidence, ranges)
    keep = (ranges >= sensor.min_range) & (ranges <= sensor.max_range) & ~lost
    keep &= np.abs(cos_incidence) >= np.cos(np.radians(options.max_incidence_deg)) - 1e-12
    keep &= relative >= options.min_intensity
    noisy = ranges + noise
    keep &= noisy > 0
    points = sensor.directions[cells] * noisy[:, None]
    rings, columns = np.divmod(cells, sensor.columns)
    rows = np.zeros(int(keep.sum()), RETURN_DTYPE)
    rows["x"], rows["y"], rows["z"] = points[keep].T
    rows["intensity"] = dataset_intensity(relative[keep], sensor.dataset)
    rows["ring"], rows["column"] = rings[keep], columns[keep]
    rows["azimuth"] = sensor.cell_azimuths.ravel()[cells[keep]]
    rows["time"] = sensor.cell_times(rings[keep], columns[keep])
    rows["range"] = noisy[keep]
    rows["face"] = faces[keep]
    rows["time_lag"] = sweep * sensor.sweep_seconds
    rows["sweep"] = sweep
    return rows


def scan_object(target: ScanTarget, sensor: Sensor, x: float, y: float, heading: float,
                options: ScanOptions = ScanOptions()) -> Scan:
    """One sweep of ``target`` standing on the ground at (x, y) m, ``heading`` rad."""
    return cast_rays(target, sensor, placement(target.bounds, sensor, x, y, heading), options)
