"""The ground under a scan: a grid of local planes fitted to its lowest returns.

Sensor frame, metres. The xy plane is cut into square cells of ``cell`` m, the grid
centred on the sensor and ``radius`` m out; each cell holds a plane
``z = a (x - xc) + b (y - yc) + c`` about its centre (xc, yc). The fit, vectorised
over cells:

1. **Seeds**: per cell, the returns within ``seed_band`` of its lowest return.
2. **Not ground**: a cell whose lowest return lies more than ``step`` plus the slope
   allowance (``max_slope_deg`` over one cell) above the lowest of its 3 x 3
   neighbourhood is dropped: a car roof, a wall, a hedge top.
3. **Planes**: least squares on the seeds, through their mean height; a cell whose
   returns spread less than a quarter of a uniform cell's across some direction (one
   or two rings cross it: no slope across them) takes its slopes from its 3 x 3
   neighbourhood's returns; the slopes pulled towards level by a ridge worth two
   returns spread over the cell; then refitted twice on the returns from ``inlier`` m
   below it to half that above it (nothing lies under the ground but noise; things
   stand on it).
4. **Checks**: planes steeper than ``max_slope_deg``, or farther than ``step`` from the
   median of their neighbours' planes extended to the cell centre, are dropped (a
   car's flank caught low in a cell of its own).
5. **Fill**: cells left without a plane take the height of the nearest fitted cell,
   level, and are flagged ``measured`` False.

Accuracy (tests/test_placement.py, exact rays on analytic surfaces): cell centres
within 3.5 cm of a 3 % grade and of a level road beside a kerb; a cell holding nothing
but the foot of a wall or of a
vehicle's flank reads up to 0.1 m high (the seed band's mean, 0.15 m, pulled down by the two refits).
On an 8 degree grade the fitted slopes follow it (median over 0.9 of it) and heights
are within 1 cm at the median; a few cells still read nearly level, off by up to the
grade times a cell (0.1 m at 3 degrees).

Ground lies below the sensor: a cell whose lowest return is not at least
``clearance`` m below the sensor, give or take a road of ``max_grade_deg`` rising
towards it, holds no ground (a scan of a ceiling, of tree tops, or in the wrong
columns has none). Kerbs (about 0.15 m) stay ground; slopes up to ``max_slope_deg``
are followed.
"""

from dataclasses import dataclass

import numpy as np
from scipy import ndimage  # imported here once: scipy's lazy import costs milliseconds a call

from ..errors import InputError

GROUND_TOLERANCE = 0.2  # m: a return this close to the ground plane is ground
OBSTACLE_BAND = (0.3, 3.0)  # m above the ground: returns of things an object would collide with


@dataclass
class Ground:
    """Per-cell planes: ``coefficients`` (ny, nx, 3) a, b, c (slopes along x and y,
    height at the cell centre, m); ``measured`` (ny, nx) bool, fitted from returns;
    cell (iy, ix) spans x in ``origin[0] + [ix, ix + 1) * cell``, likewise y."""

    origin: np.ndarray
    cell: float
    coefficients: np.ndarray
    measured: np.ndarray

    def _cells(self, xy: np.ndarray) -> tuple:
        """(iy, ix) of the cells holding (N, 2) points, clipped to the grid (the border
        cells extend outwards), and the points' offsets (N, 2) from those cells' centres."""
        ny, nx = self.measured.shape
        index = np.floor((np.asarray(xy, np.float64) - self.origin) / self.cell).astype(np.int64)
        ix, iy = np.clip(index[:, 0], 0, nx - 1), np.clip(index[:, 1], 0, ny - 1)
        centres = self.origin + (np.column_stack([ix, iy]) + 0.5) * self.cell
        return iy, ix, np.asarray(xy, np.float64) - centres

    def height(self, xy: np.ndarray) -> np.ndarray:
        """(N,) ground height z (m) under (N, 2) points x, y."""
        iy, ix, offset = self._cells(xy)
        a, b, c = np.moveaxis(self.coefficients[iy, ix], -1, 0)
        return a * offset[:, 0] + b * offset[:, 1] + c

    def normal(self, xy: np.ndarray) -> np.ndarray:
        """(N, 3) unit upward normals of the ground under (N, 2) points."""
        iy, ix, _ = self._cells(xy)
        a, b, _ = np.moveaxis(self.coefficients[iy, ix], -1, 0)
        normals = np.column_stack([-a, -b, np.ones_like(a)])
        return normals / np.linalg.norm(normals, axis=1, keepdims=True)

    def is_measured(self, xy: np.ndarray) -> np.ndarray:
        """(N,) bool: the points' cells were fitted from returns (not filled)."""
        iy, ix, _ = self._cells(xy)
        return self.measured[iy, ix]

    def under_boxes(self, boxes: np.ndarray) -> np.ndarray:
        """(N,) the height (m) an object in each of (N, >= 7) centre boxes stands on: the mean
        ground height under its centre and four footprint corners (a long truck spans
        several cells of a crowned or graded road)."""
        from .collision import footprint_corners

        boxes = np.asarray(boxes, np.float64).reshape(-1, np.shape(boxes)[-1])
        spots = np.concatenate([boxes[:, None, :2], footprint_corners(boxes)], axis=1)
        return self.height(spots.reshape(-1, 2)).reshape(len(boxes), 5).mean(axis=1)

    def height_above(self, points: np.ndarray) -> np.ndarray:
        """(N,) height (m) of (N, >= 3) points above the ground under them."""
        return points[:, 2] - self.height(points[:, :2])


