"""The intensity estimator's data: real objects from KITTI scans and GT databases, RGB
objects from scans of colored vehicles, farthest point sampling, class pairing."""

import pickle

import numpy as np
import pytest

from pgt_blender.core.errors import InputError
from pgt_blender.core.intensity.objects import (LidarObject, builtin_rgb_objects, farthest_point_sample,
                                                gt_database_objects, kitti_label_boxes, kitti_scan_objects,
                                                object_set, paired_classes, real_objects, training_sets)
from pgt_blender.core.scan.sensors import PRESETS


@pytest.fixture(scope="module")
def kitti(shared_data):
    return shared_data / "kitti_scans"


@pytest.fixture(scope="module")
def gt_database(shared_data):
    return shared_data / "mmdet3d_kitti_gtdb" / "kitti_dbinfos_train.pkl"


def test_kitti_crops_equal_the_mmdet3d_database_object(kitti, gt_database):
    crops = {obj.name: obj for obj in kitti_scan_objects(kitti)}
    assert {"000000:0:Pedestrian", "000001:0:Truck", "000002:1:Car"} <= set(crops)
    pedestrian = crops["000000:0:Pedestrian"]
    (stored,) = gt_database_objects(gt_database, "mmdet3d", "kitti")
    assert stored.class_name == pedestrian.class_name == "pedestrian"
    assert len(stored.points) == len(pedestrian.points) == 377
    order = np.lexsort(pedestrian.points.T), np.lexsort(stored.points.T)
    assert np.abs(pedestrian.points[order[0]] - stored.points[order[1]]).max() < 1e-5
    assert np.array_equal(pedestrian.values[order[0]], stored.values[order[1]])
    assert 0 <= pedestrian.values.min() and pedestrian.values.max() <= 1


def test_kitti_label_boxes_match_the_database_box(kitti, gt_database):
    kind, centre, dims, heading = kitti_label_boxes(kitti / "label_2" / "000000.txt", kitti / "calib" / "000000.txt")[0]
    info = pickle.loads(gt_database.read_bytes())["Pedestrian"][0]
    box = np.asarray(info["box3d_lidar"], np.float64)  # mmdet3d: bottom centre
    assert kind == "Pedestrian" and np.allclose(dims, box[3:6], atol=1e-6)
    # box3d_lidar's x is 1.4 mm off the centre its points were stored about (they equal
    # our crop to 1e-5 m, test above): the database's own rounding.
    assert np.allclose(centre, box[:3] + [0, 0, box[5] / 2], atol=2e-3)
    assert np.isclose(np.cos(heading - box[6]), 1.0, atol=1e-9)


def _label_line(change):
    def damage(label, calib):
        fields = label.read_text().splitlines()[0].split()
        change(fields)
        label.write_text(" ".join(fields) + "\n")
    return damage


def _calib_line(key, numbers):
    def damage(label, calib):
        calib.write_text("\n".join(f"{key}: {numbers}" if line.startswith(key + ":") else line
                                   for line in calib.read_text().splitlines()) + "\n")
    return damage


@pytest.mark.parametrize("damage, named, problem", [
    (_label_line(lambda f: f.__setitem__(8, "nan")), "label", "line 1: the box must be finite numbers"),
    (_label_line(lambda f: f.__setitem__(9, "-1.5")), "label", "line 1: the box must be finite numbers with positive"),
    (_label_line(lambda f: f.__setitem__(11, "1e200")), "label",  # fit_ground's neighbour search overflowed
     "line 1: the box must be finite numbers with positive dimensions, within 1e+08 m"),
    (lambda label, calib: label.write_bytes(b"Car \xff\xfe 0 0\n"), "label", "not a readable text file"),
    (lambda label, calib: calib.write_bytes(b"R0_rect: \xff\n"), "calib", "not a readable text file"),
    (_calib_line("R0_rect", "abc"), "calib", "not a KITTI calib file"),
    (_calib_line("R0_rect", " ".join(["0"] * 9)), "calib", "not a finite, invertible transform"),
    (_calib_line("Tr_velo_to_cam", " ".join(["1e308"] * 12)), "calib", "not a finite, invertible transform"),
])
def test_damaged_kitti_labels_and_calibs_name_the_file(kitti, tmp_path, damage, named, problem):
    label, calib = tmp_path / "label.txt", tmp_path / "calib.txt"
    label.write_bytes((kitti / "label_2" / "000000.txt").read_bytes())
    calib.write_bytes((kitti / "calib" / "000000.txt").read_bytes())
    damage(label, calib)
    with pytest.raises(InputError) as error:
        kitti_label_boxes(label, calib)
    assert error.value.path == {"label": label, "calib": calib}[named] and problem in error.value.problem


