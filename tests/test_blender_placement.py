"""The placed-scene import: a placement folder (place_objects.py) as Blender objects,
each point exactly as scan.bin holds it, each box where boxes.json puts it; a damaged
folder leaves the scene as it was."""

import json
import shutil

import numpy as np
import pytest

from pgt_blender.commands.place_objects import main as place_objects
from pgt_blender.core.placement.folder import read_placement

from .conftest import datablock_counts

bpy = pytest.importorskip("bpy")


@pytest.fixture(scope="module")
def placed(tmp_path_factory, shared_data):
    """KITTI frame 000001 with three pedestrians of the real mmdet3d KITTI database."""
    out = tmp_path_factory.mktemp("placed")
    frame = shared_data / "kitti_scans"
    assert place_objects(["--scan", str(frame / "velodyne" / "000001.bin"), "--info", str(frame / "label_2" / "000001.txt"),
                          "--bank", str(shared_data / "mmdet3d_kitti_gtdb" / "kitti_dbinfos_train.pkl"),
                          "--convention", "mmdet3d", "--objects", "Pedestrian=3", "--out", str(out)]) == 0
    return out


def vertices(obj) -> np.ndarray:
    positions = np.zeros(3 * len(obj.data.vertices), np.float32)
    obj.data.attributes["position"].data.foreach_get("vector", positions)
    return positions.reshape(-1, 3)


def test_the_placed_scene_loads_as_its_points_and_boxes(scene, placed):
    points, record = read_placement(placed)
    assert bpy.ops.import_scene.pgt_placed_scene(directory=str(placed)) == {"FINISHED"}
    collection = bpy.data.collections["PGT Placed Scene"]
    meshes = [obj for obj in collection.objects if obj.type == "MESH"]
    inserted = [box for box in record["boxes"] if box["inserted"]]
    assert len(inserted) == 3 and len(meshes) == 1 + len(inserted)
    scene_points = next(obj for obj in meshes if obj.name.startswith("000001 scene"))
    np.testing.assert_array_equal(vertices(scene_points), points[inserted[-1]["rows"][1]:, :3])
    intensity = np.zeros(len(scene_points.data.vertices), np.float32)
    scene_points.data.attributes["intensity"].data.foreach_get("value", intensity)
    np.testing.assert_array_equal(intensity, points[inserted[-1]["rows"][1]:, 3])
    for index, box in enumerate(inserted):
        obj = next(o for o in meshes if o.name.startswith(f"Pedestrian {index} "))
        start, stop = box["rows"]
        np.testing.assert_array_equal(vertices(obj), points[start:stop, :3])
        cube = collection.objects[f"{obj.name} box"]
        np.testing.assert_allclose(cube.location, box["box"][:3], atol=1e-6)
        np.testing.assert_allclose(cube.scale, np.array(box["box"][3:6]) / 2, atol=1e-6)
        assert cube.rotation_euler.z == pytest.approx(box["box"][6], abs=1e-6)
    assert sum(1 for obj in collection.objects if obj.type == "EMPTY") == len(record["boxes"])
    count = len(collection.objects)
    assert bpy.ops.import_scene.pgt_placed_scene(directory=str(placed)) == {"FINISHED"}  # replaces, not adds
    assert [c.name for c in bpy.data.collections] == ["PGT Placed Scene"]
    assert len(bpy.data.collections["PGT Placed Scene"].objects) == count == len(bpy.data.objects)


@pytest.mark.parametrize("damage, problem", [
    (lambda folder: (folder / "boxes.json").write_text("{"), "boxes.json: not a placement record"),
    (lambda folder: (folder / "scan.bin").write_bytes((folder / "scan.bin").read_bytes()[:-4]),
     "scan.bin: .* bytes are not whole rows of 4"),
    (lambda folder: (folder / "boxes.json").write_text(json.dumps(
        {**json.loads((folder / "boxes.json").read_text()),
         "boxes": [{"class": "Car", "box": [0, 0, 0, 1, 1, 1, 0], "rows": [0, 10 ** 9]}]})),
     "boxes.json: box 0: rows .* are not within the scan"),
])
def test_a_damaged_placement_folder_is_refused_and_nothing_is_made(scene, placed, tmp_path, damage, problem, capsys):
    folder = shutil.copytree(placed, tmp_path / "placed")
    damage(folder)
    before = datablock_counts(bpy), len(bpy.data.collections)
    with pytest.raises(RuntimeError, match=problem):
        bpy.ops.import_scene.pgt_placed_scene(directory=str(folder))
    assert (datablock_counts(bpy), len(bpy.data.collections)) == before
