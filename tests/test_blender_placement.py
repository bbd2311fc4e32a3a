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


def record_changed(change):
    """A damage: ``change(record)`` applied to boxes.json."""
    def damage(folder):
        record = json.loads((folder / "boxes.json").read_text())
        change(record)
        (folder / "boxes.json").write_text(json.dumps(record))
    return damage


def box_changed(change):
    """A damage: ``change(box)`` applied to the first inserted box of boxes.json."""
    return record_changed(lambda record: change(next(box for box in record["boxes"] if box.get("rows"))))


@pytest.mark.parametrize("damage, problem", [
    (lambda folder: (folder / "boxes.json").write_text("{"), "boxes.json: not a placement record"),
    (lambda folder: (folder / "scan.bin").write_bytes((folder / "scan.bin").read_bytes()[:-4]),
     "scan.bin: .* bytes are not whole rows of 4"),
    (lambda folder: (folder / "boxes.json").write_text(json.dumps(
        {**json.loads((folder / "boxes.json").read_text()),
         "boxes": [{"class": "Car", "box": [0, 0, 0, 1, 1, 1, 0], "rows": [0, 10 ** 9], "entry": "car.bin"}]})),
     "boxes.json: box 0: rows .* are not within the scan"),
    (box_changed(lambda box: box.pop("class")), r"boxes.json: not a placement record: box \d+: class must be a string"),
    (box_changed(lambda box: box.update(rows=[1.5, 3.5])),
     r"box \d+: rows must be two integers \[start, stop\] >= 0, got \[1.5, 3.5\]"),
    (box_changed(lambda box: box.update(object=None, entry=None)),
     r"box \d+: an inserted box needs the entry or object it came from"),
    (box_changed(lambda box: box["box"].__setitem__(2, float("nan"))),
     r"box \d+: box must be 7 or more finite numbers with positive dims"),
    (record_changed(lambda record: record.update(columns=["x", "x", "x", "x"])),
     "columns must be distinct names including x, y and z"),
    (record_changed(lambda record: record.update(scan=5)), "scan must be a string, got 5"),
    (record_changed(lambda record: record.update(dataset=["kitti"])), r"dataset must be a string, got \['kitti'\]"),
])
def test_a_damaged_placement_folder_is_refused_and_nothing_is_made(scene, placed, tmp_path, damage, problem, capsys):
    folder = shutil.copytree(placed, tmp_path / "placed")
    damage(folder)
    before = datablock_counts(bpy), len(bpy.data.collections)
    with pytest.raises(RuntimeError, match=problem):
        bpy.ops.import_scene.pgt_placed_scene(directory=str(folder))
    assert (datablock_counts(bpy), len(bpy.data.collections)) == before


def test_a_users_collection_of_the_same_name_stays(scene, placed):
    mine = bpy.data.collections.new("PGT Placed Scene")
    scene.collection.children.link(mine)
    note = bpy.data.objects.new("My note", None)
    mine.objects.link(note)
    for _ in range(2):  # the second load replaces the first, never the user's
        assert bpy.ops.import_scene.pgt_placed_scene(directory=str(placed)) == {"FINISHED"}
    assert sorted(c.name for c in bpy.data.collections) == ["PGT Placed Scene", "PGT Placed Scene.001"]
    assert list(bpy.data.collections["PGT Placed Scene"].objects) == [note]


def test_what_the_user_copied_from_a_placement_stays(scene, placed):
    """A Shift+D copy of a loaded object and a duplicated, renamed collection are the
    user's: the next load replaces only what the last one made."""
    assert bpy.ops.import_scene.pgt_placed_scene(directory=str(placed)) == {"FINISHED"}
    loaded = bpy.data.collections["PGT Placed Scene"]
    kept = loaded.objects[0].copy()
    loaded.objects.link(kept)  # Shift+D puts the copy beside the original
    mine = loaded.copy()  # Duplicate Collection: the tags come along, the objects are copies
    for obj in list(mine.objects):
        mine.objects.unlink(obj)
        mine.objects.link(obj.copy())
    mine.name = "My placement"
    scene.collection.children.link(mine)
    count = len(mine.objects)
    assert bpy.ops.import_scene.pgt_placed_scene(directory=str(placed)) == {"FINISHED"}
    assert kept.name in scene.collection.objects and kept.name not in bpy.data.collections["PGT Placed Scene"].objects
    assert bpy.data.collections.get("My placement") == mine and len(mine.objects) == count


def test_the_users_own_objects_linked_into_a_placement_stay(scene, placed):
    """An object the user made and linked into the placement's collection (alone, or also
    in the scene's own) is theirs: the next load keeps it."""
    assert bpy.ops.import_scene.pgt_placed_scene(directory=str(placed)) == {"FINISHED"}
    loaded = bpy.data.collections["PGT Placed Scene"]
    marker, car = bpy.data.objects.new("my marker", None), bpy.data.objects.new("my car", None)
    loaded.objects.link(marker)
    scene.collection.objects.link(car)
    loaded.objects.link(car)
    assert bpy.ops.import_scene.pgt_placed_scene(directory=str(placed)) == {"FINISHED"}
    assert {"my marker", "my car"} <= set(scene.collection.objects.keys())


def test_an_inserted_object_with_no_points_loads_empty(scene, placed, tmp_path):
    folder = shutil.copytree(placed, tmp_path / "placed")
    box_changed(lambda box: box.update(rows=[box["rows"][0], box["rows"][0]]))(folder)
    assert bpy.ops.import_scene.pgt_placed_scene(directory=str(folder)) == {"FINISHED"}
    assert sorted(len(obj.data.vertices) for obj in bpy.data.collections["PGT Placed Scene"].objects
                  if obj.type == "MESH")[0] == 0
