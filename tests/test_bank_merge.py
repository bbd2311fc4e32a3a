"""core.bank.merge and headless_scripts/mix_bank.py: a real database mixed with a bank
at a GT:PGT ratio, on synthetic pickles and on the real mmdet3d KITTI database."""

import os
import pickle
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from pgt_blender.core.bank.merge import mix_databases, parse_ratio
from pgt_blender.core.errors import InputError

from .conftest import CodeOnLoad, run_script


# Pedestrian (2 in the bank) and Truck (none) are short at 1:1; Bus is not in the real database.
REAL_COUNTS = {"Car": 5, "Pedestrian": 3, "Cyclist": 2, "Truck": 4}
BANK_COUNTS = {"Bus": 4, "Car": 20, "Cyclist": 5, "Pedestrian": 2}
REAL_GROUP_START = 10  # real group ids 10, 12, 14, ...: the bank's must start above the maximum


def write_database(pickle_path, counts, folder, box_values=7, group_ids=False, bank=False):
    """An info pickle at ``pickle_path`` with one points file per info under
    ``pickle_path.parent / folder``; returns the path."""
    infos, group = {}, REAL_GROUP_START
    for name, count in counts.items():
        infos[name] = []
        for index in range(count):
            info = {"name": name, "path": f"{folder}/{name}_{index:03d}.bin",
                    "image_idx": f"pgt_{index:06d}" if bank else index, "gt_idx": index,
                    "box3d_lidar": np.arange(box_values, dtype=np.float32) + index,
                    "num_points_in_gt": 3 + index, "difficulty": 0}
            if group_ids:
                info["group_id"], group = group, group + 2
            file = pickle_path.parent / info["path"]
            file.parent.mkdir(parents=True, exist_ok=True)
            np.zeros((info["num_points_in_gt"], 4), np.float32).tofile(file)
            infos[name].append(info)
    pickle_path.write_bytes(pickle.dumps(infos))
    return pickle_path


@pytest.fixture
def real(tmp_path):
    """An mmdet3d-style real database (with group_id) at tmp/data, its dataset root."""
    (tmp_path / "data").mkdir()
    return write_database(tmp_path / "data" / "kitti_dbinfos_train.pkl", REAL_COUNTS, "kitti_gt_database",
                          group_ids=True)


@pytest.fixture
def bank(tmp_path):
    """A bank laid out like a dataset root, inside the real dataset root."""
    (tmp_path / "data" / "pgt").mkdir(parents=True)
    return write_database(tmp_path / "data" / "pgt" / "kitti_dbinfos_pgt.pkl", BANK_COUNTS, "pgt_gt_database",
                          group_ids=True, bank=True)


def load(path):
    return pickle.loads(Path(path).read_bytes())


def bank_index(info):
    return int(Path(info["path"]).stem.split("_")[-1])


def assert_nothing_written(out):
    assert not out.exists()
    assert not list(out.parent.glob(f".{out.name}*"))  # no partial file either


@pytest.mark.parametrize("text, expected", [("1:1", (1.0, 1.0)), ("2:1", (2.0, 1.0)), ("1:0.5", (1.0, 0.5)),
                                            ("1:0", (1.0, 0.0)), (" 3 : 2 ", (3.0, 2.0))])
def test_parse_ratio(text, expected):
    assert parse_ratio(text) == expected


@pytest.mark.parametrize("text", ["", "1", "1:1:1", "a:b", "0:1", "-1:1", "1:-0.5", "inf:1", "1:nan", "1/1"])
def test_parse_ratio_rejects(text):
    with pytest.raises(ValueError, match=f"ratio '{text}'"):
        parse_ratio(text)


# Requested per class = round(n_real * pgt / gt), halves to even (Car 2.5 -> 2); used = min(requested, bank).
@pytest.mark.parametrize("ratio, used", [
    ((1, 1), {"Car": 5, "Pedestrian": 2, "Cyclist": 2, "Truck": 0}),
    ((2, 1), {"Car": 2, "Pedestrian": 2, "Cyclist": 1, "Truck": 0}),
    ((1, 0.5), {"Car": 2, "Pedestrian": 2, "Cyclist": 1, "Truck": 0}),
    ((1, 3), {"Car": 15, "Pedestrian": 2, "Cyclist": 5, "Truck": 0}),
    ((1, 0), {"Car": 0, "Pedestrian": 0, "Cyclist": 0, "Truck": 0}),
])
def test_counts_per_ratio(real, bank, tmp_path, ratio, used):
    out = tmp_path / "mixed.pkl"
    summary = mix_databases(real, bank, out, ratio)
    mixed = load(out)
    assert list(mixed) == list(REAL_COUNTS)  # the real class order
    assert {name: len(infos) - REAL_COUNTS[name] for name, infos in mixed.items()} == used
    for name, counts in summary["classes"].items():
        assert counts["real"] == REAL_COUNTS[name] and counts["bank_used"] == used[name]
        assert counts["requested"] == round(REAL_COUNTS[name] * ratio[1] / ratio[0])
        assert counts["bank_available"] == BANK_COUNTS.get(name, 0)
        assert counts["effective_ratio"] == pytest.approx(used[name] / REAL_COUNTS[name])
    assert summary["total"]["bank_used"] == sum(used.values()) and summary["total"]["real"] == 14
    assert summary["skipped"] == ["Bus"] and summary["out"] == str(out)