def estimate_ground(points: np.ndarray, radius: float = 80.0, cell: float = 2.0, seed_band: float = 0.3,
                    inlier: float = 0.15, step: float = 0.3, max_slope_deg: float = 15.0, max_grade_deg: float = 10.0,
                    clearance: float = 0.5, source="scan") -> Ground:
    """The Ground of (N, >= 3) sensor-frame returns (the module docstring's fit).
    InputError naming ``source`` when no cell holds ground."""
    xyz = np.asarray(points[:, :3], np.float64)
    size = int(np.ceil(2 * radius / cell))
    origin = np.array([-radius, -radius])
    index = np.floor((xyz[:, :2] - origin) / cell).astype(np.int64)
    inside = ((index >= 0) & (index < size)).all(axis=1) & np.isfinite(xyz).all(axis=1)
    xyz, index = xyz[inside], index[inside]
    cells = index[:, 1] * size + index[:, 0]
    lowest = np.full(size * size, np.inf)
    np.minimum.at(lowest, cells, xyz[:, 2])
    slope = np.tan(np.radians(max_slope_deg))
    floor = ndimage.minimum_filter(lowest.reshape(size, size), size=3, mode="constant", cval=np.inf).ravel()
    centre_range = np.hypot(*np.meshgrid(origin[0] + (np.arange(size) + 0.5) * cell,
                                         origin[1] + (np.arange(size) + 0.5) * cell)).ravel()
    below_sensor = lowest <= -clearance + centre_range * np.tan(np.radians(max_grade_deg))
    candidate = np.isfinite(lowest) & below_sensor & (lowest <= floor + step + slope * cell)

    centres = origin + (index + 0.5) * cell
    offsets = xyz[:, :2] - centres  # u, v about the cell centre
    use = candidate[cells] & (xyz[:, 2] <= lowest[cells] + seed_band)
    coefficients = _fit_planes(offsets, xyz[:, 2], cells, use, size, cell)
    for _ in range(2):
        residual = xyz[:, 2] - np.einsum("ij,ij->i", coefficients[cells, :2], offsets) - coefficients[cells, 2]
        use = candidate[cells] & (residual >= -inlier) & (residual <= inlier / 2)
        coefficients = _fit_planes(offsets, xyz[:, 2], cells, use, size, cell)
    counts = np.bincount(cells[use], minlength=size * size)
    fitted = candidate & (counts >= 3) & (np.hypot(coefficients[:, 0], coefficients[:, 1]) <= slope)
    coefficients = coefficients.reshape(size, size, 3)
    fitted = fitted.reshape(size, size) & _agrees_with_neighbours(coefficients, fitted.reshape(size, size), cell,
                                                                  step)
    if not fitted.any():
        raise InputError(source, "no ground found: no part of the scan has returns on a level enough surface "
                                 "below the sensor and below everything around it")
    nearest = ndimage.distance_transform_edt(~fitted, return_distances=False, return_indices=True)
    filled = coefficients[nearest[0], nearest[1]].copy()
    filled[~fitted, :2] = 0.0  # level where no return was fitted
    return Ground(origin, float(cell), filled, fitted)


