"""Real scenes to place objects into: a scan, its labelled boxes and its pose.

Read from the scan file (raw float32 rows: KITTI 4 columns x y z intensity, nuScenes
and Lyft 5) and one of the infos below. A nuScenes or Lyft scan is the key frame's file
that the info names, whose fifth column is the laser's ring index: it becomes the key
frame's time lag, 0, as OpenPCDet's and mmdetection3d's loaders make it, so the rows
come out in the bank's columns x y z intensity time_lag.

- a **KITTI label file** (``label_2/<frame>.txt``, its ``calib/<frame>.txt`` beside
  ``label_2``): boxes from camera 2's frame (core.boxes.kitti_camera_to_lidar);
  DontCare left out; no world pose (identity);
- an **OpenPCDet info pickle**: KITTI's (``point_cloud.lidar_idx`` names the frame,
  ``annos.gt_boxes_lidar``, DontCare left out) or nuScenes' / Lyft's (``lidar_path``,
  ``gt_boxes`` x y z dx dy dz heading [vx vy], ``gt_names``; pose
  ``inv(ref_from_car @ car_from_global)``);
- an **mmdetection3d info pickle** (``data_list``): LiDAR boxes ``instances[].bbox_3d``
  with ``bbox_label_3d`` indexing the metainfo's classes, pose
  ``ego2global @ lidar_points.lidar2ego``. Version 1.1 infos (metainfo
  ``categories``) store x y z(centre) l w h yaw; the older infos (metainfo
  ``CLASSES``, such as mmdet3d 1.0's test data) x y z(centre) w l h with
  yaw = -heading - pi/2. KITTI infos store camera boxes (``images.CAM2.lidar2cam``).

The sample is the one whose lidar file name equals the scan's. Boxes come out as
centre boxes in the scan's LiDAR frame (7 values, or 9 with velocity).
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..boxes import kitti_camera_to_lidar
from ..errors import InputError
from ..files import read_float32_rows, regular_file
from ..safe_pickle import load_pickle
from ..scan.sensors import BIN_COLUMNS

SKIPPED = ("DontCare",)


@dataclass
class Scene:
    """``points`` (N, C) float32 rows as in the scan file (columns ``BIN_COLUMNS[dataset]``),
    ``boxes`` (M, 7 or 9) centre boxes, ``names`` (M,) the dataset's class names,
    ``lidar_to_world`` (4, 4), ``dataset`` kitti / nuscenes / lyft, ``source`` the scan."""

    points: np.ndarray
    boxes: np.ndarray
    names: np.ndarray
    lidar_to_world: np.ndarray
    dataset: str
    source: Path


def read_scene(scan, info, dataset: str | None = None) -> Scene:
    """The Scene of the ``scan`` file described by ``info`` (a KITTI label file or an info
    pickle; module docstring). ``dataset`` overrides the one the info implies (Lyft
    infos look like nuScenes'). InputError naming the file at fault."""
    scan, info = regular_file(scan), regular_file(info)
    if info.suffix == ".txt":
        boxes, names, pose, implied = _kitti_label(info)
    else:
        data = load_pickle(info)
        try:  # third-party structures: any field may be missing or of another type
            if isinstance(data, dict) and isinstance(data.get("data_list"), list):
                boxes, names, pose, implied = _mmdet3d_sample(info, data, scan.name)
            elif isinstance(data, list):
                boxes, names, pose, implied = _openpcdet_sample(info, data, scan)
            else:
                raise InputError(info, "not a KITTI label file or an OpenPCDet / mmdetection3d info pickle")
        except InputError:
            raise
        except (AttributeError, KeyError, IndexError, TypeError, ValueError) as error:  # LinAlgError is a ValueError
            raise InputError(info, f"the scan's sample is not a usable info ({type(error).__name__}: "
                                   f"{error})") from None
    dataset = dataset or implied
    if dataset not in BIN_COLUMNS:
        raise InputError(info, f"unknown dataset {dataset!r} ({', '.join(BIN_COLUMNS)})")
    columns = len(BIN_COLUMNS[dataset])
    points = read_float32_rows(scan, columns, f"point columns ({', '.join(BIN_COLUMNS[dataset])})")
    if not len(points):
        raise InputError(scan, "the scan has no points")
    if dataset != "kitti":
        points[:, 4] = 0.0  # the key frame's ring index becomes its time lag
    return Scene(points, np.asarray(boxes, np.float64), np.asarray(names, str), np.asarray(pose, np.float64),
                 dataset, scan)


def frame_warning(scan, info) -> str | None:
    """A warning when ``info`` is a KITTI label file of another frame than ``scan``
    (label_2/000002.txt for velodyne/000001.bin): its boxes and calibration are then
    another scene's. An info pickle gives the scan's own sample, so it never warns."""
    scan, info = Path(scan), Path(info)
    if info.suffix != ".txt" or info.stem == scan.stem:
        return None
    return (f"{info}: the labels and calibration of frame {info.stem} are used for the scan {scan.name}; "
            f"give label_2/{scan.stem}.txt unless the scan was renamed")


def _kitti_label(label: Path) -> tuple:
    from ..intensity.objects import kitti_label_boxes

    calib = label.parent.parent / "calib" / label.name
    if not calib.is_file():
        raise InputError(label, f"no calib file {calib} beside its label_2 folder")
    labels = kitti_label_boxes(label, calib)
    boxes = np.array([[*centre, *dims, heading] for _, centre, dims, heading in labels]).reshape(-1, 7)
    return boxes, [kind for kind, *_ in labels], np.eye(4), "kitti"


def _openpcdet_sample(info: Path, infos: list, scan: Path) -> tuple:
    for sample in infos:
        if not isinstance(sample, dict):
            break
        if "point_cloud" in sample:  # KITTI
            if str(sample["point_cloud"].get("lidar_idx")) != scan.stem:
                continue
            annos = sample.get("annos") or {}
            names = np.asarray(annos.get("name", []), str)
            names = names[~np.isin(names, SKIPPED)]
            boxes = np.asarray(annos.get("gt_boxes_lidar", np.zeros((0, 7))), np.float64).reshape(-1, 7)
            return _checked(info, boxes, names), names, np.eye(4), "kitti"
        if Path(str(sample.get("lidar_path", ""))).name == scan.name:
            boxes = np.asarray(sample.get("gt_boxes", np.zeros((0, 9))), np.float64)
            names = np.asarray(sample.get("gt_names", []), str)
            pose = np.linalg.inv(np.asarray(sample["ref_from_car"]) @ np.asarray(sample["car_from_global"])) \
                if "ref_from_car" in sample and "car_from_global" in sample else np.eye(4)
            return _checked(info, np.nan_to_num(boxes.reshape(len(names), -1)), names), names, pose, "nuscenes"
    else:
        raise InputError(info, f"no sample of this info pickle is the scan {scan.name}")
    raise InputError(info, "not an OpenPCDet info pickle: expected a list of sample dicts")


def _mmdet3d_sample(info: Path, data: dict, scan_name: str) -> tuple:
    metainfo = data.get("metainfo") or {}
    classes = list(metainfo.get("categories") or metainfo.get("classes") or metainfo.get("CLASSES") or [])
    dataset = str(metainfo.get("dataset") or metainfo.get("DATASET") or "nuscenes").lower()
    for sample in data["data_list"]:
        lidar = (sample or {}).get("lidar_points") or {}
        if Path(str(lidar.get("lidar_path", ""))).name != scan_name:
            continue
        instances = [obj for obj in sample.get("instances", []) if 0 <= obj.get("bbox_label_3d", -1) < len(classes)]
        names = np.array([classes[obj["bbox_label_3d"]] for obj in instances], str)
        boxes = np.array([obj["bbox_3d"] for obj in instances], np.float64).reshape(-1, 7)
        if dataset == "kitti":
            lidar2cam = np.asarray(sample["images"]["CAM2"]["lidar2cam"], np.float64)
            boxes = kitti_camera_to_lidar(boxes, np.linalg.inv(lidar2cam))
            pose = np.eye(4)
        else:
            if "categories" not in metainfo:  # mmdet3d 1.0's infos: w l h and the old yaw
                boxes = np.column_stack([boxes[:, :3], boxes[:, 4], boxes[:, 3], boxes[:, 5],
                                         np.angle(np.exp(1j * (-boxes[:, 6] - np.pi / 2)))])
            velocity = np.array([obj.get("velocity", [0.0, 0.0]) for obj in instances], np.float64).reshape(-1, 2)
            boxes = np.column_stack([boxes, np.nan_to_num(velocity)])
            pose = np.asarray(sample.get("ego2global", np.eye(4)), np.float64) @ \
                np.asarray(lidar.get("lidar2ego", np.eye(4)), np.float64)
        return _checked(info, boxes, names), names, pose, dataset if dataset in BIN_COLUMNS else "nuscenes"
    raise InputError(info, f"no sample of this info pickle is the scan {scan_name}")


def _checked(info: Path, boxes: np.ndarray, names: np.ndarray) -> np.ndarray:
    if len(boxes) != len(names):
        raise InputError(info, f"{len(boxes)} boxes for {len(names)} names in the scan's sample")
    if not np.isfinite(boxes).all() or (len(boxes) and (boxes[:, 3:6] <= 0).any()):
        raise InputError(info, "the scan's sample has a box with non-finite values or non-positive dims")
    return boxes
