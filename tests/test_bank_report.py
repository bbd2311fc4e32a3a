"""core.bank.report: a bank's statistics from its chunk records agree with a recount of
its info pickle and .bin files; real-database statistics; the Markdown + PNG report."""

import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest

from pgt_blender.core.bank.folder import INTENSITY_BINS
from pgt_blender.core.bank.report import (REPORT_MD, REPORT_PNG, _quantiles, bank_statistics, real_reference,
                                          real_statistics, write_report)
from pgt_blender.core.errors import InputError
from pgt_blender.core.samples import write_sample

from .conftest import run_script

ROOT = Path(__file__).resolve().parents[1]

# A tiny KITTI bank: 2 headings x 3 x 3 positions x 4 objects (mesh + reconstruction of a
# truck and a bicycle: classes Truck and Cyclist); min_points drops some far bicycles.
CONFIG = """
[bank]
dataset = "kitti"
min_points = 60
chunk_size = 8
[grid]
headings_deg = [0, 180, 180]
x = [5, 45, 20]
y = [-20, 20, 20]
"""


@pytest.fixture(scope="module")
def bank(tmp_path_factory) -> Path:
    """The exported bank folder (built once for the module, about 3 s)."""
    work = tmp_path_factory.mktemp("bank")
    for class_name in ("truck", "bicycle"):
        raw = work / f"raw_{class_name}"
        write_sample(raw, class_name, seed=0, points=2000)
        (raw / f"{class_name}_truth.json").unlink()
        run_script("prepare_objects.py", "--in", raw, "--class", class_name, "--out", work / "prepared",
                   "--up", "+z", "--heading", "baseline", check=True)
    (work / "bank.toml").write_text(CONFIG)
    run_script("export_bank.py", "--objects", work / "prepared", "--config", work / "bank.toml",
               "--out", work / "out", "--workers", 1, check=True)
    return work / "out"


@pytest.fixture
def bank_copy(bank, tmp_path) -> Path:
    """A writable copy of the bank, for breaking it, without the report export_bank.py wrote."""
    out = Path(shutil.copytree(bank, tmp_path / "out"))
    for name in (REPORT_MD, REPORT_PNG):
        (out / name).unlink()
    return out


def manifest(out: Path) -> dict:
    return json.loads((out / "manifest.json").read_text())


def infos(out: Path, fmt="mmdet3d") -> dict:
    return pickle.loads((out / manifest(out)["info_pickles"][fmt]).read_bytes())


def recount(out: Path, class_infos: list, fmt="mmdet3d") -> tuple:
    """(points per entry from the .bin files, all their intensities) of one class."""
    rows = [np.fromfile(out / fmt / info["path"], np.float32).reshape(-1, 4) for info in class_infos]
    return np.array([len(r) for r in rows]), np.concatenate(rows)[:, 3]


def test_quantiles_equal_numpy_on_the_values():
    rng = np.random.default_rng(0)
    for size in (1, 2, 7, 100):
        values = rng.integers(0, 50, size)
        np.testing.assert_allclose(_quantiles(np.bincount(values)), np.quantile(values, [0.5, 0.1, 0.9]))
    assert _quantiles(np.zeros(1, np.int64)) == [None, None, None]


def test_bank_statistics_agree_with_a_recount(bank):
    statistics = bank_statistics(bank)
    database = infos(bank)
    assert statistics["dataset"] == "kitti" and sorted(statistics["classes"]) == ["Cyclist", "Truck"]
    assert {name: stats["kept"] for name, stats in statistics["classes"].items()} == manifest(bank)["counts"]
    for name, stats in statistics["classes"].items():
        points, intensities = recount(bank, database[name])
        np.testing.assert_array_equal(points, [info["num_points_in_gt"] for info in database[name]])
        np.testing.assert_allclose([stats["points"][q] for q in ("median", "p10", "p90")],
                                   np.quantile(points, [0.5, 0.1, 0.9]))
        assert stats["intensity"].sum() == points.sum()
        np.testing.assert_array_equal(stats["intensity"], np.histogram(intensities, INTENSITY_BINS, (0, 1))[0])
        centres = np.array([info["box3d_lidar"][:2] for info in database[name]], np.float64)
        rings = np.floor(np.hypot(*centres.T) / 10)
        assert [ring["entries"] for ring in stats["distance"]] == np.unique(rings, return_counts=True)[1].tolist()
        for ring in stats["distance"]:
            assert ring["median"] == np.median(points[rings == ring["from_m"] / 10])
        assert stats["coverage"].sum() == len(points)


