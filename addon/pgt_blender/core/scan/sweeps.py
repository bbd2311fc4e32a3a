"""Virtual object sweeps (paper sec. 3.3): nuScenes and Lyft detectors train on 10
merged sweeps, so a moving object leaves a trail. Each sweep k (0 = current, k = k
sweeps earlier, at t = -k * sensor.sweep_interval: the dataset's sweep spacing) scans
the object where a rigid-body motion model puts it then:

    s(t) = speed * t + acceleration * t^2 / 2   along its heading (m, t in s, t <= 0)

The ego vehicle moves too (``ego``, the same model along the sensor's forward axis on
flat ground, no turning): sweep k is cast from where the sensor was at t, and its
returns are motion-compensated into the key frame (the current sweep's sensor frame)
as nuScenes' sweeps are, so a still object's sweeps hit different points. The object
holds still during one sweep. Every return of sweep k gets ``time_lag = k *
sensor.sweep_interval``; the box is the current one with velocity (vx, vy) = speed *
(cos heading, sin heading), relative to the ground.
"""

import time
from dataclasses import dataclass

import numpy as np

from .raycast import Ground, ScanOptions, placed_box, placement, sensor_draws, trace_rays, trace_returns
from .returns import Scan
from .sensors import Sensor
from .targets import ScanTarget

# Plausible urban motion per class, not fitted to a dataset: chance of standing still,
# then speed ~ N(mean, std) clipped to [0, 2 mean] m/s and acceleration ~ N(0, std) m/s^2.
STILL = (1.0, 0.0, 0.0, 0.0)
CLASS_MOTION = {
    "car": (0.5, 8.0, 4.0, 1.0),
    "truck": (0.5, 6.0, 3.0, 0.8),
    "bus": (0.3, 6.0, 3.0, 0.8),
    "trailer": (0.7, 6.0, 3.0, 0.5),
    "construction_vehicle": (0.7, 2.0, 1.5, 0.5),
    "motorcycle": (0.4, 8.0, 4.0, 1.5),
    "bicycle": (0.5, 4.0, 2.0, 1.0),
    "pedestrian": (0.3, 1.3, 0.4, 0.3),
    # the other classes of the datasets' databases (formats.DATABASE_CLASSES), lower case
    "van": (0.5, 8.0, 4.0, 1.0), "emergency_vehicle": (0.5, 8.0, 4.0, 1.0), "other_vehicle": (0.5, 6.0, 3.0, 0.8),
    "tram": (0.3, 6.0, 3.0, 0.8), "cyclist": (0.5, 4.0, 2.0, 1.0), "animal": (0.7, 1.0, 0.5, 0.3),
    "person_sitting": STILL, "traffic_cone": STILL, "barrier": STILL, "misc": STILL,
}
# Sweeps merged per sample by the datasets' 10-sweep databases (OpenPCDet's
# nuscenes_dbinfos_10sweeps_withvelo.pkl and lyft_dbinfos_10sweeps.pkl; mmdet3d's
# nuScenes and Lyft pipelines load 10 sweeps); KITTI frames are single sweeps.
SWEEPS_PER_SAMPLE = {"nuscenes": 10, "kitti": 1, "lyft": 10}
# The ego vehicle's motion per dataset, drawn like CLASS_MOTION: plausible for the cities
# each was recorded in (nuScenes: Boston and Singapore downtown; Lyft: Palo Alto
# suburbs; KITTI: Karlsruhe), not fitted to the datasets' ego poses.
EGO_MOTION = {"nuscenes": (0.3, 5.0, 3.0, 0.8), "lyft": (0.2, 8.0, 4.0, 0.8), "kitti": (0.2, 8.0, 4.0, 0.8)}


@dataclass(frozen=True)
class Motion:
    """Speed (m/s, along the heading; negative = reversing) and acceleration (m/s^2);
    arrays of them work too (displacement is elementwise)."""

    speed: float = 0.0
    acceleration: float = 0.0

    def displacement(self, seconds: float) -> float:
        return self.speed * seconds + 0.5 * self.acceleration * seconds**2


def motion_class(*names: str) -> str | None:
    """The first of ``names`` (lower-cased: KITTI's "Truck" is "truck") with a motion
    model in CLASS_MOTION, or None."""
    return next((name.lower() for name in names if name and name.lower() in CLASS_MOTION), None)


def sample_motion(class_name: str, rng: np.random.Generator) -> Motion:
    """A draw from ``class_name``'s entry of CLASS_MOTION (``motion_class`` names one)."""
    return _draw(CLASS_MOTION[class_name], rng)


def sample_ego_motion(dataset: str, rng: np.random.Generator) -> Motion:
    """A draw of the ego vehicle's motion from ``dataset``'s entry of EGO_MOTION."""
    return _draw(EGO_MOTION[dataset], rng)