def test_bank_entries_the_stock_kitti_filter_drops_are_never_drawn(real, bank, tmp_path):
    """Difficulty -1 (out of camera 2's view; filter_by_difficulty [-1] in every stock
    KITTI config): real ones are kept and counted as they are, bank ones never drawn."""
    for path, hidden in ((real, {"Car": [0, 1]}), (bank, {"Car": range(0, 20, 2), "Cyclist": [0, 1, 2, 3]})):
        infos = load(path)
        for name, indices in hidden.items():
            for index in indices:
                infos[name][index]["difficulty"] = -1
        path.write_bytes(pickle.dumps(infos))
    summary = mix_databases(real, bank, tmp_path / "mixed.pkl", (1.0, 2.0))
    mixed = load(tmp_path / "mixed.pkl")
    assert summary["classes"]["Car"] == {"real": 5, "requested": 10, "bank_available": 10, "bank_used": 10,
                                         "effective_ratio": 2.0}
    assert summary["classes"]["Cyclist"]["bank_available"] == 1 and summary["classes"]["Cyclist"]["bank_used"] == 1
    drawn = [info for infos in mixed.values() for info in infos if str(info["image_idx"]).startswith("pgt_")]
    assert len(drawn) == 10 + 1 + 2 and all(info["difficulty"] != -1 for info in drawn)


def test_real_infos_first_and_unchanged_inputs_untouched(real, bank, tmp_path):
    real_bytes, bank_bytes = real.read_bytes(), bank.read_bytes()
    mix_databases(real, bank, tmp_path / "mixed.pkl")
    mixed, original = load(tmp_path / "mixed.pkl"), load(real)
    for name, infos in original.items():
        assert pickle.dumps(mixed[name][:len(infos)]) == pickle.dumps(infos)
        assert all(info["image_idx"].startswith("pgt_") for info in mixed[name][len(infos):])
    assert real.read_bytes() == real_bytes and bank.read_bytes() == bank_bytes


def test_seed_decides_the_selection_and_bank_order_is_kept(real, bank, tmp_path):
    outs = [tmp_path / name for name in ("a.pkl", "b.pkl", "c.pkl")]
    for out, seed in zip(outs, (7, 7, 8)):
        mix_databases(real, bank, out, (1, 1), seed=seed)
    assert outs[0].read_bytes() == outs[1].read_bytes()
    chosen = [[bank_index(info) for info in load(out)["Car"][5:]] for out in outs]
    assert chosen[0] != chosen[2]  # 5 of 20 cars: another seed draws others
    for indices in chosen:
        assert indices == sorted(indices) and len(set(indices)) == 5


def test_bank_paths_relative_to_root_and_resolvable(real, bank, tmp_path):
    mix_databases(real, bank, tmp_path / "mixed.pkl")
    added = load(tmp_path / "mixed.pkl")["Car"][5:]
    for info in added:
        assert info["path"].startswith("pgt/pgt_gt_database/Car_")
        # mmdet3d's join; OpenPCDet's root_path / path is the same file.
        file = os.path.join(real.parent, info["path"])
        assert np.fromfile(file, np.float32).reshape(-1, 4).shape[0] == info["num_points_in_gt"]
    mix_databases(real, bank, tmp_path / "mixed2.pkl", root=bank.parent)
    assert load(tmp_path / "mixed2.pkl")["Car"][5]["path"].startswith("pgt_gt_database/")


