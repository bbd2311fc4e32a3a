"""Rotating LiDARs as data: beam table, column timing, range limits, mounting.

Sensor frame: origin at the optical centre, +z up, right-handed; azimuth is measured
from +x counter-clockwise about +z, elevation from the xy plane upwards. It is the
dataset's own LiDAR frame (KITTI: x forward, y left; nuScenes: x right, y forward).
The ground is the plane z = -mounting_height.

A ray is one (beam, column) cell. Beam ``b`` (its *ring*, 0 = lowest) points at
``elevations_deg[b]``; column ``c`` of ``columns`` per revolution fires at
``time = (c + firing_us[b] * 1e-6 * columns * rate_hz) / (columns * rate_hz)`` seconds
after the sweep starts, towards azimuth
``start_azimuth_deg + direction * 360 * (c + 0.5) / columns + azimuth_offsets_deg[b]``
(the cell's centre: the paper's phi', theta').

Each laser also sits off the sensor origin, as Velodyne calibration tables give it
(ROS velodyne_pointcloud: ``vert_offset_correction``, ``horiz_offset_correction``): its
ray starts at ``vertical_offsets_m[b] * (-sin e * a + cos e * z) +
horizontal_offsets_m[b] * (z x a)``, with ``e`` the beam's elevation, ``a`` the cell's
horizontal azimuth unit vector and ``z`` up: the origin turns with the head. A return is
that origin + range * direction; the range is measured from the laser.

``ray_drop`` = (a, k) is the sensor's ray-drop model (ray_drop.py): the chance that a
ray meeting a surface returns nothing, fitted to real scans (empty: none known).
``intensity_law`` = (scale, range_exponent, spread) sets its physical intensity
(physical_intensity.py; empty: the unfitted default).
"""

from dataclasses import dataclass, field, fields, replace
from functools import cached_property

import numpy as np

from ..classes import DATASETS
from ..errors import InputError
from ..files import TEXT_LIMIT, read_toml, regular_file

# Point formats of the datasets: intensity scale and .bin columns (REFERENCE.md 1-2).
INTENSITY_MAX = {"nuscenes": 255.0, "kitti": 1.0, "lyft": 255.0}
BIN_COLUMNS = {
    "nuscenes": ("x", "y", "z", "intensity", "time_lag"),
    "kitti": ("x", "y", "z", "intensity"),
    "lyft": ("x", "y", "z", "intensity", "time_lag"),
}
# Seconds between the sweeps a dataset's files merge (its time_lag step): nuScenes
# LIDAR_TOP sweeps at 20 Hz; Lyft's LiDAR files come at 5 Hz (real objects' lags are
# multiples of 0.2 s); KITTI has one sweep per frame.
SWEEP_INTERVAL_S = {"nuscenes": 0.05, "kitti": 0.1, "lyft": 0.2}
# The ego vehicle's forward direction (x, y) in the dataset's LiDAR frame: nuScenes'
# LIDAR_TOP faces +y; KITTI's Velodyne and Lyft's roof LiDAR +x.
FORWARD = {"nuscenes": (0.0, 1.0), "kitti": (1.0, 0.0), "lyft": (1.0, 0.0)}


# Fitted sensor models (tuples of numbers): what their numbers are.
_MODELS = {"ray_drop": "(a, k)", "intensity_law": "(scale, range_exponent, spread)"}
# intensity_law bounds: beyond them a law saturates or overflows (exp(spread x normal))
MAX_LAW = (1e6, 10.0, 10.0)
PER_BEAM = ("elevations_deg", "azimuth_offsets_deg", "firing_us", "vertical_offsets_m", "horizontal_offsets_m")


