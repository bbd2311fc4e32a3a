"""Oriented boxes in a LiDAR's sensor frame, OpenPCDet's ``box3d_lidar`` layout:
x y z (centre, m), dx dy dz (length along the heading, width, height, m), heading
(rad, from +x counter-clockwise about +z)."""

import numpy as np


def centred_bounds(dims) -> np.ndarray:
    """(2, 3) float64 min and max corners of a box of ``dims`` (3,) m centred on the
    origin: an authored object's box in its object frame."""
    dims = np.asarray(dims, np.float64)
    return np.stack([-dims / 2, dims / 2])


def box_frame(points: np.ndarray, centre: np.ndarray, heading: float) -> np.ndarray:
    """(N, 3) sensor-frame points into the frame of a box at ``centre`` turned by ``heading``."""
    cos, sin = np.cos(heading), np.sin(heading)
    shifted = points - centre
    return np.column_stack([shifted[:, 0] * cos + shifted[:, 1] * sin,
                            -shifted[:, 0] * sin + shifted[:, 1] * cos, shifted[:, 2]])


def inside_box(points: np.ndarray, box: np.ndarray, tolerance: float = 0.0) -> np.ndarray:
    """(N,) bool: (N, 3) sensor-frame points within ``tolerance`` m of the (>= 7,) box.
    Only the points in the square around the box's circumscribed circle are turned into
    its frame (the answer is the same; a scan's other points cost two comparisons)."""
    reach = np.hypot(box[3], box[4]) / 2 + tolerance
    near = np.flatnonzero((np.abs(points[:, 0] - box[0]) <= reach) & (np.abs(points[:, 1] - box[1]) <= reach))
    inside = np.zeros(len(points), bool)
    inside[near] = np.all(np.abs(box_frame(points[near], box[:3], box[6])) <= box[3:6] / 2 + tolerance, axis=1)
    return inside


def kitti_camera_to_lidar(camera_boxes: np.ndarray, velodyne_from_rect: np.ndarray) -> np.ndarray:
    """(N, 7) centre boxes in the velodyne frame of (N, 7) KITTI camera boxes
    ``x y z l h w ry`` (bottom centre in the rectified camera frame, ry about its -y axis),
    with ``velodyne_from_rect`` (4, 4) the inverse of R0_rect @ Tr_velo_to_cam:
    heading = -ry - pi/2."""
    camera_boxes = np.asarray(camera_boxes, np.float64).reshape(-1, 7)
    bottoms = np.column_stack([camera_boxes[:, :3], np.ones(len(camera_boxes))]) @ np.asarray(velodyne_from_rect).T
    length, height, width, ry = camera_boxes[:, 3], camera_boxes[:, 4], camera_boxes[:, 5], camera_boxes[:, 6]
    return np.column_stack([bottoms[:, :2], bottoms[:, 2] + height / 2, length, width, height, -ry - np.pi / 2])
