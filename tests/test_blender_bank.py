"""The .blend route of the bank: objects authored in Blender give the same bank as the
same objects prepared headless (prepare_objects.py's folder); the Bank section's report
beside a real database, with the bank's quality score against it."""

import math

import numpy as np
import pytest

from pgt_blender.core.authoring.prepare import prepare, write_prepared
from pgt_blender.core.bank.config import MAX_SWEEPS
from pgt_blender.core.bank.inputs import prepared_objects
from pgt_blender.core.errors import InputError
from pgt_blender.core.importing import load_reconstruction
from pgt_blender.core.quality.reference import kitti_scan_database
from pgt_blender.core.samples import write_sample

from .test_bank import CHRONO_TRUCK, SMALL, bank_bytes, run_export, write_config

bpy = pytest.importorskip("bpy")

from pgt_blender.blender import objects as blender_objects  # noqa: E402  (needs bpy)
from pgt_blender.blender.authoring import status as authoring_status  # noqa: E402
from pgt_blender.blender.bank import bank_config, scene_bank_objects  # noqa: E402


@pytest.fixture(scope="module")
def sources(tmp_path_factory, shared_data) -> dict:
    folder = tmp_path_factory.mktemp("sources")
    sample = write_sample(folder, "bicycle", seed=3, points=3000)["reconstruction.ply"]
    return {"sample": sample, "chrono": shared_data / "chrono_vehicles" / CHRONO_TRUCK}


def author_in_blender(scene, sources, dataset: str = "nuscenes") -> None:
    """The Align / Heading / Size operators, with the settings prepare() is given below."""
    settings = scene.pgt_authoring
    for key, up, heading, size in (("sample", "pca", "baseline", "class"), ("chrono", "+z", None, "keep")):
        obj = blender_objects.add_reconstruction(scene, load_reconstruction(sources[key]))
        bpy.context.view_layer.objects.active = obj
        settings.up, settings.heading_method, settings.size_mode = up, heading or "baseline", size
        bicycle = "cyclist" if dataset == "kitti" else "bicycle"  # the dataset's class of a bicycle
        settings.dataset, settings.class_name, settings.seed = dataset, bicycle if key == "sample" else "truck", 4
        assert bpy.ops.object.pgt_align() == {"FINISHED"}
        if heading:
            assert bpy.ops.object.pgt_auto_heading() == {"FINISHED"}
        assert bpy.ops.object.pgt_set_size() == {"FINISHED"}


def prepare_headless(sources, folder) -> None:
    write_prepared(prepare(load_reconstruction(sources["sample"]), "bicycle", up="pca", heading_method="baseline",
                           seed=4), "bicycle", "nuscenes", folder)
    write_prepared(prepare(load_reconstruction(sources["chrono"]), "truck", up="+z", heading_method="none",
                           size="keep"), "truck", "nuscenes", folder)


def test_blend_and_prepared_folder_give_the_same_bank(scene, sources, tmp_path):
    author_in_blender(scene, sources)
    bpy.ops.object.select_all(action="DESELECT")
    incomplete = blender_objects.add_reconstruction(scene, load_reconstruction(sources["sample"]))
    incomplete.name = "unsized"
    found, missing = scene_bank_objects(scene)
    assert missing == [("unsized", "no class and no size set")]
    blend = tmp_path / "objects.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    folder = tmp_path / "prepared"
    prepare_headless(sources, folder)
    headless, _ = prepared_objects(folder)
    assert [obj.name for obj in sorted(found, key=lambda o: o.name)] == [obj.name for obj in headless]
    for ours, theirs in zip(sorted(found, key=lambda o: o.name), headless):
        assert ours.summary() == theirs.summary()
        np.testing.assert_array_equal(ours.dims, theirs.dims)

    config = write_config(tmp_path / "bank.toml", SMALL)
    refused = run_export("--blend", blend, "--config", config, "--out", tmp_path / "from_blend", check=False)
    assert refused.returncode == 1 and "unsized: no class and no size set" in refused.stderr
    run_export("--blend", blend, "--config", config, "--out", tmp_path / "from_blend", "--skip-incomplete")
    run_export("--objects", folder, "--config", config, "--out", tmp_path / "from_folder")
    assert bank_bytes(tmp_path / "from_blend") == bank_bytes(tmp_path / "from_folder")


def test_a_bad_blend_file_is_named(tmp_path):
    broken = tmp_path / "broken.blend"
    broken.write_bytes(b"not a blend file")
    result = run_export("--blend", broken, "--out", tmp_path / "bank", check=False)
    assert result.returncode == 1 and f"{broken}: not a readable .blend file" in result.stderr
    assert not (tmp_path / "bank").exists()