@dataclass(frozen=True, eq=False)
class Sensor:
    """One rotating LiDAR. Angles in degrees, distances in metres, times in seconds
    unless the name says otherwise. Tables are per beam, sorted by elevation."""

    name: str
    elevations_deg: tuple
    columns: int
    rate_hz: float
    min_range: float
    max_range: float
    mounting_height: float
    range_noise_sigma: float = 0.0
    azimuth_offsets_deg: tuple = ()
    firing_us: tuple = ()
    vertical_offsets_m: tuple = ()
    horizontal_offsets_m: tuple = ()
    start_azimuth_deg: float = -180.0
    ray_drop: tuple = ()
    intensity_law: tuple = ()
    direction: int = -1  # -1 clockwise seen from above, as Velodyne and Hesai spin
    dataset: str = "nuscenes"
    note: str = field(default="", compare=False)

    def __post_init__(self):
        for name in PER_BEAM:
            try:
                if isinstance(getattr(self, name), (str, bytes)):
                    raise TypeError
                values = tuple(float(v) for v in getattr(self, name))
            except (TypeError, ValueError, OverflowError):
                raise ValueError(f"sensor {self.name!r}: {name} must be a list of numbers, got "
                                 f"{getattr(self, name)!r}") from None
            object.__setattr__(self, name, values or ((0.0,) * len(self.elevations_deg) if name != "elevations_deg"
                                                      else ()))
        for name, meaning in _MODELS.items():
            try:
                object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
            except (TypeError, ValueError, OverflowError):
                raise ValueError(f"sensor {self.name!r}: {name} must be {meaning}, got "
                                 f"{getattr(self, name)!r}") from None
        validate(self)

    @property
    def beams(self) -> int:
        return len(self.elevations_deg)

    @property
    def azimuth_step_deg(self) -> float:
        return 360.0 / self.columns

    @property
    def sweep_seconds(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def sweep_interval(self) -> float:
        """Seconds between the merged sweeps of the sensor's dataset (SWEEP_INTERVAL_S)."""
        return SWEEP_INTERVAL_S[self.dataset]

    @property
    def forward(self) -> np.ndarray:
        """(2,) the ego vehicle's forward direction (x, y) in this sensor's frame (FORWARD)."""
        return np.array(FORWARD[self.dataset])

    @property
    def intensity_max(self) -> float:
        return INTENSITY_MAX[self.dataset]

    @cached_property
    def cell_azimuths(self) -> np.ndarray:
        """(beams, columns) float64 radians in (-pi, pi]: each cell's centre azimuth."""
        column = self.start_azimuth_deg + self.direction * self.azimuth_step_deg * (np.arange(self.columns) + 0.5)
        degrees = column[None, :] + np.asarray(self.azimuth_offsets_deg)[:, None]
        return np.radians(180.0 - np.mod(180.0 - degrees, 360.0))

    @cached_property
    def directions(self) -> np.ndarray:
        """(beams * columns, 3) float64 unit ray directions, cell ``b * columns + c``.
        Computed once and indexed, so a subset of rays is bit-identical to the same
        rays of a full revolution."""
        elevation = np.radians(np.asarray(self.elevations_deg))[:, None]
        azimuth = self.cell_azimuths
        table = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                          np.broadcast_to(np.sin(elevation), azimuth.shape)], axis=-1)
        table.setflags(write=False)
        return table.reshape(-1, 3)

    @cached_property
    def cell_origins(self) -> np.ndarray | None:
        """(beams * columns, 3) float64 laser origins per cell (sensor frame, m), or None
        when every laser sits at the sensor origin (the rays share one origin)."""
        vertical, horizontal = np.asarray(self.vertical_offsets_m), np.asarray(self.horizontal_offsets_m)
        if not (vertical.any() or horizontal.any()):
            return None
        elevation = np.radians(np.asarray(self.elevations_deg))[:, None]
        cos_a, sin_a = np.cos(self.cell_azimuths), np.sin(self.cell_azimuths)
        radial = -vertical[:, None] * np.sin(elevation)
        table = np.stack([radial * cos_a - horizontal[:, None] * sin_a, radial * sin_a + horizontal[:, None] * cos_a,
                          np.broadcast_to(vertical[:, None] * np.cos(elevation), cos_a.shape)], axis=-1)
        table.setflags(write=False)
        return table.reshape(-1, 3)

    @property
    def max_origin_offset(self) -> float:
        """The farthest any laser sits from the sensor origin (m)."""
        return float(np.hypot(self.vertical_offsets_m, self.horizontal_offsets_m).max(initial=0.0))

    @cached_property
    def direction_axes(self) -> tuple:
        """The x, y, z columns of ``directions`` as three contiguous (cells,) arrays."""
        return tuple(np.ascontiguousarray(self.directions[:, axis]) for axis in range(3))

    def ring_span(self, low_deg: np.ndarray, high_deg: np.ndarray) -> tuple:
        """(first ring, ring count), (T,) int64, of the beams whose elevations lie within
        [low_deg, high_deg] (T,) degrees."""
        elevations = np.asarray(self.elevations_deg)
        first = np.searchsorted(elevations, low_deg - 1e-7)
        count = np.searchsorted(elevations, high_deg + 1e-7, side="right") - first
        return first.astype(np.int64), np.maximum(count, 0).astype(np.int64)

    def column_span(self, centre_deg: np.ndarray, low_deg: np.ndarray, high_deg: np.ndarray) -> tuple:
        """(first column, column count), (T,) int64, of the cells whose rays' azimuths
        (each laser's offset included) can fall within [centre + low, centre + high] (T,)
        degrees, with a column of margin each side; the first column is not reduced
        modulo ``columns``."""
        offsets = np.asarray(self.azimuth_offsets_deg)
        steps = [self.direction * (centre_deg + side - beam - self.start_azimuth_deg) / self.azimuth_step_deg - 0.5
                 for side in (low_deg, high_deg) for beam in (offsets.min(initial=0.0), offsets.max(initial=0.0))]
        first = np.floor(np.min(steps, axis=0)).astype(np.int64) - 1
        count = np.minimum(np.ceil(np.max(steps, axis=0)).astype(np.int64) + 1 - first + 1, self.columns)
        return first, count

    def return_points(self, cells: np.ndarray, ranges: np.ndarray) -> np.ndarray:
        """(M, 3) float64 sensor frame: the returns at ``ranges`` (M,) m along the rays of
        ``cells`` (M,), each from its laser's origin."""
        points = np.take(self.directions, cells, axis=0)
        points *= np.asarray(ranges, np.float64)[:, None]
        if self.cell_origins is not None:
            points += self.cell_origins[cells]
        return points

    def cell_times(self, rings: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """Seconds after the sweep's start at which cells (rings, columns) fire."""
        column_seconds = self.sweep_seconds / self.columns
        return columns * column_seconds + np.asarray(self.firing_us)[rings] * 1e-6


MAX_CELLS = 2**24  # beams x columns: the ray table (24 bytes a cell) stays within 400 MB
MAX_ORIGIN_OFFSET_M = 1.0  # a laser farther than this from the sensor origin is a unit error
RATE_HZ_RANGE = (0.1, 1000.0)  # rotating LiDARs spin at 5-20 Hz; beyond this, float32 time lags overflow


def validate(sensor: Sensor) -> None:
    """Raise ValueError naming the fields that do not make a usable sensor."""
    if not isinstance(sensor.name, str) or not sensor.name or "\0" in sensor.name:
        raise ValueError(f"the sensor's name must be a non-empty text, got {sensor.name!r}")
    scalars = ("rate_hz", "min_range", "max_range", "mounting_height", "range_noise_sigma", "start_azimuth_deg")
    wrong = [name for name in scalars if isinstance(getattr(sensor, name), bool)
             or not isinstance(getattr(sensor, name), (int, float, np.integer, np.floating))
             or not np.isfinite(getattr(sensor, name))]
    if wrong:  # the checks below compare numbers: stop here with the keys named
        raise ValueError(f"sensor {sensor.name!r}: " + "; ".join(
            f"{name} must be a finite number, got {getattr(sensor, name)!r}" for name in wrong))
    try:
        elevations = np.asarray(sensor.elevations_deg, np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"sensor {sensor.name!r}: elevations_deg must be a list of numbers") from None
    problems = []
    if elevations.size == 0:
        problems.append("elevations_deg is empty")
    elif not np.isfinite(elevations).all() or np.abs(elevations).max() >= 90:
        problems.append("elevations_deg must be finite and strictly between -90 and 90")
    elif (np.diff(elevations) <= 0).any():
        problems.append("elevations_deg must be strictly increasing (ring 0 = lowest beam)")
    for name in PER_BEAM[1:]:
        values = np.asarray(getattr(sensor, name), np.float64)
        if len(values) != len(elevations):
            problems.append(f"{name} has {len(values)} entries for {len(elevations)} beams")
        elif not np.isfinite(values).all() or (name == "firing_us" and values.min(initial=0) < 0):
            problems.append(f"{name} must be finite" + (" and >= 0" if name == "firing_us" else ""))
        elif name.endswith("_offsets_m") and np.abs(values).max(initial=0) > MAX_ORIGIN_OFFSET_M:
            problems.append(f"{name} must lie within +-{MAX_ORIGIN_OFFSET_M} m of the sensor origin")
    if len(sensor.azimuth_offsets_deg) == len(elevations) and elevations.size and \
            np.abs(sensor.azimuth_offsets_deg).max() >= 180:
        problems.append("azimuth_offsets_deg must lie strictly between -180 and 180")
    if not (isinstance(sensor.columns, int | np.integer) and not isinstance(sensor.columns, bool)
            and sensor.columns > 0):
        problems.append(f"columns must be a positive integer, got {sensor.columns!r}")
    elif sensor.columns * max(len(elevations), 1) > MAX_CELLS:
        problems.append(f"columns x beams = {sensor.columns * len(elevations):,} exceeds {MAX_CELLS:,} rays per "
                        f"revolution")
    if not sensor.max_range > 0:
        problems.append(f"max_range must be positive, got {sensor.max_range!r}")
    if not RATE_HZ_RANGE[0] <= sensor.rate_hz <= RATE_HZ_RANGE[1]:
        problems.append(f"rate_hz must lie between {RATE_HZ_RANGE[0]:g} and {RATE_HZ_RANGE[1]:g}, "
                        f"got {sensor.rate_hz!r}")
    if not 0 <= sensor.min_range < sensor.max_range:
        problems.append("min_range must be >= 0 and below max_range")
    if not sensor.mounting_height >= 0 or not sensor.range_noise_sigma >= 0:
        problems.append("mounting_height and range_noise_sigma must be >= 0")
    for name, meaning in _MODELS.items():
        values = getattr(sensor, name)
        if values and (len(values) != len(meaning.split(",")) or not np.isfinite(values).all()):
            problems.append(f"{name} must be empty or {meaning}, got {list(values)}")
    if len(sensor.intensity_law) == 3 and not (0 < sensor.intensity_law[0] <= MAX_LAW[0]
                                               and 0 <= sensor.intensity_law[1] <= MAX_LAW[1]
                                               and 0 <= sensor.intensity_law[2] <= MAX_LAW[2]):
        problems.append("intensity_law needs 0 < scale <= {:g}, 0 <= range_exponent <= {:g} and "
                        "0 <= spread <= {:g}".format(*MAX_LAW))
    if isinstance(sensor.direction, bool) or sensor.direction not in (-1, 1):
        problems.append("direction must be -1 (clockwise) or 1 (counter-clockwise)")
    if sensor.dataset not in DATASETS:
        problems.append(f"dataset must be one of {', '.join(DATASETS)}, got {sensor.dataset!r}")
    if problems:
        raise ValueError(f"sensor {sensor.name!r}: " + "; ".join(problems))


def _hdl32e() -> Sensor:
    elevations = (np.arange(32) - 23) * 4.0 / 3.0  # -30.67 .. +10.67, 0 at ring 23
    # Laser ids alternate between the lower and upper half, 1.152 us apart (HDL-32E manual).
    firing = np.where(np.arange(32) < 16, 2 * np.arange(32), 2 * (np.arange(32) - 16) + 1) * 1.152
    return Sensor("nuscenes", tuple(np.round(elevations, 2)), columns=1080, rate_hz=20.0,
                  min_range=1.0, max_range=70.0, mounting_height=1.84, range_noise_sigma=0.02,
                  firing_us=tuple(firing), intensity_law=NUSCENES_INTENSITY_LAW, dataset="nuscenes",
                  note="Velodyne HDL-32E as on nuScenes LIDAR_TOP: 32 beams -30.67..+10.67 deg "
                       "every 4/3 deg, 20 Hz, 1080 columns (0.333 deg)")


# The KITTI HDL-64E fitted to KITTI's own raw scans (headless_scripts/fit_sensor.py on
# the three frames of ../shared/data/kitti_scans; KITTI publishes no calibration): per
# laser, sorted by elevation, its elevation (deg) and its origin's offset along the beam
# normal (m). z residual 0.3 mm median; fitted on two frames, the third's elevations are
# off by <= 0.004 deg RMS (the nominal S2 table: 0.6 to 1.4 deg).
KITTI_ELEVATIONS_DEG = (
    -24.9997, -24.5064, -23.9711, -23.3225, -22.8560, -22.4381, -21.9355, -21.3180, -20.7887, -20.2223, -19.7364,
    -19.3203, -18.7975, -18.3230, -17.7297, -17.1871, -16.5544, -16.1769, -15.6568, -15.1888, -14.5970, -14.0483,
    -13.4849, -13.0407, -12.5621, -12.1149, -11.5992, -10.9565, -10.4705, -10.0625, -9.5735, -9.0259, -8.7114,
    -8.3105, -8.0581, -7.6787, -7.2872, -6.9990, -6.6757, -6.3289, -5.9583, -5.6106, -5.2508, -4.9138, -4.5881,
    -4.2155, -3.9359, -3.5393, -3.2359, -2.8738, -2.5466, -2.2076, -1.8332, -1.4939, -1.2012, -0.8031, -0.4518,
    -0.0887, 0.1806, 0.5788, 0.8716, 1.3048, 1.5740, 1.9367)
KITTI_VERTICAL_OFFSETS_M = (
    0.1052, 0.1058, 0.1065, 0.1074, 0.1079, 0.1085, 0.1091, 0.1099, 0.1106, 0.1112, 0.1119, 0.1124, 0.1130, 0.1135,
    0.1142, 0.1150, 0.1157, 0.1162, 0.1168, 0.1173, 0.1179, 0.1186, 0.1193, 0.1197, 0.1203, 0.1208, 0.1214, 0.1221,
    0.1226, 0.1231, 0.1237, 0.1243, 0.1956, 0.1961, 0.1964, 0.1969, 0.1974, 0.1977, 0.1981, 0.1986, 0.1990, 0.1995,
    0.2000, 0.2004, 0.2008, 0.2013, 0.2016, 0.2021, 0.2025, 0.2030, 0.2034, 0.2038, 0.2043, 0.2047, 0.2051, 0.2056,
    0.2060, 0.2064, 0.2068, 0.2073, 0.2077, 0.2082, 0.2086, 0.2090)
KITTI_COLUMNS = 2000  # fitted: the scans step 0.180 deg in azimuth
# Ray drop (a, k) fitted on the labelled objects of the same frames (fit_returns.py,
# ray_drop.py): a surface of reflectivity 0.5 met head-on loses 2 % of its returns at 10 m,
# 12 % at 35 m, 25 % at 60 m.
KITTI_RAY_DROP = (-4.541, 0.800)
# Intensity laws (scale, range_exponent, spread), physical_intensity.py, fitted by
# fit_returns.py: KITTI on the labelled objects of the shared frames (mean 0.165, no
# range falloff across objects); nuScenes on the nuScenes format sample's 600 points
# (scene points: no labelled object has a point in that subset, so the scale is the
# scene's mean, 8.9 of 255, which real objects exceed).
KITTI_INTENSITY_LAW = (0.7067, 0.0, 1.0398)
NUSCENES_INTENSITY_LAW = (0.0640, 0.0, 1.2007)


def _hdl64e() -> Sensor:
    # Both blocks (the lower and upper 32 rings) fire together, one laser each per 1/32 of a column.
    firing = np.tile(np.arange(32), 2) * (1e6 / (10.0 * KITTI_COLUMNS) / 32)
    return Sensor("kitti", KITTI_ELEVATIONS_DEG, columns=KITTI_COLUMNS, rate_hz=10.0, min_range=2.0,
                  max_range=120.0, mounting_height=1.73, range_noise_sigma=0.02,
                  firing_us=tuple(firing), vertical_offsets_m=KITTI_VERTICAL_OFFSETS_M, ray_drop=KITTI_RAY_DROP,
                  intensity_law=KITTI_INTENSITY_LAW, dataset="kitti",
                  note="Velodyne HDL-64E as on KITTI: 64 beams -25.0..+1.94 deg with per-laser vertical offsets "
                       "fitted to KITTI's raw scans, 10 Hz, 2000 columns (0.18 deg)")


def _pandar40p() -> Sensor:
    elevations = np.concatenate([[-25, -19], np.arange(-14, -6), -6 + np.arange(25) / 3.0,
                                 [3, 5, 8, 11, 15]])
    return Sensor("lyft", tuple(np.round(elevations, 2)), columns=1800, rate_hz=10.0,
                  min_range=0.3, max_range=200.0, mounting_height=1.8, range_noise_sigma=0.02,
                  dataset="lyft",
                  note="40-beam roof LiDAR modelled on the Hesai Pandar40P table (-25..+15 deg, "
                       "1/3 deg between -6 and +2), 10 Hz, 0.2 deg; Lyft's cars carry 40- or "
                       "64-beam roof units and do not publish the table, so check per log")


def _vlp16() -> Sensor:
    elevations = -15.0 + 2.0 * np.arange(16)
    laser_of_ring = np.argsort([-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15])
    return Sensor("vlp16", tuple(elevations), columns=1800, rate_hz=10.0, min_range=0.5,
                  max_range=100.0, mounting_height=1.8, range_noise_sigma=0.03,
                  firing_us=tuple(laser_of_ring * 2.304), dataset="kitti",
                  note="Velodyne VLP-16 (Puck): 16 beams -15..+15 every 2 deg, 10 Hz, 0.2 deg")


PRESETS = {sensor.name: sensor for sensor in (_hdl32e(), _hdl64e(), _pandar40p(), _vlp16())}

_TOML_KEYS = {f.name for f in fields(Sensor)} - {"note"}
MAX_LASERS = 1024


def read_velodyne_calibration(path) -> dict:
    """The per-laser table of a ROS velodyne_pointcloud calibration YAML (``lasers``:
    ``vert_correction`` and ``rot_correction`` in radians, ``vert_offset_correction``
    and ``horiz_offset_correction`` in metres) as Sensor per-beam fields, ordered by
    elevation (ring 0 = lowest): elevations_deg, azimuth_offsets_deg,
    vertical_offsets_m, horizontal_offsets_m.

    The driver's azimuth is the encoder angle minus ``rot_correction``, clockwise; in
    the counter-clockwise sensor frame that is + ``rot_correction``. ``dist_correction``
    is what the driver adds to a raw range to calibrate it: calibrated points, which the
    datasets hold and the scans make, carry none, so it is not read. InputError naming
    the file for anything else."""
    import yaml

    path = regular_file(path, TEXT_LIMIT)
    try:
        table = yaml.safe_load(path.read_text())
        lasers = table["lasers"]
        if not isinstance(lasers, list) or not 0 < len(lasers) <= MAX_LASERS:
            raise ValueError(f"'lasers' must list 1 to {MAX_LASERS} lasers")
        rows = np.array([[float(laser["vert_correction"]), float(laser.get("rot_correction", 0.0)),
                          float(laser.get("vert_offset_correction", 0.0)),
                          float(laser.get("horiz_offset_correction", 0.0))] for laser in lasers])
    except (OSError, UnicodeDecodeError, yaml.YAMLError, RecursionError) as error:
        raise InputError(path, f"not a readable YAML file: {' '.join(str(error).split())}") from None
    except (KeyError, TypeError, ValueError, OverflowError) as error:
        raise InputError(path, f"not a velodyne_pointcloud calibration ({type(error).__name__}: {error})") from None
    if not np.isfinite(rows).all():
        raise InputError(path, "calibration values must be finite numbers")
    rows = rows[np.argsort(rows[:, 0], kind="stable")]
    return {"elevations_deg": tuple(np.degrees(rows[:, 0])), "azimuth_offsets_deg": tuple(np.degrees(rows[:, 1])),
            "vertical_offsets_m": tuple(rows[:, 2]), "horizontal_offsets_m": tuple(rows[:, 3])}


def load_sensor_toml(path) -> Sensor:
    """A custom sensor from TOML: the Sensor fields as top-level keys, or ``base`` =
    a preset name and only the keys that differ, e.g. the paper's ablation::

        base = "nuscenes"
        columns = 3600

    ``calibration`` = a ROS velodyne_pointcloud YAML (path relative to the TOML) sets
    the per-laser table (read_velodyne_calibration); the preset gives the rest::

        base = "nuscenes"
        calibration = "32db.yaml"
    """
    path = regular_file(path, TEXT_LIMIT)
    table = read_toml(path)
    unknown = sorted(set(table) - _TOML_KEYS - {"base", "calibration"})
    if unknown:
        raise InputError(path, f"unknown sensor keys {', '.join(unknown)}; known: {', '.join(sorted(_TOML_KEYS))}")
    base = table.pop("base", None)
    if base is not None and not (isinstance(base, str) and base in PRESETS):
        raise InputError(path, f"base {base!r} is not a preset ({', '.join(PRESETS)})")
    table.setdefault("name", path.stem)
    calibration = table.pop("calibration", None)
    if calibration is not None:
        if not isinstance(calibration, str):
            raise InputError(path, f"calibration must be the path of a calibration YAML, got {calibration!r}")
        laser_table = read_velodyne_calibration(path.parent / calibration)
        if base is not None and len(laser_table["elevations_deg"]) != PRESETS[base].beams:
            raise InputError(path, f"the calibration has {len(laser_table['elevations_deg'])} lasers, the {base} "
                                   f"preset {PRESETS[base].beams} beams")
        table = {**laser_table, **table}
    try:
        if base is None:
            missing = sorted({"elevations_deg", "columns", "rate_hz", "min_range", "max_range",
                              "mounting_height"} - set(table))
            if missing:
                raise ValueError(f"missing keys {', '.join(missing)}")
            return Sensor(**table)
        return replace(PRESETS[base], **table)
    except (TypeError, ValueError) as error:
        raise InputError(path, str(error)) from None


def sensor_files(name: str) -> list:
    """The files the sensor ``name`` (as sensor_from_name takes it) is read from: none
    for a preset; a TOML, and the calibration YAML it names."""
    if not name.endswith(".toml"):
        return []
    path = regular_file(name, TEXT_LIMIT)
    calibration = read_toml(path).get("calibration")
    return [path, *([path.parent / calibration] if isinstance(calibration, str) else [])]


def sensor_from_name(name: str) -> Sensor:
    """A preset by name, or a custom sensor from a .toml path."""
    if name in PRESETS:
        return PRESETS[name]
    if name.endswith(".toml"):
        return load_sensor_toml(name)
    raise InputError(name, f"not a sensor preset ({', '.join(PRESETS)}) or a .toml file")
