"""The learned front/back classifier: training, checkpoints, flip antisymmetry, the
shipped checkpoint, ground-truth databases and train_heading.py (real torch, no mocks)."""

import importlib.util
import json
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pgt_blender.core.authoring import heading_classifier as hc
from pgt_blender.core.classes import CLASS_SIZES
from pgt_blender.core.errors import InputError

from .conftest import run_script

ROOT = Path(__file__).resolve().parents[1]
needs_torch = pytest.mark.skipif(importlib.util.find_spec("torch") is None, reason="needs PyTorch (the 'learn' extra)")
FLIP = np.array([-1.0, -1.0, 1.0])


@pytest.fixture(scope="module")
def samples():
    return hc.sample_point_sets()


@pytest.fixture(scope="module")
def short_run(samples):
    """A short training run on the six built-in sample vehicles."""
    return hc.train(samples, seed=0, steps=250)


def draw(item, count, seed):
    rng = np.random.default_rng(seed)
    return item.points[rng.choice(len(item.points), count, replace=False)]


@needs_torch
def test_short_training_learns(samples, short_run):
    right = []
    for item in samples:
        for seed in range(4):  # fresh samplings, half of them turned 180 degrees
            cloud = draw(item, 1024, 100 + seed)
            front_at_x = seed % 2 == 0
            p = hc.front_probability(cloud if front_at_x else cloud * FLIP, item.dims, short_run)
            right.append((p > 0.5) == front_at_x)
    assert np.mean(right) > 0.9
    assert short_run.config["flip_p"] == 0.5 and short_run.config["rotation_augmentation"] is False


@needs_torch
def test_collapsed_training_is_an_error_not_a_checkpoint(samples):
    # batch normalisation keeps the ReLUs alive at any sane rate; one this absurd overflows the weights
    with pytest.raises(InputError, match="collapsed after 30 steps"):
        hc.train(samples, seed=0, steps=30, lr=1e20)


@needs_torch
def test_training_needs_batches_of_two(samples):
    with pytest.raises(ValueError, match="batch 1"):  # batch normalisation has nothing to normalise
        hc.train(samples, steps=1, batch=1)


@needs_torch
def test_checkpoint_round_trip_keeps_probabilities_and_config(samples, short_run, tmp_path):
    path = tmp_path / "heading.pt"
    hc.save_checkpoint(path, short_run)
    loaded = hc.load_checkpoint(path)
    assert loaded.config == short_run.config
    assert [s["source"].split(" ")[0] for s in loaded.config["sources"]] == sorted(
        f"sample:{item.name}" for item in samples)
    for item in samples:
        cloud = draw(item, 300, 7)
        assert hc.front_probability(cloud, item.dims, path) == hc.front_probability(cloud, item.dims, short_run)
    assert not list(tmp_path.glob("*.partial"))


@needs_torch
def test_same_seed_same_checkpoint_bytes(samples, tmp_path):
    paths = []
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        paths.append(tmp_path / f"{name}.pt")
        hc.save_checkpoint(paths[-1], hc.train(samples[:2], seed=seed, steps=5))
    first, again, other = (p.read_bytes() for p in paths)
    assert first == again and first != other


@needs_torch
@pytest.mark.parametrize("seed", range(4))
def test_flip_antisymmetry(samples, seed):
    rng = np.random.default_rng(seed)
    item = samples[seed]
    cloud = draw(item, int(rng.integers(10, 2000)), seed) + rng.normal(scale=0.05, size=3)
    p = hc.front_probability(cloud, item.dims)
    assert hc.front_probability(cloud * FLIP, item.dims) == pytest.approx(1 - p, abs=1e-12)
    assert hc.front_probability(cloud, item.dims) == p  # deterministic


@needs_torch
def test_shipped_checkpoint_gets_the_samples_right_both_ways(samples):
    assert hc.DEFAULT_CHECKPOINT.stat().st_size < 300_000
    config = hc.load_checkpoint().config
    assert (config["flip_p"], config["rotation_augmentation"], config["seed"]) == (0.5, False, 0)
    sources = [source["source"] for source in config["sources"]]
    for item in samples:  # trained on what a LiDAR sees of every vehicle as well as on dense samples
        assert sum(source.startswith(f"sample:{item.name} ") for source in sources) == 2, item.name
        assert any(source.startswith(f"sample:{item.name} ") and source.endswith(" scans:nuscenes")
                   for source in sources), item.name
    for item in samples:
        cloud = draw(item, 2048, 1)
        assert hc.front_probability(cloud, item.dims) > 0.5, item.name
        assert hc.front_probability(cloud * FLIP, item.dims) < 0.5, item.name


