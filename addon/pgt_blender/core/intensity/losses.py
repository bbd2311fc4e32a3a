"""Ball patches and the paper's group intensity loss (sec. 3.2, eq. 3), numpy first.

An object (P points in its box frame divided by dims / 2, so the box is [-1, 1]^3) is
split into N ball patches: N centres by farthest point sampling, each patch the points
within ``radius`` of its centre (a centre is always in its own patch, so no patch is
empty). The fake object (the rgb object's points with generated intensities) and the
real one are matched patch to patch by the Hungarian algorithm on the L1 distance of
their centres; the loss is

    L_group = weight * sum_j | mean_{x in b_j} x - mean_{y in b_sigma(j)} y |

Everything here works on numpy arrays; ``patch_means`` and ``matched_patch_loss`` are
written with operators only, so training runs the very same code on torch tensors.
"""

import numpy as np
from scipy.optimize import linear_sum_assignment

PATCHES = 16  # N
PATCH_RADIUS = 0.5  # in the normalised box frame: a quarter of the box's extent
GROUP_WEIGHT = 0.1  # the paper's lambda


def squared_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., M, N) squared distances of points ``a`` (..., M, 3) to ``b`` (..., N, 3),
    one coordinate at a time (numpy reduces a length-3 axis slowly)."""
    return sum((a[..., :, None, i] - b[..., None, :, i]) ** 2 for i in range(3))


def farthest_point_centres(xyz: np.ndarray, count: int, lengths: np.ndarray | None = None) -> np.ndarray:
    """(..., count) int64 indices into the points of ``xyz`` (..., P, 3): farthest point
    sampling from the point farthest from the centroid (no seed: the result does not
    depend on a random start). Ties go to the lower index. count > P repeats points.
    ``lengths`` (B,) for xyz (B, P, 3): only each row's first lengths[b] points count
    (the rest is padding, never chosen; count <= lengths)."""
    xyz = np.asarray(xyz, np.float64)
    batch = xyz.shape[:-2]
    flat = xyz.reshape(-1, *xyz.shape[-2:])
    rows = np.arange(len(flat))
    valid = np.ones(flat.shape[:2], bool) if lengths is None else np.arange(flat.shape[1]) < lengths[:, None]
    centroid = (flat * valid[..., None]).sum(axis=1, keepdims=True) / valid.sum(axis=1)[:, None, None]
    chosen = np.empty((len(flat), count), np.int64)
    chosen[:, 0] = np.argmax(np.where(valid, squared_distances(centroid, flat)[:, 0], -1.0), axis=1)
    distance = np.where(valid, np.inf, -np.inf)
    for i in range(1, count):
        latest = flat[rows, chosen[:, i - 1]][:, None]
        np.minimum(distance, squared_distances(latest, flat)[:, 0], out=distance)
        chosen[:, i] = np.argmax(distance, axis=1)
    return chosen.reshape(*batch, count)


def ball_patches(xyz: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    """(..., N, P) bool: which of the P points of ``xyz`` (..., P, 3) lie within
    ``radius`` of each centre, ``centres`` (..., N) being indices into those points."""
    xyz = np.asarray(xyz, np.float64)
    centre_xyz = np.take_along_axis(xyz, centres[..., None], axis=-2)
    return squared_distances(centre_xyz, xyz) <= radius**2


def match_patches(centres_fake: np.ndarray, centres_real: np.ndarray) -> tuple:
    """(rows, cols) int64 arrays: the assignment of fake patch rows[j] to real patch
    cols[j] minimising the summed L1 distance of their centres (N, 3) each (Hungarian
    algorithm); rows is 0..N-1."""
    cost = np.abs(np.asarray(centres_fake)[:, None, :] - np.asarray(centres_real)[None, :, :]).sum(axis=-1)
    rows, cols = linear_sum_assignment(cost)
    return rows.astype(np.int64), cols.astype(np.int64)


def patch_means(masks, values):
    """(..., N) mean value per patch: ``masks`` (..., N, P) as 0/1 numbers (bool for
    numpy), ``values`` (..., P). numpy arrays or torch tensors (same kind for both)."""
    return (masks * values[..., None, :]).sum(-1) / masks.sum(-1)


def matched_patch_loss(means_fake, means_real, cols, weight: float = GROUP_WEIGHT):
    """weight * sum_j |means_fake[j] - means_real[cols[j]]| for (N,) patch means (or
    (B, N) with cols (B, N), summed over patches, averaged over the batch)."""
    matched = np.take_along_axis(means_real, cols, -1) if isinstance(means_real, np.ndarray) \
        else means_real.gather(-1, cols)
    return weight * abs(means_fake - matched).sum(-1).mean()


def group_intensity_loss(xyz_fake: np.ndarray, intensity_fake: np.ndarray, xyz_real: np.ndarray,
                         intensity_real: np.ndarray, patches: int = PATCHES, radius: float = PATCH_RADIUS,
                         weight: float = GROUP_WEIGHT) -> float:
    """The group intensity loss of one fake object (xyz (P, 3), intensity (P,)) against
    one real object (xyz (Q, 3), intensity (Q,)), both in the normalised box frame."""
    sides = []
    for xyz, intensity in ((xyz_fake, intensity_fake), (xyz_real, intensity_real)):
        centres = farthest_point_centres(xyz, patches)
        means = patch_means(ball_patches(xyz, centres, radius), np.asarray(intensity, np.float64))
        sides.append((np.asarray(xyz, np.float64)[centres], means))
    (centres_fake, means_fake), (centres_real, means_real) = sides
    _, cols = match_patches(centres_fake, centres_real)
    return float(matched_patch_loss(means_fake, means_real, cols, weight))
