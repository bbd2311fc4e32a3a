"""Foreground without masks: remove the support plane (table, turntable, the ground under
a real vehicle) and keep the connected object at the centre of the camera orbit.

1. **Orbit centre**: the point nearest (least squares) to every camera's optical axis;
   the median element when there are no cameras or the axes are near parallel (a
   forward-facing capture). Only a centre from the cameras constrains the plane.
2. **Up**: the direction square to every camera's x axis (photos are taken without
   roll, so their x axes are level), or the mean of their up axes (``camera_up``).
3. **Support plane**: RANSAC (seeded) over planes through three elements; a candidate
   must tilt at most 25 degrees from up (when known) and have the orbit centre above it
   (the object stands on its support, not under it); without either, its normal points
   to the side most elements off it lie on. The plane with the most elements within
   ``tolerance`` wins; it must hold at least 5 % of the elements and be flat (see
   ``fit_support_plane``). It is refit by least squares to the elements within its
   thickness: 3 robust standard deviations (1.4826 x the median absolute distance) of
   its elements from it, at least half an element spacing and at most ``tolerance``.
   The elements within that thickness and everything below go, so an object standing
   on the plane loses only a thin slice.
4. **Object**: what is left is linked into connected components (elements closer than
   ``link`` element spacings, a cKDTree radius graph); the component with the element
   nearest the orbit centre, among those holding at least 1 % of what is left, is kept.
"""

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

_HYPOTHESES = 512
_RANSAC_SAMPLE = 20_000
_MAX_TILT_DEG = 25.0
_MIN_PLANE_SHARE = 0.05
_MAX_SPREAD = 0.75
_MIN_COMPONENT_SHARE = 0.01


def orbit_centre(cameras: list) -> np.ndarray | None:
    """(3,) least-squares meeting point of the cameras' optical axes, or None (fewer than
    two cameras, or axes too close to parallel to meet)."""
    if len(cameras) < 2:
        return None
    centres = np.array([view.centre for view in cameras])
    axes = np.array([view.world_from_camera[:3, 2] for view in cameras])
    projectors = np.eye(3) - axes[:, :, None] * axes[:, None, :]  # onto the plane across each axis
    system = projectors.sum(axis=0)
    if np.linalg.cond(system) > 1e4:
        return None
    return np.linalg.solve(system, np.einsum("nij,nj->i", projectors, centres))


def camera_up(cameras: list) -> np.ndarray | None:
    """(3,) unit up of the capture, or None when the cameras do not tell. Photos are
    taken without roll, so every camera's x axis is level: up is the direction most
    nearly perpendicular to all of them (the smallest eigenvector of the sum of their
    outer products), turned to agree with the mean of the cameras' up axes (-y). When
    the x axes do not pin it down (all nearly parallel: every photo from one side), the
    mean up axis itself, if the cameras agree on it (mean length >= 0.5)."""
    if not cameras:
        return None
    rotations = np.array([view.world_from_camera[:3, :3] for view in cameras])
    mean_up = -rotations[:, :, 1].mean(axis=0)
    values, vectors = np.linalg.eigh(np.einsum("ni,nj->ij", rotations[:, :, 0], rotations[:, :, 0]))
    if values[1] > 4 * values[0] and values[1] > 0.05 * len(cameras):
        up = vectors[:, 0]
        return up if up @ mean_up >= 0 else -up
    length = np.linalg.norm(mean_up)
    return mean_up / length if length >= 0.5 else None


