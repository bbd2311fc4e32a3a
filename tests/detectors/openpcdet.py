"""OpenPCDet's own ground-truth sampler (``DataBaseSampler``), run on our banks.

The files in ../shared/consumers/OpenPCDet are OpenPCDet's, unmodified. Three things
keep them from importing as shipped, and this harness supplies exactly those:

1. ``pcdet/datasets/__init__.py`` imports every dataset class and their dependencies:
   the copy made here replaces that one file with an empty module. OpenPCDet's
   ``setup.py`` also generates ``pcdet/version.py``, absent from the copy: written here.
2. ``iou3d_nms_utils.boxes_bev_iou_cpu`` calls the compiled ``iou3d_nms_cuda``:
   ``iou3d_nms_cuda.boxes_iou_bev_cpu`` below ports ``src/iou3d_cpu.cpp`` line by line
   (its polygon clipping with the 1 cm corner margin, float32).
3. ``roiaware_pool3d_utils.points_in_boxes_cpu`` calls the compiled
   ``roiaware_pool3d_cuda``: ``roiaware_pool3d_cuda.points_in_boxes_cpu`` below ports
   ``src/roiaware_pool3d.cpp`` (float32, |z - cz| <= dz/2, |local x, y| < d/2 + 1 cm).

The two ports are modules put in ``sys.modules`` under the extensions' names, so every
Python line of OpenPCDet runs as written. ``SharedArray`` (imported by common_utils and
the sampler, used only with USE_SHARED_MEMORY, which the stock configs leave off) is an
empty stand-in module.

Scenes are handed to the sampler as OpenPCDet's datasets do (``kitti_scene``,
``nuscenes_scene``): points, centre boxes ``gt_boxes`` (N, 7; nuScenes 9 with
velocity), ``gt_names``, ``gt_boxes_mask``, and for KITTI ``calib`` and ``road_plane``.
"""

import logging
import pickle
import shutil
import sys
import types
from functools import cache
from pathlib import Path

import numpy as np

from pgt_blender.dev import SHARED_DATA

SOURCE = SHARED_DATA.parent / "consumers" / "OpenPCDet"
CONFIGS = SOURCE / "tools" / "cfgs"
KITTI_IMAGE_SHAPE = (375, 1242)  # rows, columns: KittiDataset.get_image_shape of the shared frames

# The model configs' CLASS_NAMES: the nuScenes and Lyft ones from OpenPCDet's
# cbgs_voxel0075_res3d_centerpoint.yaml and lyft_models/cbgs_second_multihead.yaml,
# KITTI's from its 3-class models (pointpillar.yaml, second.yaml, pv_rcnn.yaml).
CLASS_NAMES = {
    "nuscenes": ["car", "truck", "construction_vehicle", "bus", "trailer", "barrier", "motorcycle", "bicycle",
                 "pedestrian", "traffic_cone"],
    "kitti": ["Car", "Pedestrian", "Cyclist"],
    "lyft": ["car", "truck", "bus", "emergency_vehicle", "other_vehicle", "motorcycle", "bicycle", "pedestrian",
             "animal"],
}
DATASET_CONFIGS = {name: CONFIGS / "dataset_configs" / f"{name}_dataset.yaml" for name in CLASS_NAMES}


# --- numpy ports of the compiled CPU functions ---------------------------------------


MARGIN = np.float32(1e-2)  # both C++ files: const float MARGIN = 1e-2
EPS = np.float32(1e-8)  # iou3d_cpu.cpp: const float EPS = 1e-8


def _cross(p1, p2, p0):
    """iou3d_cpu.cpp cross(p1, p2, p0) on (..., 2) arrays: (p1 - p0) x (p2 - p0)."""
    return (p1[..., 0] - p0[..., 0]) * (p2[..., 1] - p0[..., 1]) - (p2[..., 0] - p0[..., 0]) * (p1[..., 1] - p0[..., 1])


def _corners(boxes: np.ndarray) -> np.ndarray:
    """(N, 5, 2) float32 footprint corners in box_overlap's order (x1y1, x2y1, x2y2, x1y2,
    then the first again), rotated about the centre by +heading."""
    x, y, dx, dy, heading = (boxes[:, k, None] for k in (0, 1, 3, 4, 6))
    cx = np.concatenate([x - dx / 2, x + dx / 2, x + dx / 2, x - dx / 2], axis=1) - x
    cy = np.concatenate([y - dy / 2, y - dy / 2, y + dy / 2, y + dy / 2], axis=1) - y
    cos, sin = np.cos(heading), np.sin(heading)
    corners = np.stack([cx * cos + cy * -sin + x, cx * sin + cy * cos + y], axis=-1)
    return np.concatenate([corners, corners[:, :1]], axis=1)


