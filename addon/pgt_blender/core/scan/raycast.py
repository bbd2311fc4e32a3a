"""Ray-cast scan of one placed object with its BVH (mathutils), in Blender and headless.

Frames: the object frame of ScanTarget (box on the ground = its lowest point at z = 0
after placement) and the sensor frame of sensors.py. ``sensor_from_object`` (4, 4)
float64 places the object; the geometry never moves: every pose transforms the rays
into the object frame instead, so one BVH serves all poses and the float32 BVH stays
near its origin (accurate for objects far from the sensor).

A return lies exactly on its cell's ray: the laser's origin + range x the cell's float64
direction, the range solved in float64 on the plane of the polygon the BVH hit. Rays
share the sensor origin unless the sensor's lasers sit off it (sensors.py); ``origin``
below is then one row per ray, (M, 3), else (3,).

Only the rays a scene needs are cast: the (beam, column) cells inside the object's
angular window, then only those whose ray meets its bounding box (exact float64 slab
test). A full revolution casts every cell; both return the same rows, bit for bit.
"""

import math
import time
from dataclasses import dataclass
from functools import lru_cache
from itertools import chain, repeat

import numpy as np

from .gaussians import gaussian_hits
from .physical_intensity import dataset_intensity, relative_intensity
from .ray_drop import drop_probability
from .returns import RETURN_DTYPE, Scan
from .sensors import Sensor
from .targets import ScanTarget


ENGINES = ("auto", "bvh", "embree")
MAX_SEE_THROUGH = 4  # see-through surfaces a ray passes (both sides of a cabin, twice)
SEE_THROUGH_STEP = 1e-4  # m: how far past a see-through hit the ray goes on


def resolve_engine(engine: str) -> str:
    """The engine ``engine`` names: "auto" is "embree" when embreex imports, else "bvh"."""
    return ("embree" if embree_available() else "bvh") if engine == "auto" else engine


@lru_cache(maxsize=None)
def embree_available() -> bool:
    try:
        import embreex  # noqa: F401  (only whether it imports)
    except ImportError:
        return False
    return True


@dataclass(frozen=True)
class ScanOptions:
    """Sensor effects beyond geometry, all off by default (the exact scan).

    range_noise:       add the sensor's noise: Gaussian range noise with its sigma and
                       its intensity law's spread (physical_intensity.py).
    max_incidence_deg: drop returns hitting the surface more obliquely than this.
    min_intensity:     drop returns whose relative intensity (0..1) is below this.
    drop_rate:         drop each remaining return with this probability.
    ray_drop:          drop returns with the sensor's ray-drop model (ray_drop.py), if it has one.
    seed:              the seed of the noise and the random drop.
    window:            cast only cells that can meet the box (False: full revolution).
    engine:            "bvh" (Blender's BVHTree, one call per ray: exact, everywhere),
                       "embree" (embreex, one batched call per scan, about 20x faster on
                       the rays; it may pick the other polygon at a shared edge) or
                       "auto" (the default: embree where embreex imports, which the
                       package and the extension ship, else bvh); resolved on creation.
    """

    range_noise: bool = False
    max_incidence_deg: float = 90.0
    min_intensity: float = 0.0
    drop_rate: float = 0.0
    ray_drop: bool = False
    seed: int = 0
    window: bool = True
    engine: str = "auto"

    def __post_init__(self):
        if self.engine not in ENGINES:
            raise ValueError(f"scan options: engine must be one of {', '.join(ENGINES)}")
        object.__setattr__(self, "engine", resolve_engine(self.engine))
        if not 0 < self.max_incidence_deg <= 90 or not 0 <= self.min_intensity <= 1 \
                or not 0 <= self.drop_rate < 1:
            raise ValueError("scan options: max_incidence_deg in (0, 90], min_intensity in [0, 1], "
                             "drop_rate in [0, 1)")


@dataclass(frozen=True)
class Ground:
    """The ground under an object: ``height`` (m) of the ground under it above the flat
    plane z = -mounting_height, and the ``pitch`` (rad, nose up > 0) and ``roll`` (rad,
    left side up > 0) it stands at. The default is the flat plane."""

    height: float = 0.0
    pitch: float = 0.0
    roll: float = 0.0

    @property
    def flat(self) -> bool:
        return self.height == 0.0 and self.pitch == 0.0 and self.roll == 0.0


