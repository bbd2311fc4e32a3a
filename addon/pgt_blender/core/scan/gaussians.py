"""Gaussian splats scanned as Gaussians: each ray meets the 3-D Gaussians themselves,
not a surface made from them (targets.surfel_target).

A splat has a mean mu (3,), scales s (3,) (standard deviations along its own axes, m),
a rotation R (3, 3) whose columns are those axes (the w x y z quaternion of the file)
and an opacity o in (0, 1); its response at x is o exp(-q(x) / 2) with q the squared
Mahalanobis distance |diag(1/s) R^T (x - mu)|^2. Along a ray x(t) = p + t d (unit d,
t in m) q is a convex quadratic in t, least at

    t* = -(a . b) / (b . b),    a = diag(1/s) R^T (p - mu),    b = diag(1/s) R^T d,

and the splat's *peak response* on the ray is alpha = min(o exp(-q(t*) / 2), MAX_ALPHA)
(3DGS's per-splat alpha, taken where the ray passes closest). A splat counts when the
ray meets its CUTOFF_SIGMAS ellipsoid in front of the laser (q(t*) <= CUTOFF_SIGMAS^2,
t* > 0) and alpha >= MIN_ALPHA (3DGS skips fainter ones too).

The splats a ray meets are composited front to back in order of t*: transmittance
T_k = prod_{j<k} (1 - alpha_j), accumulated opacity A_k = 1 - T_k (1 - alpha_k). The
ray returns at the t* of the first splat where A_k reaches HIT_OPACITY (0.5: the depth
where half of the light is stopped, 3DGS's median depth), and that splat is the
return's ``face``; a ray whose A never reaches HIT_OPACITY returns nothing (it passes
through faint splats, as a LiDAR passes through a sparse fringe).

Candidates without a per-ray loop: every ray of a scan leaves the sensor (or a laser
near it) along a (beam, column) cell, so a splat's CUTOFF_SIGMAS ellipsoid covers a
block of rings x columns in the sensor frame (``_cell_blocks``: its exact azimuth span,
a bound on its elevation span): one (ray, splat) pair per cell of the block that the
scan casts, then the exact test above. It is 3DGS's tile rasterisation with the LiDAR's
cells for tiles, vectorised over pairs in chunks of PAIRS_PER_CHUNK.
"""

from dataclasses import dataclass

import numpy as np

CUTOFF_SIGMAS = 3.0  # beyond 3 sigma the response is below 1.1 % of the opacity
HIT_OPACITY = 0.5  # accumulated opacity at which a ray returns
MAX_ALPHA = 0.99  # as 3DGS: one splat never stops all the light
MIN_ALPHA = 1.0 / 255.0  # as 3DGS: fainter splat crossings are skipped
MIN_SCALE = 1e-9  # m: a flat splat's zero scale is floored, so 1 / s stays finite
PAIRS_PER_CHUNK = 1 << 20  # (ray, splat) pairs tested at once: bounded memory