def _in_box2d(x, y, dx, dy, heading, px, py):
    """check_in_box2d: the point in the footprint, strictly, with the 1 cm margin (float32)."""
    cos, sin = np.cos(-heading), np.sin(-heading)
    rot_x = (px - x) * cos + (py - y) * -sin
    rot_y = (px - x) * sin + (py - y) * cos
    return (np.abs(rot_x) < dx / 2 + MARGIN) & (np.abs(rot_y) < dy / 2 + MARGIN)


def _edge_crossings(ca: np.ndarray, cb: np.ndarray):
    """intersection() of edge i of every a with edge j of every b, i-major as box_overlap
    loops: (N, M, 16, 2) points and (N, M, 16) flags (proper crossings only: s1*s2 > 0 and
    s3*s4 > 0, so touching or collinear edges give none)."""
    p0, p1 = ca[:, None, :4, None], ca[:, None, 1:, None]  # (N, 1, 4, 1, 2)
    q0, q1 = cb[None, :, None, :4], cb[None, :, None, 1:]  # (1, M, 1, 4, 2)
    rect = np.ones((), bool)
    for k in (0, 1):  # check_rect_cross
        rect = rect & (np.minimum(p0[..., k], p1[..., k]) <= np.maximum(q0[..., k], q1[..., k])) \
            & (np.minimum(q0[..., k], q1[..., k]) <= np.maximum(p0[..., k], p1[..., k]))
    s1, s2 = _cross(q0, p1, p0), _cross(p1, q1, p0)
    s3, s4 = _cross(p0, q1, q0), _cross(q1, p1, q0)
    found = rect & (s1 * s2 > 0) & (s3 * s4 > 0)
    s5 = _cross(q1, p1, p0)
    with np.errstate(divide="ignore", invalid="ignore"):
        general = (s5[..., None] * q0 - s1[..., None] * q1) / (s5 - s1)[..., None]
        a0, b0 = p0[..., 1] - p1[..., 1], p1[..., 0] - p0[..., 0]
        c0 = p0[..., 0] * p1[..., 1] - p1[..., 0] * p0[..., 1]
        a1, b1 = q0[..., 1] - q1[..., 1], q1[..., 0] - q0[..., 0]
        c1 = q0[..., 0] * q1[..., 1] - q1[..., 0] * q0[..., 1]
        d = a0 * b1 - a1 * b0
        parallel = np.stack([(b0 * c1 - b1 * c0) / d, (a1 * c0 - a0 * c1) / d], axis=-1)
    points = np.where((np.abs(s5 - s1) > EPS)[..., None], general, parallel)
    n, m = len(ca), len(cb)
    return points.reshape(n, m, 16, 2), found.reshape(n, m, 16)


def _overlap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """box_overlap for every pair: (N, M) float32 footprint intersection area, m^2."""
    n, m = len(a), len(b)
    ca, cb = _corners(a), _corners(b)
    crossings, crossing_found = _edge_crossings(ca, cb)
    box_a = [a[:, k, None, None] for k in (0, 1, 3, 4, 6)]  # (N, 1, 1)
    box_b = [b[None, :, k, None] for k in (0, 1, 3, 4, 6)]  # (1, M, 1)
    b_in_a = _in_box2d(*box_a, cb[None, :, :4, 0], cb[None, :, :4, 1])  # (N, M, 4)
    a_in_b = _in_box2d(*box_b, ca[:, None, :4, 0], ca[:, None, :4, 1])
    # "check corners": for each k, b's corner k (if in a), then a's corner k (if in b)
    corners = np.stack([np.broadcast_to(cb[None, :, :4], (n, m, 4, 2)),
                        np.broadcast_to(ca[:, None, :4], (n, m, 4, 2))], axis=3).reshape(n, m, 8, 2)
    found = np.concatenate([crossing_found, np.stack([b_in_a, a_in_b], axis=3).reshape(n, m, 8)], axis=2)
    points = np.where(found[..., None], np.concatenate([crossings, corners], axis=2), np.float32(0))
    count = found.sum(axis=2)
    centre = points.sum(axis=2) / np.maximum(count, 1)[..., None].astype(np.float32)
    # the bubble sort by atan2 about the centre is a stable ascending sort; unfound points last
    angle = np.arctan2(points[..., 1] - centre[..., None, 1], points[..., 0] - centre[..., None, 0])
    order = np.argsort(np.where(found, angle, np.float32(np.inf)), axis=2, kind="stable")
    ring = np.take_along_axis(points, order[..., None], axis=2)
    d = ring - ring[:, :, :1]
    fan = d[..., :-1, 0] * d[..., 1:, 1] - d[..., :-1, 1] * d[..., 1:, 0]  # cross(p_k - p_0, p_k+1 - p_0)
    fan = np.where(np.arange(1, points.shape[2]) < count[..., None], fan, np.float32(0))
    return np.abs(fan.sum(axis=2)) / 2


