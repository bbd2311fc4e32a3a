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

- both: name (the dataset's class), path (joined to the dataset root by the framework:
  see export.assemble), image_idx (int, unique in the bank: the entry's group id; no
  bank entry has a camera image), pgt_object (the authored object's name), gt_idx (the
  entry's grid index), box3d_lidar, num_points_in_gt (= the file's rows);
- openpcdet KITTI: + difficulty, bbox, score (-1, KITTI's value for ground truth);
- mmdet3d: + group_id (= image_idx), difficulty.

Every pickle holds a list for every class of its dataset (DATABASE_CLASSES, empty when
the bank has none): the samplers index the pickle by every class their config names.

KITTI difficulty follows KITTI's rules (``kitti_difficulty``) on camera 2's view of the
box (nominal calibration below): the projected box, clipped to the image, is ``bbox``;
truncation is the share of the unclipped box's area outside the image; occlusion is 0
(fully visible: a bank entry is scanned alone). Elsewhere difficulty is 0, no bbox.
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
    "kitti": {"car": "Car", "van": "Van", "truck": "Truck", "pedestrian": "Pedestrian", "bicycle": "Cyclist",
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
# KITTI's difficulty levels (devkit object benchmark): easy, moderate, hard. A box that
# meets none of them is -1, which OpenPCDet's and mmdet3d's KITTI configs filter out.
KITTI_MIN_HEIGHT_PX = (40.0, 25.0, 25.0)
KITTI_MAX_OCCLUSION = (0, 1, 2)
KITTI_MAX_TRUNCATION = (0.15, 0.3, 0.5)

# Every class of each dataset's ground-truth database as the frameworks' builders write it.
DATABASE_CLASSES = {
    "nuscenes": ("car", "truck", "construction_vehicle", "bus", "trailer", "barrier", "motorcycle", "bicycle",
                 "pedestrian", "traffic_cone"),
    "kitti": ("Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Tram", "Misc"),
    "lyft": ("car", "truck", "bus", "emergency_vehicle", "other_vehicle", "motorcycle", "bicycle", "pedestrian",
             "animal"),
}
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


def kitti_difficulty(height_px: float, truncation: float, occlusion: int) -> int:
    """KITTI's difficulty of a labelled box: 0 easy, 1 moderate, 2 hard, -1 none of them.
    ``height_px`` = y2 - y1 of the 2-D box, ``truncation`` in [0, 1], ``occlusion`` 0..3."""
    for level, (height, occluded, truncated) in enumerate(zip(KITTI_MIN_HEIGHT_PX, KITTI_MAX_OCCLUSION,
                                                                  KITTI_MAX_TRUNCATION)):
        if height_px >= height and occlusion <= occluded and truncation <= truncated:
            return level
    return -1


def kitti_image_box(box: np.ndarray) -> tuple:
    """(bbox [x1, y1, x2, y2] float32 px, truncation, difficulty) of a centre box seen
    by KITTI's camera 2. A box with a corner behind the camera, or none of it in the
    image, has bbox [0, 0, 0, 0], truncation 1 and difficulty -1."""
    corners = np.column_stack([box_corners(box), np.ones(8)]) @ KITTI_CAM_FROM_VELO.T
    if np.any(corners[:, 2] < 0.1):
        return np.zeros(4, np.float32), 1.0, -1
    projected = corners @ KITTI_P2.T
    uv = projected[:, :2] / projected[:, 2:]
    full_low, full_high = uv.min(0), uv.max(0)
    # Pixel centres run 0 .. size - 1, as the frameworks clip projected boxes.
    low, high = np.maximum(full_low, 0), np.minimum(full_high, np.subtract(KITTI_IMAGE, 1))
    if np.any(high <= low):
        return np.zeros(4, np.float32), 1.0, -1
    truncation = 1.0 - np.prod(high - low) / np.prod(full_high - full_low)
    bbox = np.array([*low, *high], np.float32)
    return bbox, float(truncation), kitti_difficulty(float(bbox[3] - bbox[1]), truncation, 0)


def entry_points(rows: np.ndarray, dataset: str) -> np.ndarray:
    """(N, C) float64 sensor-frame points in the dataset's columns (sensors.BIN_COLUMNS)."""
    points = np.empty((len(rows), len(BIN_COLUMNS[dataset])))
    for column, name in enumerate(BIN_COLUMNS[dataset]):
        points[:, column] = rows[name]
    return points


def database_record(fmt: str, dataset: str, points: np.ndarray, box: np.ndarray, info: dict) -> tuple:
    """(float32 rows for the .bin, info) of one entry in format ``fmt``. ``points`` (N, C)
    sensor frame, ``box`` (9,) centre box, ``info`` the shared keys (name, path,
    image_idx, pgt_object, gt_idx)."""
    origin = box[:3].copy()
    if fmt == "mmdet3d":
        origin[2] -= box[5] / 2  # bottom centre
    offset = np.zeros(points.shape[1])  # intensity and time_lag pass unchanged
    offset[:3] = origin
    rows = (points - offset).astype(np.float32)  # in float64, rounded once
    stored = box[:BOX_VALUES[dataset]].astype(np.float32) + np.float32(0)  # a still box has vx = +0, not -0
    stored[2] = origin[2]
    record = {key: info[key] for key in ("name", "path", "image_idx", "pgt_object", "gt_idx")}
    record.update(box3d_lidar=stored, num_points_in_gt=len(rows))
    difficulty, bbox = 0, None
    if dataset == "kitti":
        bbox, _, difficulty = kitti_image_box(box)
    if fmt == "openpcdet" and dataset == "kitti":
        record.update(difficulty=difficulty, bbox=bbox, score=np.float32(-1.0))
    if fmt == "mmdet3d":
        record.update(group_id=info["image_idx"], difficulty=difficulty)
    return rows, record