def test_farthest_point_sampling_by_hand():
    points = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [10, 0, 0], [4, 0, 0]])
    first = farthest_point_sample(points, 3, seed=0)
    start = int(first[0])
    # from any start the farthest point is an end of the line, then the other end or the middle
    assert len(set(first.tolist())) == 3 and np.array_equal(first, farthest_point_sample(points, 3, seed=0))
    expected = {0: [0, 3, 4], 1: [1, 3, 0], 2: [2, 3, 0], 3: [3, 0, 4], 4: [4, 3, 0]}[start]
    assert first.tolist() == expected
    with pytest.raises(ValueError, match="5 points are fewer than the 6"):
        farthest_point_sample(points, 6)


def test_object_sets_are_normalised_boxes_of_fixed_size():
    rng = np.random.default_rng(0)
    dims = np.array([4.0, 2.0, 1.5])
    objects = [LidarObject(f"o{i}", "car", rng.uniform(-dims / 2, dims / 2, (300 + i, 3)), dims,
                           rng.random((300 + i, 1)).astype(np.float32)) for i in range(3)]
    objects.append(LidarObject("bus", "bus", np.zeros((256, 3)), dims, np.zeros((256, 1), np.float32)))
    result = object_set(objects, ("car",), "kitti", points=256, seed=1)
    assert result.xyz.shape == (3, 256, 3) and result.values.shape == (3, 256, 1)
    assert np.abs(result.xyz).max() <= 1.0 and result.class_index.tolist() == [0, 0, 0]
    assert result.names == ["o0", "o1", "o2"]
    assert result.xyz.tobytes() == object_set(objects, ("car",), "kitti", points=256, seed=1).xyz.tobytes()


def test_rgb_objects_take_their_face_colors():
    objects = builtin_rgb_objects(PRESETS["nuscenes"], classes=["truck"])
    assert len(objects) == 12 and all(obj.class_name == "truck" for obj in objects)
    near = objects[0]
    assert len(near.points) > 256 and near.values.shape == (len(near.points), 3)
    noise = 5 * PRESETS["nuscenes"].range_noise_sigma  # scanned with the sensor's range noise
    assert np.all(np.abs(near.points) <= near.dims / 2 + noise)
    from pgt_blender.core.samples import vehicle_parts

    part_colors = np.array([part.color for part in vehicle_parts("truck")], np.float32)
    assert np.isin(near.values.view([("", np.float32)] * 3), part_colors.view([("", np.float32)] * 3)).all()


def test_too_few_objects_name_the_class_the_count_and_the_thresholds():
    dims = np.ones(3)
    real = [LidarObject("a", "car", np.zeros((300, 3)), dims, np.zeros((300, 1), np.float32)),
            LidarObject("b", "truck", np.zeros((100, 3)), dims, np.zeros((100, 1), np.float32))]
    rgb = [LidarObject("c", "car", np.zeros((300, 3)), dims, np.zeros((300, 3), np.float32)),
           LidarObject("d", "truck", np.zeros((300, 3)), dims, np.zeros((300, 3), np.float32))]
    assert paired_classes(real, rgb, 256) == ("car",)
    with pytest.raises(InputError, match=r"at least 256 points \(need 1 per class in each domain\): truck: 0 real, 1 rgb"):
        paired_classes(real, rgb, 256, classes=["car", "truck"])
    with pytest.raises(InputError, match="truck: 0 real, 1 rgb"):
        paired_classes(real[1:], rgb, 256)


