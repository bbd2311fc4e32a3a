"""Ray-cast scans of placed objects with Embree or Blender's BVH (mathutils), in Blender
and headless.

Frames: the object frame of ScanTarget (the bottom of the object's box on the ground
after placement) and the sensor frame of sensors.py. ``sensor_from_object`` (4, 4)
float64 places the object; the geometry never moves: every pose transforms the rays
into the object frame instead, so one target serves all poses (and, stretched, all size
variants) and the float32 geometry stays near its origin (accurate for objects far from
the sensor). Many poses are cast in one engine call (``trace_rays``).

A return lies exactly on its cell's ray: the laser's origin + range x the cell's float64
direction, the range solved in float64 on the plane of the polygon the engine hit.

Only the rays a scene needs are cast: the (beam, column) cells inside the object's
angular window (the BVH engine, one Python call per ray, only those whose ray meets the
geometry's box: an exact float64 slab test). A full revolution casts every cell; both
return the same rows, bit for bit.
"""

import time
from dataclasses import dataclass
from functools import cache
from itertools import chain

import numpy as np

from .gaussians import gaussian_hits
from .physical_intensity import dataset_intensity, relative_intensity
from .ray_drop import drop_probability
from .returns import Scan, return_dtype
from .sensors import Sensor
from .targets import TARGET_ENGINES, ScanTarget, embree_scene, ready_for, resolve_engine


