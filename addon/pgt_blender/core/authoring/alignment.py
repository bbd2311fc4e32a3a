"""PCA axis alignment: source frame -> object frame (+x length, +y width, +z up).

The paper (section 3.3, "Aligning to Data Geometry") aligns a generated object with
PCA and rotations about the normals of the xy, yz and zx planes. Here that is two
rotations: the *vertical* (a rotation in the plane spanned by the source's z and the
chosen up direction), then the *yaw* (a rotation about the new z, in the xy plane)
from the 2-D PCA of the footprint.

Up, in order of preference: an explicit ``up`` vector (the COLMAP cameras' mean up,
see :func:`camera_up`, or a user-chosen axis), else the PCA minor axis.

Determinism on hard cases (all decisions are properties of the points, never of a
LAPACK sign or ordering):

* Eigenvalues within ``ISOTROPY`` (5 %, relative to the larger) of each other are
  equal: sampling noise alone separates them by ~1 % at 20k points.
  - 3-D, no up prior: all equal (sphere, one point) -> up is the source +z; the two
    smallest equal (cylinder, line) -> up is the direction perpendicular to the major
    axis closest to the source +z.
  - Footprint, two equal eigenvalues (square, disc): a square's edges are found from
    the fourth-order moment and x is the edge direction closest to the source +x
    (the 90 degree ambiguity the heading step resolves); with no fourfold structure
    either (a disc), x is the source +x projected onto the footprint.
* Signs: x points, and without an up prior z points, towards the positive third
  moment (the longer tail); when the third moment is below ``ISOTROPY`` of sigma^3
  (a symmetric shape) the sign closest to the source axis wins. The 180 degree
  heading ambiguity is left to the heading step.

Robustness: floaters are dropped by a k-nearest-neighbour density test
(:func:`density_inliers`) before any moment is taken; moments are float64 after
subtracting the median, so float32 clouds 1e6 m from the origin lose nothing more
than their own rounding.
"""

from dataclasses import dataclass

import numpy as np

from ..errors import InputError

ISOTROPY = 0.05
BOX_TRIM = 0.001
NEIGHBOURS = 8


@dataclass
class Alignment:
    """What :func:`align_axes` found.

    transform: (4, 4) float64 rigid object_from_source: rotation, then the box centre
               moved to the origin. Source units are kept (sizing scales later).
    dims:      (3,) float64 box extents (length x, width y, height z) of the inliers
               less the 0.1 % most extreme per side, in source units.
    inliers:   (N,) bool, the points the moments and the box were taken from.
    up_from:   "prior", "pca" or "source" (see the module notes).
    yaw_from:  "pca", "fourfold" or "source".
    """

    transform: np.ndarray
    dims: np.ndarray
    inliers: np.ndarray
    up_from: str
    yaw_from: str


