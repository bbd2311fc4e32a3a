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

Refinement from the object's own geometry (``refine=True``, what ``prepare`` and the
Blender panel use): vehicles are built from large flat faces (sides, roof, floor, ends)
that meet at right angles, so the object frame is the *Manhattan frame* of the surface
normals. :func:`surface_estimate` fits a plane to each point's ``NORMAL_NEIGHBOURS``
nearest neighbours (normal, planarity, local noise); :func:`refine_to_planes` then
rotates a starting frame until the planar normals line up with its axes (each normal
assigned to the nearest axis inside a cone that narrows from 20 to 5 degrees, the
rotation solved by weighted Kabsch/SVD, weights planarity squared). It starts from
:func:`dominant_frame`, the most populated normal direction and the most populated one
perpendicular to it, which needs no PCA and no source axis, and, given a prior, also
from the prior (up, then the footprint yaw as above); the result with more planar
weight inside the last cone wins, its axis nearest the prior being up. So a prior a
few degrees off is corrected, one far off (a 3D cursor placed roughly, 20 to 40
degrees: from it alone the cones lock onto the wrong planes) is overruled, and the
correction is reported as ``tilt_deg``. Which refined axis is up
then: x is the longest extent, y the axis across which the object is mirror-symmetric
(:func:`mirror_error`: left and right of a vehicle match, top and bottom do not), z the
third, its sign from the third moment as without refinement (cabins and greenhouses
narrow upwards); where the third moment does not tell (a box-shaped bus), from the wheels
(:func:`_wheels_down`: the end band covering far less of the length is the bottom), else
the source +z. The up sign without a prior is a property of vehicles, not of geometry in
general: an upside-down box is a box. Last, for clouds, the frame is sharpened
(:func:`sharpest_turn`): turned by a few degrees at most about each axis to make the
histograms of the denoised points along x, y and z the sharpest (least summed
entropy, bins half the noise wide). The plane fit reads a noisy curved body's normals
with a bias of a degree or two in pitch (a sedan, an SUV; a bicycle has few planes at
all), while its level floor, roof and sills and its upright sides still each fall into
few bins only when level. A mesh's face normals are exact, so meshes skip it. Shapes
without enough planar structure (less than ``MIN_PLANAR_SHARE`` of the weight assigned
to an axis: spheres, cylinders) keep the unrefined frame (``refined`` is False).