def _draw(model: tuple, rng: np.random.Generator) -> Motion:
    """(chance of standing still, mean speed, speed std, acceleration std): still, or
    speed ~ N(mean, std) clipped to [0, 2 mean] m/s and acceleration ~ N(0, std) m/s^2."""
    static, mean, std, acceleration_std = model
    still, speed, acceleration = rng.random(), rng.normal(mean, std), rng.normal(0.0, acceleration_std)
    if still < static:
        return Motion()
    return Motion(float(np.clip(speed, 0.0, 2 * mean)), float(acceleration))


def scan_sweeps(target: ScanTarget, sensor: Sensor, x: float, y: float, heading: float, motion: Motion,
                sweeps: int, options: ScanOptions = ScanOptions(), bounds: np.ndarray | None = None,
                box_margin: float | None = None, ego: Motion = Motion(), ground: Ground = Ground(),
                scale: np.ndarray | None = None) -> Scan:
    """``sweeps`` sweeps of ``target`` moving with ``motion``, seen from an ego vehicle
    moving with ``ego``, merged in the key frame, current sweep first: ``scan_many`` of
    one object, its noise seeded by ``options.seed``."""
    return scan_many(target, sensor, [x], [y], [heading], motion, sweeps, options, [options.seed], bounds,
                     box_margin, ego, ground, scale)[0]


