"""Collisions of a candidate box with what the scene holds: other boxes (rotated
bird's-eye overlap, separating-axis test) and scene returns standing inside it.
Boxes are centre boxes x y z dx dy dz heading (sensor frame, m, rad)."""

import numpy as np


def footprint_corners(boxes: np.ndarray) -> np.ndarray:
    """(N, 4, 2) bird's-eye corners of (N, >= 7) boxes, counter-clockwise."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, np.shape(boxes)[-1])
    half = boxes[:, 3:5] / 2
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], np.float64)
    local = signs[None] * half[:, None]  # (N, 4, 2) in the box frame
    cos, sin = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    return np.stack([local[..., 0] * cos - local[..., 1] * sin + boxes[:, None, 0],
                     local[..., 0] * sin + local[..., 1] * cos + boxes[:, None, 1]], axis=-1)


def bev_overlaps(boxes_a: np.ndarray, boxes_b: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(N, M) bool: the footprints of (N, >= 7) and (M, >= 7) boxes, each grown by
    ``margin`` m on every side, overlap (touching does not count). Separating-axis test on
    the four edge normals of each pair."""
    a = np.asarray(boxes_a, np.float64).reshape(-1, np.shape(boxes_a)[-1]).copy()
    b = np.asarray(boxes_b, np.float64).reshape(-1, np.shape(boxes_b)[-1]).copy()
    if not len(a) or not len(b):
        return np.zeros((len(a), len(b)), bool)
    a[:, 3:5] += 2 * margin
    b[:, 3:5] += 2 * margin
    # only pairs whose circumscribed circles meet can overlap: the test runs on those
    reach = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
    first, second = np.nonzero(reach < (np.hypot(a[:, 3], a[:, 4])[:, None] + np.hypot(b[:, 3], b[:, 4])[None]) / 2)
    corners_a, corners_b = footprint_corners(a)[first], footprint_corners(b)[second]
    axes = np.concatenate([_normals(a)[first], _normals(b)[second]], axis=1)  # (P, 4, 2)
    project_a = np.einsum("pkd,pcd->pkc", axes, corners_a)
    project_b = np.einsum("pkd,pcd->pkc", axes, corners_b)
    apart = (project_a.max(-1) <= project_b.min(-1)) | (project_b.max(-1) <= project_a.min(-1))
    overlaps = np.zeros((len(a), len(b)), bool)
    overlaps[first, second] = ~apart.any(axis=1)
    return overlaps


def _normals(boxes: np.ndarray) -> np.ndarray:
    """(N, 2, 2) unit normals of each box's length and width edges."""
    cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    return np.stack([np.stack([cos, sin], -1), np.stack([-sin, cos], -1)], axis=1)
