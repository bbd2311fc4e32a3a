"""Oriented boxes in a LiDAR's sensor frame, OpenPCDet's ``box3d_lidar`` layout:
x y z (centre, m), dx dy dz (length along the heading, width, height, m), heading
(rad, from +x counter-clockwise about +z)."""

import numpy as np


def box_frame(points: np.ndarray, centre: np.ndarray, heading: float) -> np.ndarray:
    """(N, 3) sensor-frame points into the frame of a box at ``centre`` turned by ``heading``."""
    cos, sin = np.cos(heading), np.sin(heading)
    shifted = points - centre
    return np.column_stack([shifted[:, 0] * cos + shifted[:, 1] * sin,
                            -shifted[:, 0] * sin + shifted[:, 1] * cos, shifted[:, 2]])


def inside_box(points: np.ndarray, box: np.ndarray, tolerance: float = 0.0) -> np.ndarray:
    """(N,) bool: (N, 3) sensor-frame points within ``tolerance`` m of the (>= 7,) box."""
    return np.all(np.abs(box_frame(points, box[:3], box[6])) <= box[3:6] / 2 + tolerance, axis=1)