def placement(bounds: np.ndarray, sensor: Sensor, x: float, y: float, heading: float,
              ground: Ground = Ground()) -> np.ndarray:
    """(4, 4) sensor_from_object: the object-frame origin at (x, y) (m, sensor frame),
    turned by ``heading`` (rad, counter-clockwise from +x), its lowest point on the
    ground z = -mounting_height (+ ``ground.height``); on sloped ground the object is
    tilted by pitch and roll about the bottom centre of ``bounds``' z axis."""
    cos, sin = np.cos(heading), np.sin(heading)
    matrix = np.eye(4)
    matrix[:2, :2] = [[cos, -sin], [sin, cos]]
    matrix[:3, 3] = [x, y, -sensor.mounting_height - bounds[0, 2]]
    if ground.flat:
        return matrix
    cp, sp, cr, sr = np.cos(ground.pitch), np.sin(ground.pitch), np.cos(ground.roll), np.sin(ground.roll)
    # Nose up: +x rises (a rotation by -pitch about y); left side up: +y rises (+roll about x).
    tilt = np.array([[cp, 0.0, -sp], [0.0, 1.0, 0.0], [sp, 0.0, cp]]) @ np.array([[1.0, 0.0, 0.0],
                                                                                [0.0, cr, -sr], [0.0, sr, cr]])
    rotation = matrix[:3, :3] @ tilt
    pivot = np.array([0.0, 0.0, bounds[0, 2]])  # object frame; it lands on the ground at (x, y)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = np.array([x, y, -sensor.mounting_height + ground.height]) - rotation @ pivot
    return matrix


def placed_box(bounds: np.ndarray, sensor_from_object: np.ndarray, velocity=(0.0, 0.0)) -> np.ndarray:
    """(9,) OpenPCDet box x, y, z, dx, dy, dz, heading, vx, vy of ``bounds`` placed."""
    centre = sensor_from_object[:3, :3] @ bounds.mean(axis=0) + sensor_from_object[:3, 3]
    heading = np.arctan2(sensor_from_object[1, 0], sensor_from_object[0, 0])
    return np.array([*centre, *(bounds[1] - bounds[0]), heading, *velocity])


_MISS = (-1, 0.0)
_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
_AXES = np.arange(3)


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
    placed = box[_CORNERS, _AXES] @ rotation.T + translation  # (8, 3) corners, sensor frame
    sensor_in_object = rotation.T @ -translation
    r_min = 0.0
    if abs(rotation[2, 2] - 1.0) < 1e-12:  # upright: the footprint is the box's xy rectangle
        r_min = math.hypot(*(min(max(sensor_in_object[axis], box[0, axis]), box[1, axis]) - sensor_in_object[axis]
                             for axis in (0, 1)))
    distances = np.hypot(placed[:, 0], placed[:, 1])
    r_max, z_low, z_high = distances.max(), placed[:, 2].min(), placed[:, 2].max()
    elevation_high = math.degrees(math.atan2(z_high, r_min if z_high > 0 else r_max))
    elevation_low = math.degrees(math.atan2(z_low, r_max if z_low > 0 else r_min))
    rings = np.arange(np.searchsorted(sensor.elevations_deg, elevation_low - 1e-7),
                      np.searchsorted(sensor.elevations_deg, elevation_high + 1e-7, side="right"))
    if r_min == 0.0:
        columns = np.arange(sensor.columns)
    else:
        azimuths = np.degrees(np.arctan2(placed[:, 1], placed[:, 0]))
        centre = math.degrees(math.atan2(placed[:, 1].mean(), placed[:, 0].mean()))
        offsets = np.mod(azimuths - centre + 180.0, 360.0) - 180.0  # the footprint spans < 180 deg
        steps = [sensor.direction * (centre + end - beam - sensor.start_azimuth_deg) / sensor.azimuth_step_deg - 0.5
                 for end in (offsets.min(), offsets.max())
                 for beam in (min(sensor.azimuth_offsets_deg), max(sensor.azimuth_offsets_deg))]
        first, last = math.floor(min(steps)) - 1, math.ceil(max(steps)) + 1
        columns = np.arange(first, min(last, first + sensor.columns - 1) + 1) % sensor.columns
    return np.sort((rings[:, None] * sensor.columns + columns[None, :]).ravel())


