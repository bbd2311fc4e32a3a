"""Fit a rotating LiDAR's beam table to its own raw scans (fit_sensor.py).

Input: raw scans as (N, 3+) float64 rows in the sensor frame (sensors.py), stored laser
by laser, each laser's revolution starting at the same azimuth, as KITTI's velodyne
files are: the laser of a point is recovered from scan order (a new laser starts where
the azimuth, taken in [0, 360) degrees, falls back by more than half a turn); KITTI files
have no ring column.

Model (the Velodyne calibration's, sensors.py): laser k's rays start at its vertical
offset ``v_k`` along the beam's normal, so its returns lie on the cone
``z = d tan(e_k) + v_k / cos(e_k)`` with ``d`` the horizontal distance from the sensor
axis. A least-squares line of z on d per laser gives its elevation ``e_k`` and offset
``v_k``; the residual is the points' distance from the cone in z (m). The columns per
revolution come from the median azimuth step between neighbouring points of a laser.
Azimuth and horizontal offsets are not fitted (they do not move a point off its cone).
"""

from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError
from .sensors import Sensor

MIN_POINTS_PER_LASER = 50
_STEP_WINDOW = (0.85, 1.15)  # azimuth steps kept around the median: neighbours, not gaps or repeats


@dataclass(frozen=True)
class LaserFit:
    """Per laser in scan order: elevation (deg), vertical offset (m), z residual RMS (m)
    and the points it was fitted on; ``columns`` per revolution."""

    elevations_deg: np.ndarray
    vertical_offsets_m: np.ndarray
    residual_m: np.ndarray
    points: np.ndarray
    columns: int


def scan_order_lasers(points: np.ndarray, name="scan") -> np.ndarray:
    """(N,) int laser index of each row of a scan stored laser by laser (see above)."""
    azimuth = np.mod(np.arctan2(points[:, 1], points[:, 0]), 2 * np.pi)
    starts = np.flatnonzero(np.diff(azimuth) < -np.pi) + 1
    if not len(starts):
        raise InputError(name, "its points do not go round laser by laser (no azimuth wrap in scan order)")
    return np.searchsorted(starts, np.arange(len(points)), side="right")


def fit_lasers(scans: list, names: list | None = None) -> LaserFit:
    """The beam table of ``scans`` (list of (N, 3+) arrays of one sensor), pooled; every
    scan must show the same number of lasers, each with MIN_POINTS_PER_LASER points."""
    names = names or [f"scan {index}" for index in range(len(scans))]
    lasers = [scan_order_lasers(scan, name) for scan, name in zip(scans, names)]
    counts = {int(laser.max()) + 1 for laser in lasers}
    if len(counts) != 1:
        raise InputError(names[0], f"the scans show different numbers of lasers ({sorted(counts)})")
    count = counts.pop()
    distance = np.concatenate([np.hypot(scan[:, 0], scan[:, 1]) for scan in scans])
    height = np.concatenate([scan[:, 2] for scan in scans])
    laser = np.concatenate(lasers)
    points = np.bincount(laser, minlength=count)
    if points.min() < MIN_POINTS_PER_LASER:
        raise InputError(names[0], f"laser {int(points.argmin())} has {points.min()} points; the fit needs "
                                   f"{MIN_POINTS_PER_LASER}")
    # Per-laser least squares of z = slope d + intercept from the sums (no Python loop over points).
    n, sd, sz = points.astype(float), np.bincount(laser, distance), np.bincount(laser, height)
    sdd, sdz = np.bincount(laser, distance * distance), np.bincount(laser, distance * height)
    slope = (n * sdz - sd * sz) / (n * sdd - sd * sd)
    intercept = (sz - slope * sd) / n
    residual = height - (slope[laser] * distance + intercept[laser])
    elevation = np.arctan(slope)
    return LaserFit(np.degrees(elevation), intercept * np.cos(elevation),
                    np.sqrt(np.bincount(laser, residual**2) / n), points, fit_columns(scans, lasers))


def fit_columns(scans: list, lasers: list) -> int:
    """Columns per revolution: a full turn over the median azimuth step between scan-order
    neighbours of one laser, among the steps within _STEP_WINDOW of the overall median
    (a dropped return doubles a step; offsets and motion blur them both ways)."""
    steps = []
    for scan, laser in zip(scans, lasers):
        azimuth = np.mod(np.arctan2(scan[:, 1], scan[:, 0]), 2 * np.pi)
        step = np.diff(azimuth)[np.diff(laser) == 0]
        steps.append(step[step > 0])
    steps = np.concatenate(steps)
    median = np.median(steps)
    kept = steps[(steps > _STEP_WINDOW[0] * median) & (steps < _STEP_WINDOW[1] * median)]
    return int(round(2 * np.pi / np.median(kept)))


def elevation_errors(fit: LaserFit, scan: np.ndarray, elevations_deg=None, vertical_offsets_m=None) -> np.ndarray:
    """(N,) degrees: each point's elevation seen from its laser's origin minus the
    laser's elevation, for a table in scan order (default ``fit``'s: give another table
    to score it, e.g. a preset matched by rank)."""
    elevations = np.radians(fit.elevations_deg if elevations_deg is None else np.asarray(elevations_deg))
    offsets = fit.vertical_offsets_m if vertical_offsets_m is None else np.asarray(vertical_offsets_m)
    laser = scan_order_lasers(scan)
    if laser.max() >= len(elevations):
        raise InputError("scan", f"shows {laser.max() + 1} lasers, the table has {len(elevations)}")
    cos, sin = np.cos(elevations[laser]), np.sin(elevations[laser])
    # Move each point back by its laser's offset along the beam normal, then measure its angle.
    distance = np.hypot(scan[:, 0], scan[:, 1]) + offsets[laser] * sin
    height = scan[:, 2] - offsets[laser] * cos
    return np.degrees(np.arctan2(height, distance) - elevations[laser])


def fitted_sensor(base: Sensor, fit: LaserFit, name: str | None = None) -> Sensor:
    """``base`` with the fitted elevations and vertical offsets (sorted by elevation:
    ring 0 = lowest) and columns; firing times scaled to the new column period."""
    order = np.argsort(fit.elevations_deg, kind="stable")
    firing = np.asarray(base.firing_us) * base.columns / fit.columns
    return replace(base, name=name or base.name, elevations_deg=tuple(np.round(fit.elevations_deg[order], 4)),
                   vertical_offsets_m=tuple(np.round(fit.vertical_offsets_m[order], 5)), columns=fit.columns,
                   firing_us=tuple(firing), horizontal_offsets_m=(), azimuth_offsets_deg=())