The refined box is taken from the surface estimate, not the raw points: each point is
moved towards its neighbourhood plane by at most ``DENOISE_CLAMP`` times the
estimated noise (the standard deviation :func:`_plane_noise` reads from the flattest
small neighbourhoods; 0 for a noise-free sampling of flat faces, which then moves
nothing), so noise inflates the box less
while thin parts with too few points for a plane stay where they are. A side where a
wall faces outwards is then the median of the wall's points, not their extreme
(:func:`_surface_bounds`). Any other side (a tyre, a rounded roof, a handlebar end,
whose points thin out towards the extreme, which the plane fit pulls inwards) is taken
from the raw points: their histogram along the axis is the surface's blurred by the
noise, so it is deconvolved (non-negative spikes blurred by the estimated noise) and
the side is where the deblurred points end, less the same 0.1 % as the trim
(:func:`_deblurred_edge`). Thin real parts that stick out of the body (mirrors, a few
dozen points of 20,000) are neither trimmed by quantile nor cut at the wall: the points
beyond a side's noise band (``PROTRUSION_BAND`` x noise) that crowd together at the
sampling's scale, far more than the same number spread evenly over the side would, are
a surface, and the side moves out to them (:func:`_protrusion`); floaters, spread over a
volume, and a wall's own noise tail, spread over the wall, do not crowd. What is left:
features of a few dozen points (a small mirror, a roof rail) that stick out by about
the noise or less are not told from the noise tail of the wall behind them and are
cut off; the deblurred edge itself scatters by about half the noise per side
(bench/alignment.md). A cloud denser than ``BOX_POINTS`` has its box read from a
seeded sample of that many: the nearest neighbours of a point lie near its own offset
from the surface, so the denser the cloud, the lower the noise reads (on a noisy plane
0.93 sigma where the 24th neighbour lies 4 sigma away, as in 20,000 points of a vehicle
at 0.5 % noise, 0.83 at 2.8, 0.71 at 1.9, 0.52 at 1.1), and every band above, set at
20,000 points, narrowed with it: 100,000 points of the built-in samples gave boxes
1-6 % too large in the median (up to 9 %). (Reading the noise in columns along the
surface instead removes that bias on a plane but reads a curved body's curvature as
noise, up to 3x on the SUV: measured and left.)

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
NORMAL_NEIGHBOURS = 48
NOISE_NEIGHBOURS = 24
NOISE_PERCENTILE = 10
# DENOISE_CLAMP, SIDE_BAND and PROTRUSION_BAND are in units of the noise estimate, which
# reads sigma itself since it is chi-corrected; they keep the widths they had in units
# of the former estimate (6, 2 and 2.5 x the plain percentile, about 0.87 sigma)
DENOISE_CLAMP = 5.2
REFINE_CONES_DEG = (20.0, 12.0, 8.0, 5.0, 5.0)
MIN_PLANAR_SHARE = 0.05
MIRROR_SAMPLE = 4000
FACING_DEG = 30.0
SIDE_BAND = 1.75
WALL_RATIO = 2.0
PROTRUSION_BAND = 2.2
WHEEL_BAND = 0.05
MESH_SAMPLES = 20000
BOX_POINTS = 20000  # a refined cloud's box is read from a seeded sample of at most this many points
LENGTH_BINS = 50
WHEEL_COVER_RATIO = 0.5
PROTRUSION_RADIUS = 3.0
PROTRUSION_NEIGHBOURS = 4
PROTRUSION_CHANCE = 1e-3
EDGE_STEP = 0.25
EDGE_WINDOW = (8.0, 5.0)
SHARPEN_PASSES_DEG = ((2.0, 0.2), (0.3, 0.05), (0.06, 0.01))  # (half range, step) of each pass
SHARPEN_BIN_NOISE = 0.5  # histogram bin width, in surface noise standard deviations ...
SHARPEN_MIN_BIN = 1e-3  # ... and at least this share of the box diagonal


@dataclass
class Alignment:
    """What :func:`align_axes` found.

    transform: (4, 4) float64 rigid object_from_source: rotation, then the box centre
               moved to the origin. Source units are kept (sizing scales later).
    dims:      (3,) float64 box extents (length x, width y, height z) of the inliers
               less the 0.1 % most extreme per side, in source units.
    inliers:   (N,) bool, the points the moments and the box were taken from.
    up_from:   "prior", "pca" or "source" (see the module notes), "planes" when the
               refinement chose up without a prior.
    yaw_from:  "pca", "fourfold" or "source"; "planes" when refined.
    refined:   True when the frame was refined to the surface planes.
    tilt_deg:  angle (degrees) between the up before refinement (the prior, else the PCA
               up) and the refined up: the residual tilt the refinement removed; 0 when
               not refined.
    noise:     estimated surface noise (standard deviation, source units) the box was read
               with (of the ``BOX_POINTS`` sample of a denser cloud); 0 when not refined.
    """

    transform: np.ndarray
    dims: np.ndarray
    inliers: np.ndarray
    up_from: str
    yaw_from: str
    refined: bool = False
    tilt_deg: float = 0.0
    noise: float = 0.0


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


def camera_up(world_from_cameras, source="cameras") -> np.ndarray:
    """(3,) unit mean up vector of OpenCV cameras (their -y axis), given (C, 4, 4)
    world_from_camera matrices; photos of an object are mostly taken upright.
    InputError(source) when the ups cancel out."""
    ups = -np.asarray(world_from_cameras, np.float64)[:, :3, 1]
    mean = ups.sum(axis=0)
    norm = np.linalg.norm(mean)
    if norm < 1e-9 * len(ups):
        raise InputError(source, "camera up vectors cancel out: choose the up axis by hand")
    return mean / norm