ENGINES = ("auto", *TARGET_ENGINES)
MAX_SEE_THROUGH = 4  # see-through surfaces a ray passes (both sides of a cabin, twice)
SEE_THROUGH_STEP = 1e-4  # m: how far past a see-through hit the ray goes on
# Rays per pass of the per-ray arithmetic: a bank chunk casts about 250k rays, whose
# float64 temporaries (2 MB each) would spill out of a core's cache (the rays' frames:
# 1.3-1.5x faster in blocks, docs/benchmarks.md).
RAY_BLOCK = 8192


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
    columns:           the return columns to fill besides x, y, z (returns.return_dtype);
                       None: all of them. A bank asks only for what its files hold.
    """

    range_noise: bool = False
    max_incidence_deg: float = 90.0
    min_intensity: float = 0.0
    drop_rate: float = 0.0
    ray_drop: bool = False
    seed: int = 0
    window: bool = True
    engine: str = "auto"
    columns: tuple | None = None

    def __post_init__(self):
        if self.engine not in ENGINES:
            raise ValueError(f"scan options: engine must be one of {', '.join(ENGINES)}")
        return_dtype(self.columns)  # names only known columns
        object.__setattr__(self, "engine", resolve_engine(self.engine))
        if not 0 < self.max_incidence_deg <= 90 or not 0 <= self.min_intensity <= 1 \
                or not 0 <= self.drop_rate < 1:
            raise ValueError("scan options: max_incidence_deg in (0, 90], min_intensity in [0, 1], "
                             "drop_rate in [0, 1)")


@dataclass(frozen=True)
class Ground:
    """The ground under an object: ``height`` (m) of the ground under it above the flat
    plane z = -mounting_height, and the ``pitch`` (rad, nose up > 0) and ``roll`` (rad,
    left side up > 0) it stands at (arrays of them: one per object). The default is
    the flat plane."""

    height: float = 0.0
    pitch: float = 0.0
    roll: float = 0.0


def placement(bounds: np.ndarray, sensor: Sensor, x, y, heading, ground: Ground = Ground()) -> np.ndarray:
    """(4, 4) sensor_from_object: the object-frame origin at (x, y) (m, sensor frame),
    turned by ``heading`` (rad, counter-clockwise from +x), the bottom of ``bounds``
    (2, 3) on the ground z = -mounting_height (+ ``ground.height``); on sloped ground the object is
    tilted by pitch and roll about the bottom centre of ``bounds``' z axis. Arrays of
    x, y, heading (and of the ground's fields, and (..., 2, 3) bounds) give (..., 4, 4),
    one per element."""
    x, y, heading, height, pitch, roll, bottom = np.broadcast_arrays(*(np.asarray(value, np.float64) for value in (
        x, y, heading, ground.height, ground.pitch, ground.roll, np.asarray(bounds)[..., 0, 2])))
    cos, sin = np.cos(heading), np.sin(heading)
    matrix = np.zeros(x.shape + (4, 4))
    matrix[..., 0, 0], matrix[..., 0, 1], matrix[..., 1, 0], matrix[..., 1, 1] = cos, -sin, sin, cos
    matrix[..., 2, 2] = matrix[..., 3, 3] = 1.0
    matrix[..., 0, 3], matrix[..., 1, 3], matrix[..., 2, 3] = x, y, -sensor.mounting_height - bottom
    tilted = (height != 0.0) | (pitch != 0.0) | (roll != 0.0)
    if not tilted.any():
        return matrix
    cp, sp, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    zero, one = np.zeros_like(cp), np.ones_like(cp)
    # Nose up: +x rises (a rotation by -pitch about y); left side up: +y rises (+roll about x).
    tilt = np.stack([cp, zero, -sp, zero, one, zero, sp, zero, cp], -1).reshape(x.shape + (3, 3)) @ \
        np.stack([one, zero, zero, zero, cr, -sr, zero, sr, cr], -1).reshape(x.shape + (3, 3))
    rotation = matrix[..., :3, :3] @ tilt
    pivot = rotation[..., 2] * bottom[..., None]  # the bottom centre (0, 0, bottom) turned: it lands at (x, y)
    lifted = np.stack([x, y, -sensor.mounting_height + height], -1) - pivot
    matrix[tilted, :3, :3], matrix[tilted, :3, 3] = rotation[tilted], lifted[tilted]
    return matrix


def placed_box(bounds: np.ndarray, sensor_from_object: np.ndarray, velocity=(0.0, 0.0)) -> np.ndarray:
    """(9,) OpenPCDet box x, y, z, dx, dy, dz, heading, vx, vy of ``bounds`` (2, 3) placed
    by ``sensor_from_object`` (4, 4); (E, 4, 4) poses, (E, 2) velocities and (E, 2, 3)
    bounds give (E, 9)."""
    bounds = np.asarray(bounds)
    middle = bounds.mean(axis=-2)[..., None]
    centre = (sensor_from_object[..., :3, :3] @ middle)[..., 0] + sensor_from_object[..., :3, 3]
    heading = np.arctan2(sensor_from_object[..., 1, 0], sensor_from_object[..., 0, 0])
    velocity = np.broadcast_to(velocity, centre.shape[:-1] + (2,))
    dims = np.broadcast_to(bounds[..., 1, :] - bounds[..., 0, :], centre.shape)
    return np.concatenate([centre, dims, heading[..., None], velocity], axis=-1)


_MISS = (-1, 0.0)
_CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def _padded(bounds: np.ndarray) -> np.ndarray:
    """``bounds`` (..., 2, 3) grown so that no hit on the float32 geometry falls outside."""
    pad = 1e-4 + 1e-5 * np.abs(bounds).max(axis=(-2, -1))
    return bounds + np.stack([-pad, pad], axis=-1)[..., None]


def cell_window(sensor: Sensor, bounds: np.ndarray, poses: np.ndarray) -> tuple:
    """(first ring, rings, first column, columns), (T,) int64 each: the block of cells
    whose rays' angles fall within the angular window of each box ``bounds`` (T, 2, 3)
    placed by ``poses`` (T, 4, 4) sensor_from_object; a superset of the cells whose rays
    meet the box. A sensor inside the footprint (_footprint_distance: the rectangle along
    the box's heading that holds its corners seen from above) opens every azimuth;
    elevations follow the nearest and farthest footprint distance, so overhead and close
    objects keep all the beams they need."""
    corners = np.take_along_axis(_padded(bounds), np.broadcast_to(_CORNERS, (len(bounds), 8, 3)), axis=1)
    placed = np.einsum("tij,tcj->tci", poses[:, :3, :3], corners) + poses[:, None, :3, 3]  # (T, 8, 3) sensor frame
    r_min = _footprint_distance(placed[..., :2], np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    r_max = np.hypot(placed[..., 0], placed[..., 1]).max(axis=1)
    z_low, z_high = placed[..., 2].min(axis=1), placed[..., 2].max(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        high = np.degrees(np.arctan2(z_high, np.where(z_high > 0, r_min, r_max)))
        low = np.degrees(np.arctan2(z_low, np.where(z_low > 0, r_max, r_min)))
    first_ring, rings = sensor.ring_span(low, high)
    azimuths = np.degrees(np.arctan2(placed[..., 1], placed[..., 0]))
    centre = np.degrees(np.arctan2(placed[..., 1].mean(axis=1), placed[..., 0].mean(axis=1)))
    offsets = np.mod(azimuths - centre[:, None] + 180.0, 360.0) - 180.0  # the footprint spans < 180 deg
    first_column, columns = sensor.column_span(centre, offsets.min(axis=1), offsets.max(axis=1))
    every = r_min == 0.0
    first_column[every], columns[every] = 0, sensor.columns
    return first_ring, rings, first_column % sensor.columns, columns


def _footprint_distance(corners: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """(T,) distance (m) from the sensor's z axis to each box's footprint, 0 when the axis
    passes through it: to the rectangle, along the box's ``heading`` (T,) rad, that
    holds its corners' ``corners`` (T, 8, 2) sensor-frame xy (the footprint of an
    upright box itself; for a tilted one a rectangle a little larger, so never farther)."""
    cos, sin = np.cos(heading)[:, None], np.sin(heading)[:, None]
    along = corners[..., 0] * cos + corners[..., 1] * sin
    across = corners[..., 1] * cos - corners[..., 0] * sin
    return np.hypot(np.maximum(np.maximum(along.min(1), -along.max(1)), 0.0),
                    np.maximum(np.maximum(across.min(1), -across.max(1)), 0.0))


def window_cells(sensor: Sensor, first_ring, rings, first_column, columns) -> np.ndarray:
    """(M,) int64 every cell (ring * columns + column) of each pose's block
    (cell_window), pose by pose, ascending within a pose; pose t has rings[t] *
    columns[t] of them."""
    # Each pose's columns in ascending order: a block that wraps past the last column
    # starts its run at column 0.
    pose = np.repeat(np.arange(len(columns)), columns)
    starts = np.cumsum(columns) - columns
    within = np.arange(len(pose)) - starts[pose]
    wrap = np.where(first_column + columns > sensor.columns, sensor.columns - first_column, 0)
    column = (first_column[pose] + (within + wrap[pose]) % columns[pose]) % sensor.columns
    # Then every ring of the pose runs through them.
    pair = np.repeat(np.arange(len(rings)), rings)  # (pose, ring) pairs, pose by pose
    ring = first_ring[pair] + np.arange(len(pair)) - (np.cumsum(rings) - rings)[pair]
    width = columns[pair]
    pair_start = np.cumsum(width) - width
    index = np.repeat(starts[pair] - pair_start, width) + np.arange(width.sum())
    return column[index] + np.repeat(ring * sensor.columns, width)


def _in_object_frame(poses: np.ndarray, sizes: np.ndarray, cells: np.ndarray, sensor: Sensor,
                     stretch: np.ndarray) -> tuple:
    """Ray origins (M, 3) and directions (M, 3), float64, of ``cells`` (M,) cast from
    ``poses`` (T, 4, 4), ``sizes[t]`` rays from pose t, in the object frame shrunk by
    ``stretch`` (3,) or (T, 3) per pose (the frame of a target that the object is
    stretched from; the directions are unit ones over stretch). Written out elementwise
    (no BLAS), so a ray's bits depend on its pose and cell only, never on its batch; done
    in runs of whole poses of about RAY_BLOCK rays, whose temporaries stay in cache."""
    rotation, translation = poses[:, :3, :3], poses[:, :3, 3]
    stretch = np.broadcast_to(stretch, (len(poses), 3))
    # coefficient [t, i, row]: how ray axis ``row`` of pose t adds to object axis i
    coefficients = rotation.transpose(0, 2, 1) / stretch[:, :, None]
    sensor_origin = -np.einsum("tji,tj->ti", rotation, translation) / stretch
    origins, directions = np.empty((len(cells), 3)), np.empty((len(cells), 3))
    ends = np.cumsum(sizes)
    for first, last in _pose_runs(ends, RAY_BLOCK):
        run = slice(ends[first] - sizes[first], ends[last - 1])
        counts = sizes[first:last]
        block = cells[run]
        axes = [axis[block] for axis in sensor.direction_axes]
        offsets = None if sensor.cell_origins is None else sensor.cell_origins[block].T
        for i in range(3):
            weights = [np.repeat(coefficients[first:last, i, row], counts) for row in range(3)]
            directions[run, i] = axes[0] * weights[0] + axes[1] * weights[1] + axes[2] * weights[2]
            origins[run, i] = np.repeat(sensor_origin[first:last, i], counts)
            if offsets is not None:
                origins[run, i] += offsets[0] * weights[0] + offsets[1] * weights[1] + offsets[2] * weights[2]
    return origins, directions


def _pose_runs(ends: np.ndarray, block: int) -> list:
    """(first, last + 1) runs of whole poses of about ``block`` rays each (a pose of more
    is a run alone), from ``ends`` (T,) the poses' cumulative ray counts; none for T = 0."""
    cuts = np.searchsorted(ends, np.arange(block, ends[-1] if len(ends) else 0, block), side="right")
    bounds = np.unique(np.concatenate([[0], cuts, [len(ends)]]))
    return list(zip(bounds[:-1].tolist(), bounds[1:].tolist()))


def _meets_box(origins: np.ndarray, directions: np.ndarray, box: np.ndarray, far: float) -> np.ndarray:
    """Slab test: (M,) bool, rays from ``origins`` (M, 3) along ``directions`` (M, 3)
    meeting ``box`` (2, 3) between ray parameter 0 and ``far``."""
    enter, leave = np.zeros(len(directions)), np.full(len(directions), far)
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in range(3):
            t0 = (box[0, axis] - origins[:, axis]) / directions[:, axis]
            t1 = (box[1, axis] - origins[:, axis]) / directions[:, axis]
            # fmin/fmax skip the NaN of a ray lying in a slab plane: kept, as a superset must.
            enter = np.fmax(enter, np.fmin(t0, t1))
            leave = np.fmin(leave, np.fmax(t0, t1))
    return enter <= leave


def rays_to_cast(sensor: Sensor, cast_bounds: np.ndarray, poses: np.ndarray, window: bool = True,
                 stretch: np.ndarray = np.ones(3)) -> tuple:
    """The rays of the poses ``poses`` (T, 4, 4) sensor_from_object: (pose (M,), cells
    (M,), origins (M, 3), directions (M, 3)), float64, pose by pose and cells
    ascending, in the object frame shrunk by ``stretch`` ((3,) or (T, 3) per pose;
    _in_object_frame: unit directions without one). ``window``: the cells of the angular
    window of the padded ``cast_bounds`` (T, 2, 3), object frame (lasers off the origin
    widen it by their offset); else every cell. Poses whose cast box is empty (a max
    below its min) cast nothing."""
    if window:
        widened = cast_bounds + np.array([[-1.0], [1.0]]) * sensor.max_origin_offset
        blocks = cell_window(sensor, widened, poses)
        blocks[1][np.any(cast_bounds[:, 1] < cast_bounds[:, 0], axis=1)] = 0
    else:
        count = len(poses)
        blocks = (np.zeros(count, np.int64), np.full(count, sensor.beams), np.zeros(count, np.int64),
                  np.full(count, sensor.columns))
    sizes = blocks[1] * blocks[3]
    cells = window_cells(sensor, *blocks)
    return (np.repeat(np.arange(len(poses)), sizes), cells,
            *_in_object_frame(poses, sizes, cells, sensor, stretch))


def _refined_ranges(planes: np.ndarray, origins: np.ndarray, directions: np.ndarray, engine_range: np.ndarray):
    """Ranges of hits solved in float64 on the hit polygon's plane (n . x = offset,
    ``planes`` (H, 4)) along ``origins`` + range x ``directions`` (the engine's float32
    distance is off by up to a few micrometres at 100 m), and n . direction. Near-grazing
    hits, where the plane solve is ill-conditioned, keep the engine's range."""
    # Written out, not BLAS: a ray's bits must not depend on the batch it is in.
    along = planes[:, 0] * directions[:, 0] + planes[:, 1] * directions[:, 1] + planes[:, 2] * directions[:, 2]
    height = planes[:, 3] - (planes[:, 0] * origins[:, 0] + planes[:, 1] * origins[:, 1]
                             + planes[:, 2] * origins[:, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        solved = height / along
    usable = (np.abs(along) > 1e-3) & (np.abs(solved - engine_range) < 1e-3 * (1 + engine_range))
    return np.where(usable, solved, engine_range), along


@dataclass(frozen=True)
class Trace:
    """What the rays of T poses met, before any sensor effect: ``rays`` (T,) the rays
    cast per pose, and for the hits, pose by pose and cells ascending within a pose,
    their ``pose`` (H,) index, cells, float64 ranges (m), cosines of incidence and
    polygons; ``seconds`` the wall time, ``engine_seconds`` its part in the ray
    engine's own calls (BVH or Embree; Gaussian compositing for splats)."""

    rays: np.ndarray
    pose: np.ndarray
    cells: np.ndarray
    ranges: np.ndarray
    cos_incidence: np.ndarray
    polygons: np.ndarray
    seconds: float
    engine_seconds: float

    def of_pose(self) -> np.ndarray:
        """(T + 1,) offsets: pose t's hits are rows [offsets[t], offsets[t + 1])."""
        return _pose_offsets(self.pose, len(self.rays))


def _pose_offsets(pose: np.ndarray, count: int) -> np.ndarray:
    """(count + 1,) offsets of the runs of a sorted pose index (M,): pose t is rows
    [offsets[t], offsets[t + 1])."""
    return np.searchsorted(pose, np.arange(count + 1))


def trace_rays(target: ScanTarget, sensor: Sensor, poses: np.ndarray, window: bool = True,
               cast_bounds: np.ndarray | None = None, engine: str = "auto", scale: np.ndarray | None = None) -> Trace:
    """Cast the rays of ``target`` placed by each of ``poses`` (T, 4, 4) sensor_from_object
    (or one (4, 4)) through ``engine`` (ENGINES), all poses in one engine call (Gaussian targets:
    gaussians.gaussian_hits, pose by pose, the same for every engine). ``cast_bounds``
    ((T, 2, 3) or (2, 3), object frame; default the geometry's): only the rays of that
    box's window are cast (a scan that wants part of the object: its window's hits
    anywhere on the geometry are returned; sweeps.scan_many crops them to the box).

    ``scale`` (3,) or (T, 3) per pose: the target stretched by it along its axes (size
    variants of one target: positions x scale; not for Gaussian targets). The rays are
    cast in the target's own frame, origin / scale along direction / scale, which keeps
    the ray parameter of a hit: its range in metres (the BVH casts along the unit
    direction, its distance is divided by that direction's length); the incidence is the
    stretched normal's, (n . direction / scale) / |n / scale|."""
    # the ray table and what the engine casts on (ready_for): built on first use, kept out of the timing
    sensor.directions
    engine = resolve_engine(engine)
    ready_for(target, engine)
    start = time.perf_counter()
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    stretch = np.broadcast_to(np.ones(3) if scale is None else np.asarray(scale, np.float64), (len(poses), 3))
    whole = target.cast_bounds * stretch[:, None]
    cast_bounds = whole if cast_bounds is None else np.broadcast_to(cast_bounds, (len(poses), 2, 3))
    pose, cells, origins, directions = rays_to_cast(sensor, cast_bounds, poses, window, stretch)
    if engine == "bvh" and len(cells):
        # One Python call per ray: a slab test first costs far less. Only against the
        # whole geometry's box, the same hits: every engine casts a part's whole window.
        whole_pose = np.all(cast_bounds == whole, axis=(1, 2))[pose]
        inside = ~whole_pose | _meets_box(origins, directions, _padded(target.cast_bounds), sensor.max_range)
        pose, cells, origins, directions = pose[inside], cells[inside], origins[inside], directions[inside]
    rays = np.bincount(pose, minlength=len(poses))
    engine_start = time.perf_counter()
    if target.gaussians is not None:  # splats: their own compositing, whatever the engine
        if scale is not None:
            raise ValueError("a Gaussian target is stretched as Gaussians (transform_gaussians), not by scale")
        polygons, ranges, cos_incidence = _gaussian_hits(target, sensor, poses, pose, cells, origins, directions)
        engine_seconds = time.perf_counter() - engine_start
    else:
        cast = _embree_hits if engine == "embree" else _bvh_hits
        if scale is not None and engine == "bvh":
            cast = _unit_cast(cast)
        polygons, engine_range = cast(target, origins, directions, sensor.max_range)
        if target.see_through is not None:
            polygons, engine_range = _through_glass(target, cast, origins, directions, polygons, engine_range,
                                                    sensor.max_range)
        engine_seconds = time.perf_counter() - engine_start
        # Misses are solved too (elementwise, cheaper than sorting them out), in runs of
        # RAY_BLOCK rays whose temporaries stay in cache.
        ranges, cos_incidence = np.empty(len(cells)), np.empty(len(cells))
        for first in range(0, len(cells), RAY_BLOCK):
            run = slice(first, first + RAY_BLOCK)
            planes = np.take(target.planes, np.maximum(polygons[run], 0), axis=0)
            ranges[run], cos_incidence[run] = _refined_ranges(planes, origins[run], directions[run],
                                                              engine_range[run])
            if scale is not None:  # n . (direction / stretch) over |n / stretch|: the stretched polygon's cosine
                normals = planes[:, :3] / np.take(stretch, pose[run], axis=0)
                cos_incidence[run] *= 1.0 / np.sqrt(np.einsum("ij,ij->i", normals, normals))
    hit = np.flatnonzero(polygons >= 0)
    pose, cells, ranges, cos_incidence, polygons = (np.take(values, hit) for values in (
        pose, cells, ranges, cos_incidence, polygons))
    return Trace(rays, pose, cells, ranges, cos_incidence, polygons, time.perf_counter() - start, engine_seconds)


def _unit_cast(cast):
    """``cast`` for directions of any length, as the BVH casts along unit ones: the
    distances it returns (and its limits) are ray parameters again."""
    def stretched(target, origins, directions, far):
        length = np.sqrt(np.einsum("ij,ij->i", directions, directions))
        polygons, distances = cast(target, origins, directions / length[:, None], far * length)
        return polygons, distances / length

    return stretched


def _gaussian_hits(target: ScanTarget, sensor: Sensor, poses: np.ndarray, pose: np.ndarray, cells: np.ndarray,
                   origins: np.ndarray, directions: np.ndarray) -> tuple:
    """gaussians.gaussian_hits of each pose's rays: (M,) splat (-1: none), range, cosine."""
    found, ranges, cosines = np.full(len(cells), -1, np.int64), np.full(len(cells), np.nan), np.zeros(len(cells))
    offsets = _pose_offsets(pose, len(poses))
    for index, (first, last) in enumerate(zip(offsets[:-1], offsets[1:])):
        if last > first:
            rays = slice(first, last)
            found[rays], ranges[rays], cosines[rays] = gaussian_hits(
                target.gaussians, sensor, poses[index], cells[rays], origins[rays], directions[rays])
    return found, ranges, cosines


def _through_glass(target: ScanTarget, cast, origins: np.ndarray, directions: np.ndarray, polygons: np.ndarray,
                   ranges: np.ndarray, far) -> tuple:
    """(polygons, ranges from ``origins``) after the rays that hit see-through polygons
    went on from just past them, up to MAX_SEE_THROUGH times (then they are lost)."""
    polygons, ranges, travelled = polygons.copy(), ranges.copy(), np.zeros(len(directions))
    for _ in range(MAX_SEE_THROUGH):
        passing = np.flatnonzero(polygons >= 0)
        passing = passing[target.see_through[polygons[passing]]]
        if not len(passing):
            return polygons, ranges
        travelled[passing] = ranges[passing] + SEE_THROUGH_STEP
        starts = origins[passing] + travelled[passing, None] * directions[passing]
        found, further = cast(target, starts, directions[passing],
                              np.broadcast_to(far, len(directions))[passing] - travelled[passing])
        polygons[passing], ranges[passing] = found, travelled[passing] + further
    polygons[(polygons >= 0) & target.see_through[np.maximum(polygons, 0)]] = -1
    return polygons, ranges


def _bvh_hits(target: ScanTarget, origins: np.ndarray, directions: np.ndarray, far) -> tuple:
    """(M,) int64 polygon hit by each ray (-1: none) and (M,) float64 its distance;
    ``origins`` (M, 3), unit ``directions`` (M, 3), ``far`` a distance or (M,) distances."""
    from mathutils import Vector

    limits = np.broadcast_to(far, len(directions)).tolist()
    results = map(target.bvh.ray_cast, map(Vector, origins.tolist()), directions.tolist(), limits)
    # One pass over the results: (polygon, distance) per ray, polygon -1 for a miss.
    found = np.fromiter(chain.from_iterable(_MISS if result[2] is None else result[2:] for result in results),
                        np.float64, 2 * len(directions)).reshape(-1, 2)
    return found[:, 0].astype(np.int64), found[:, 1]


def _embree_hits(target: ScanTarget, origins: np.ndarray, directions: np.ndarray, far) -> tuple:
    """As ``_bvh_hits``, in one batched Embree call on the target's triangles."""
    if not len(directions):
        return np.zeros(0, np.int64), np.zeros(0)
    result = embree_scene(target).run(origins.astype(np.float32), directions.astype(np.float32),
                                     dists=np.broadcast_to(far, len(directions)).astype(np.float32), output=1)
    triangle = result["primID"]
    polygons = np.where(triangle >= 0, target.triangle_polygon[np.maximum(triangle, 0)], -1)
    return polygons.astype(np.int64), result["tfar"].astype(np.float64)


def cast_rays(target: ScanTarget, sensor: Sensor, sensor_from_object: np.ndarray, options: ScanOptions,
              sweep: int = 0) -> Scan:
    """Scan ``target`` placed by ``sensor_from_object``: one row per return (returns.py)."""
    trace = trace_rays(target, sensor, sensor_from_object, options.window, engine=options.engine)
    start = time.perf_counter()
    returns, _ = trace_returns(target, sensor, trace, options, sweep)
    box = placed_box(target.bounds, sensor_from_object)
    return Scan(returns, box, int(trace.rays.sum()), trace.seconds + time.perf_counter() - start, sensor.dataset,
                [sensor_from_object], cast_seconds=trace.engine_seconds)


def trace_returns(target: ScanTarget, sensor: Sensor, trace: Trace, options: ScanOptions, sweep=0, hits=None,
                  draws=None):
    """build_returns of ``trace``'s hits (or of those it picks with ``hits``, an index
    array: a hit may serve several sweeps) after the sensor effects of ``options``;
    ``sweep`` and ``draws`` as build_returns takes them."""
    hits = slice(None) if hits is None else hits
    polygons = trace.polygons[hits]
    return build_returns(sensor, trace.cells[hits], trace.ranges[hits], target.reflectivity[polygons],
                         trace.cos_incidence[hits], target.source_index[polygons], options, sweep, draws)


def sensor_draws(options: ScanOptions, sensor: Sensor, counts: np.ndarray, seeds) -> tuple | None:
    """The random draws of ``options``' sensor effects for E object scans' candidate
    returns, ``counts`` (E, S) per object and sweep, concatenated object by object (and
    within an object sweep by sweep, current first, cells ascending): object e draws
    from its own generator ``default_rng(seeds[e])``, first the drop's uniforms for all
    its candidates (when a drop can happen), then standard normals for all of them: the
    range noise's (times the sensor's sigma, m), then, when the intensity spread is on,
    the spread's. Returns (uniform, noise, spread), each (R,) or None when that effect is
    off; None when no effect draws."""
    drops = bool(options.drop_rate or (options.ray_drop and sensor.ray_drop))
    if not (drops or options.range_noise):
        return None
    spread = options.range_noise and len(sensor.intensity_law) == 3 and sensor.intensity_law[2] > 0
    uniform, noise, normal = [], [], []
    for seed, count in zip(np.asarray(seeds).tolist(), np.sum(counts, axis=1).tolist()):
        rng = np.random.default_rng(seed)
        if drops:
            uniform.append(rng.random(count))
        if options.range_noise:
            normals = rng.standard_normal((2 if spread else 1, count))
            noise.append(normals[0] * sensor.range_noise_sigma)
            if spread:
                normal.append(normals[1])
    return tuple(np.concatenate(part) if part else None for part in (uniform, noise, normal))


def build_returns(sensor: Sensor, cells: np.ndarray, ranges: np.ndarray, reflectivity: np.ndarray,
                  cos_incidence: np.ndarray, faces: np.ndarray, options: ScanOptions, sweep=0,
                  draws=None) -> tuple:
    """(rows, kept): rows (returns.return_dtype of options.columns) for returns at
    ``ranges`` (M,) m along the rays of ``cells`` (M,) after the min/max range gate and
    the options' drops and noise, and (K,) int64 the candidates they come from.
    ``sweep``: the sweep index, or (M,) one per candidate; ``draws``: sensor_draws for
    the candidates, by default those of one object scan seeded by options.seed."""
    keep = (ranges >= sensor.min_range) & (ranges <= sensor.max_range)
    if draws is None:
        draws = sensor_draws(options, sensor, [[len(cells)]], [options.seed])
    uniform, noise, normal = draws or (None, None, None)
    noisy = ranges
    if uniform is not None:
        drop = options.drop_rate
        if options.ray_drop and sensor.ray_drop:
            drop = 1.0 - (1.0 - drop) * (1.0 - drop_probability(sensor.ray_drop, reflectivity, cos_incidence, ranges))
        keep &= uniform >= drop
    if noise is not None:
        noisy = ranges + noise
        keep &= noisy > 0
    relative = relative_intensity(reflectivity, cos_incidence, ranges, sensor.intensity_law, normal)
    if options.max_incidence_deg < 90:
        keep &= np.abs(cos_incidence) >= np.cos(np.radians(options.max_incidence_deg))
    if options.min_intensity:
        keep &= relative >= options.min_intensity
    keep = np.flatnonzero(keep)
    cells, noisy = cells[keep], noisy[keep]
    sweep = sweep if np.ndim(sweep) == 0 else sweep[keep]
    ring_and_column = cache(lambda: np.divmod(cells, sensor.columns))  # ring, column and time share it
    column = {  # each made only when asked for
        "intensity": lambda: dataset_intensity(relative[keep], sensor.dataset),
        "ring": lambda: ring_and_column()[0],
        "column": lambda: ring_and_column()[1],
        "azimuth": lambda: sensor.cell_azimuths.ravel()[cells],
        "time": lambda: sensor.cell_times(*ring_and_column()),
        "range": lambda: noisy,
        "true_range": lambda: ranges[keep],
        "face": lambda: faces[keep],
        "time_lag": lambda: sweep * sensor.sweep_interval,
        "sweep": lambda: sweep,
    }
    rows = np.empty(len(cells), return_dtype(options.columns))
    for axis, values in enumerate(sensor.return_points(cells, noisy).T):
        rows["xyz"[axis]] = values
    for name in rows.dtype.names[3:]:
        rows[name] = column[name]()
    return rows, keep


def scan_object(target: ScanTarget, sensor: Sensor, x: float, y: float, heading: float,
                options: ScanOptions = ScanOptions()) -> Scan:
    """One sweep of ``target`` standing on the ground at (x, y) m, ``heading`` rad."""
    return cast_rays(target, sensor, placement(target.bounds, sensor, x, y, heading), options)