def test_a_bank_assembled_for_a_data_root_resolves_through_its_manifest(real, tmp_path):
    """export_bank.py --data-root writes paths relative to the dataset root and records
    it in OUT/manifest.json (relative to OUT); the mix resolves bank paths through it."""
    out = tmp_path / "data" / "banks" / "pgt"
    (out / "mmdet3d").mkdir(parents=True)
    bank = write_database(out / "mmdet3d" / "kitti_dbinfos_pgt.pkl", BANK_COUNTS, "pgt_gt_database",
                          group_ids=True, bank=True)
    infos = load(bank)
    for entries in infos.values():
        for info in entries:
            info["path"] = f"banks/pgt/mmdet3d/{info['path']}"
    bank.write_bytes(pickle.dumps(infos | {"Van": []}))  # an empty class, as banks list every class
    (out / "manifest.json").write_text('{"data_root": "../.."}')
    summary = mix_databases(real, bank, tmp_path / "mixed.pkl")
    assert summary["skipped"] == ["Bus"]  # a class the bank has no entry for is not "skipped"
    for info in load(tmp_path / "mixed.pkl")["Car"][5:]:
        assert info["path"].startswith("banks/pgt/mmdet3d/pgt_gt_database/Car_")
        assert (real.parent / info["path"]).is_file()
    for manifest, problem in (('{"data_root": 5}', "data_root must be a folder path or null"),
                              ('{"data_root": "../../moved"}', "data_root '../../moved' is no folder from here"),
                              ("[" * 100_000, "damaged (RecursionError")):
        (out / "manifest.json").write_text(manifest)  # damaged, or the bank moved away from its root
        with pytest.raises(InputError, match=re.escape(f"{out / 'manifest.json'}: {problem}")):
            mix_databases(real, bank, tmp_path / "again.pkl")
    assert not (tmp_path / "again.pkl").exists()


def test_bank_outside_root_gets_absolute_paths(real, tmp_path):
    (tmp_path / "elsewhere").mkdir()
    bank = write_database(tmp_path / "elsewhere" / "bank.pkl", BANK_COUNTS, "pgt_gt_database", group_ids=True,
                          bank=True)
    mix_databases(real, bank, tmp_path / "mixed.pkl")
    for info in load(tmp_path / "mixed.pkl")["Cyclist"][2:]:
        assert Path(info["path"]).is_absolute() and Path(info["path"]).is_file()
        assert os.path.join(real.parent, info["path"]) == info["path"]  # the join keeps it


def test_group_ids_fresh_and_unique(real, bank, tmp_path):
    mix_databases(real, bank, tmp_path / "mixed.pkl", (1, 3))
    mixed, original = load(tmp_path / "mixed.pkl"), load(real)
    real_ids = [info["group_id"] for infos in original.values() for info in infos]
    added_ids = [info["group_id"] for name, infos in mixed.items() for info in infos[len(original[name]):]]
    assert added_ids == list(range(max(real_ids) + 1, max(real_ids) + 1 + len(added_ids)))  # in output order
    all_ids = [info["group_id"] for infos in mixed.values() for info in infos]
    assert len(set(all_ids)) == len(all_ids)


def test_openpcdet_databases_mix_without_group_ids(tmp_path):
    """OpenPCDet's format has no group_id, and the merge adds none."""
    (tmp_path / "data" / "pgt").mkdir(parents=True)
    real = write_database(tmp_path / "data" / "pcdet_dbinfos.pkl", REAL_COUNTS, "gt_database")
    bank = write_database(tmp_path / "data" / "pgt" / "kitti_dbinfos_pgt.pkl", BANK_COUNTS, "pgt_gt_database",
                          bank=True)
    mix_databases(real, bank, tmp_path / "mixed.pkl")
    mixed = load(tmp_path / "mixed.pkl")
    assert len(mixed["Car"]) == 10 and not any("group_id" in info for infos in mixed.values() for info in infos)


def garbage(path):
    path.write_bytes(b"\x80\x04not a pickle at all")


def not_a_dict(path):
    path.write_bytes(pickle.dumps([1, 2, 3]))


def nuscenes_boxes(path):
    write_database(path, {"Car": 3}, "pgt_gt_database", box_values=9, group_ids=True, bank=True)


def openpcdet_bank(path):
    """The bank's openpcdet/ pickle (points about the box centre) for an mmdet3d database."""
    write_database(path, BANK_COUNTS, "pgt_gt_database", bank=True)


def missing_box(path):
    infos = load(path)
    del infos["Car"][1]["box3d_lidar"]
    path.write_bytes(pickle.dumps(infos))


def missing_difficulty(path):
    infos = load(path)
    del infos["Cyclist"][0]["difficulty"]
    path.write_bytes(pickle.dumps(infos))


