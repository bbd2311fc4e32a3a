"""Ground-truth database formats (REFERENCE.md 1): one float32 ``.bin`` per entry and
one info per entry in ``<dataset>_dbinfos_pgt.pkl`` = ``{class name: [info, ...]}``.

| format    | box3d_lidar z       | points relative to   | box values                         |
|-----------|---------------------|----------------------|------------------------------------|
| openpcdet | box centre          | box centre           | nuScenes 9 (+ vx, vy), KITTI/Lyft 7 |
| mmdet3d   | box bottom          | box bottom centre    | nuScenes 9 (+ vx, vy), KITTI/Lyft 7 |

Points keep the sensor frame's orientation (not turned into the box frame); columns:
KITTI x y z intensity (0..1); nuScenes and Lyft x y z intensity (0..255) time_lag (s).
Boxes: x y z dx dy dz heading [vx vy], sensor frame, dx along the heading, heading from
+x counter-clockwise, float32. Info keys:

- both: name (the dataset's class), path (relative to the format folder, the dataset
  root to give the framework), image_idx ("pgt/<object>"), gt_idx (the entry's grid
  index), box3d_lidar, num_points_in_gt (= the file's rows);
- openpcdet KITTI: + difficulty, bbox, score (-1, KITTI's value for ground truth);
- mmdet3d: + group_id (unique in the bank), difficulty.

KITTI difficulty and bbox come from KITTI's camera 2 (nominal calibration below):
0/1/2 for a projected box height >= 40 / >= 25 / < 25 px, -1 when the box is not in
the image (OpenPCDet's KITTI configs drop -1 with ``filter_by_difficulty``). Elsewhere
difficulty is 0 and there is no bbox.
"""

import numpy as np

from ..scan.sensors import BIN_COLUMNS

BOX_VALUES = {"nuscenes": 9, "kitti": 7, "lyft": 7}
DATABASE_FOLDER = "pgt_gt_database"

# Default dataset class per authored class (nuScenes names). Missing = no counterpart:
# the config's [classes] table must name one (or "" to skip the class).
CLASS_NAMES = {
    "nuscenes": {name: name for name in ("car", "truck", "trailer", "bus", "construction_vehicle", "bicycle",
                                         "motorcycle", "pedestrian", "traffic_cone", "barrier")},
    "kitti": {"car": "Car", "truck": "Truck", "pedestrian": "Pedestrian", "bicycle": "Cyclist",
              "cyclist": "Cyclist", "motorcycle": "Cyclist"},
    "lyft": {name: name for name in ("car", "truck", "bus", "emergency_vehicle", "other_vehicle", "motorcycle",
                                     "bicycle", "pedestrian", "animal")} | {"trailer": "other_vehicle",
                                                                              "construction_vehicle": "other_vehicle"},
}

# KITTI camera 2: P2 of the KITTI object benchmark and the usual velodyne -> camera
# transform (x forward, y left, z up -> x right, y down, z forward); 1242 x 375 px.
KITTI_P2 = np.array([[721.5377, 0.0, 609.5593, 44.85728], [0.0, 721.5377, 172.854, 0.2163791],
                     [0.0, 0.0, 1.0, 0.002745884]])
KITTI_CAM_FROM_VELO = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, -0.08], [1.0, 0.0, 0.0, -0.27],
                                [0.0, 0.0, 0.0, 1.0]])
KITTI_IMAGE = (1242, 375)
_CORNERS = np.array([[i, j, k] for i in (-0.5, 0.5) for j in (-0.5, 0.5) for k in (-0.5, 0.5)])


def class_name_for(dataset: str, class_name: str, overrides: dict) -> str | None:
    """The dataset's name for an authored class: the config's override, else CLASS_NAMES;
    None when there is neither."""
    if class_name in overrides:
        return overrides[class_name]
    return CLASS_NAMES[dataset].get(class_name)


def box_corners(box: np.ndarray) -> np.ndarray:
    """(8, 3) corners of a (>= 7,) centre box, sensor frame."""
    cos, sin = np.cos(box[6]), np.sin(box[6])
    local = _CORNERS * box[3:6]
    rotated = np.column_stack([local[:, 0] * cos - local[:, 1] * sin, local[:, 0] * sin + local[:, 1] * cos,
                               local[:, 2]])
    return rotated + box[:3]


def kitti_image_box(box: np.ndarray) -> tuple:
    """(bbox [x1, y1, x2, y2] float32 px, difficulty) of a centre box seen by KITTI's
    camera 2; ([0, 0, 0, 0], -1) when it is not in front of the camera and in the image."""
    corners = np.column_stack([box_corners(box), np.ones(8)]) @ KITTI_CAM_FROM_VELO.T
    if np.any(corners[:, 2] < 0.1):
        return np.zeros(4, np.float32), -1
    projected = corners @ KITTI_P2.T
    uv = projected[:, :2] / projected[:, 2:]
    low, high = np.maximum(uv.min(0), 0), np.minimum(uv.max(0), KITTI_IMAGE)
    if np.any(high <= low):
        return np.zeros(4, np.float32), -1
    height = high[1] - low[1]
    return np.array([*low, *high], np.float32), 0 if height >= 40 else 1 if height >= 25 else 2


def entry_points(rows: np.ndarray, dataset: str) -> np.ndarray:
    """(N, C) float64 sensor-frame points in the dataset's columns (sensors.BIN_COLUMNS)."""
    return np.column_stack([rows[name] for name in BIN_COLUMNS[dataset]]).astype(np.float64)


def database_record(fmt: str, dataset: str, points: np.ndarray, box: np.ndarray, info: dict) -> tuple:
    """(float32 rows for the .bin, info) of one entry in format ``fmt``. ``points`` (N, C)
    sensor frame, ``box`` (9,) centre box, ``info`` the shared keys (name, path,
    image_idx, gt_idx, group_id)."""
    origin = box[:3].copy()
    if fmt == "mmdet3d":
        origin[2] -= box[5] / 2  # bottom centre
    rows = points.copy()
    rows[:, :3] -= origin
    stored = box[:BOX_VALUES[dataset]].astype(np.float32) + np.float32(0)  # a still box has vx = +0, not -0
    stored[2] = origin[2]
    record = {key: info[key] for key in ("name", "path", "image_idx", "gt_idx")}
    record.update(box3d_lidar=stored, num_points_in_gt=len(rows))
    difficulty, bbox = 0, None
    if dataset == "kitti":
        bbox, difficulty = kitti_image_box(box)
    if fmt == "openpcdet" and dataset == "kitti":
        record.update(difficulty=difficulty, bbox=bbox, score=np.float32(-1.0))
    if fmt == "mmdet3d":
        record.update(group_id=info["group_id"], difficulty=difficulty)
    return rows.astype(np.float32), record