@needs_torch
def test_missing_and_corrupt_checkpoints_name_the_file(tmp_path):
    cloud, dims = np.zeros((5, 3)), (4.0, 2.0, 1.5)
    missing = tmp_path / "missing.pt"
    with pytest.raises(InputError, match="no heading-classifier checkpoint here") as error:
        hc.front_probability(cloud, dims, missing)
    assert error.value.path == missing
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"PK\x03\x04 not really a zip archive")
    with pytest.raises(InputError, match="not a readable heading-classifier checkpoint") as error:
        hc.load_checkpoint(corrupt)
    assert str(error.value).startswith(f"{corrupt}: ") and "\n" not in str(error.value)
    text = tmp_path / "report.md"
    text.write_text("# not a checkpoint\n")
    with pytest.raises(InputError) as error:  # torch's own text advises weights_only=False: not passed on
        hc.load_checkpoint(text)
    assert str(error.value) == (f"{text}: not a readable heading-classifier checkpoint (not a torch file of tensors "
                                "and plain values, the only kind read)")
    import torch

    foreign = tmp_path / "foreign.pt"
    torch.save({"state_dict": {}}, foreign)
    with pytest.raises(InputError, match="format None"):
        hc.load_checkpoint(foreign)
    shipped = torch.load(hc.DEFAULT_CHECKPOINT, weights_only=True)
    no_points = {key: value for key, value in shipped["config"].items() if key != "points"}
    for config in (None, {**shipped["config"], "points": 0}, no_points):
        damaged = tmp_path / "damaged.pt"
        torch.save({**shipped, "config": config}, damaged)
        with pytest.raises(InputError, match=f"^{damaged}: not a readable heading-classifier checkpoint "
                                             r"\(ValueError: its config"):
            hc.load_checkpoint(damaged)