def align_axes(positions, weights=None, up=None, source="points", refine: bool = False,
               faces=None) -> Alignment:
    """Align ``positions`` (N, 3), any float dtype, source frame) to the object frame.

    weights: optional (N,) non-negative per-point weights (Gaussian-splat opacity).
    up:      optional (3,) up direction in the source frame; its sign is kept.
    refine:  refine the frame to the object's surface planes and take the box from the
             surface estimate (module notes).
    faces:   optional (F, 3) vertex indices of a mesh: refinement then takes the face
             normals weighted by face area (exact, whatever the vertex density) and the
             box the vertices as they are (no density test: a mesh's vertex density
             varies with its detail, not with floaters).
    """
    points, weights = checked_points(positions, weights, source)
    median = np.median(points, axis=0)
    centred = points - median
    inliers = weights > 0  # zero-weight points (transparent splats) take no part
    if not (refine and faces is not None and len(faces)):  # a mesh's vertex density says nothing of floaters
        inliers[inliers] = density_inliers(centred[inliers])
    kept, kept_weights = centred[inliers], weights[inliers]
    mean = np.average(kept, axis=0, weights=kept_weights)
    kept = kept - mean
    if up is not None:
        z = np.asarray(up, np.float64)
        if z.shape != (3,) or not np.isfinite(z).all() or np.linalg.norm(z) == 0:
            raise InputError(source, f"up must be a non-zero 3-vector, got {z.tolist()}")
        z, up_from = z / np.linalg.norm(z), "prior"
    else:
        z, up_from = _minor_axis(kept, kept_weights)
    x, yaw_from = _footprint_axis(kept, kept_weights, z)
    rotation = np.stack([x, np.cross(z, x), z])  # rows: object axes in the source frame
    box_points, box_raw, box_normals, box_trim, extra = kept, kept, None, BOX_TRIM, {}
    is_mesh = faces is not None and len(faces) > 0
    if refine and (is_mesh or len(kept) > 2 * NORMAL_NEIGHBOURS):
        surface = mesh_surface(kept, centred - mean, faces, source) if is_mesh else surface_estimate(kept)
        planar = surface.planarity**2 * (kept_weights if len(surface.planarity) == len(kept) else 1)
        free, free_share = refine_to_planes(dominant_frame(surface.normals, planar), surface.normals, planar)
        refined, share = (free, free_share) if up is None else refine_to_planes(rotation, surface.normals, planar)
        if up is not None and free_share > share:  # the prior was too far off: it locked onto the wrong planes
            refined, share = _relabelled(free, rotation), free_share
        if share >= MIN_PLANAR_SHARE:
            if up is None:
                # a mesh's vertices crowd where it has detail: its moments are its surface's
                label_points, label_weights = ((surface.samples, np.ones(len(surface.samples))) if is_mesh
                                               else (surface.denoised, kept_weights))
                label_points = label_points - np.average(label_points, axis=0, weights=label_weights)
                refined = _label_axes(refined, label_points, label_weights)
                up_from = "planes"
            else:
                refined = _length_first(refined, surface.denoised, kept_weights)
            if not is_mesh:  # a mesh's face normals are exact; a cloud's are not
                local = surface.denoised @ refined.T
                bin_width = max(SHARPEN_BIN_NOISE * surface.noise, SHARPEN_MIN_BIN * np.linalg.norm(np.ptp(local, 0)))
                refined = sharpest_turn(local, kept_weights, bin_width) @ refined
            tilt = np.degrees(np.arccos(np.clip(abs(refined[2] @ z), 0, 1)))
            if not is_mesh and len(kept) > BOX_POINTS:  # a denser cloud reads its noise low
                box_raw = kept[np.sort(np.random.default_rng(0).choice(len(kept), BOX_POINTS, replace=False))]
                surface = surface_estimate(box_raw)
            rotation, box_points, yaw_from = refined, surface.denoised, "planes"
            box_trim = 0.0 if is_mesh else BOX_TRIM
            box_normals = None if is_mesh or surface.noise == 0 else surface.normals
            extra = {"refined": True, "tilt_deg": float(tilt), "noise": surface.noise}
    if box_normals is None:
        low, high = _trimmed_bounds(box_points @ rotation.T, box_trim)
    else:
        low, high = _surface_bounds(box_points @ rotation.T, box_normals @ rotation.T, extra["noise"],
                                    box_raw @ rotation.T)
    centre = (low + high) / 2
    transform = np.eye(4)
    transform[:3, :3] = rotation
    # source point p -> rotation @ (p - median - mean) - centre
    transform[:3, 3] = -rotation @ (median + mean) - centre
    return Alignment(transform, high - low, inliers, up_from, yaw_from, **extra)