def fit_support_plane(positions: np.ndarray, tolerance: float, floor: float, rng: np.random.Generator,
                      up: np.ndarray | None = None, centre: np.ndarray | None = None) -> dict | None:
    """The support plane as {"normal": (3,) unit, pointing to the object's side,
    "offset": d with normal . x = d on the plane, "elements": count within
    ``tolerance``, "thickness": 3 x 1.4826 x the median absolute distance of the
    elements within it, clipped to [``floor``, ``tolerance``]}, or None when no
    admissible plane holds 5 % of the elements or its elements are not flat (their
    3 x 1.4826 x median distance exceeds 0.75 ``tolerance``: a band cut through a
    curved surface spreads evenly, about 2.2 ``tolerance``). The RANSAC winner is refit twice by
    least squares to the elements within its thickness (a refit that leaves the
    admissible tilt is not taken)."""
    points = positions.astype(np.float64)
    sample = points if len(points) <= _RANSAC_SAMPLE else points[rng.choice(len(points), _RANSAC_SAMPLE, replace=False)]
    triples = sample[rng.integers(0, len(sample), (_HYPOTHESES, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    usable = lengths > 0
    normals, triples = normals[usable] / lengths[usable, None], triples[usable]
    offsets = np.einsum("hj,hj->h", normals, triples[:, 0])
    if centre is not None:  # orient towards the object, which stands above its support
        flip = np.where(normals @ centre - offsets < 0, -1.0, 1.0)
    elif up is not None:
        flip = np.where(normals @ up < 0, -1.0, 1.0)
    else:  # towards the side most elements off the plane are on
        signed = sample @ normals.T - offsets
        flip = np.where((signed > tolerance).sum(axis=0) < (signed < -tolerance).sum(axis=0), -1.0, 1.0)
    normals, offsets = normals * flip[:, None], offsets * flip
    admissible = _admissible(normals, offsets, tolerance, up, centre)
    if not admissible.any():
        return None
    normals, offsets = normals[admissible], offsets[admissible]
    counts = (np.abs(sample @ normals.T - offsets) <= tolerance).sum(axis=0)
    best = int(np.argmax(counts))
    normal, offset, band = normals[best], float(offsets[best]), tolerance
    if (np.abs(points @ normal - offset) <= tolerance).sum() < _MIN_PLANE_SHARE * len(points):
        return None
    for _ in range(2):
        near = np.abs(points @ normal - offset) <= band
        if near.sum() >= 3:
            middle = points[near].mean(axis=0)
            refit = np.linalg.svd(points[near] - middle, full_matrices=False)[2][2]
            refit = refit if refit @ normal >= 0 else -refit
            if _admissible(refit[None], np.array([refit @ middle]), tolerance, up, centre)[0]:
                normal, offset = refit, float(refit @ middle)
        distance = np.abs(points @ normal - offset)
        spread = 3 * 1.4826 * float(np.median(distance[distance <= tolerance]))
        band = float(np.clip(spread, floor, tolerance))
    if spread > _MAX_SPREAD * tolerance:  # elements spread evenly over the band: a curved surface cut, not a plane
        return None
    return {"normal": normal, "offset": offset, "elements": int((distance <= tolerance).sum()), "thickness": band}


def _admissible(normals, offsets, tolerance, up, centre) -> np.ndarray:
    """Planes tilted at most 25 degrees from ``up`` with ``centre`` above them (each when known)."""
    admissible = np.ones(len(normals), bool)
    if up is not None:
        admissible &= normals @ up >= np.cos(np.radians(_MAX_TILT_DEG))
    if centre is not None:
        admissible &= normals @ centre - offsets > tolerance
    return admissible


def central_component(positions: np.ndarray, candidates: np.ndarray, centre: np.ndarray, link: float) -> np.ndarray:
    """(N,) bool: the connected component (elements of ``candidates`` closer than
    ``link``) with the element nearest ``centre`` among components holding at least 1 %
    of the candidates."""
    keep = np.zeros(len(positions), bool)
    index = np.flatnonzero(candidates)
    if not len(index):
        return keep
    points = positions[index]
    pairs = cKDTree(points).query_pairs(link, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])), shape=(len(points),) * 2)
    _, labels = connected_components(graph, directed=False)
    sizes = np.bincount(labels)
    distance = np.linalg.norm(points - centre, axis=1)
    eligible = sizes[labels] >= max(1, _MIN_COMPONENT_SHARE * len(points))
    nearest = np.argmin(np.where(eligible, distance, np.inf))
    keep[index[labels == labels[nearest]]] = True
    return keep


def plane_foreground(positions: np.ndarray, cameras: list, spacing: float, rng: np.random.Generator,
                     tolerance: float = 4.0, link: float = 3.0) -> tuple:
    """(keep (N,) bool, report dict): steps 1-4 above; ``tolerance`` (the plane search's
    band, the most its thickness can be) and ``link`` in element spacings."""
    orbit = orbit_centre(cameras)
    centre = orbit if orbit is not None else np.median(positions, axis=0).astype(np.float64)
    centre_from = "camera axes" if orbit is not None else "median element"
    up = camera_up(cameras)
    plane = fit_support_plane(positions, tolerance * spacing, 0.5 * spacing, rng, up, orbit)
    above = np.ones(len(positions), bool)
    if plane is not None:
        above = positions.astype(np.float64) @ plane["normal"] - plane["offset"] > plane["thickness"]
    keep = central_component(positions, above, centre, link * spacing)
    report = {"centre": [round(float(c), 6) for c in centre], "centre_from": centre_from,
              "up": None if up is None else [round(float(c), 6) for c in up],
              "plane": None if plane is None else {"normal": [round(float(c), 6) for c in plane["normal"]],
                                                   "offset": round(plane["offset"], 6),
                                                   "elements": plane["elements"],
                                                   "thickness": round(plane["thickness"], 9)},
              "removed_with_plane": int((~above).sum()), "kept": int(keep.sum())}
    return keep, report