def test_without_torch_the_message_is_clear():
    code = ("import sys; sys.modules['torch'] = None; sys.path.insert(0, sys.argv[1])\n"
            "from pgt_blender.core.authoring.heading_classifier import front_probability\n"
            "from pgt_blender.core.errors import InputError\n"
            "try:\n    front_probability([[0.0, 0.0, 0.0]], [4.0, 2.0, 1.5])\n"
            "except InputError as error:\n    print(error)\n")
    result = subprocess.run([sys.executable, "-c", code, str(ROOT / "addon")], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == (f"{hc.DEFAULT_CHECKPOINT}: the heading classifier needs PyTorch "
                                     "(torch==2.13.0), which this Python cannot import")


def test_gt_database_reader_on_the_real_mmdet3d_sample(shared_data):
    database = shared_data / "mmdet3d_kitti_gtdb" / "kitti_dbinfos_train.pkl"
    (pedestrian,) = hc.read_gt_database(database, "mmdet3d")
    assert pedestrian.name == "Pedestrian:kitti_gt_database/0_Pedestrian_0.bin"
    assert pedestrian.points.shape == (377, 3)
    np.testing.assert_allclose(pedestrian.dims, [1.2, 0.48, 1.89], rtol=1e-6)
    half = pedestrian.dims / 2
    assert (np.abs(pedestrian.points) <= half + 0.01).all()  # inside the box, centred
    assert pedestrian.points[:, 2].min() == pytest.approx(-half[2], abs=0.01)  # feet on the box bottom
    (same,) = hc.read_gt_database(database)  # the convention read from its infos (a group_id each)
    np.testing.assert_array_equal(same.points, pedestrian.points)
    with pytest.raises(InputError, match="holds mmdetection3d infos .* not openpcdet's: leave the convention out"):
        hc.read_gt_database(database, "openpcdet")  # read as if centred, it would float half its height


@pytest.mark.parametrize("convention", ["mmdet3d", "openpcdet"])
def test_gt_database_reader_undoes_the_box_pose(tmp_path, convention):
    """Points written the way each tool writes them come back in the object frame."""
    rng = np.random.default_rng(0)
    dims, heading, centre = np.array([4.0, 1.8, 1.5]), 2.5, np.array([10.0, -3.0, -0.8])
    local = rng.uniform(-0.5, 0.5, (50, 3)) * dims
    cos, sin = np.cos(heading), np.sin(heading)
    lidar = local @ np.array([[cos, -sin, 0], [sin, cos, 0], [0, 0, 1]]).T + centre
    origin = centre - [0, 0, dims[2] / 2] if convention == "mmdet3d" else centre
    stored = np.column_stack([lidar - origin, rng.random(50)]).astype(np.float32)  # x, y, z, intensity
    (tmp_path / "db").mkdir()
    stored.tofile(tmp_path / "db" / "0_Car_0.bin")
    box = np.concatenate([origin, dims, [heading]]).astype(np.float32)
    infos = {"Car": [{"name": "Car", "path": "db/0_Car_0.bin", "box3d_lidar": box, "num_points_in_gt": 50},
                     {"name": "Car", "path": "db/0_Car_1.bin", "box3d_lidar": box, "num_points_in_gt": 2}]}
    if convention == "mmdet3d":  # its create_groundtruth_database gives every info a group_id
        for index, info in enumerate(infos["Car"]):
            info["group_id"] = index
    (tmp_path / "dbinfos.pkl").write_bytes(pickle.dumps(infos))
    (car,) = hc.read_gt_database(tmp_path / "dbinfos.pkl", convention)  # the 2-point object is skipped
    np.testing.assert_allclose(car.points, local, atol=1e-5)
    np.testing.assert_allclose(car.dims, dims)


def test_gt_database_reader_rejects_a_bad_pickle(tmp_path):
    bad = tmp_path / "bad.pkl"
    bad.write_bytes(b"not a pickle")
    with pytest.raises(InputError, match="not a readable pickle") as error:
        hc.read_gt_database(bad, "mmdet3d")
    assert error.value.path == bad


@needs_torch
@pytest.mark.parametrize("case", ["missing_chrono", "bad_pickle"])
def test_train_script_bad_input_exits_non_zero_and_writes_nothing(tmp_path, case):
    out = tmp_path / "out" / "heading.pt"
    if case == "missing_chrono":
        culprit = tmp_path / "no_such_folder"
        result = run_script("train_heading.py", "--out", out, "--chrono", culprit)
        expected = f"error: {culprit}: no such mesh folder"
    else:
        culprit = tmp_path / "bad.pkl"
        culprit.write_bytes(b"\x80\x04garbage")
        result = run_script("train_heading.py", "--out", out, "--gt-database", culprit, "--gt-convention", "openpcdet")
        expected = f"error: {culprit}: "
    assert result.returncode == 1
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and errors[0].startswith(expected), result.stderr
    assert not out.parent.exists()


@needs_torch
def test_bench_script_runs(tmp_path):
    result = run_script("bench_heading.py", "--steps", "2", "--samplings", "2", "--seeds", "2",
                        "--out", tmp_path / "heading")
    assert result.returncode == 0, result.stderr
    report = json.loads((tmp_path / "heading.json").read_text())
    assert len(report["cells"]) == 12 and report["settings"]["training_steps"] == 2
    assert report["settings"]["training_seeds"] == 2 and {row["seed"] for row in report["rows"]} == {0, 1}
    assert {m["mesh"] for m in report["per_mesh"]} >= {"truck", "bicycle"}
    classes = {m["class"] for m in report["per_mesh"]}
    assert {"truck", "trailer"} <= classes <= set(CLASS_SIZES["nuscenes"])  # the Chrono chassis' too
    assert (tmp_path / "heading.png").stat().st_size > 0
    assert "| points | noise (of box diagonal) | baseline | classifier |" in result.stdout
    assert "| class | meshes | dense: baseline |" in result.stdout


def test_training_draws_each_kind_of_set_equally_often():
    """One dense set among 30 scanned views still fills about half of the batches."""
    dense = hc.PointSet("dense", np.zeros((8, 3)), np.ones(3), "mesh:a")
    views = [hc.PointSet(f"view{i}", np.full((8, 3), 0.1), np.ones(3), "mesh:a scans:x", kind="scan")
             for i in range(30)]
    config = {"count_range": [8, 8], "batch": 2000, "points": 8, "noise_max": 0.0, "scale_jitter": 0.0,
              "flip_p": 0.0, "mirror_p": 0.0}
    clouds, _ = hc._training_batch(hc._by_kind([dense, *views]), config, np.random.default_rng(0))
    dense_share = np.mean(np.all(clouds[:, :, :3] == 0, axis=(1, 2)))
    assert 0.45 < dense_share < 0.55


@pytest.fixture(scope="module")
def truck_scans():
    name, mesh, source = hc.sample_meshes(["truck"])[0]
    return hc.scanned_point_sets(mesh, name, source, "nuscenes", ranges=(10.0, 30.0), headings=4), mesh


def test_scans_are_partial_one_sided_views_in_the_object_frame(truck_scans):
    """Each view holds only what the sensor saw: inside the box, fewer points far away,
    the rear seen when the front points away (heading 0) and the front when turned
    180 degrees; the dims are the whole mesh's box."""
    views, mesh = truck_scans
    assert [v.name for v in views] == [f"truck@{r}m/{h}deg" for r in (10, 30) for h in (0, 90, 180, 270)]
    dims = mesh.extents
    for view in views:
        np.testing.assert_allclose(view.dims, dims)
        assert (np.abs(view.points) <= dims / 2 + 1e-6).all()
        assert view.source.endswith("scans:nuscenes")
    near, far = views[:4], views[4:]
    assert all(len(n.points) > 2 * len(f.points) for n, f in zip(near, far))
    assert near[0].points[:, 0].mean() < -dims[0] / 4 < dims[0] / 4 < near[2].points[:, 0].mean()
    assert near[3].points[:, 1].mean() < 0 < near[1].points[:, 1].mean()  # turned left: its left side faces us


@needs_torch
def test_short_training_on_scans_learns_them(samples, truck_scans):
    """Dense samples plus scans, a short run: the scanned views are told front from back."""
    views, _ = truck_scans
    classifier = hc.train(samples + views, seed=0, steps=250)
    right = [(hc.front_probability(cloud, view.dims, classifier) > 0.5) == front
             for view in views for front, cloud in ((True, view.points), (False, view.points * FLIP))]
    assert np.mean(right) >= 0.85
    assert any("scans:nuscenes" in source["source"] for source in classifier.config["sources"])
