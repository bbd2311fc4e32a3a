"""The "real" ground-truth databases the detector tests put beside a bank, written the
way the frameworks' database builders write theirs.

- KITTI: the real one, from the shared KITTI frames (labels, calib, full scans), as
  OpenPCDet's ``KittiDataset.create_groundtruth_database`` builds it: every labelled
  box but DontCare, its points (OpenPCDet's points-in-box test), KITTI difficulty from
  the label (OpenPCDet's ``Object3d.level``), ``bbox``, ``score``.
- nuScenes and Lyft: no real database is shared (the full ones are gigabytes), so a
  labelled stand-in: ``STANDIN_ENTRIES`` boxes per class of the dataset's mean size at
  seeded positions, each with ``STANDIN_POINTS`` seeded points inside it (Lyft:
  intensity 100, as its files).

Layouts (both frameworks): ``{class: [info]}``, paths relative to the dataset root.
OpenPCDet: centre boxes, points relative to the box centre. mmdet3d: bottom-centre
boxes and points, ``group_id``. Columns: KITTI 4, nuScenes and Lyft 5 (time lag 0).
"""

import pickle
from pathlib import Path

import numpy as np

from pgt_blender.core.classes import CLASS_SIZES

STANDIN_ENTRIES, STANDIN_POINTS = 3, 40
COLUMNS = {"kitti": 4, "nuscenes": 5, "lyft": 5}


def _write(root: Path, pickle_name: str, folder: str, fmt: str, entries: list) -> Path:
    """Write ``entries`` = [(name, centre box (7 or 9,), points (N, C) sensor frame, extra
    info keys)] as a database under ``root``; returns the pickle path."""
    infos, database = {}, root / folder
    database.mkdir(parents=True, exist_ok=True)
    for index, (name, box, points, extra) in enumerate(entries):
        origin = np.asarray(box[:3], np.float64).copy()
        if fmt == "mmdet3d":
            origin[2] -= box[5] / 2
        stored = np.asarray(box, np.float32).copy()
        stored[2] = origin[2]
        rows = np.asarray(points, np.float32).copy()
        rows[:, :3] -= origin
        path = database / f"{index}_{name}_{index}.bin"
        rows.tofile(path)
        info = {"name": name, "path": path.relative_to(root).as_posix(), "image_idx": index, "gt_idx": index,
                "box3d_lidar": stored, "num_points_in_gt": len(rows), **extra}
        if fmt == "mmdet3d":
            info["group_id"] = index
        infos.setdefault(name, []).append(info)
    out = root / pickle_name
    out.write_bytes(pickle.dumps(infos))
    return out


def kitti_database(pcdet, frames_folder: Path, root: Path, pickle_name: str, folder: str, fmt: str) -> Path:
    """The real KITTI database of the shared frames (see the module docstring)."""
    from pcdet.ops.roiaware_pool3d import roiaware_pool3d_utils
    from pcdet.utils import box_utils, calibration_kitti, object3d_kitti

    entries = []
    for label in sorted((frames_folder / "label_2").glob("*.txt")):
        frame = label.stem
        calib = calibration_kitti.Calibration(frames_folder / "calib" / f"{frame}.txt")
        points = np.fromfile(frames_folder / "velodyne" / f"{frame}.bin", np.float32).reshape(-1, 4)
        objects = [obj for obj in object3d_kitti.get_objects_from_label(label) if obj.cls_type != "DontCare"]
        camera = np.array([[*obj.loc, obj.l, obj.h, obj.w, obj.ry] for obj in objects], np.float32)
        boxes = box_utils.boxes3d_kitti_camera_to_lidar(camera, calib)
        inside = roiaware_pool3d_utils.points_in_boxes_cpu(points[:, :3], boxes)
        for obj, box, mask in zip(objects, boxes, inside):
            extra = {"difficulty": obj.level, "bbox": obj.box2d, "score": obj.score} if fmt == "openpcdet" \
                else {"difficulty": obj.level}
            entries.append((obj.cls_type, box, points[mask > 0], extra))
    return _write(root, pickle_name, folder, fmt, entries)


def standin_database(dataset: str, classes: list, root: Path, pickle_name: str, folder: str, fmt: str,
                     seed: int = 0) -> Path:
    """A labelled stand-in database for ``classes`` of nuScenes or Lyft (module docstring)."""
    rng = np.random.default_rng(seed)
    mounting = {"nuscenes": 1.84, "lyft": 1.8}[dataset]
    entries = []
    for name in classes:
        dims = np.array(CLASS_SIZES[dataset][name])
        for _ in range(STANDIN_ENTRIES):
            centre = [*rng.uniform(-40, 40, 2), -mounting + dims[2] / 2]
            box = [*centre, *dims, rng.uniform(-np.pi, np.pi)] + ([0.0, 0.0] if dataset == "nuscenes" else [])
            local = rng.uniform(-0.45, 0.45, (STANDIN_POINTS, 3)) * dims
            cos, sin = np.cos(box[6]), np.sin(box[6])
            xyz = np.column_stack([local[:, 0] * cos - local[:, 1] * sin, local[:, 0] * sin + local[:, 1] * cos,
                                   local[:, 2]]) + centre
            intensity = np.full(STANDIN_POINTS, 100) if dataset == "lyft" else rng.integers(0, 256, STANDIN_POINTS)
            points = np.column_stack([xyz, intensity, np.zeros(STANDIN_POINTS)])
            entries.append((name, np.array(box), points, {"difficulty": 0} if fmt == "mmdet3d" else {}))
    return _write(root, pickle_name, folder, fmt, entries)
