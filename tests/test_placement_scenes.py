"""Scenes for the placement read the same from every description of one frame: the KITTI
label file, an OpenPCDet KITTI info pickle and an mmdetection3d KITTI info pickle (camera
boxes and lidar2cam as their converters write them), all built here from the shared
frame's own label and calib; a nuScenes-style OpenPCDet info keeps its boxes and pose."""

import pickle

import numpy as np
import pytest

from pgt_blender.core.errors import InputError
from pgt_blender.core.intensity.objects import _read_calibration
from pgt_blender.core.placement.scenes import read_scene

FRAME = "000001"


def label_rows(shared_data) -> list:
    """(type, h, w, l, x, y, z, ry) of the frame's label lines, DontCare left out."""
    lines = (shared_data / "kitti_scans" / "label_2" / f"{FRAME}.txt").read_text().splitlines()
    return [(f[0], *map(float, f[8:15])) for f in (line.split() for line in lines) if f and f[0] != "DontCare"]


def test_kitti_infos_of_both_frameworks_give_the_label_files_boxes(shared_data, tmp_path):
    folder = shared_data / "kitti_scans"
    scan = folder / "velodyne" / f"{FRAME}.bin"
    from_label = read_scene(scan, folder / "label_2" / f"{FRAME}.txt")
    rows = label_rows(shared_data)
    names = [row[0] for row in rows]
    # OpenPCDet (kitti_dataset.get_infos): annos.name with DontCare, gt_boxes_lidar without
    openpcdet = [{"point_cloud": {"num_features": 4, "lidar_idx": "000000"}, "annos": {"name": np.array(["Car"])}},
                 {"point_cloud": {"num_features": 4, "lidar_idx": FRAME},
                  "annos": {"name": np.array(names + ["DontCare"]), "gt_boxes_lidar": from_label.boxes.copy()}}]
    (tmp_path / "kitti_infos_train.pkl").write_bytes(pickle.dumps(openpcdet))
    # mmdetection3d 1.x (update_infos_to_v2): bbox_3d = x y z l h w ry in camera 2's rectified frame
    lidar2cam = _read_calibration(folder / "calib" / f"{FRAME}.txt")
    instances = [{"bbox_3d": [x, y, z, l, h, w, ry], "bbox_label_3d": ["Pedestrian", "Cyclist", "Car", "Truck",
                                                                     "Misc"].index(kind)}
                 for kind, h, w, l, x, y, z, ry in rows]
    mmdet3d = {"metainfo": {"categories": {"Pedestrian": 0, "Cyclist": 1, "Car": 2, "Truck": 3, "Misc": 4},
                            "dataset": "kitti", "info_version": "1.1"},
               "data_list": [{"lidar_points": {"lidar_path": f"{FRAME}.bin", "num_pts_feats": 4},
                              "images": {"CAM2": {"lidar2cam": lidar2cam.tolist()}}, "instances": instances}]}
    (tmp_path / "kitti_infos_v2.pkl").write_bytes(pickle.dumps(mmdet3d))
    for info in ("kitti_infos_train.pkl", "kitti_infos_v2.pkl"):
        scene = read_scene(scan, tmp_path / info)
        assert scene.dataset == "kitti" and scene.names.tolist() == from_label.names.tolist()
        np.testing.assert_allclose(scene.boxes, from_label.boxes, atol=1e-9)
        np.testing.assert_array_equal(scene.points, from_label.points)
        np.testing.assert_array_equal(scene.lidar_to_world, np.eye(4))


@pytest.mark.parametrize("sample", [
    {"lidar_points": {"lidar_path": f"{FRAME}.bin"}, "instances": [None]},
    {"lidar_points": {"lidar_path": f"{FRAME}.bin"}, "instances": [{"bbox_label_3d": 0, "bbox_3d": "big"}]},
    {"lidar_points": {"lidar_path": f"{FRAME}.bin"}, "images": {"CAM2": {"lidar2cam": np.zeros((4, 4)).tolist()}},
     "instances": [{"bbox_label_3d": 0, "bbox_3d": [0, 0, 0, 1, 1, 1, 0]}]},
])
def test_an_info_sample_of_other_types_is_named_not_a_traceback(shared_data, tmp_path, sample):
    data = {"metainfo": {"categories": {"Car": 0}, "dataset": "kitti"}, "data_list": [sample]}
    (tmp_path / "infos.pkl").write_bytes(pickle.dumps(data))
    with pytest.raises(InputError, match="infos.pkl: the scan's sample is not a usable info"):
        read_scene(shared_data / "kitti_scans" / "velodyne" / f"{FRAME}.bin", tmp_path / "infos.pkl")


def test_a_scan_with_nan_points_is_named(shared_data, tmp_path):
    folder = shared_data / "kitti_scans"
    points = np.fromfile(folder / "velodyne" / f"{FRAME}.bin", np.float32)
    points[:40] = np.nan
    (tmp_path / f"{FRAME}.bin").write_bytes(points.tobytes())
    with pytest.raises(InputError, match=f"{FRAME}.bin: 40 of {points.size} float32 point columns .* are NaN or Inf"):
        read_scene(tmp_path / f"{FRAME}.bin", folder / "label_2" / f"{FRAME}.txt")


def test_a_nuscenes_openpcdet_info_keeps_its_boxes_and_pose(shared_data, tmp_path):
    folder = shared_data / "nuscenes_format_sample"
    scan = folder / "samples" / "LIDAR_TOP" / "n015-2018-08-02-17-16-37+0800__LIDAR_TOP__1533201470948018.pcd.bin"
    reference = read_scene(scan, folder / "nus_info.pkl")
    raw = np.fromfile(scan, np.float32).reshape(-1, 5)
    assert np.unique(raw[:, 4]).size > 1  # the file's fifth column is the ring index ...
    np.testing.assert_array_equal(reference.points[:, :4], raw[:, :4])
    assert not reference.points[:, 4].any()  # ... and the key frame's time lag, 0, in the scene
    car_from_global, ref_from_car = np.eye(4), np.eye(4)
    car_from_global[:3, 3] = [-100.0, -200.0, 0.0]
    ref_from_car[:3, 3] = [-0.9, 0.0, -1.84]
    infos = [{"lidar_path": f"samples/LIDAR_TOP/{scan.name}", "gt_boxes": reference.boxes, "gt_names": reference.names,
              "car_from_global": car_from_global, "ref_from_car": ref_from_car, "token": "t"}]
    (tmp_path / "nuscenes_infos_10sweeps_train.pkl").write_bytes(pickle.dumps(infos))
    scene = read_scene(scan, tmp_path / "nuscenes_infos_10sweeps_train.pkl")
    np.testing.assert_array_equal(scene.boxes, reference.boxes)
    np.testing.assert_allclose(scene.lidar_to_world[:3, 3], [100.9, 200.0, 1.84])
    with pytest.raises(InputError, match="no sample of this info pickle is the scan other.bin"):
        other = tmp_path / "other.bin"
        other.write_bytes(scan.read_bytes())
        read_scene(other, tmp_path / "nuscenes_infos_10sweeps_train.pkl")
