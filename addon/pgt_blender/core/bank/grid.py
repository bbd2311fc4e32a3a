"""The bank's poses: per object, every heading x every (x, y) of the grid (paper sec. 4),
each jittered, with its size variant, motion, noise seed, ego motion and ground drawn.

Every random draw of entry ``index`` of object ``object`` comes from its own generator
``default_rng([seed, ENTRY_STREAM, object, index])``, so an entry is the same whatever the chunking,
worker count, shard or resume. Poses are filtered after the jitter: the box centre
beyond ``max_distance`` m (when set) or the box footprint within ``ego_clearance`` m of
the sensor in any sweep (the ego vehicle stands there, or drove there) drops the entry.

Sensor frame throughout: (x, y) the box centre in metres, heading in radians from +x
counter-clockwise (OpenPCDet's box3d_lidar convention).
"""

import numpy as np

from ..scan.sensors import FORWARD, SWEEP_INTERVAL_S
from ..scan.sweeps import SWEEPS_PER_SAMPLE, Motion, sample_ego_motion, sample_motion
from .config import BankConfig, grid_values
from .ground import sample_ground

ENTRY_STREAM, SIZE_STREAM = 0, 1  # seed-sequence keys: entry draws and size variants never share a stream
ENTRY_DTYPE = np.dtype([
    ("object", "i4"), ("index", "i4"), ("heading", "f8"), ("x", "f8"), ("y", "f8"),
    ("variant", "i2"), ("speed", "f8"), ("acceleration", "f8"), ("noise_seed", "u4"),
    ("ego_speed", "f8"), ("ego_acceleration", "f8"), ("ground_height", "f8"), ("pitch", "f8"), ("roll", "f8"),
])


def sweeps_of(config: BankConfig) -> int:
    return config.sweeps or SWEEPS_PER_SAMPLE[config.dataset]


def size_variants(config: BankConfig, object_index: int, dims: np.ndarray) -> np.ndarray:
    """(K, 3) float64 box dims of the object's size variants: each axis times
    1 + N(0, size_jitter) clipped to +-size_jitter (the paper's clipped size noise)."""
    rng = np.random.default_rng([config.seed, SIZE_STREAM, object_index])
    sigma = config.size_jitter
    factors = 1 + np.clip(rng.normal(0.0, sigma, (config.size_variants, 3)), -sigma, sigma)
    return dims * factors


def footprint_distance(x, y, heading, length: float, width: float) -> np.ndarray:
    """Distance (m) from the sensor (origin) to the rectangle of the box footprint; 0 inside."""
    cos, sin = np.cos(heading), np.sin(heading)
    along, across = -(x * cos + y * sin), -(-x * sin + y * cos)  # the origin in the box frame
    outside = np.stack([np.abs(along) - length / 2, np.abs(across) - width / 2])
    return np.hypot(*np.maximum(outside, 0.0))


def object_entries(config: BankConfig, object_index: int, class_name: str, dims: np.ndarray) -> np.ndarray:
    """The entries of one object, grid order (heading, then x, then y), filtered."""
    headings = np.radians(grid_values(*config.headings_deg))
    heading, x, y = (a.ravel() for a in np.meshgrid(headings, grid_values(*config.x), grid_values(*config.y),
                                                    indexing="ij"))
    entries = np.zeros(len(heading), ENTRY_DTYPE)
    entries["object"], entries["index"], entries["heading"] = object_index, np.arange(len(heading)), heading
    moving = sweeps_of(config) > 1
    for entry, nominal_x, nominal_y in zip(entries, x, y):
        rng = np.random.default_rng([config.seed, ENTRY_STREAM, object_index, int(entry["index"])])
        entry["variant"] = rng.integers(config.size_variants)
        entry["x"], entry["y"] = np.array([nominal_x, nominal_y]) + rng.uniform(-1, 1, 2) * config.centre_jitter
        if moving:
            motion = sample_motion(class_name, rng)
            entry["speed"], entry["acceleration"] = motion.speed, motion.acceleration
        entry["noise_seed"] = rng.integers(2**32)
        if moving and config.ego_motion:  # drawn last: the entry's other draws stay as they were
            ego = sample_ego_motion(config.dataset, rng)
            entry["ego_speed"], entry["ego_acceleration"] = ego.speed, ego.acceleration
        if config.grade_deg or config.slope_deg:
            ground = sample_ground(entry["x"], entry["y"], config.grade_deg, config.slope_deg, rng)
            entry["ground_height"], entry["pitch"], entry["roll"] = ground.height, ground.pitch, ground.roll
    variants = size_variants(config, object_index, dims)[entries["variant"]]
    keep = np.ones(len(entries), bool)
    forward, interval = np.array(FORWARD[config.dataset]), SWEEP_INTERVAL_S[config.dataset]
    direction = np.column_stack([np.cos(entries["heading"]), np.sin(entries["heading"])])
    motions = Motion(entries["speed"], entries["acceleration"])  # every entry at once
    egos = Motion(entries["ego_speed"], entries["ego_acceleration"])
    for sweep in range(sweeps_of(config)):  # the ego never drives through the object, in any sweep
        t = -sweep * interval
        centre = np.column_stack([entries["x"], entries["y"]]) + motions.displacement(t)[:, None] * direction \
            - egos.displacement(t)[:, None] * forward
        keep &= footprint_distance(centre[:, 0], centre[:, 1], entries["heading"], variants[:, 0], variants[:, 1]) \
            > config.ego_clearance
    if config.max_distance:
        keep &= np.hypot(entries["x"], entries["y"]) <= config.max_distance
    return entries[keep]