@pytest.mark.parametrize("which, spoil, problem", [
    ("real", Path.unlink, r"cannot read the file \(No such file or directory\)"),
    ("real", lambda path: path.unlink() or path.mkdir(), "is a folder; expected a file"),
    ("real", garbage, "not a readable pickle"),
    ("bank", not_a_dict, "not an info database"),
    ("bank", nuscenes_boxes, r"9 values \(nuScenes layout\) .* 7 values \(KITTI layout\)"),
    ("bank", openpcdet_bank, r"holds OpenPCDet infos \(points about the box centre, no group_id\) but the real "
                             r"database \(kitti_dbinfos_train.pkl\) holds mmdetection3d infos .*; mix the bank's "
                             r"mmdet3d/ pickle"),
    ("real", missing_box, "info 1 of 'Car' lacks box3d_lidar"),
    ("bank", missing_difficulty, "info 0 of 'Cyclist' lacks difficulty"),
])
def test_bad_input_names_the_file_and_writes_nothing(real, bank, tmp_path, which, spoil, problem):
    bad = {"real": real, "bank": bank}[which]
    spoil(bad)
    out = tmp_path / "mixed.pkl"
    with pytest.raises(InputError, match=problem) as caught:
        mix_databases(real, bank, out)
    assert str(caught.value).startswith(f"{bad}: ") and "\n" not in str(caught.value)
    assert_nothing_written(out)


def test_a_bank_with_no_real_class_is_refused(real, tmp_path):
    """Nothing of the bank would be used: refused, unless the ratio asks for no bank entry."""
    bank = write_database(tmp_path / "data" / "buses.pkl", {"Bus": 3, "Car": 0}, "pgt_gt_database", group_ids=True,
                          bank=True)
    with pytest.raises(InputError, match=r"buses.pkl: has no entry of a class kitti_dbinfos_train.pkl has "
                                         r"\(bank classes: Bus\): nothing to mix"):
        mix_databases(real, bank, tmp_path / "mixed.pkl")
    assert_nothing_written(tmp_path / "mixed.pkl")
    assert mix_databases(real, bank, tmp_path / "mixed.pkl", (1, 0))["total"]["bank_used"] == 0


def test_output_must_not_be_an_input(real, bank):
    real_bytes, bank_bytes = real.read_bytes(), bank.read_bytes()
    with pytest.raises(InputError, match="is or holds the input"):
        mix_databases(real, bank, real)
    with pytest.raises(InputError, match="is or holds the input"):
        mix_databases(real, bank, bank.parent / ".." / "pgt" / bank.name)  # the same file, spelt otherwise
    assert real.read_bytes() == real_bytes and bank.read_bytes() == bank_bytes


@pytest.mark.parametrize("ratio", [(0, 1), (1, -1), (1, 2, 3)])
def test_bad_ratio_writes_nothing(real, bank, tmp_path, ratio):
    with pytest.raises(ValueError, match="ratio"):
        mix_databases(real, bank, tmp_path / "mixed.pkl", ratio)
    assert_nothing_written(tmp_path / "mixed.pkl")


def test_real_mmdet3d_kitti_database(shared_data, tmp_path):
    """The real mmdet3d database (one Pedestrian, group_id 0) and a Pedestrian bank
    inside its root: both files load through mmdet3d's join with the right row count."""
    data_root = Path(shutil.copytree(shared_data / "mmdet3d_kitti_gtdb", tmp_path / "kitti"))
    real = data_root / "kitti_dbinfos_train.pkl"
    real_bytes = real.read_bytes()
    (data_root / "pgt").mkdir()
    bank = write_database(data_root / "pgt" / "kitti_dbinfos_pgt.pkl", {"Pedestrian": 4, "Car": 2},
                          "pgt_gt_database", group_ids=True, bank=True)
    summary = mix_databases(real, bank, data_root / "kitti_dbinfos_train_pgt.pkl", parse_ratio("1:1"), seed=3)
    assert summary["classes"]["Pedestrian"] == {"real": 1, "requested": 1, "bank_available": 4, "bank_used": 1,
                                                "effective_ratio": 1.0}
    assert summary["skipped"] == ["Car"]
    mixed = load(data_root / "kitti_dbinfos_train_pgt.pkl")
    assert list(mixed) == ["Pedestrian"] and len(mixed["Pedestrian"]) == 2
    original, added = mixed["Pedestrian"]
    assert original["path"] == "kitti_gt_database/0_Pedestrian_0.bin" and original["num_points_in_gt"] == 377
    assert added["path"].startswith("pgt/pgt_gt_database/Pedestrian_") and added["group_id"] == 1
    for info in mixed["Pedestrian"]:
        points = np.fromfile(os.path.join(data_root, info["path"]), np.float32).reshape(-1, 4)
        assert len(points) == info["num_points_in_gt"] and info["box3d_lidar"].shape == (7,)
    assert real.read_bytes() == real_bytes

    nuscenes = write_database(data_root / "pgt" / "nus.pkl", {"Pedestrian": 2}, "nus", box_values=9, group_ids=True,
                              bank=True)
    with pytest.raises(InputError, match="nuScenes layout"):
        mix_databases(real, nuscenes, tmp_path / "never.pkl")