def _fit_planes(offsets: np.ndarray, z: np.ndarray, cells: np.ndarray, use: np.ndarray, size: int,
                cell: float) -> np.ndarray:
    """(size * size, 3) least-squares planes a u + b v + c of the used returns per cell
    (u, v about the cell centre), NaN where a cell has none. Solved about the returns'
    centroid, where the plane passes through their mean height. A cell whose returns
    spread too little across one direction (one or two rings) takes its slopes from the
    returns of its 3 x 3 neighbourhood; the slopes are ridged towards level."""
    u, v, z, cells = offsets[use, 0], offsets[use, 1], z[use], cells[use]
    sums = np.stack([np.bincount(cells, weights=w, minlength=size * size) for w in (
        np.ones_like(u), u, v, z, u * u, u * v, v * v, u * z, v * z)]).astype(np.float64).reshape(9, size, size)
    n, mu, mv, mz, own = _scatter(sums)
    _, _, _, _, pooled = _scatter(_neighbourhood_sums(sums, cell))
    cuu, cuv, cvv = own[:3]
    spread = (cuu + cvv) / 2 - np.sqrt(((cuu - cvv) / 2) ** 2 + cuv ** 2)  # the least, over any direction
    scatter = np.where(spread < n * cell * cell / 48, pooled, own)  # under a quarter of a uniform cell's
    ridge = 2 * cell * cell / 12  # two returns spread uniformly over the cell
    cuu, cuv, cvv, cuz, cvz = scatter[0] + ridge, scatter[1], scatter[2] + ridge, scatter[3], scatter[4]
    with np.errstate(invalid="ignore", divide="ignore"):  # cells without returns: NaN
        determinant = cuu * cvv - cuv * cuv
        a, b = (cvv * cuz - cuv * cvz) / determinant, (cuu * cvz - cuv * cuz) / determinant
        planes = np.stack([a, b, mz - a * mu - b * mv], axis=-1).reshape(-1, 3)
    planes[(n == 0).ravel()] = np.nan
    return planes


def _scatter(sums: np.ndarray) -> tuple:
    """(n, mean u, mean v, mean z, centred scatter (5, ...): uu, uv, vv, uz, vz) of the
    (9, ...) sums n, u, v, z, uu, uv, vv, uz, vz."""
    n, su, sv, sz, suu, suv, svv, suz, svz = sums
    with np.errstate(invalid="ignore", divide="ignore"):
        mu, mv, mz = su / n, sv / n, sz / n
    mu, mv, mz = (np.where(n > 0, m, 0.0) for m in (mu, mv, mz))
    return n, mu, mv, mz, np.stack([suu - su * mu, suv - su * mv, svv - sv * mv, suz - su * mz, svz - sv * mz])


def _neighbourhood_sums(sums: np.ndarray, cell: float) -> np.ndarray:
    """(9, ny, nx) sums of each cell's 3 x 3 neighbourhood, every neighbour's u, v moved to
    the centre cell's frame (its centre du, dv away)."""
    padded = np.pad(sums, ((0, 0), (1, 1), (1, 1)))
    ny, nx = sums.shape[1:]
    total = np.zeros_like(sums)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            n, su, sv, sz, suu, suv, svv, suz, svz = padded[:, 1 + di:1 + di + ny, 1 + dj:1 + dj + nx]
            du, dv = dj * cell, di * cell
            total += np.stack([n, su + n * du, sv + n * dv, sz, suu + 2 * du * su + n * du * du,
                               suv + du * sv + dv * su + n * du * dv, svv + 2 * dv * sv + n * dv * dv,
                               suz + du * sz, svz + dv * sz])
    return total


def _agrees_with_neighbours(coefficients: np.ndarray, fitted: np.ndarray, cell: float, step: float) -> np.ndarray:
    """(ny, nx) bool: each fitted cell's height lies within ``step`` of the median of its
    fitted 8-neighbours' planes extended to its centre (cells with fewer than two such
    neighbours pass)."""
    ny, nx = fitted.shape
    padded = np.pad(np.where(fitted[..., None], coefficients, np.nan), ((1, 1), (1, 1), (0, 0)),
                    constant_values=np.nan)
    predictions = []
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di or dj:
                a, b, c = np.moveaxis(padded[1 + di:1 + di + ny, 1 + dj:1 + dj + nx], -1, 0)
                predictions.append(c - a * dj * cell - b * di * cell)
    predictions = np.sort(np.where(np.isnan(predictions), np.inf, predictions), axis=0)
    valid = np.isfinite(predictions).sum(axis=0)
    rows, cols = np.indices(fitted.shape)
    low, high = np.maximum((valid - 1) // 2, 0), np.maximum(valid // 2, 0)
    median = (predictions[low, rows, cols] + predictions[high, rows, cols]) / 2
    return (valid < 2) | (np.abs(coefficients[..., 2] - median) <= step)