def test_dropped_counts_equal_the_manifests(bank):
    dropped = {name: stats["dropped"] for name, stats in bank_statistics(bank)["classes"].items()}
    expected = manifest(bank)["dropped_below_min_points"]
    assert sum(expected.values()) > 0  # the bank does drop poses: the check means something
    assert dropped == {name: expected.get(name, 0) for name in dropped}


def test_bank_statistics_read_no_database_file(bank_copy):
    expected = bank_statistics(bank_copy)
    for fmt in ("openpcdet", "mmdet3d"):
        shutil.rmtree(bank_copy / fmt)
    assert_same_statistics(bank_statistics(bank_copy), expected, dropped=True)


def assert_same_statistics(found: dict, expected: dict, dropped: bool) -> None:
    assert sorted(found["classes"]) == sorted(expected["classes"])
    for name, stats in expected["classes"].items():
        for key in ("kept", "points", "distance", "intensity_mean") + (("dropped",) if dropped else ()):
            assert found["classes"][name][key] == stats[key], (name, key)
        for key in ("intensity", "coverage"):
            np.testing.assert_array_equal(found["classes"][name][key], stats[key])


@pytest.mark.parametrize("fmt", ["openpcdet", "mmdet3d"])
def test_real_statistics_of_the_banks_own_pickle_equal_the_banks(bank, fmt):
    config = manifest(bank)["config"]
    real = real_statistics(bank / manifest(bank)["info_pickles"][fmt], dataset="kitti",
                           grid=(config["x"], config["y"]))
    assert real["config"] is None
    assert all(stats["dropped"] is None for stats in real["classes"].values())
    assert_same_statistics(real, bank_statistics(bank), dropped=False)


def test_real_statistics_of_the_mmdet3d_kitti_database(shared_data):
    real = real_statistics(shared_data / "mmdet3d_kitti_gtdb" / "kitti_dbinfos_train.pkl", dataset="kitti")
    assert list(real["classes"]) == ["Pedestrian"]
    pedestrian = real["classes"]["Pedestrian"]
    assert pedestrian["kept"] == 1 and pedestrian["dropped"] is None
    assert pedestrian["points"] == {"median": 377.0, "p10": 377.0, "p90": 377.0}
    assert pedestrian["distance"] == [{"from_m": 0.0, "to_m": 10.0, "entries": 1, "median": 377.0}]  # 8.9 m
    assert pedestrian["intensity"].sum() == 377
    assert 0 < pedestrian["intensity_mean"] < 1
    assert pedestrian["coverage"].sum() == 1  # inside KITTI's grid


@pytest.mark.parametrize("dataset", ["nuscenes", "lyft"])
def test_a_real_database_of_another_dataset_is_named_as_such(shared_data, dataset):
    """The KITTI database against a nuScenes or Lyft bank: its classes say so before its
    4-column .bin files are read as 5-column ones."""
    real = shared_data / "mmdet3d_kitti_gtdb" / "kitti_dbinfos_train.pkl"
    with pytest.raises(InputError) as caught:
        real_statistics(real, dataset=dataset)
    assert caught.value.path == real
    assert str(caught.value) == (f"{real}: holds no {dataset} class (it has Pedestrian): the database of another "
                                 f"dataset? The bank is {dataset}; choose a {dataset} database")


def test_write_report(bank_copy):
    md_path, png_path = write_report(bank_copy)
    assert (md_path, png_path) == (bank_copy / REPORT_MD, bank_copy / REPORT_PNG)
    text = md_path.read_text()
    counts, dropped = manifest(bank_copy)["counts"], manifest(bank_copy)["dropped_below_min_points"]
    for name in ("Cyclist", "Truck"):
        assert f"| {name} | {counts[name]} | {dropped.get(name, 0)} |" in text
        assert f"| {name} | bank |" in text
    assert "Dataset **kitti**" in text and "seed **0**" in text and "x 5..45 m step 20" in text
    assert "## Columns" in text and REPORT_PNG in text
    assert png_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    first = md_path.read_bytes(), png_path.read_bytes()
    write_report(bank_copy)
    assert (md_path.read_bytes(), png_path.read_bytes()) == first
    assert not list(bank_copy.glob(".*.partial"))