def scan_many(target: ScanTarget, sensor: Sensor, x, y, heading, motion: Motion, sweeps: int,
              options: ScanOptions, seeds, bounds: np.ndarray | None = None, box_margin: float | None = None,
              ego: Motion = Motion(), ground: Ground = Ground(), scale: np.ndarray | None = None) -> list:
    """One Scan per object (E of them: ``x``, ``y`` (m), ``heading`` (rad), ``seeds`` (E,)
    and the fields of ``motion``, ``ego`` and ``ground`` arrays or scalars), each of
    ``sweeps`` sweeps of ``target`` moving with ``motion`` seen from an ego vehicle moving
    with ``ego``, merged in the key frame, current sweep first. Every sweep of every
    object is cast in one engine call (raycast.trace_rays); sweeps that see an object at
    the same pose (a still object from a still ego) share their rays, while their noise
    and drops still differ: each object draws from its own generator seeded by its seed
    (raycast.sensor_draws), so its scan is the same whatever else is in the batch.

    Each object stands on ``ground`` (raycast.placement) and moves along its heading up
    or down its pitch. ``bounds`` ((2, 3) or (E, 2, 3), object frame) is the box that
    stands on the ground and that the Scan reports (default: the geometry's bounds, times
    ``scale``). ``box_margin`` (m): keep only the returns whose hit (before range noise)
    lies within the object's current box (the reported, yaw-only box) grown by it, as a
    database keeps a box's points, and cast only the rays that can meet it: older sweeps
    of a moving object then cost only the part that overlaps the box. ``scale`` ((3,) or
    (E, 3)): scan ``target`` stretched by it along its axes (size variants of one target,
    all cast in the one call; raycast.trace_rays)."""
    if sweeps < 1:
        raise ValueError(f"sweeps must be at least 1, got {sweeps}")
    start = time.perf_counter()
    x, y, heading, seeds = (np.atleast_1d(np.asarray(value)) for value in (x, y, heading, seeds))
    count = len(x)
    stretch = np.broadcast_to(np.ones(3) if scale is None else np.asarray(scale, np.float64), (count, 3))
    geometry_bounds = target.cast_bounds * stretch[:, None]  # (E, 2, 3)
    bounds = target.bounds * stretch[:, None] if bounds is None else np.broadcast_to(bounds, (count, 2, 3))
    at = -np.arange(sweeps) * sensor.sweep_interval  # (S,) s, each sweep's time
    travelled = np.broadcast_to(Motion(np.reshape(motion.speed, (-1, 1)),
                                       np.reshape(motion.acceleration, (-1, 1))).displacement(at), (count, sweeps))
    driven = np.broadcast_to(Motion(np.reshape(ego.speed, (-1, 1)),
                                    np.reshape(ego.acceleration, (-1, 1))).displacement(at), (count, sweeps))
    cos, sin = np.cos(heading)[:, None], np.sin(heading)[:, None]
    ground_height, pitch, roll = (np.broadcast_to(np.reshape(value, (-1, 1)), (count, sweeps))
                                  for value in (ground.height, ground.pitch, ground.roll))
    under = Ground(np.where(travelled != 0, ground_height + travelled * np.sin(pitch), ground_height), pitch, roll)
    at_x, at_y = x[:, None] + travelled * cos, y[:, None] + travelled * sin
    origins = np.zeros((count, sweeps, 3))  # where the sensor fired each sweep from, key frame
    origins[..., :2] = driven[..., None] * sensor.forward
    poses = placement(bounds[:, None], sensor, at_x, at_y, heading[:, None], under)  # (E, S, 4, 4), key frame
    seen_from = placement(bounds[:, None], sensor, at_x - origins[..., 0], at_y - origins[..., 1], heading[:, None],
                          under)
    cast_bounds = np.broadcast_to(geometry_bounds[:, None], (count, sweeps, 2, 3))
    if box_margin is not None:  # the current box in each sweep's object frame, met with the geometry's
        low = np.stack([-travelled - box_margin, np.full_like(travelled, -box_margin),
                        np.full_like(travelled, -box_margin)], -1)
        high = np.stack([-travelled + box_margin, np.full_like(travelled, box_margin),
                         np.full_like(travelled, box_margin)], -1)
        current = bounds[:, None] + np.stack([low, high], -2)
        cast_bounds = np.stack([np.maximum(current[..., 0, :], geometry_bounds[:, None, 0]),
                                np.minimum(current[..., 1, :], geometry_bounds[:, None, 1])], -2)
    # Sweeps alike in pose, cast box and stretch cast once.
    stretches = np.broadcast_to(stretch[:, None], (count, sweeps, 3))
    keys = np.concatenate([seen_from[..., :3, :].reshape(count, sweeps, 12), cast_bounds.reshape(count, sweeps, 6),
                           stretches], -1).reshape(count * sweeps, 21)
    _, first, shared = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    trace = trace_rays(target, sensor, seen_from.reshape(-1, 4, 4)[first], options.window,
                       cast_bounds.reshape(-1, 2, 3)[first], options.engine,
                       None if scale is None else stretches.reshape(-1, 3)[first])
    offsets = trace.of_pose()
    group = shared.ravel()  # (E * S,) the trace pose of each object's sweep
    hits = np.diff(offsets)[group]
    picked = np.repeat(offsets[:-1][group] - np.cumsum(hits) + hits, hits) + np.arange(hits.sum())
    velocity = np.broadcast_to(motion.speed, count)[:, None] * np.column_stack([cos[:, 0], sin[:, 0]])
    boxes = placed_box(bounds, poses[:, 0], velocity)  # (E, 9), key frame
    if box_margin is not None:
        inside = _in_current_box(sensor, trace, picked, hits, origins, boxes, box_margin)
        picked = picked[inside]
        hits = np.bincount(np.repeat(np.arange(count * sweeps), hits)[inside], minlength=count * sweeps)
    sweep_of = np.tile(np.arange(sweeps), count)
    draws = sensor_draws(options, sensor, hits.reshape(count, sweeps), seeds)
    returns, kept = trace_returns(target, sensor, trace, options, np.repeat(sweep_of, hits), picked, draws)
    row_group = np.repeat(np.arange(count * sweeps), hits)[kept]
    returns["x"] += origins[..., 0].ravel()[row_group]  # motion compensation: each sweep's frame to the key frame
    returns["y"] += origins[..., 1].ravel()[row_group]
    ends = np.cumsum(np.bincount(row_group // sweeps, minlength=count))
    rays = trace.rays[group].reshape(count, sweeps).sum(axis=1)
    share = rays / max(rays.sum(), 1)  # the batch's time, shared by rays cast
    seconds = time.perf_counter() - start
    return [Scan(returns[end - length:end], boxes[index], int(rays[index]), seconds * share[index], sensor.dataset,
                 list(poses[index]), list(origins[index]), trace.engine_seconds * share[index])
            for index, (end, length) in enumerate(zip(ends, np.diff(ends, prepend=0)))]


def _in_current_box(sensor: Sensor, trace, picked: np.ndarray, hits: np.ndarray, origins: np.ndarray,
                    boxes: np.ndarray, margin: float) -> np.ndarray:
    """(K,) bool: the hits ``picked`` (``hits`` (E * S,) of them per object sweep, in
    order) that lie, where the ray hit in the key frame, within their object's current
    box ``boxes`` (E, >= 7) grown by ``margin`` m: the yaw-only box3d_lidar, as the
    datasets' database builders crop."""
    sweeps = origins.shape[1]
    centres = np.repeat(boxes[:, :3], sweeps, axis=0) - origins.reshape(-1, 3)  # (E * S, 3) in each sweep's frame
    points = sensor.return_points(trace.cells[picked], trace.ranges[picked])  # each sweep's sensor frame
    dx, dy, dz = (points[:, axis] - np.repeat(centres[:, axis], hits) for axis in range(3))
    cos, sin = (np.repeat(np.repeat(turn(boxes[:, 6]), sweeps), hits) for turn in (np.cos, np.sin))
    half = np.repeat(boxes[:, 3:6] / 2 + margin, sweeps, axis=0)
    return ((np.abs(dx * cos + dy * sin) <= np.repeat(half[:, 0], hits))
            & (np.abs(dy * cos - dx * sin) <= np.repeat(half[:, 1], hits)) & (np.abs(dz) <= np.repeat(half[:, 2], hits)))