def _in_object_frame(sensor_from_object: np.ndarray, components, origins=None) -> tuple:
    """The ray origins, (3,) the sensor's or (M, 3) the lasers' ``origins`` (sensor
    frame), and the x, y, z components of ray directions, in the object frame,
    elementwise (no BLAS), so a ray's bits do not depend on its batch."""
    rotation, translation = sensor_from_object[:3, :3], sensor_from_object[:3, 3]
    x, y, z = components
    directions = tuple(x * rotation[0, i] + y * rotation[1, i] + z * rotation[2, i] for i in range(3))
    sensor_origin = -(rotation.T @ translation)
    if origins is None:
        return sensor_origin, directions
    ox, oy, oz = origins.T
    return np.column_stack([ox * rotation[0, i] + oy * rotation[1, i] + oz * rotation[2, i] + sensor_origin[i]
                            for i in range(3)]), directions


def _meets_box(origin: np.ndarray, components, box: np.ndarray, far: float) -> np.ndarray:
    """Slab test: (M,) bool, rays from ``origin`` with direction ``components`` meeting
    ``box`` between range 0 and ``far``."""
    enter, leave = np.zeros(len(components[0])), np.full(len(components[0]), far)
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis, direction in enumerate(components):
            start = origin[..., axis]
            t0, t1 = (box[0, axis] - start) / direction, (box[1, axis] - start) / direction
            # fmin/fmax skip the NaN of a ray lying in a slab plane: kept, as a superset must.
            enter = np.fmax(enter, np.fmin(t0, t1))
            leave = np.fmin(leave, np.fmax(t0, t1))
    return enter <= leave


def rays_to_cast(sensor: Sensor, cast_bounds: np.ndarray, sensor_from_object: np.ndarray, window: bool = True):
    """The cells a scan casts, (M,) sorted, with their origins ((3,) the sensor's, or
    (M, 3) per laser) and unit directions (M, 3) in the object frame, float64.
    ``window``: only cells inside the angular window whose rays meet the padded
    ``cast_bounds`` from range 0 (not min_range: a hit in the blind zone still takes its
    random draws, as in a full revolution, so both give the same bytes with noise on);
    else every cell. Lasers off the origin widen the window by their offset."""
    origins = sensor.cell_origins
    if window:
        widened = cast_bounds + np.array([[-1.0], [1.0]]) * sensor.max_origin_offset
        cells = candidate_cells(sensor, widened, sensor_from_object)
        origin, local = _in_object_frame(sensor_from_object, [axis[cells] for axis in sensor.direction_axes],
                                         None if origins is None else origins[cells])
        inside = _meets_box(origin, local, _padded(cast_bounds), sensor.max_range)
        cells, local = cells[inside], [axis[inside] for axis in local]
        origin = origin if origins is None else origin[inside]
    else:
        cells = np.arange(sensor.beams * sensor.columns)
        origin, local = _in_object_frame(sensor_from_object, sensor.direction_axes, origins)
    return cells, origin, np.column_stack(local)


