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
from dataclasses import dataclass, replace

import numpy as np

from .raycast import Ground, ScanOptions, Trace, placed_box, placement, trace_rays, trace_returns
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
                box_margin: float | None = None, ego: Motion = Motion(), ground: Ground = Ground()) -> Scan:
    """``sweeps`` sweeps of ``target`` moving with ``motion``, seen from an ego vehicle
    moving with ``ego``, merged in the key frame, current sweep first. The object stands
    on ``ground`` (raycast.placement) and moves along its heading up or down its pitch.
    ``bounds`` (2, 3, object frame) is the box that stands on the ground and that the
    Scan reports (default: the geometry's bounds). Sweeps that see the object at the
    same pose (a still object) share one ray cast; their noise and drops still differ.

    ``box_margin`` (m): cast only the rays that meet the current box grown by it, the
    only rays whose returns can lie in that box (a database keeps just those): older
    sweeps of a moving object then cost only the part that overlaps the box."""
    if sweeps < 1:
        raise ValueError(f"sweeps must be at least 1, got {sweeps}")
    bounds = target.bounds if bounds is None else bounds
    start = time.perf_counter()
    direction = np.array([np.cos(heading), np.sin(heading)])
    parts, poses, origins, traces, rays = [], [], [], {}, 0
    for sweep in range(sweeps):
        travelled = motion.displacement(-sweep * sensor.sweep_interval)
        shift = travelled * direction
        origin = np.append(ego.displacement(-sweep * sensor.sweep_interval) * sensor.forward, 0.0)
        under = ground if not travelled else replace(ground, height=ground.height + travelled * np.sin(ground.pitch))
        pose = placement(bounds, sensor, x + shift[0], y + shift[1], heading, under)
        seen_from = placement(bounds, sensor, x + shift[0] - origin[0], y + shift[1] - origin[1], heading, under)
        cast_bounds = None
        if box_margin is not None:  # the current box in this sweep's object frame, met with the geometry's
            current = bounds + np.array([[-travelled - box_margin, -box_margin, -box_margin],
                                         [-travelled + box_margin, box_margin, box_margin]])
            cast_bounds = np.stack([np.maximum(current[0], target.cast_bounds[0]),
                                    np.minimum(current[1], target.cast_bounds[1])])
        key = (seen_from.tobytes(), None if cast_bounds is None else cast_bounds.tobytes())
        if key not in traces:
            if cast_bounds is not None and np.any(cast_bounds[1] < cast_bounds[0]):
                traces[key] = Trace(0, *(np.zeros(0, dtype) for dtype in ("i8", "f8", "f8", "i8")), 0.0)
            else:
                traces[key] = trace_rays(target, sensor, seen_from, options.window, cast_bounds, options.engine)
        returns = trace_returns(target, sensor, traces[key], options, sweep)
        if origin.any():  # motion compensation: the sweep's sensor frame to the key frame
            returns["x"] += origin[0]
            returns["y"] += origin[1]
        parts.append(returns)
        poses.append(pose)
        origins.append(origin)
        rays += traces[key].rays
    box = placed_box(bounds, poses[0], motion.speed * direction)
    return Scan(np.concatenate(parts), box, rays, time.perf_counter() - start, sensor.dataset, poses, origins,
                sum(trace.seconds for trace in traces.values()))