@dataclass
class SurfaceEstimate:
    """Local planes of a cloud (N points, centred float64, source units).

    normals:   (N, 3) unit normal of the plane through each point's neighbourhood.
    planarity: (N,) (l2 - l1) / l3 of the neighbourhood's covariance eigenvalues
               l1 <= l2 <= l3, in [0, 1]: 1 for a flat patch, 0 for a line or a blob.
    denoised:  (N, 3) points moved towards their plane by at most ``DENOISE_CLAMP`` x ``noise``.
    noise:     the surface noise (standard deviation) from the ``NOISE_NEIGHBOURS``
               nearest of each neighbourhood (:func:`_plane_noise`).
    samples:   (MESH_SAMPLES, 3) points spread evenly over a mesh's area (None for a
               cloud): its moments, which the vertices (dense where the detail is) are not.
    """

    normals: np.ndarray
    planarity: np.ndarray
    denoised: np.ndarray
    noise: float
    samples: np.ndarray | None = None


def surface_estimate(points: np.ndarray, neighbours: int = NORMAL_NEIGHBOURS) -> SurfaceEstimate:
    """Plane fits to the ``neighbours`` nearest points of each of ``points`` (N, 3)
    float64 (centred), vectorised (one batched eigh)."""
    from scipy.spatial import cKDTree

    neighbours = min(neighbours, len(points))
    _, index = cKDTree(points).query(points, k=neighbours, workers=-1)
    hood = points[index]
    centres = hood.mean(axis=1)
    spread = hood - centres[:, None]
    values, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", spread, spread) / neighbours)
    values = np.maximum(values, 0)
    normals = vectors[:, :, 0]
    planarity = (values[:, 1] - values[:, 0]) / np.maximum(values[:, 2], np.finfo(float).tiny)
    noise = _plane_noise(spread[:, :NOISE_NEIGHBOURS])
    offsets = np.einsum("ni,ni->n", points - centres, normals)
    denoised = points - np.clip(offsets, -DENOISE_CLAMP * noise, DENOISE_CLAMP * noise)[:, None] * normals
    return SurfaceEstimate(normals, planarity, denoised, noise)


def _plane_noise(spread: np.ndarray) -> float:
    """The surface noise (standard deviation, source units) from neighbourhoods
    ``spread`` (N, k, 3), each the k nearest points of a larger neighbourhood centred
    on that one's mean (what surface_estimate has at hand; it reads sigma as closely as
    recentring would, measured on noisy planes): the out-of-plane spread sqrt(l1) of a
    flat patch is sigma x sqrt(chi2(k - 3) / k) (the plane takes three degrees of
    freedom), so the ``NOISE_PERCENTILE``th percentile over the points (flat patches
    exist on every vehicle; curved ones and edges spread more) divided by that law's is
    sigma. Small neighbourhoods (``NOISE_NEIGHBOURS``) see less of a surface's curvature."""
    from scipy.special import chdtri

    k = spread.shape[1]
    if k <= 3:
        return 0.0
    values = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", spread, spread) / k)[:, 0]
    law = np.sqrt(chdtri(k - 3, 1 - NOISE_PERCENTILE / 100) / k)  # the chi2(k - 3) percentile
    return float(np.percentile(np.sqrt(np.maximum(values, 0)), NOISE_PERCENTILE) / law)


