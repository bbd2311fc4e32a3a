"""The whole pipeline from the panels' operators (issue 15 must 4 and 5): a folder of
reconstructions imported, authored in one batch, exported as a bank chunk by chunk (the
modal export's step), stopped and resumed, its config saved for the command line, and
previewed; every bad input leaves the scene and the disk as they were."""

import json
import pickle
import math
from pathlib import Path

import numpy as np
import pytest

from pgt_blender.core.bank.config import BankConfig, config_toml
from pgt_blender.core.gt_database import load_infos
from pgt_blender.core.samples import write_sample

from .conftest import datablock_counts
from .test_bank import bank_bytes, run_export

bpy = pytest.importorskip("bpy")

from pgt_blender.blender import authoring, bank  # noqa: E402  (needs bpy)


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """Two built-in sample reconstructions (point PLYs) in one folder."""
    folder = tmp_path_factory.mktemp("captures")
    for name, seed in (("truck", 1), ("bus", 2)):
        write_sample(tmp_path_factory.mktemp(name), name, seed=seed, points=3000)["reconstruction.ply"].rename(
            folder / f"{name}.ply")
    return folder


def refused(operator, message: str, **arguments) -> None:
    """``operator`` reports ``message`` as an error (bpy.ops raises it) and returns CANCELLED."""
    with pytest.raises(RuntimeError, match=message):
        operator(**arguments)


def small_bank(settings, out: Path) -> None:
    """A bank of a few entries per object: nuScenes, one sweep, headings every 180 deg,
    a 25 m grid."""
    settings.output, settings.sweeps = str(out), 1
    settings.heading_step, settings.grid_step = math.radians(180.0), 25.0


def import_and_author(scene, folder: Path) -> list:
    assert bpy.ops.import_scene.pgt_folder(directory=str(folder)) == {"FINISHED"}
    chosen = [obj for obj in bpy.context.selected_objects if authoring.is_reconstruction(obj)]
    assert sorted(obj.name for obj in chosen) == ["bus", "truck"]
    settings = scene.pgt_authoring
    settings.up, settings.heading_method, settings.dataset, settings.class_name = "pca", "baseline", "nuscenes", "truck"
    assert bpy.ops.object.pgt_author_selected() == {"FINISHED"}
    assert all(all(authoring.status(obj).values()) for obj in chosen)
    return chosen