def write_database(folder, columns: np.ndarray, count: int):
    (folder / "db").mkdir()
    columns.astype(np.float32).tofile(folder / "db" / "0_Car_0.bin")
    infos = {"Car": [{"name": "Car", "path": "db/0_Car_0.bin", "box3d_lidar": np.array([5, 0, 0, 4, 2, 1.5, 0.0]),
                      "num_points_in_gt": count}]}
    (folder / "dbinfos.pkl").write_bytes(pickle.dumps(infos))
    return folder / "dbinfos.pkl"


@pytest.mark.parametrize("columns, problem", [
    (np.zeros((10, 3)), "has no intensity column"),
    (np.column_stack([np.zeros((10, 3)), np.full(10, np.nan)]), "0_Car_0.bin: 10 of 40 float32 values are NaN"),
    (np.column_stack([np.zeros((10, 3)), np.full(10, 200.0)]), "outside kitti's 0..1"),
    (np.zeros(31), "do not split into the 10 points"),
])
def test_bad_databases_are_clear_errors(tmp_path, columns, problem):
    path = write_database(tmp_path, columns, 10)
    with pytest.raises(InputError, match=problem):
        gt_database_objects(path, "openpcdet", "kitti")


def test_an_object_file_of_gigabytes_is_named_unread(tmp_path):
    """A (sparse) 8 GiB object file whose info declares 10 points: named from its size,
    before numpy would read it all (18 s and 10 GB of memory)."""
    path = write_database(tmp_path, np.zeros((10, 4)), 10)
    with open(tmp_path / "db" / "0_Car_0.bin", "wb") as stream:
        stream.truncate(8 * 2**30)
    with pytest.raises(InputError, match=r"0_Car_0.bin: 2147483648 floats do not split into the 10 points its info "
                                         r"declares \(3 to 64 values each\)"):
        gt_database_objects(path, "openpcdet", "kitti")


def test_training_sets_from_the_shared_data(kitti, gt_database):
    real, rgb = training_sets([kitti, gt_database], [], "kitti", min_points=64, convention="mmdet3d")
    assert real.classes == rgb.classes == ("truck",)
    assert real.values.shape == (1, 256, 1) and rgb.values.shape[1:] == (256, 3) and len(rgb.names) >= 8
    assert real.dataset == "kitti" and abs(real.values.mean() - 0.15) < 0.02
    with pytest.raises(InputError, match=f"^{kitti}: too few objects with at least 256 points"):
        training_sets([kitti], [], "kitti")
    from pgt_blender.core.intensity.objects import paired_classes

    with pytest.raises(InputError, match=r"\(need 1 per class in each domain\): no class has any \(real: 0 objects, "
                                         r"rgb: 0 objects\)$"):
        paired_classes([], [], 256)  # the message used to end in a dangling ":"


def test_material_colors_of_a_real_mesh(chrono_meshes):
    from pgt_blender.core.intensity.objects import material_mesh_rgb_objects

    sedan = next(p for p in chrono_meshes if p.name == "sedan_chassis_vis.obj")
    with pytest.warns(UserWarning, match="zero-area faces"):
        objects = material_mesh_rgb_objects(sedan, "Car", PRESETS["kitti"])
    body = np.array([102, 6, 1], np.float32) / 255  # Material.001's Kd as trimesh reads it
    near = objects[0]
    assert near.class_name == "car" and len(near.points) > 500
    assert np.isclose(near.values, body, atol=1e-6).all(axis=1).mean() > 0.3  # mostly red paint


@pytest.mark.parametrize("dataset", ["nuscenes", "lyft"])
def test_a_kitti_folder_trains_only_a_kitti_model(kitti, dataset):
    """KITTI's 0..1 intensities would be read as 0..255 ones (every painted point then
    came out near 130 of 255): named, not trained on."""
    with pytest.raises(InputError, match=f"is a KITTI folder .*: train a {dataset} model on a {dataset} database"):
        real_objects(kitti, dataset)
    assert real_objects(kitti, "kitti")