@pytest.mark.parametrize("crafted", ["real", "bank"])
def test_a_crafted_database_runs_no_code(real, bank, tmp_path, crafted):
    """Info pickles are read with an unpickler that builds only containers, numbers,
    strings and numpy arrays (core/safe_pickle.py): a payload is refused, not run."""
    marker = tmp_path / "code_ran"
    target = real if crafted == "real" else bank
    infos = load(target)
    infos["Car"][0]["score"] = CodeOnLoad(marker)  # hidden inside an otherwise valid database
    target.write_bytes(pickle.dumps(infos))
    out = tmp_path / "mixed.pkl"
    result = run_script("mix_bank.py", "--real", real, "--bank", bank, "--out", out)
    assert result.returncode == 1 and not marker.exists() and not out.exists()
    assert result.stderr.strip() == f"error: {target}: not a readable pickle (UnpicklingError: refused to load " \
                                    f"posix.system: only containers, numbers, strings and numpy arrays may be in it)"


@pytest.mark.parametrize("key, value, problem", [
    ("box3d_lidar", np.array([0, 0, np.nan, 1, 1, 1, 0], np.float32), "box3d_lidar must be 7 or more finite numbers"),
    ("box3d_lidar", "big", "box3d_lidar must be 7 or more finite numbers"),
    ("box3d_lidar", np.array([0, 0, 0, 4, 0, 1.5, 0], np.float32), "box3d_lidar must be .* its dimensions positive"),
    ("box3d_lidar", np.array([1e30, 0, 0, 4, 2, 1.5, 0], np.float32), r"box3d_lidar must be .* within 1e\+08 m"),
    ("num_points_in_gt", -3, "num_points_in_gt must be a count >= 0, got -3"),
    ("num_points_in_gt", 10**30, "num_points_in_gt must be a count >= 0"),
    ("path", 5, "path must be a file path string, got 5"),
    ("path", "a\0b.bin", "path must be a file path string"),
])
def test_garbage_infos_are_refused_not_copied(real, bank, tmp_path, key, value, problem):
    infos = load(bank)
    infos["Car"][2][key] = value
    bank.write_bytes(pickle.dumps(infos))
    with pytest.raises(InputError, match=f"info 2 of 'Car': {problem}"):
        mix_databases(real, bank, tmp_path / "never.pkl")
    assert not (tmp_path / "never.pkl").exists()


def test_gt_database_readers_run_no_code(tmp_path):
    from pgt_blender.core.authoring.heading_classifier import read_gt_database
    from pgt_blender.core.bank.report import real_statistics

    marker = tmp_path / "code_ran"
    crafted = tmp_path / "kitti_dbinfos_train.pkl"
    crafted.write_bytes(pickle.dumps({"Car": [CodeOnLoad(marker)]}))
    for read in (lambda: read_gt_database(crafted, "mmdet3d"), lambda: real_statistics(crafted, dataset="kitti")):
        with pytest.raises(InputError, match="refused to load posix.system"):
            read()
    assert not marker.exists()


def test_cli(real, bank, tmp_path):
    out = tmp_path / "mixed.pkl"
    result = run_script("mix_bank.py", "--real", real, "--bank", bank, "--out", out, "--ratio", "2:1", "--seed", "4")
    assert result.returncode == 0, result.stderr
    rows = {line.split()[0]: line.split()[1:] for line in result.stdout.splitlines() if line.strip()}
    assert rows["Car"] == ["5", "2", "20", "2", "1:0.40"]
    assert rows["Truck"] == ["4", "2", "0", "0", "1:0.00", "(bank", "short)"]
    assert "skipped bank classes absent from the real database: Bus" in result.stdout
    assert f"wrote {out}" in result.stdout
    assert len(load(out)["Car"]) == 7

    again = tmp_path / "again.pkl"
    result = run_script("mix_bank.py", "--real", real, "--bank", bank, "--out", again, "--ratio", "2:1", "--seed", "4",
                        blender_style=True)
    assert result.returncode == 0, result.stderr
    assert again.read_bytes() == out.read_bytes()

    garbage(bank)
    failed = tmp_path / "failed.pkl"
    result = run_script("mix_bank.py", "--real", real, "--bank", bank, "--out", failed)
    assert result.returncode == 1 and result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {bank}: not a readable pickle")
    assert_nothing_written(failed)