def checked_points(positions, weights=None, source="points") -> tuple:
    """(N, 3) float64 positions and (N,) float64 weights; InputError for an empty
    cloud, NaN/Inf, or weights that are negative, non-finite or all zero."""
    points = np.asarray(positions, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise InputError(source, f"expected (N, 3) points with N >= 1, got shape {points.shape}")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise InputError(source, f"{int(bad.sum())} of {len(points)} points have NaN or Inf coordinates")
    if weights is None:
        return points, np.ones(len(points))
    weights = np.asarray(weights, np.float64).ravel()
    if weights.shape != (len(points),):
        raise InputError(source, f"{len(weights)} weights for {len(points)} points")
    if not np.isfinite(weights).all() or (weights < 0).any() or weights.sum() <= 0:
        raise InputError(source, "weights must be finite, non-negative and not all zero")
    return points, weights


def density_inliers(points: np.ndarray, neighbours: int = NEIGHBOURS, threshold: float = 3.0) -> np.ndarray:
    """(N,) bool: False for floaters, points whose mean distance to their
    ``neighbours`` nearest distinct neighbours exceeds the median by ``threshold``
    robust standard deviations (1.4826 MAD) *and* is over twice the median, so the rim of
    an evenly sampled surface (up to ~2x the median spacing at a corner) stays.
    Duplicates count once. Clouds too small to judge keep every point."""
    from scipy.spatial import cKDTree

    distinct, inverse = np.unique(points, axis=0, return_inverse=True)
    if len(distinct) <= 4 * neighbours:
        return np.ones(len(points), bool)
    distances, _ = cKDTree(distinct).query(distinct, k=neighbours + 1, workers=-1)
    spacing = distances[:, 1:].mean(axis=1)
    median = np.median(spacing)
    limit = median + max(threshold * 1.4826 * np.median(np.abs(spacing - median)), median)
    return (spacing <= limit)[inverse.ravel()]


def camera_up(world_from_cameras) -> np.ndarray:
    """(3,) unit mean up vector of OpenCV cameras (their -y axis), given (C, 4, 4)
    world_from_camera matrices; photos of an object are mostly taken upright."""
    ups = -np.asarray(world_from_cameras, np.float64)[:, :3, 1]
    mean = ups.sum(axis=0)
    norm = np.linalg.norm(mean)
    if norm < 1e-9 * len(ups):
        raise ValueError("camera up vectors cancel out: choose the up axis by hand")
    return mean / norm


def align_axes(positions, weights=None, up=None, source="points") -> Alignment:
    """Align ``positions`` (N, 3), any float dtype, source frame) to the object frame.

    weights: optional (N,) non-negative per-point weights (Gaussian-splat opacity).
    up:      optional (3,) up direction in the source frame; its sign is kept.
    """
    points, weights = checked_points(positions, weights, source)
    median = np.median(points, axis=0)
    centred = points - median
    inliers = weights > 0  # zero-weight points (transparent splats) take no part
    inliers[inliers] = density_inliers(centred[inliers])
    kept, kept_weights = centred[inliers], weights[inliers]
    mean = np.average(kept, axis=0, weights=kept_weights)
    kept = kept - mean
    if up is not None:
        z = np.asarray(up, np.float64)
        if z.shape != (3,) or not np.isfinite(z).all() or np.linalg.norm(z) == 0:
            raise InputError(source, f"up must be a non-zero 3-vector, got {up!r}")
        z, up_from = z / np.linalg.norm(z), "prior"
    else:
        z, up_from = _minor_axis(kept, kept_weights)
    x, yaw_from = _footprint_axis(kept, kept_weights, z)
    rotation = np.stack([x, np.cross(z, x), z])  # rows: object axes in the source frame
    low, high = _trimmed_bounds(kept @ rotation.T)
    centre = (low + high) / 2
    transform = np.eye(4)
    transform[:3, :3] = rotation
    # source point p -> rotation @ (p - median - mean) - centre
    transform[:3, 3] = -rotation @ (median + mean) - centre
    return Alignment(transform, high - low, inliers, up_from, yaw_from)


def _trimmed_bounds(local: np.ndarray) -> tuple:
    """Per-axis (low, high) of ``local`` (N, 3) without the ``BOX_TRIM`` share of most
    extreme points on each side (none below 1 / BOX_TRIM points): floaters that sit
    next to the surface pass the density test but must not widen the box."""
    trim = int(BOX_TRIM * len(local))
    ordered = np.partition(local, (trim, len(local) - 1 - trim), axis=0)
    return ordered[trim], ordered[len(local) - 1 - trim]


def _weighted_cov(points, weights) -> np.ndarray:
    return (points * weights[:, None]).T @ points / weights.sum()


def _minor_axis(points, weights) -> tuple:
    """The up direction from the 3-D PCA and where it came from."""
    values, vectors = np.linalg.eigh(_weighted_cov(points, weights))
    source_z = np.array([0.0, 0.0, 1.0])
    if _equal(values[0], values[2]):
        return source_z, "source"
    if _equal(values[0], values[1]):  # a line or cylinder: up is perpendicular to it
        major = vectors[:, 2]
        z = source_z - major * (major @ source_z)
        if np.linalg.norm(z) < 1e-6:
            z = np.array([1.0, 0.0, 0.0]) - major * major[0]
        return z / np.linalg.norm(z), "source"
    return _signed(vectors[:, 0], points, weights, source_z), "pca"


def _equal(smaller, larger) -> bool:
    """Eigenvalues within ISOTROPY of the larger one (both zero counts as equal)."""
    return larger - smaller <= ISOTROPY * larger


def _signed(axis, points, weights, reference) -> np.ndarray:
    """``axis`` or ``-axis``: towards the positive third moment, else nearest ``reference``."""
    along = points @ axis
    sigma = np.sqrt(np.average(along**2, weights=weights))
    third = np.average(along**3, weights=weights)
    if abs(third) > ISOTROPY * sigma**3:
        return axis if third > 0 else -axis
    return axis if axis @ reference >= 0 else -axis


def _footprint_axis(points, weights, z) -> tuple:
    """The unit x axis (perpendicular to ``z``) from the footprint's 2-D moments."""
    # A footprint basis (e1, e2) that depends only on z: e1 is the source x projected.
    e1 = np.array([1.0, 0.0, 0.0]) - z * z[0]
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.array([0.0, 1.0, 0.0]) - z * z[1]
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(z, e1)
    u, v = points @ e1, points @ e2
    flat = np.column_stack([u, v])
    values, vectors = np.linalg.eigh(_weighted_cov(flat, weights))
    if not _equal(values[0], values[1]):
        major = vectors[:, 1]
        x = major[0] * e1 + major[1] * e2
        return _signed(x, points, weights, e1), "pca"
    # Square or round: the fourth harmonic of the footprint points at the corners.
    complex_uv = u + 1j * v
    fourth = np.average(complex_uv**4, weights=weights)
    scale = np.average(np.abs(complex_uv) ** 4, weights=weights)
    if scale > 0 and abs(fourth) > ISOTROPY * scale:
        edge = (np.angle(fourth) - np.pi) / 4
        edge = (edge + np.pi / 4) % (np.pi / 2) - np.pi / 4  # the edge nearest e1
        return np.cos(edge) * e1 + np.sin(edge) * e2, "fourfold"
    return e1, "source"