def mesh_surface(kept: np.ndarray, vertices: np.ndarray, faces, source="points") -> SurfaceEstimate:
    """The surface of a mesh: unit face normals of ``vertices`` (V, 3) with planarity
    sqrt(area / largest area) (so the weight, planarity squared, is the relative area),
    the ``kept`` (N, 3) vertices as they are, noise 0 and ``MESH_SAMPLES`` points
    uniform over the area (seeded, so deterministic)."""
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu" or faces.min() < 0 \
            or faces.max() >= len(vertices):
        raise InputError(source, f"faces must be (F, 3) integer indices into {len(vertices)} vertices")
    corners = vertices[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = np.linalg.norm(cross, axis=1)
    used = area > 0
    if not used.any():
        raise InputError(source, "every face has zero area: no surface to align")
    normals = cross[used] / area[used, None]
    rng = np.random.default_rng(0)  # fixed: the same mesh gives the same frame
    face = rng.choice(len(area), MESH_SAMPLES, p=area / area.sum())
    u, v = rng.random((2, MESH_SAMPLES))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    edges = corners[face, 1:] - corners[face, :1]
    samples = corners[face, 0] + u[:, None] * edges[:, 0] + v[:, None] * edges[:, 1]
    return SurfaceEstimate(normals, np.sqrt(area[used] / area.max()), kept, 0.0, samples)


def refine_to_planes(rotation: np.ndarray, normals: np.ndarray, weights: np.ndarray,
                     cones_deg=REFINE_CONES_DEG) -> tuple:
    """(refined (3, 3) rotation, share): ``rotation`` (rows: object axes in the source
    frame) turned until the ``normals`` (N, 3) line up with its axes (weighted Kabsch
    over the normals within each cone of the nearest axis, up to sign); ``share`` is the
    weight share inside the last cone. Rows keep their meaning (a small turn)."""
    rows = np.arange(len(normals))
    total = weights.sum()
    share = 0.0
    for cone in cones_deg:
        along = normals @ rotation.T
        nearest = np.abs(along).argmax(axis=1)
        cosine = along[rows, nearest]
        inside = np.abs(cosine) > np.cos(np.radians(cone))
        share = float(weights[inside].sum() / total) if total > 0 else 0.0
        if share == 0:
            break
        targets = np.zeros_like(along)
        targets[rows, nearest] = np.sign(cosine)
        u, _, vt = np.linalg.svd((targets[inside] * weights[inside, None]).T @ normals[inside])
        rotation = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return rotation, share


def histogram_entropy(values: np.ndarray, weights: np.ndarray, bin_width: float) -> float:
    """Entropy (nats) of the weighted histogram of ``values`` (N,) in bins of
    ``bin_width``, each value shared linearly between its two nearest bins, so that the
    entropy changes smoothly as the values move."""
    position = (values - values.min()) / bin_width
    index = position.astype(np.int64)
    upper = position - index
    size = int(index.max()) + 2
    counts = np.bincount(index, weights * (1 - upper), size) + np.bincount(index + 1, weights * upper, size)
    share = counts[counts > 0] / counts.sum()
    return float(-(share * np.log(share)).sum())


def sharpest_turn(points: np.ndarray, weights: np.ndarray, bin_width: float,
                  passes=SHARPEN_PASSES_DEG) -> np.ndarray:
    """(3, 3) small rotation that makes the histograms of ``points`` (N, 3, object
    frame, weighted by ``weights`` (N,)) along x, y and z the sharpest: the least sum
    of their entropies (:func:`histogram_entropy`). Level floors, roofs and sills and
    upright sides each fall into few bins wherever they lie, however curved the body
    around them, where the normals of a noisy curved body pull a plane fit off by a
    degree or two. Coordinate descent over turns about x, y and z, two rounds per pass,
    each pass a grid of (half range, step) degrees around the best so far."""
    turn = np.eye(3)
    for span, step in passes:
        angles = np.arange(-span, span + step / 2, step)
        for _ in range(2):
            for axis in range(3):
                turned = points @ turn.T
                moved = [other for other in range(3) if other != axis]  # the histogram along axis stays
                costs = [sum(histogram_entropy(values, weights, bin_width) for values in (turned @ about[moved].T).T)
                         for about in (_turn_about(axis, angle) for angle in angles)]
                turn = _turn_about(axis, angles[int(np.argmin(costs))]) @ turn
    return turn


def _turn_about(axis: int, degrees: float) -> np.ndarray:
    """(3, 3) rotation by ``degrees`` about object axis ``axis`` (0 x, 1 y, 2 z)."""
    cos, sin = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    first, second = (axis + 1) % 3, (axis + 2) % 3  # the plane it turns, right-handed
    turn = np.eye(3)
    turn[first, first] = turn[second, second] = cos
    turn[second, first], turn[first, second] = sin, -sin
    return turn


def dominant_frame(normals: np.ndarray, weights: np.ndarray, cone_deg: float = 10.0,
                   candidates: int = 1500) -> np.ndarray:
    """(3, 3) rotation whose first row is the most populated normal direction (the
    largest weight of normals within ``cone_deg``, up to sign, among an evenly spread
    subset of the normals themselves) and second row the most populated direction
    perpendicular to it. Deterministic: the subset is every k-th normal."""
    step = max(1, len(normals) // candidates)
    pool = normals[::step]
    cosine = np.cos(np.radians(cone_deg))

    def most_populated(directions):
        votes = (np.abs(directions @ normals.T) > cosine) @ weights
        return directions[int(np.argmax(votes))]

    first = most_populated(pool)
    across = pool - np.outer(pool @ first, first)
    length = np.linalg.norm(across, axis=1)
    perpendicular = length > np.cos(np.radians(90 - cone_deg))
    if not perpendicular.any():
        return _completed(first, np.eye(3)[int(np.argmin(np.abs(first)))])
    second = most_populated(across[perpendicular] / length[perpendicular, None])
    return _completed(first, second)


def _relabelled(frame, like) -> np.ndarray:
    """``frame``'s rows reordered and signed as ``like``'s (both (3, 3) rotations, rows
    the axes): z the row nearest ``like``'s z, x the other row nearest its x."""
    along = frame @ like[2]
    z_row = int(np.argmax(np.abs(along)))
    z = np.copysign(1.0, along[z_row]) * frame[z_row]
    others = [row for row in range(3) if row != z_row]
    across = frame[others] @ like[0]
    nearest = int(np.argmax(np.abs(across)))
    x = np.copysign(1.0, across[nearest]) * frame[others[nearest]]
    return np.stack([x, np.cross(z, x), z])


def _completed(first, second) -> np.ndarray:
    second = second - first * (first @ second)
    second /= np.linalg.norm(second)
    return np.stack([first, second, np.cross(first, second)])


def mirror_error(points: np.ndarray, axis: np.ndarray) -> float:
    """Median distance from ``points`` (N, 3) mirrored across the plane normal to
    ``axis`` (through the middle of their trimmed extent along it) to the nearest original
    point: about the point spacing for a mirror-symmetric shape, more otherwise."""
    from scipy.spatial import cKDTree

    (low,), (high,) = _trimmed_bounds((points @ axis)[:, None])
    middle = (low + high) / 2
    sample = points[:: max(1, len(points) // MIRROR_SAMPLE)]
    mirrored = sample - 2 * np.outer(sample @ axis - middle, axis)
    distances, _ = cKDTree(points).query(mirrored, workers=-1)
    return float(np.median(distances))


def _length_first(rotation, points, weights) -> np.ndarray:
    """``rotation`` with x on the longer of its two horizontal axes (the footprint's
    PCA can pick the width of a sparse mesh); x signed as without refinement."""
    low, high = _trimmed_bounds(points @ rotation[:2].T)
    if high[1] - low[1] <= high[0] - low[0]:
        return rotation
    x = _signed(rotation[1], points, weights, rotation[0])
    return np.stack([x, np.cross(rotation[2], x), rotation[2]])


def _label_axes(rotation, points, weights) -> np.ndarray:
    """Rows of ``rotation`` reordered and signed: x the longest extent, y the axis of
    mirror symmetry of the other two, z the remaining one; when both are mirror axes
    alike (errors within ISOTROPY: a plain box), z the one nearer the source +z, not
    whichever the noise favours (signs as the unrefined frame's: the longer
    third-moment tail, else the source axes)."""
    low, high = _trimmed_bounds(points @ rotation.T)
    x_row = int(np.argmax(high - low))
    others = [row for row in range(3) if row != x_row]
    errors = [mirror_error(points, rotation[row]) for row in others]
    if _equal(min(errors), max(errors)):
        z_row = others[int(np.argmax(np.abs(rotation[others, 2])))]
    else:
        z_row = others[int(np.argmax(errors))]
    x = _signed(rotation[x_row], points, weights, np.array([1.0, 0.0, 0.0]))
    z = _signed(rotation[z_row], points, weights, _wheels_down(rotation[z_row], x, points))
    return np.stack([x, np.cross(z, x), z])


def _wheels_down(axis, x, points) -> np.ndarray:
    """``axis`` or ``-axis``, whichever points away from the wheels, for the up sign of a
    shape whose third moment does not tell (a box-shaped bus or trailer); else the
    source +z. Wheels touch the ground at a few places along the length while a roof
    runs along all of it: of the two end bands along ``axis`` (``WHEEL_BAND`` of the
    extent), the one whose points cover at most half as many of ``LENGTH_BINS`` bins
    along ``x`` as the other's is the bottom. (A chassis without wheels has a floor
    there instead; its third moment decides, as cabins and greenhouses narrow upwards.)"""
    along, length = points @ axis, points @ x
    (low, high), (start, stop) = (np.percentile(values, [0.1, 99.9]) for values in (along, length))
    band = WHEEL_BAND * (high - low)
    bins = np.clip(((length - start) / max(stop - start, np.finfo(float).tiny) * LENGTH_BINS).astype(int),
                   0, LENGTH_BINS - 1)
    bottom, top = (len(np.unique(bins[mask])) for mask in (along <= low + band, along >= high - band))
    if top <= WHEEL_COVER_RATIO * bottom:
        return -axis
    if bottom <= WHEEL_COVER_RATIO * top:
        return axis
    return np.array([0.0, 0.0, 1.0])


def _trimmed_bounds(local: np.ndarray, share: float = BOX_TRIM) -> tuple:
    """Per-axis (low, high) of ``local`` (N, 3) without the ``share`` of most extreme
    points on each side (none below 1 / share points): floaters that sit next to the
    surface pass the density test but must not widen the box. A refined mesh is not
    trimmed (it has no floaters; its extremes are thin parts such as mirrors)."""
    trim = int(share * len(local))
    ordered = np.partition(local, (trim, len(local) - 1 - trim), axis=0)
    return ordered[trim], ordered[len(local) - 1 - trim]


def _surface_bounds(local: np.ndarray, normals: np.ndarray, noise: float, raw: np.ndarray) -> tuple:
    """Per-axis (low, high) of a denoised noisy surface ``local`` (N, 3) with its
    ``normals`` (N, 3), same frame, ``noise`` the surface noise (source units).

    First the body: a side where a wall faces outwards (the points whose normal is
    within ``FACING_DEG`` of the axis crowd into the outer band, ``SIDE_BAND`` x
    ``noise`` wide, at least ``WALL_RATIO`` times as many as in the band inside it) is
    the median of that crowd (denoised points still scatter about a wall, so their
    extreme lies outside it); any other side is where the raw points' deblurred
    histogram ends (:func:`_deblurred_edge`). Then what sticks
    out of the body (:func:`_protrusion`): thin real parts (mirrors, handles) that the
    trim or the wall median cut off, told from floaters by being a cluster."""
    low, high = _trimmed_bounds(local)
    facing = np.abs(normals) > np.cos(np.radians(FACING_DEG))
    band = SIDE_BAND * noise
    for axis in range(3):
        values = local[facing[:, axis], axis]
        for sign, bounds in ((1, high), (-1, low)):
            outward = sign * values
            edge = sign * bounds[axis]
            outer = outward[outward >= edge - band]
            inner = np.count_nonzero((outward < edge - band) & (outward >= edge - 2 * band))
            if len(outer) >= 1 / BOX_TRIM and len(outer) >= WALL_RATIO * inner:
                bounds[axis] = sign * np.median(outer)
            else:
                bounds[axis] = sign * _deblurred_edge(sign * raw[:, axis], noise)
    spacing = _spacing(raw)
    body = high - low
    for axis in range(3):
        face = np.prod(np.delete(body, axis))
        for sign, bounds in ((1, high), (-1, low)):
            bounds[axis] = sign * _protrusion(sign * raw[:, axis], raw, sign * bounds[axis],
                                              PROTRUSION_BAND * noise, spacing, face)
    return low, high


def _deblurred_edge(outward: np.ndarray, noise: float, share: float = BOX_TRIM) -> float:
    """Where a surface ends along ``outward`` ((N,) coordinates of its noisy points,
    increasing away from the body) when its points are blurred by Gaussian ``noise``
    (standard deviation, same units) and the side is no wall (a tyre, a rounded roof,
    a handlebar end: their points thin out towards the extreme, which the wall median
    cannot take and the plane fit pulls inwards).

    The histogram of the outermost points (bins of ``EDGE_STEP`` x ``noise``, from
    ``EDGE_WINDOW`` x ``noise`` inside to outside the trimmed extreme) is deconvolved:
    a non-negative least-squares fit (Poisson-weighted) of Gaussian-blurred spikes on a
    grid of the same step, plus a constant for the floaters left near the surface. The
    edge is the outermost spike position where the deblurred mass counted from outside
    reaches ``share`` of the points, the share the trimmed extreme leaves out (so a
    noise-free cloud gives the trimmed extreme, and noise no longer widens it). Fewer
    than 1 / ``share`` points, or a window holding less than that share, keep the
    trimmed extreme."""
    from scipy.optimize import nnls
    from scipy.special import ndtr

    mass = int(share * len(outward))  # as _trimmed_bounds
    trimmed = np.partition(outward, len(outward) - 1 - mass)[len(outward) - 1 - mass]
    if noise <= 0 or mass == 0:  # noise-free, or too few points (under 1 / share) to deconvolve
        return float(trimmed)
    inner, outer = EDGE_WINDOW
    step = EDGE_STEP * noise
    edges = trimmed + step * np.arange(-round(inner / EDGE_STEP), round(outer / EDGE_STEP) + 1)
    spikes = trimmed + step * np.arange(-round((inner + 2) / EDGE_STEP), round((outer - 1) / EDGE_STEP))
    counts, _ = np.histogram(outward, edges)
    blurred = ndtr((edges[1:, None] - spikes) / noise) - ndtr((edges[:-1, None] - spikes) / noise)
    design = np.column_stack([blurred, np.diff(edges)])
    weight = 1 / np.sqrt(counts + 1.0)
    try:
        found, _ = nnls(design * weight[:, None], counts * weight, maxiter=50 * design.shape[1])
    except RuntimeError:  # no convergence: keep the trimmed extreme
        return float(trimmed)
    from_outside = found[:-1][::-1].cumsum()
    if from_outside[-1] < mass:  # the window holds less than the trimmed share: nothing to place the edge by
        return float(trimmed)
    return float(spikes[::-1][int(np.searchsorted(from_outside, mass))])


def _spacing(points: np.ndarray) -> float:
    """Median distance (source units) from a point of ``points`` (N, 3) to its nearest
    distinct neighbour: the sampling's scale."""
    from scipy.spatial import cKDTree

    distances, _ = cKDTree(points).query(points, k=2, workers=-1)
    return float(np.median(distances[:, 1]))


def _protrusion(outward: np.ndarray, points: np.ndarray, edge: float, band: float, spacing: float,
                face: float) -> float:
    """The side ``edge`` (a coordinate along ``outward``, (N,) the points' coordinates
    increasing away from the body) moved out to a protrusion when there is one.

    Candidates are the points beyond the edge's noise ``band``; a candidate is part of
    a real surface when at least ``PROTRUSION_NEIGHBOURS`` other candidates lie within
    ``PROTRUSION_RADIUS`` x ``spacing`` of it, and more than the candidates spread evenly
    over the side's ``face`` (its area, source units squared) would put there but with
    probability ``PROTRUSION_CHANCE`` (a Poisson count). A surface sampled at that
    spacing has its neighbours there; floaters, spread over a volume, seldom do (at 10 %
    floaters in a box 1.5x the object's their density is about 1/50 of a surface's);
    nor does the noise tail of a wall, spread over the wall (at 1 % noise, near the
    point spacing, the noise estimate reads low and hundreds of a wall's points cross
    the band). The side is then the second most outward such point (one stray cluster
    member aside). Floaters within the band of a wall remain and widen the box by at
    most the band."""
    from scipy.spatial import cKDTree
    from scipy.stats import poisson

    beyond = outward > edge + band
    count = np.count_nonzero(beyond)
    if count <= PROTRUSION_NEIGHBOURS:
        return edge
    candidates = points[beyond]
    radius = PROTRUSION_RADIUS * spacing
    spread_evenly = (count - 1) * np.pi * radius**2 / max(face, np.finfo(float).tiny)
    needed = max(PROTRUSION_NEIGHBOURS - 1, poisson.isf(PROTRUSION_CHANCE, spread_evenly))
    others = cKDTree(candidates).query_ball_point(candidates, radius, return_length=True) - 1
    clustered = np.sort(outward[beyond][others > needed])
    return float(clustered[-2]) if len(clustered) >= 2 else edge


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