def test_folder_to_exported_and_previewed_bank(scene, folder, tmp_path):
    chosen = import_and_author(scene, folder)
    sizes = {obj.name: tuple(obj.pgt.dims) for obj in chosen}
    assert len(set(sizes.values())) == 2  # each object its own size seed (--seed + index, by name)
    settings = scene.pgt_bank
    small_bank(settings, tmp_path / "bank")
    assert bpy.ops.scene.pgt_export_bank() == {"FINISHED"}
    manifest = json.loads((tmp_path / "bank" / "manifest.json").read_text())
    assert settings.status.startswith(f"{manifest['entries']:,} entries [")  # kept, not poses
    assert (tmp_path / "bank" / "report.md").is_file()

    # the same settings as a config file give the command line the same bank
    assert bpy.ops.scene.pgt_save_bank_config(filepath=str(tmp_path / "bank.toml")) == {"FINISHED"}
    blend = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    run_export("--blend", blend, "--config", tmp_path / "bank.toml", "--out", tmp_path / "cli")
    assert bank_bytes(tmp_path / "bank") == bank_bytes(tmp_path / "cli")

    mine = bpy.data.texts.new("report.md")  # the user's own text of that name stays
    mine.write("my notes")
    for _ in range(2):  # opened again: the report replaces itself
        assert bpy.ops.scene.pgt_open_bank_report() == {"FINISHED"}
    assert sorted(bpy.data.texts.keys()) == ["report.md", "report.md.001"]
    assert mine.as_string() == "my notes" and bpy.data.texts["report.md.001"].as_string().startswith("#")

    settings.preview_count = 5
    assert bpy.ops.scene.pgt_preview_bank() == {"FINISHED"}
    collection = bpy.data.collections[bank.PREVIEW_COLLECTION]
    points = sorted((o for o in collection.objects if o.type == "MESH"), key=lambda o: o.name)
    boxes = {o.name: o for o in collection.objects if o.type == "EMPTY"}
    infos = {Path(info["path"]).stem: info
             for entries in load_infos(tmp_path / "bank" / json.loads((tmp_path / "bank" / "manifest.json").read_text())[
                 "info_pickles"]["openpcdet"]).values()
             for info in entries}
    assert len(points) == len(boxes) == 5
    for obj in points:
        box = np.asarray(infos[obj.name]["box3d_lidar"], np.float64)
        np.testing.assert_allclose(boxes[f"{obj.name} box"].location, box[:3], atol=1e-5)
        xyz = np.zeros(3 * len(obj.data.vertices))
        obj.data.vertices.foreach_get("co", xyz)
        local = xyz.reshape(-1, 3) - box[:3]
        cos, sin = np.cos(box[6]), np.sin(box[6])
        local[:, :2] = local[:, :2] @ np.array([[cos, -sin], [sin, cos]])
        assert (np.abs(local) <= box[3:6] / 2 + 0.2).all()  # the entry's points lie in its box
        assert "intensity" in obj.data.attributes and len(obj.data.vertices) == infos[obj.name]["num_points_in_gt"]
    names = sorted(o.name for o in collection.objects)
    assert bpy.ops.scene.pgt_preview_bank() == {"FINISHED"}  # a second preview replaces the first, names and all
    shown = list(bpy.data.collections[bank.PREVIEW_COLLECTION].objects)
    assert sorted(o.name for o in shown) == names

    # a damaged manifest is named and the preview shown stays
    manifest = tmp_path / "bank" / "manifest.json"
    record = json.loads(manifest.read_text())
    record["config"]["formats"] = ["coco"]
    manifest.write_text(json.dumps(record))
    refused(bpy.ops.scene.pgt_preview_bank, f"{manifest}: bank.formats = \\['coco'\\]: expected a non-empty list")
    assert list(bpy.data.collections[bank.PREVIEW_COLLECTION].objects) == shown
    # so is a pickle whose entry path leads out of the bank: nothing outside is read
    record["config"]["formats"] = ["openpcdet", "mmdet3d"]
    manifest.write_text(json.dumps(record))
    pickle_path = tmp_path / "bank" / record["info_pickles"]["openpcdet"]
    by_class = pickle.loads(pickle_path.read_bytes())
    for entries in by_class.values():
        for info in entries:
            info["path"] = "../../outside.bin"
    pickle_path.write_bytes(pickle.dumps(by_class))
    refused(bpy.ops.scene.pgt_preview_bank, "entry path '../../outside.bin' leads outside the bank")
    assert list(bpy.data.collections[bank.PREVIEW_COLLECTION].objects) == shown


def test_a_stopped_export_resumes_to_the_same_bank(scene, folder, tmp_path):
    import_and_author(scene, folder)
    settings = scene.pgt_bank
    config = BankConfig(sweeps=1, headings_deg=(-180.0, 180.0, 180.0), x=(-25.0, 25.0, 25.0), y=(-25.0, 25.0, 25.0),
                        chunk_size=2)
    (tmp_path / "bank.toml").write_text(config_toml(config))
    settings.config_file = str(tmp_path / "bank.toml")  # a config file replaces the fields
    settings.output = str(tmp_path / "whole")
    assert bpy.ops.scene.pgt_export_bank() == {"FINISHED"}

    settings.output = str(tmp_path / "stopped")
    run = bank.BankRun(scene, settings)  # what the modal export steps on each timer event
    assert run.step() and run.step() and run.done == 4 < run.total
    refused(bpy.ops.scene.pgt_export_bank, "another export is using this folder right now")  # while it runs
    run.stop()
    assert not (tmp_path / "stopped" / "manifest.json").exists()
    refused(bpy.ops.scene.pgt_export_bank, "is not empty: resume the bank there or overwrite it")
    settings.existing = "RESUME"
    assert bpy.ops.scene.pgt_export_bank() == {"FINISHED"}  # ... and resumed on request
    assert bank_bytes(tmp_path / "stopped") == bank_bytes(tmp_path / "whole")