def test_the_bank_report_scores_the_bank_against_the_real_database(scene, sources, shared_data, tmp_path):
    """The Bank section's Real database: a bad one refuses the export before anything is
    written; a good one puts its statistics and the quality table in the export's
    report; set after the export, Open Report writes the report anew against it."""
    author_in_blender(scene, sources, "kitti")
    settings = scene.pgt_bank
    settings.dataset, settings.mmdet3d, settings.output = "kitti", False, str(tmp_path / "bank")
    settings.heading_step, settings.grid_step = math.radians(180.0), 25.0
    settings.real_database = str(tmp_path / "absent.pkl")
    with pytest.raises(RuntimeError, match="absent.pkl"):
        bpy.ops.scene.pgt_export_bank()
    assert not (tmp_path / "bank").exists()

    # the shared mmdet3d database: one Pedestrian, a class the bank lacks (nothing to score)
    settings.real_database = str(shared_data / "mmdet3d_kitti_gtdb" / "kitti_dbinfos_train.pkl")
    assert settings.real_convention == "AUTO"  # read from its infos: mmdet3d's
    assert bpy.ops.scene.pgt_export_bank() == {"FINISHED"}
    report = tmp_path / "bank" / "report.md"
    text = report.read_text()
    assert "(kitti, entries: 1)" in text and "## Quality score against the real database" in text
    assert "| Pedestrian | real | 377 (1) |" in text
    assert "No class in common with the real database (classes in only one of them: Cyclist, Pedestrian, " in text

    settings.real_database = str(tmp_path / "absent.pkl")
    with pytest.raises(RuntimeError, match="absent.pkl"):
        bpy.ops.scene.pgt_open_bank_report()
    assert report.read_text() == text  # a bad database leaves the report as it was
    settings.real_database = str(shared_data / "mmdet3d_kitti_gtdb" / "kitti_dbinfos_train.pkl")
    settings.real_convention = "openpcdet"  # what its group_ids contradict: its objects would be half a box off
    with pytest.raises(RuntimeError, match="holds mmdetection3d infos .* not openpcdet's"):
        bpy.ops.scene.pgt_open_bank_report()
    assert report.read_text() == text

    # the KITTI scans' objects (openpcdet convention): Cyclist and Truck are scored
    settings.real_database = str(kitti_scan_database(shared_data / "kitti_scans", tmp_path / "real"))
    settings.real_convention = "openpcdet"
    assert bpy.ops.scene.pgt_open_bank_report() == {"FINISHED"}
    opened = bpy.data.texts["report.md"].as_string()
    assert opened == report.read_text() and "(kitti, entries: 6)" in opened
    quality = opened.split("## Quality score against the real database")[1].split("##")[0]
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ") for line in quality.splitlines()
            if line.startswith("| ") and not line.startswith("| class")}
    assert sorted(rows) == ["Cyclist", "Truck"] and all(row[2] == "1" for row in rows.values())
    # every feature-free metric but 1-NNA, which one real object a class cannot measure (0 by construction)
    assert all((cell.strip(" |") == "–") == (column == 6) for row in rows.values() for column, cell in enumerate(row)
               if column >= 4)

    settings.real_database = ""
    assert bpy.ops.scene.pgt_open_bank_report() == {"FINISHED"}
    assert bpy.data.texts["report.md"].as_string() == opened  # opened as it is


def test_an_emptied_object_refuses_the_export_before_the_folder_is_made(scene, sources, tmp_path):
    """An authored object whose mesh was emptied afterwards: named, CANCELLED, and no
    output folder made (a retry would otherwise find it "not empty")."""
    author_in_blender(scene, sources)
    emptied = next(obj for obj in scene.objects if authoring_status(obj)["size"] and obj.type == "MESH")
    emptied.data.clear_geometry()
    settings = scene.pgt_bank
    settings.output, settings.grid_step = str(tmp_path / "bank"), 50.0
    with pytest.raises(RuntimeError, match=f"{emptied.name}: point cloud is empty"):
        bpy.ops.scene.pgt_export_bank()
    assert not (tmp_path / "bank").exists()


def test_an_export_that_keeps_no_entry_says_nothing_is_left(scene, sources, tmp_path):
    """No pose with min_points returns: the error names it, the folder is removed, and
    the status does not offer a resume of it."""
    author_in_blender(scene, sources)
    settings = scene.pgt_bank
    settings.output, settings.config_file = str(tmp_path / "bank"), str(
        write_config(tmp_path / "bank.toml", {"bank": {"min_points": 100_000}, "grid": {"x": [10, 10, 1],
                                                                                         "y": [0, 0, 1]}}))
    with pytest.raises(RuntimeError, match="no entry kept: all 26 poses had fewer than 100000 points"):
        bpy.ops.scene.pgt_export_bank()
    assert not (tmp_path / "bank").exists()
    assert settings.status == "failed: nothing written stays (the error says why)"