def rotation_matrices(wxyz: np.ndarray) -> np.ndarray:
    """(N, 3, 3) float64 rotation matrices of (N, 4) quaternions w x y z (normalised here)."""
    wxyz = np.asarray(wxyz, np.float64)
    w, x, y, z = (wxyz / np.linalg.norm(wxyz, axis=1, keepdims=True)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


def quaternions(matrices: np.ndarray) -> np.ndarray:
    """(N, 4) float64 unit quaternions w x y z (w >= 0) of (N, 3, 3) rotation matrices,
    each from its largest component (Shepperd's method: stable for every rotation)."""
    m = np.asarray(matrices, np.float64)
    trace = np.trace(m, axis1=1, axis2=2)
    squares = np.stack([1 + trace, 1 + 2 * m[:, 0, 0] - trace, 1 + 2 * m[:, 1, 1] - trace,
                        1 + 2 * m[:, 2, 2] - trace], axis=1)  # 4 w^2, 4 x^2, 4 y^2, 4 z^2
    largest = np.argmax(squares, axis=1)
    root = np.sqrt(np.maximum(np.take_along_axis(squares, largest[:, None], axis=1)[:, 0], 1e-300))
    sums = {(0, 1): m[:, 2, 1] - m[:, 1, 2], (0, 2): m[:, 0, 2] - m[:, 2, 0], (0, 3): m[:, 1, 0] - m[:, 0, 1],
            (1, 2): m[:, 0, 1] + m[:, 1, 0], (1, 3): m[:, 0, 2] + m[:, 2, 0], (2, 3): m[:, 1, 2] + m[:, 2, 1]}
    result = np.empty((len(m), 4))
    for pivot in range(4):
        rows = largest == pivot
        result[rows, pivot] = root[rows] / 2
        for other in range(4):
            if other != pivot:
                result[rows, other] = sums[tuple(sorted((pivot, other)))][rows] / (2 * root[rows])
    return result * np.where(result[:, :1] < 0, -1.0, 1.0)


def transform_gaussians(scales: np.ndarray, rotations: np.ndarray, linear: np.ndarray) -> tuple:
    """The shapes of splats after the points move by ``linear`` (3, 3) (an authoring
    step's rotation and scaling): covariance A R S^2 R^T A^T, split again into (N, 3)
    float32 scales (descending per splat) and (N, 4) float32 w x y z rotations."""
    shaped = np.asarray(linear, np.float64) @ rotation_matrices(rotations) * np.asarray(scales, np.float64)[:, None]
    axes, singular, _ = np.linalg.svd(shaped)  # A R S = U S' V^T: covariance U S'^2 U^T
    axes[:, :, 2] *= np.sign(np.linalg.det(axes))[:, None]  # a proper rotation: flip the last axis if needed
    return singular.astype(np.float32), quaternions(axes).astype(np.float32)


@dataclass
class Gaussians:
    """Splats in the object frame (m): means (N, 3), axes (N, 3, 3) rotation matrices
    (columns = the splat's axes), scales (N, 3) standard deviations along them (floored
    at MIN_SCALE), opacities (N,) in (0, 1); float64."""

    means: np.ndarray
    axes: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray

    @classmethod
    def from_splats(cls, positions, scales, rotations, opacities) -> "Gaussians":
        """From a reconstruction's positions (N, 3) and its ``scale`` (N, 3), ``rotation``
        (N, 4, w x y z) and ``opacity`` (N,) attributes (activated, as importing/points.py
        loads them)."""
        return cls(np.asarray(positions, np.float64).reshape(-1, 3), rotation_matrices(rotations),
                   np.maximum(np.asarray(scales, np.float64).reshape(-1, 3), MIN_SCALE),
                   np.clip(np.asarray(opacities, np.float64).reshape(-1), 0.0, 1.0))

    def __len__(self) -> int:
        return len(self.means)

    @property
    def extents(self) -> np.ndarray:
        """(N, 3) half-widths along the object axes of each CUTOFF_SIGMAS ellipsoid."""
        return CUTOFF_SIGMAS * np.sqrt(np.einsum("nij,nj->ni", self.axes ** 2, self.scales ** 2))

    @property
    def normals(self) -> np.ndarray:
        """(N, 3) unit axis of each splat's smallest scale: a flat splat's normal."""
        return np.take_along_axis(self.axes, np.argmin(self.scales, axis=1)[:, None, None], axis=2)[:, :, 0]


def _laser_offsets(sensor) -> tuple:
    """(largest horizontal distance of a laser from the sensor's axis, lowest and highest
    laser height) in m, over every cell (0, 0, 0 when the lasers share the origin)."""
    origins = sensor.cell_origins
    if origins is None:
        return 0.0, 0.0, 0.0
    return float(np.hypot(origins[:, 0], origins[:, 1]).max()), float(origins[:, 2].min()), \
        float(origins[:, 2].max())


def _cell_blocks(gaussians: Gaussians, sensor, sensor_from_object: np.ndarray) -> tuple:
    """Per splat the block of cells (rings x columns) whose rays may meet its
    CUTOFF_SIGMAS ellipsoid: first ring, ring count, first column (may be negative:
    wrapped later), column count; (N,) int64 each.

    Azimuth: exact for the ellipsoid (its xy shadow's tangent lines through the sensor's
    axis), widened by the lasers' horizontal offset. Elevation: from its z extent and
    the nearest and farthest xy distance of its shadow, widened by the lasers' heights.
    A shadow reaching the sensor's axis opens every column."""
    rotation = sensor_from_object[:3, :3]
    centres = gaussians.means @ rotation.T + sensor_from_object[:3, 3]
    axes = np.einsum("ij,njk->nik", rotation, gaussians.axes) * gaussians.scales[:, None, :]
    covariance = np.einsum("nik,njk->nij", axes, axes)  # sensor frame
    k2 = CUTOFF_SIGMAS ** 2
    horizontal, lowest, highest = _laser_offsets(sensor)
    rho = np.hypot(centres[:, 0], centres[:, 1])
    azimuth = np.arctan2(centres[:, 1], centres[:, 0])
    # The xy shadow in a frame turned to the centre's azimuth: centre (rho, 0).
    cos, sin = np.cos(azimuth), np.sin(azimuth)
    sxx = cos * cos * covariance[:, 0, 0] + 2 * cos * sin * covariance[:, 0, 1] + sin * sin * covariance[:, 1, 1]
    syy = sin * sin * covariance[:, 0, 0] - 2 * cos * sin * covariance[:, 0, 1] + cos * cos * covariance[:, 1, 1]
    sxy = (cos * cos - sin * sin) * covariance[:, 0, 1] + cos * sin * (covariance[:, 1, 1] - covariance[:, 0, 0])
    # Tangent lines y = t x through the axis: (rho t)^2 = k2 (sxx t^2 - 2 sxy t + syy), i.e.
    # (rho^2 - k2 sxx) t^2 + 2 k2 sxy t - k2 syy = 0; both roots finite when the shadow stays in front.
    lead = rho * rho - k2 * sxx
    in_front = lead > 1e-12 * np.maximum(rho * rho, 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        root = np.sqrt(np.maximum((k2 * sxy) ** 2 + lead * k2 * syy, 0.0))
        near = np.where(in_front, rho - np.sqrt(k2 * np.maximum(sxx, 0.0)), 0.0)  # the shadow's nearest x
        widen = np.arcsin(np.clip(horizontal / near, 0.0, 1.0))
        low_azimuth = np.arctan((-k2 * sxy - root) / lead) - widen
        high_azimuth = np.arctan((-k2 * sxy + root) / lead) + widen
    every_column = ~in_front | ~(horizontal < near) | ~(high_azimuth - low_azimuth < np.pi)
    low_azimuth, high_azimuth = (np.where(every_column, 0.0, value) for value in (low_azimuth, high_azimuth))
    # Elevation: z extent (lasers' heights subtracted) over the nearest / farthest xy distance.
    reach_z = np.sqrt(k2 * covariance[:, 2, 2])
    reach_xy = np.sqrt(k2 * np.linalg.eigvalsh(covariance[:, :2, :2])[:, 1]) + horizontal
    z_low, z_high = centres[:, 2] - reach_z - highest, centres[:, 2] + reach_z - lowest
    near_xy, far_xy = np.maximum(rho - reach_xy, 0.0), rho + reach_xy
    low = np.degrees(np.arctan2(z_low, np.where(z_low > 0, far_xy, near_xy)))
    high = np.degrees(np.arctan2(z_high, np.where(z_high > 0, near_xy, far_xy)))
    first_ring, rings = sensor.ring_span(low, high)
    first_column, columns = sensor.column_span(np.degrees(azimuth), np.degrees(low_azimuth), np.degrees(high_azimuth))
    first_column[every_column], columns[every_column] = 0, sensor.columns
    return first_ring, rings, first_column, columns


def gaussian_hits(gaussians: Gaussians, sensor, sensor_from_object: np.ndarray, cells: np.ndarray,
                  origin: np.ndarray, directions: np.ndarray) -> tuple:
    """The returns of the rays ``cells`` (M,) (flat ring * columns + column), leaving
    ``origin`` ((3,), or (M, 3) per laser) along unit ``directions`` (M, 3), object frame
    (raycast.rays_to_cast): (M,) int64 the splat each ray returns from (-1: none),
    (M,) float64 range (m, the t* there) and (M,) float64 cosine between the ray and
    that splat's normal."""
    rays = len(cells)
    found, ranges, cosines = np.full(rays, -1, np.int64), np.full(rays, np.nan), np.zeros(rays)
    if not rays or not len(gaussians):
        return found, ranges, cosines
    ray_of_cell = np.full(sensor.beams * sensor.columns, -1, np.int64)
    ray_of_cell[cells] = np.arange(rays)
    first_ring, rings, first_column, columns = _cell_blocks(gaussians, sensor, sensor_from_object)
    counts = rings * columns
    ends = np.cumsum(counts)
    pairs = []
    start = 0
    while start < len(gaussians):  # chunks of whole splats, about PAIRS_PER_CHUNK pairs each
        stop = max(int(np.searchsorted(ends, (ends[start - 1] if start else 0) + PAIRS_PER_CHUNK, "right")),
                   start + 1)
        pairs.append(_crossings(gaussians, sensor, np.arange(start, stop), first_ring, first_column, columns,
                                counts, ray_of_cell, origin, directions))
        start = stop
    ray, splat, depth, alpha = (np.concatenate(part) for part in zip(*pairs))
    if not len(ray):
        return found, ranges, cosines
    order = np.lexsort((splat, depth, ray))  # per ray, front to back (ties: the lower splat first)
    ray, splat, depth, alpha = ray[order], splat[order], depth[order], alpha[order]
    # Per ray, in a (rays met, deepest) table so each ray's sum is its own (batch-independent).
    starts = np.flatnonzero(np.r_[True, ray[1:] != ray[:-1]])
    lengths = np.diff(np.r_[starts, len(ray)])
    rank = np.arange(len(ray)) - np.repeat(starts, lengths)
    row = np.repeat(np.arange(len(starts)), lengths)
    log_transmittance = np.zeros((len(starts), lengths.max()))
    log_transmittance[row, rank] = np.log1p(-alpha)
    crossed = np.cumsum(log_transmittance, axis=1) <= np.log1p(-HIT_OPACITY)
    returning = crossed.any(axis=1)
    chosen = starts[returning] + np.argmax(crossed[returning], axis=1)
    hit_rays = ray[chosen]
    found[hit_rays], ranges[hit_rays] = splat[chosen], depth[chosen]
    normals = gaussians.normals[splat[chosen]]
    hit_directions = directions[hit_rays]
    cosines[hit_rays] = (normals[:, 0] * hit_directions[:, 0] + normals[:, 1] * hit_directions[:, 1]
                         + normals[:, 2] * hit_directions[:, 2])
    return found, ranges, cosines


def _crossings(gaussians: Gaussians, sensor, chunk: np.ndarray, first_ring, first_column, columns, counts,
               ray_of_cell, origin, directions) -> tuple:
    """(ray, splat, t*, alpha) of the pairs of the splats ``chunk`` whose ray is cast and
    meets the splat (see the module docstring)."""
    splat = np.repeat(chunk, counts[chunk])
    within = np.arange(len(splat)) - np.repeat(np.cumsum(counts[chunk]) - counts[chunk], counts[chunk])
    ring = first_ring[splat] + within // columns[splat]
    column = (first_column[splat] + within % columns[splat]) % sensor.columns
    ray = ray_of_cell[ring * sensor.columns + column]
    cast = ray >= 0
    splat, ray = splat[cast], ray[cast]
    axes, scales = gaussians.axes[splat], gaussians.scales[splat]
    start = origin if origin.ndim == 1 else origin[ray]
    a = np.einsum("ni,nij->nj", start - gaussians.means[splat], axes) / scales
    b = np.einsum("ni,nij->nj", directions[ray], axes) / scales
    depth = -np.einsum("ij,ij->i", a, b) / np.einsum("ij,ij->i", b, b)
    closest = a + depth[:, None] * b  # formed before squaring: no cancellation for flat splats
    squared = np.einsum("ij,ij->i", closest, closest)
    alpha = np.minimum(gaussians.opacities[splat] * np.exp(-0.5 * squared), MAX_ALPHA)
    keep = (squared <= CUTOFF_SIGMAS ** 2) & (depth > 0) & (alpha >= MIN_ALPHA)
    return ray[keep], splat[keep], depth[keep], alpha[keep]