def test_every_operator_that_changes_blend_data_can_be_undone():
    """All but those that change only settings and files: Export Bank, Stop, Save Config."""
    from pgt_blender.blender import operators

    settings_and_files = {operators.SCENE_OT_pgt_export_bank, operators.SCENE_OT_pgt_stop_bank,
                          operators.SCENE_OT_pgt_save_bank_config}
    for operator in set(operators.classes) - settings_and_files:
        assert {"REGISTER", "UNDO"} <= operator.bl_options, operator.__name__


def test_bad_inputs_leave_scene_and_disk_as_they_were(scene, folder, tmp_path):
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "a.ply").write_bytes((folder / "truck.ply").read_bytes())
    (broken / "b.ply").write_text("not a ply\n")
    before = datablock_counts(bpy)
    refused(bpy.ops.import_scene.pgt_folder, f"{broken / 'b.ply'}: ", directory=str(broken))
    refused(bpy.ops.import_scene.pgt_folder, f"{tmp_path}: no reconstructions found", directory=str(tmp_path))
    assert datablock_counts(bpy) == before

    assert bpy.ops.import_scene.pgt_folder(directory=str(folder)) == {"FINISHED"}
    settings = scene.pgt_authoring
    settings.dataset, settings.class_name = "kitti", ""
    refused(bpy.ops.object.pgt_author_selected, "no class chosen")  # checked before any change
    assert not any(authoring.status(obj)["aligned"] for obj in bpy.context.selected_objects)

    bank_settings = scene.pgt_bank
    bank_settings.status = "179 entries; wrote an earlier bank"
    for on_bank_folder in (bpy.ops.scene.pgt_export_bank, bpy.ops.scene.pgt_open_bank_report,
                           bpy.ops.scene.pgt_preview_bank):  # greyed out: not ./report.md, not into ./
        assert not on_bank_folder.poll()
        refused(on_bank_folder, "Choose the bank's output folder first")
    bank_settings.output = str(tmp_path / "bank")
    refused(bpy.ops.scene.pgt_export_bank, "2 incomplete object")
    assert bank_settings.status.startswith("refused, nothing written: ") and "2 incomplete object" in bank_settings.status
    assert not (tmp_path / "bank").exists()
    bank_settings["dataset"] = 99  # a .blend of a version with more datasets: reads as ""
    refused(bpy.ops.scene.pgt_save_bank_config, "Bank: no dataset chosen", filepath=str(tmp_path / "stale.toml"))
    bank_settings.dataset = "nuscenes"
    bpy.ops.object.mode_set(mode="EDIT")  # an object's mesh lives in an edit mesh there
    refused(bpy.ops.scene.pgt_export_bank, "Export Bank works in Object Mode")
    bpy.ops.object.mode_set(mode="OBJECT")
    small_bank(bank_settings, tmp_path / "bank")
    bank_settings.openpcdet = bank_settings.mmdet3d = False
    refused(bpy.ops.scene.pgt_export_bank, "no format chosen")
    assert not (tmp_path / "bank").exists()
    (tmp_path / "bank").mkdir()
    refused(bpy.ops.scene.pgt_preview_bank, "is not a finished bank")
    refused(bpy.ops.scene.pgt_open_bank_report, "no report yet")
    (tmp_path / "bank" / "report.md").mkdir()
    refused(bpy.ops.scene.pgt_open_bank_report, "report.md: is a folder; expected a file")
    (tmp_path / "bank" / "report.md").rmdir()
    bank_settings.config_file = str(tmp_path / "missing.toml")
    refused(bpy.ops.scene.pgt_save_bank_config, f"^Error: {tmp_path / 'missing.toml'}: cannot read the file",
            filepath=str(tmp_path / "saved.toml"))  # the config file named, once
    refused(bpy.ops.scene.pgt_save_bank_config, "Save Config: no file chosen", filepath="")
    assert not (tmp_path / "saved.toml").exists()
    bank_settings.config_file = ""
    sensor = tmp_path / "sensor.toml"  # a file the scene reads is not written over
    sensor.write_text("base = \"nuscenes\"\n")
    scene.pgt_scan.sensor_file = str(sensor)
    refused(bpy.ops.scene.pgt_save_bank_config, f"{sensor}: is or holds the input {sensor}", filepath=str(sensor))
    assert sensor.read_text() == "base = \"nuscenes\"\n"