def test_a_defect_during_the_export_leaves_the_bank_section_as_any_failure(scene, sources, tmp_path, monkeypatch):
    """An exception that is no input or file error (a defect) still reaches Blender with
    its traceback, but the section no longer reads "exporting" and the folder is let go."""
    from pgt_blender.core.bank import export

    author_in_blender(scene, sources)
    settings = scene.pgt_bank
    settings.output, settings.grid_step = str(tmp_path / "bank"), 50.0

    def defect(*args, **kwargs):
        raise ZeroDivisionError("a defect")

    with monkeypatch.context() as patched:
        patched.setattr(export, "assemble", defect)
        with pytest.raises(RuntimeError, match="ZeroDivisionError: a defect"):
            bpy.ops.scene.pgt_export_bank()
    assert not settings.running
    assert settings.status == "failed: the written chunks stay; 'Resume' continues"
    settings.existing = "RESUME"
    assert bpy.ops.scene.pgt_export_bank() == {"FINISHED"}


def test_overwrite_refuses_a_bank_folder_holding_the_blend_or_the_config(scene, sources, tmp_path):
    """Overwrite empties the bank folder: a .blend saved there, or the config file it reads,
    is named and kept, not deleted under the export."""
    author_in_blender(scene, sources)
    settings = scene.pgt_bank
    settings.output, settings.grid_step, settings.existing = str(tmp_path / "bank"), 50.0, "OVERWRITE"
    assert bpy.ops.scene.pgt_export_bank() == {"FINISHED"}
    blend = tmp_path / "bank" / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    with pytest.raises(RuntimeError, match=f"holds the input {blend}, which overwriting the bank would delete"):
        bpy.ops.scene.pgt_export_bank()
    assert blend.is_file() and (tmp_path / "bank" / "manifest.json").is_file()


def test_a_file_saved_during_an_export_opens_with_none_running(scene, tmp_path):
    """Ctrl+S (or autosave) during a background export saves its run state; the file opens
    with Export Bank available and the status saying how to finish."""
    settings = scene.pgt_bank
    settings.output, settings.running, settings.stop_requested = str(tmp_path / "bank"), True, True
    blend = tmp_path / "during.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    settings = bpy.context.scene.pgt_bank
    assert not settings.running and not settings.stop_requested
    assert settings.status == "the file was saved during an export: choose 'Resume' and export again to finish it"
    assert bpy.ops.scene.pgt_export_bank.poll()


def test_the_bank_fields_hold_the_config_file_bounds(scene, tmp_path):
    """Sweeps beyond a config file's 100 are clamped by the field, and what the fields
    make is checked as a file is (bank.bank_config through config_from_table)."""
    settings = scene.pgt_bank
    settings.sweeps = 100_000
    assert settings.sweeps == MAX_SWEEPS
    assert bank_config(settings).sweeps == MAX_SWEEPS
    settings.openpcdet = settings.mmdet3d = False
    with pytest.raises(InputError, match="Bank: no format chosen"):
        bank_config(settings)


@pytest.mark.parametrize("field", ["output", "config_file", "real_database"])
def test_a_blend_relative_path_in_an_unsaved_file_is_named(scene, sources, tmp_path, monkeypatch, field):
    """"//bank" before the .blend is saved would be the folder Blender started in."""
    author_in_blender(scene, sources)
    monkeypatch.chdir(tmp_path)
    settings = scene.pgt_bank
    settings.output = str(tmp_path / "bank")
    setattr(settings, field, "//bank")
    with pytest.raises(RuntimeError, match="//bank: is relative to the .blend file, which is not saved yet"):
        bpy.ops.scene.pgt_export_bank()
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("name", ["bank.txt", "bank"])
def test_save_config_writes_a_toml_only(scene, tmp_path, name):
    with pytest.raises(RuntimeError, match=f"{tmp_path / name}: expected a file name ending in .toml"):
        bpy.ops.scene.pgt_save_bank_config(filepath=str(tmp_path / name))
    assert not list(tmp_path.iterdir())


def test_the_bank_fields_default_to_the_command_lines_grid(scene):
    """The Bank section's defaults make the default config's grid: its heading step, a
    float32 angle, reads 30.000001 degrees, which left out the last of the 13 headings."""
    from pgt_blender.core.bank.config import BankConfig

    fields, default = bank_config(scene.pgt_bank), BankConfig()
    assert (fields.headings_deg, fields.x, fields.y) == (default.headings_deg, default.x, default.y)