def test_without_matplotlib_the_report_has_its_text_and_no_figure(bank_copy):
    """Blender's own Python has no matplotlib: report.md is written and says so, no PNG."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['matplotlib'] = None; from pgt_blender.core.bank.report import write_report; "
            f"print(write_report({str(bank_copy)!r}))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().endswith(", None)")
    text = (bank_copy / REPORT_MD).read_text()
    assert "No figure: matplotlib is not installed here." in text and REPORT_PNG not in text
    assert not (bank_copy / REPORT_PNG).exists()


def test_write_report_beside_a_real_database(bank_copy, shared_data):
    real = shared_data / "mmdet3d_kitti_gtdb" / "kitti_dbinfos_train.pkl"
    text = write_report(bank_copy, real_reference(real, manifest(bank_copy)["config"]))[0].read_text()
    assert "`kitti_dbinfos_train.pkl` (kitti, entries: 1)" in text
    assert "| Pedestrian | – | – | 1 |" in text  # classes matched by name: the bank has no Pedestrian
    assert "| Pedestrian | real | 377 (1) |" in text
    assert "| Truck | real | – |" in text


def break_identity(out: Path) -> Path:
    (out / ".work" / "identity.json").unlink()
    return out


def break_chunk(out: Path) -> Path:
    (out / ".work" / "chunks" / "000003.json").unlink()
    return out


def garble_chunk(out: Path) -> Path:
    record = out / ".work" / "chunks" / "000002.json"
    record.write_bytes(b"not a record")
    return record


@pytest.mark.parametrize("damage, message", [(break_identity, "no .work/identity.json"),
                                             (break_chunk, "1 of 9 chunk records missing"),
                                             (garble_chunk, "a damaged chunk record; export_bank.py --resume redoes it")])
def test_a_broken_bank_raises_and_writes_nothing(bank_copy, damage, message):
    named = damage(bank_copy)
    with pytest.raises(InputError) as caught:
        write_report(bank_copy)
    assert caught.value.path == named and message in str(caught.value) and "\n" not in str(caught.value)
    assert_no_report(bank_copy)


def test_a_folder_without_a_bank_raises(tmp_path):
    with pytest.raises(InputError, match="no .work/identity.json") as caught:
        bank_statistics(tmp_path)
    assert caught.value.path == tmp_path


def test_a_bad_real_database_raises_and_writes_nothing(bank_copy, tmp_path):
    garbage = tmp_path / "garbage_dbinfos.pkl"
    garbage.write_bytes(b"\x80\x04 not a pickle")
    with pytest.raises(InputError) as caught:
        write_report(bank_copy, real_reference(garbage, manifest(bank_copy)["config"]))
    assert caught.value.path == garbage and "not a readable pickle" in str(caught.value)
    assert_no_report(bank_copy)
    real = bank_copy / "mmdet3d" / "kitti_dbinfos_pgt.pkl"
    missing = bank_copy / "mmdet3d" / infos(bank_copy)["Truck"][0]["path"]
    missing.unlink()
    with pytest.raises(InputError) as caught:
        write_report(bank_copy, real_reference(real, manifest(bank_copy)["config"]))
    assert caught.value.path == missing
    assert_no_report(bank_copy)


def test_a_real_object_file_of_gigabytes_is_named_unread(bank_copy):
    """A (sparse) 8 GiB object file in a real database: named from its size against its
    info's point count, before numpy would read it all."""
    real = bank_copy / "mmdet3d" / "kitti_dbinfos_pgt.pkl"
    info = infos(bank_copy)["Truck"][0]
    with open(bank_copy / "mmdet3d" / info["path"], "r+b") as stream:
        stream.truncate(8 * 2**30)
    with pytest.raises(InputError, match=f"{info['path']}: 536870912 rows of 4 float32 values \\(kitti database "
                                         f"columns\\), but its info declares {info['num_points_in_gt']}$"):
        real_statistics(real, dataset="kitti")


def assert_no_report(out: Path) -> None:
    assert not (out / REPORT_MD).exists() and not (out / REPORT_PNG).exists()
    assert not list(out.glob(".report*"))