def _refined_ranges(planes: np.ndarray, origin: np.ndarray, directions: np.ndarray, bvh_range: np.ndarray):
    """Ranges of hits solved in float64 on the hit polygon's plane (the BVH's float32
    distance is off by up to a few micrometres at 100 m), and the cosine of incidence.
    Near-grazing hits, where the plane solve is ill-conditioned, keep the BVH's range."""
    # Written out, not BLAS: a ray's bits must not depend on the batch it is in.
    cos_incidence = planes[:, 0] * directions[:, 0] + planes[:, 1] * directions[:, 1] + planes[:, 2] * directions[:, 2]
    height = planes[:, 3] - (planes[:, 0] * origin[..., 0] + planes[:, 1] * origin[..., 1]
                             + planes[:, 2] * origin[..., 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        solved = height / cos_incidence
    usable = (np.abs(cos_incidence) > 1e-3) & (np.abs(solved - bvh_range) < 1e-3 * (1 + bvh_range))
    return np.where(usable, solved, bvh_range), cos_incidence


@dataclass(frozen=True)
class Trace:
    """What the rays of one pose met, before any sensor effect: the cells cast (M,),
    and for the hits among them their cells, float64 ranges (m), cosines of incidence
    and BVH polygons; ``seconds`` the wall time."""

    rays: int
    cells: np.ndarray
    ranges: np.ndarray
    cos_incidence: np.ndarray
    polygons: np.ndarray
    seconds: float


def trace_rays(target: ScanTarget, sensor: Sensor, sensor_from_object: np.ndarray, window: bool = True,
               cast_bounds: np.ndarray | None = None, engine: str = "bvh") -> Trace:
    """Cast the rays of ``target`` placed by ``sensor_from_object`` through ``engine``
    (Gaussian targets: gaussians.gaussian_hits, the same for every engine); with
    ``cast_bounds`` (2, 3, object frame) the window keeps only rays meeting that box
    instead of the whole geometry's (a scan that wants part of the object)."""
    sensor.directions  # the cached ray table: built on first use, kept out of the timing
    start = time.perf_counter()
    cast_bounds = target.cast_bounds if cast_bounds is None else cast_bounds
    cells, origin, directions = rays_to_cast(sensor, cast_bounds, sensor_from_object, window)
    if target.gaussians is not None:  # splats: their own compositing, whatever the engine
        splats, ranges, cos_incidence = gaussian_hits(target.gaussians, sensor, sensor_from_object, cells, origin,
                                                      directions)
        hit = splats >= 0
        return Trace(len(cells), cells[hit], ranges[hit], cos_incidence[hit], splats[hit],
                     time.perf_counter() - start)
    cast = _embree_hits if engine == "embree" else _bvh_hits
    polygons, bvh_range = cast(target, origin, directions, sensor.max_range)
    if target.see_through is not None:
        polygons, bvh_range = _through_glass(target, cast, origin, directions, polygons, bvh_range, sensor.max_range)
    hit = polygons >= 0
    polygons, bvh_range = polygons[hit], bvh_range[hit]
    origin = origin if origin.ndim == 1 else origin[hit]
    ranges, cos_incidence = _refined_ranges(target.planes[polygons], origin, directions[hit], bvh_range)
    return Trace(len(cells), cells[hit], ranges, cos_incidence, polygons, time.perf_counter() - start)


def _through_glass(target: ScanTarget, cast, origin: np.ndarray, directions: np.ndarray, polygons: np.ndarray,
                   ranges: np.ndarray, far: float) -> tuple:
    """(polygons, ranges from ``origin``) after the rays that hit see-through polygons
    went on from just past them, up to MAX_SEE_THROUGH times (then they are lost)."""
    polygons, ranges, travelled = polygons.copy(), ranges.copy(), np.zeros(len(directions))
    for _ in range(MAX_SEE_THROUGH):
        passing = np.flatnonzero(polygons >= 0)
        passing = passing[target.see_through[polygons[passing]]]
        if not len(passing):
            return polygons, ranges
        travelled[passing] = ranges[passing] + SEE_THROUGH_STEP
        starts = (origin if origin.ndim == 1 else origin[passing]) + travelled[passing, None] * directions[passing]
        found, further = cast(target, starts, directions[passing], far - travelled[passing])
        polygons[passing], ranges[passing] = found, travelled[passing] + further
    polygons[(polygons >= 0) & target.see_through[np.maximum(polygons, 0)]] = -1
    return polygons, ranges


def _bvh_hits(target: ScanTarget, origin: np.ndarray, directions: np.ndarray, far) -> tuple:
    """(M,) int64 polygon hit by each ray (-1: none) and (M,) float64 its distance;
    ``origin`` (3,) or (M, 3), ``far`` a distance or (M,) distances."""
    from mathutils import Vector

    starts = repeat(Vector(origin), len(directions)) if origin.ndim == 1 else map(Vector, origin.tolist())
    limits = np.broadcast_to(far, len(directions)).tolist()
    results = map(target.bvh.ray_cast, starts, directions.tolist(), limits)
    # One pass over the results: (polygon, distance) per ray, polygon -1 for a miss.
    found = np.fromiter(chain.from_iterable(_MISS if result[2] is None else result[2:] for result in results),
                        np.float64, 2 * len(directions)).reshape(-1, 2)
    return found[:, 0].astype(np.int64), found[:, 1]


def _embree_hits(target: ScanTarget, origin: np.ndarray, directions: np.ndarray, far: float) -> tuple:
    """As ``_bvh_hits``, in one batched Embree call on the target's triangles."""
    if target.embree_scene is None:
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError:
            raise ImportError("the embree engine needs embreex (pip install embreex)") from None
        target.embree_scene = rtcore_scene.EmbreeScene()
        TriangleMesh(target.embree_scene, target.triangle_vertices, target.triangle_faces)
    if not len(directions):
        return np.zeros(0, np.int64), np.zeros(0)
    result = target.embree_scene.run(np.ascontiguousarray(np.broadcast_to(origin, directions.shape), np.float32),
                                     directions.astype(np.float32),
                                     dists=np.broadcast_to(far, len(directions)).astype(np.float32),
                                     output=1)
    triangle = result["primID"]
    polygons = np.where(triangle >= 0, target.triangle_polygon[np.maximum(triangle, 0)], -1)
    return polygons.astype(np.int64), result["tfar"].astype(np.float64)


def cast_rays(target: ScanTarget, sensor: Sensor, sensor_from_object: np.ndarray, options: ScanOptions,
              sweep: int = 0) -> Scan:
    """Scan ``target`` placed by ``sensor_from_object``: one row per return (returns.py)."""
    trace = trace_rays(target, sensor, sensor_from_object, options.window, engine=options.engine)
    start = time.perf_counter()
    returns = trace_returns(target, sensor, trace, options, sweep)
    box = placed_box(target.bounds, sensor_from_object)
    return Scan(returns, box, trace.rays, trace.seconds + time.perf_counter() - start, sensor.dataset,
                [sensor_from_object], cast_seconds=trace.seconds)


def trace_returns(target: ScanTarget, sensor: Sensor, trace: Trace, options: ScanOptions, sweep: int = 0):
    """RETURN_DTYPE rows of ``trace``'s hits after the sensor effects of ``options``."""
    polygons = trace.polygons
    return build_returns(sensor, trace.cells, trace.ranges, target.reflectivity[polygons], trace.cos_incidence,
                         target.source_index[polygons], options, sweep)


def build_returns(sensor: Sensor, cells: np.ndarray, ranges: np.ndarray, reflectivity: np.ndarray,
                  cos_incidence: np.ndarray, faces: np.ndarray, options: ScanOptions, sweep: int = 0) -> np.ndarray:
    """Rows of RETURN_DTYPE for returns at ``ranges`` (M,) m along the rays of ``cells``
    (M,), after the min/max range gate and the options' drops and noise. Random draws
    are one per candidate return in cell order, from a generator seeded by (seed, sweep):
    drop, range noise, intensity spread."""
    keep = (ranges >= sensor.min_range) & (ranges <= sensor.max_range)
    noisy = ranges
    drop = options.drop_rate
    if options.ray_drop and sensor.ray_drop:
        drop = 1.0 - (1.0 - drop) * (1.0 - drop_probability(sensor.ray_drop, reflectivity, cos_incidence, ranges))
    spread = options.range_noise and len(sensor.intensity_law) == 3 and sensor.intensity_law[2] > 0
    normal = None
    if options.drop_rate or options.ray_drop or options.range_noise:
        rng = np.random.default_rng([options.seed, sweep])
        keep &= rng.random(len(cells)) >= drop
        if options.range_noise:
            noisy = ranges + rng.normal(0.0, sensor.range_noise_sigma, len(cells))
            keep &= noisy > 0
        normal = rng.standard_normal(len(cells)) if spread else None
    relative = relative_intensity(reflectivity, cos_incidence, ranges, sensor.intensity_law, normal)
    if options.max_incidence_deg < 90:
        keep &= np.abs(cos_incidence) >= np.cos(np.radians(options.max_incidence_deg))
    if options.min_intensity:
        keep &= relative >= options.min_intensity
    cells, noisy = cells[keep], noisy[keep]
    points = sensor.return_points(cells, noisy)
    rings, columns = np.divmod(cells, sensor.columns)
    rows = np.zeros(len(cells), RETURN_DTYPE)
    rows["x"], rows["y"], rows["z"] = points.T
    rows["intensity"] = dataset_intensity(relative[keep], sensor.dataset)
    rows["ring"], rows["column"] = rings, columns
    rows["azimuth"] = sensor.cell_azimuths.ravel()[cells]
    rows["time"] = sensor.cell_times(rings, columns)
    rows["range"] = noisy
    rows["true_range"] = ranges[keep]
    rows["face"] = faces[keep]
    rows["time_lag"] = sweep * sensor.sweep_interval
    rows["sweep"] = sweep
    return rows


def scan_object(target: ScanTarget, sensor: Sensor, x: float, y: float, heading: float,
                options: ScanOptions = ScanOptions()) -> Scan:
    """One sweep of ``target`` standing on the ground at (x, y) m, ``heading`` rad."""
    return cast_rays(target, sensor, placement(target.bounds, sensor, x, y, heading), options)