def bev_iou(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """(N, M) float32 bird's-eye IoU of (N, >= 7) and (M, >= 7) centre boxes, as
    iou3d_cpu.cpp's boxes_iou_bev_cpu: its polygon clipping (edge crossings plus corners
    within the other box + 1 cm, fan area about the first angle-sorted point) in float32,
    overlap / max(area_a + area_b - overlap, 1e-8). The margin makes footprints less than
    1 cm apart overlap a little."""
    a = np.asarray(boxes_a, np.float32).reshape(-1, np.shape(boxes_a)[-1])[:, :7]
    b = np.asarray(boxes_b, np.float32).reshape(-1, np.shape(boxes_b)[-1])[:, :7]
    overlap = np.zeros((len(a), len(b)), np.float32)
    step = max(1, 4096 // max(len(b), 1))  # pairs per chunk bound the (N, M, 24, 2) temporaries
    for start in range(0, len(a), step):
        overlap[start:start + step] = _overlap(a[start:start + step], b)
    union = (a[:, 3] * a[:, 4])[:, None] + (b[:, 3] * b[:, 4])[None, :] - overlap
    return overlap / np.maximum(union, EPS)


def points_in_boxes(boxes: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N boxes, M points) int32 0/1: roiaware_pool3d.cpp's check_pt_in_box3d_cpu in float32."""
    boxes, points = np.asarray(boxes, np.float32), np.asarray(points, np.float32)
    margin = np.float32(1e-2)
    shift = points[None, :, :2] - boxes[:, None, :2]
    cos, sin = np.cos(-boxes[:, 6:7]), np.sin(-boxes[:, 6:7])
    local_x = shift[..., 0] * cos - shift[..., 1] * sin
    local_y = shift[..., 0] * sin + shift[..., 1] * cos
    inside = (np.abs(points[None, :, 2] - boxes[:, 2:3]) <= boxes[:, 5:6] / 2) \
        & (np.abs(local_x) < boxes[:, 3:4] / 2 + margin) & (np.abs(local_y) < boxes[:, 4:5] / 2 + margin)
    return inside.astype(np.int32)


def _extension_modules() -> dict:
    """The two compiled modules as Python: same function names and output tensors."""
    import torch

    def boxes_iou_bev_cpu(boxes_a, boxes_b, ans_iou):
        ans_iou.copy_(torch.from_numpy(bev_iou(boxes_a.numpy(), boxes_b.numpy())))
        return 1

    def points_in_boxes_cpu(boxes, pts, pts_indices):
        pts_indices.copy_(torch.from_numpy(points_in_boxes(boxes.numpy(), pts.numpy())))
        return 1

    iou = types.ModuleType("pcdet.ops.iou3d_nms.iou3d_nms_cuda")
    iou.boxes_iou_bev_cpu = boxes_iou_bev_cpu
    pool = types.ModuleType("pcdet.ops.roiaware_pool3d.roiaware_pool3d_cuda")
    pool.points_in_boxes_cpu = points_in_boxes_cpu
    return {iou.__name__: iou, pool.__name__: pool, "SharedArray": types.ModuleType("SharedArray")}


@cache
def load_pcdet(workdir: Path) -> types.ModuleType:
    """Import OpenPCDet from a copy in ``workdir`` (see the module docstring for what
    the copy adds); returns the ``pcdet`` package. Once per process."""
    copy = Path(workdir) / "OpenPCDet"
    shutil.copytree(SOURCE, copy, dirs_exist_ok=True)
    (copy / "pcdet" / "datasets" / "__init__.py").write_text("")
    (copy / "pcdet" / "version.py").write_text('__version__ = "0.6.0"\n')
    sys.modules.update(_extension_modules())
    sys.path.insert(0, str(copy))
    import pcdet.datasets.augmentor.database_sampler  # noqa: F401
    import pcdet.utils.box_utils  # noqa: F401
    import pcdet.utils.calibration_kitti  # noqa: F401
    import pcdet.utils.object3d_kitti  # noqa: F401

    return sys.modules["pcdet"]


# --- configs ------------------------------------------------------------------------


def read_config(path: Path):
    """An OpenPCDet YAML config as pcdet/config.py's cfg_from_yaml_file reads it:
    EasyDict, ``_BASE_CONFIG_`` (relative to tools/) merged first, then the file's keys."""
    import yaml
    from easydict import EasyDict

    def merge(config, new):
        if "_BASE_CONFIG_" in new:
            config.update(EasyDict(yaml.safe_load((SOURCE / "tools" / new["_BASE_CONFIG_"]).read_text())))
        for key, value in new.items():
            if not isinstance(value, dict):
                config[key] = value
                continue
            if key not in config:
                config[key] = EasyDict()
            merge(config[key], value)
        return config

    return merge(EasyDict(), yaml.safe_load(Path(path).read_text()))


def gt_sampling(config) -> dict:
    """The gt_sampling entry of a config's DATA_AUGMENTOR (dataset or model config)."""
    augmentor = config.DATA_CONFIG.DATA_AUGMENTOR if "DATA_CONFIG" in config else config.DATA_AUGMENTOR
    return next(entry for entry in augmentor.AUG_CONFIG_LIST if entry.NAME == "gt_sampling")


def build_sampler(pcdet, root: Path, sampler_config, class_names: list):
    """OpenPCDet's DataBaseSampler as DataAugmentor.gt_sampling builds it."""
    from pcdet.datasets.augmentor.database_sampler import DataBaseSampler

    return DataBaseSampler(root_path=Path(root), sampler_cfg=sampler_config, class_names=class_names,
                           logger=logging.getLogger("openpcdet"))


# --- real scenes as the datasets hand them over -------------------------------------


def kitti_scene(frame_folder: Path, frame: str, class_names: list) -> dict:
    """A KITTI training frame as KittiDataset.__getitem__ gives it to the augmentor:
    FOV points (FOV_POINTS_ONLY), label boxes in the LiDAR frame less DontCare, calib and
    the road plane. KITTI ships planes/*.txt, not shared here: the plane is fitted to
    the scan's ground (``fit_road_plane``)."""
    from pcdet.utils import box_utils, calibration_kitti, object3d_kitti

    calib = calibration_kitti.Calibration(frame_folder / "calib" / f"{frame}.txt")
    points = np.fromfile(frame_folder / "velodyne" / f"{frame}.bin", np.float32).reshape(-1, 4)
    objects = [obj for obj in object3d_kitti.get_objects_from_label(frame_folder / "label_2" / f"{frame}.txt")
               if obj.cls_type != "DontCare"]
    camera_boxes = np.array([[*obj.loc, obj.l, obj.h, obj.w, obj.ry] for obj in objects], np.float32)
    names = np.array([obj.cls_type for obj in objects])
    return {"points": points[fov_flag(points, calib)], "frame_id": frame, "calib": calib,
            "gt_boxes": box_utils.boxes3d_kitti_camera_to_lidar(camera_boxes.reshape(-1, 7), calib),
            "gt_names": names, "gt_boxes_mask": np.array([n in class_names for n in names], np.bool_),
            "road_plane": fit_road_plane(points, calib)}


def fov_flag(points: np.ndarray, calib) -> np.ndarray:
    """KittiDataset.get_fov_flag: points that project into camera 2's image, in front."""
    rect = calib.lidar_to_rect(points[:, :3])
    image, depth = calib.rect_to_img(rect)
    return (image[:, 0] >= 0) & (image[:, 0] < KITTI_IMAGE_SHAPE[1]) & (image[:, 1] >= 0) \
        & (image[:, 1] < KITTI_IMAGE_SHAPE[0]) & (depth >= 0)


def fit_road_plane(points: np.ndarray, calib, seed: int = 0) -> np.ndarray:
    """(4,) [a, b, c, d] of a*x + b*y + c*z + d = 0 in the rectified camera frame, unit
    normal facing up (b < 0), as KittiDataset.get_road_plane returns planes/*.txt: a
    seeded RANSAC (5 cm) over returns 2..40 m ahead below the sensor, refined by least
    squares on its inliers."""
    near = points[(points[:, 0] > 2) & (points[:, 0] < 40) & (np.abs(points[:, 1]) < 15) & (points[:, 2] < -1.0)]
    rect = calib.lidar_to_rect(near[:, :3]).astype(np.float64)
    rng = np.random.default_rng(seed)
    best = None
    for _ in range(200):
        sample = rect[rng.choice(len(rect), 3, replace=False)]
        normal = np.cross(sample[1] - sample[0], sample[2] - sample[0])
        if np.linalg.norm(normal) < 1e-9:
            continue
        normal /= np.linalg.norm(normal)
        inliers = np.abs((rect - sample[0]) @ normal) < 0.05
        if best is None or inliers.sum() > best.sum():
            best = inliers
    centre = rect[best].mean(axis=0)
    normal = np.linalg.svd(rect[best] - centre)[2][-1]
    plane = np.append(normal, -normal @ centre)
    return -plane if plane[1] > 0 else plane


def nuscenes_boxes(instances: list) -> np.ndarray:
    """(N, 9) float64 OpenPCDet boxes [x, y, z, dx, dy, dz, heading, vx, vy] from the shared
    nus_info.pkl's instances. Their bbox_3d is mmdet3d's pre-1.0 LiDAR convention
    [x, y, z_centre, w, l, h, yaw_old] with yaw_old = -heading - pi/2 (the file's headings
    agree with the velocity directions only that way; its car boxes' bottoms z - h/2 lie on
    the ground about 1.84 m under the sensor, so z is the gravity centre, as OpenPCDet wants)."""
    box = np.array([obj["bbox_3d"] for obj in instances], np.float64).reshape(-1, 7)
    velocity = np.array([obj["velocity"] for obj in instances], np.float64).reshape(-1, 2)
    heading = -box[:, 6] - np.pi / 2
    heading = (heading + np.pi) % (2 * np.pi) - np.pi
    return np.column_stack([box[:, :3], box[:, 4], box[:, 3], box[:, 5], heading, velocity])


def nuscenes_scene(sample_folder: Path, index: int = 0, class_names: list = CLASS_NAMES["nuscenes"]) -> dict:
    """A nuScenes sample as NuScenesDataset.__getitem__ gives it (key frame only, as the
    shared sample has no sweep list): points x y z intensity time_lag (0), boxes with
    at least one LiDAR point (FILTER_MIN_POINTS_IN_GT: 1), velocity NaN -> 0."""
    infos = pickle.loads((sample_folder / "nus_info.pkl").read_bytes())
    classes, sample = infos["metainfo"]["CLASSES"], infos["data_list"][index]
    raw = np.fromfile(sample_folder / "samples" / "LIDAR_TOP" / sample["lidar_points"]["lidar_path"], np.float32)
    points = raw.reshape(-1, 5).copy()
    points[:, 4] = 0.0  # the ring column becomes the key frame's time lag
    kept = [obj for obj in sample["instances"] if obj["num_lidar_pts"] > 0 and obj["bbox_label_3d"] >= 0]
    boxes = nuscenes_boxes(kept).astype(np.float32)
    boxes[np.isnan(boxes)] = 0.0
    names = np.array([classes[obj["bbox_label_3d"]] for obj in kept])
    return {"points": points, "gt_boxes": boxes, "gt_names": names,
            "gt_boxes_mask": np.array([n in class_names for n in names], np.bool_)}


# nuScenes names as Lyft's (no barrier or traffic cone in Lyft).
LYFT_FROM_NUSCENES = {"car": "car", "truck": "truck", "bus": "bus", "trailer": "other_vehicle",
                      "construction_vehicle": "other_vehicle", "bicycle": "bicycle", "motorcycle": "motorcycle",
                      "pedestrian": "pedestrian"}


def lyft_scene(sample_folder: Path) -> dict:
    """No Lyft scan is shared: the real nuScenes sample stands in, its classes renamed
    to Lyft's (same 5 columns; barriers and cones have no Lyft class and are dropped).
    The 7-value boxes are what LyftDataset gives (no velocity)."""
    scene = nuscenes_scene(sample_folder)
    keep = np.array([name in LYFT_FROM_NUSCENES for name in scene["gt_names"]], bool)
    names = np.array([LYFT_FROM_NUSCENES[name] for name in scene["gt_names"][keep]])
    return {"points": scene["points"], "gt_boxes": scene["gt_boxes"][keep, :7], "gt_names": names,
            "gt_boxes_mask": np.ones(len(names), np.bool_)}
