"""The learned intensity estimator: ball patches, Hungarian matching and the group
intensity loss by hand, CycleGAN training (loss goes down, resume == uninterrupted,
checkpoints), inference, the physical fallback and bad input. Synthetic sets only."""

import csv
import importlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pgt_blender.core.errors import InputError
from pgt_blender.core.intensity import losses
from pgt_blender.core.intensity.estimator import scan_intensity
from pgt_blender.core.intensity.objects import ObjectSet
from pgt_blender.core.scan.physical_intensity import dataset_intensity
from pgt_blender.core.scan.returns import RETURN_DTYPE, Scan

ROOT = Path(__file__).resolve().parents[1]
CLASSES = ("car", "truck")
SMALL = dict(points=128, batch=4, steps=6, checkpoint_every=3, threads=1)


def box_surface(count: int, rng) -> np.ndarray:
    """(count, 3) points on the faces of the box [-1, 1]^3."""
    xyz = rng.uniform(-1, 1, (count, 3))
    face = rng.integers(3, size=count)
    xyz[np.arange(count), face] = rng.choice([-1.0, 1.0], size=count)
    return xyz.astype(np.float32)


def synthetic_set(count: int, channels: int, seed: int, points: int = 128) -> ObjectSet:
    """Objects on box surfaces: intensity bright above the middle, color from position."""
    rng = np.random.default_rng(seed)
    xyz = np.stack([box_surface(points, rng) for _ in range(count)])
    values = (0.2 + 0.6 * (xyz[..., 2:] > 0)) if channels == 1 else 0.5 + 0.4 * xyz
    return ObjectSet(xyz, values.astype(np.float32), np.arange(count) % len(CLASSES), CLASSES,
                     [f"object{i}" for i in range(count)], "kitti")


@pytest.fixture(scope="module")
def sets():
    return synthetic_set(6, 1, 0), synthetic_set(6, 3, 1)


@pytest.fixture(scope="module")
def trained(sets, tmp_path_factory):
    """A short run: the folder it wrote."""
    pytest.importorskip("torch")
    from pgt_blender.core.intensity.training import TrainConfig, train

    out = tmp_path_factory.mktemp("trained")
    train(*sets, TrainConfig(**{**SMALL, "steps": 30, "checkpoint_every": 10}), out, progress=False)
    return out


# --- patches, matching and the group loss, by hand -------------------------------------

def test_farthest_point_centres_on_a_line():
    xyz = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [10, 0, 0]], float)
    # centroid x = 3.25: start at x = 10, then the farthest from it (x = 0), then x = 2 (2 from x = 0)
    assert losses.farthest_point_centres(xyz, 3).tolist() == [3, 0, 2]
    padded = np.concatenate([xyz, np.full((2, 3), 99.0)])[None]  # padding rows never chosen
    assert losses.farthest_point_centres(padded, 3, np.array([4])).tolist() == [[3, 0, 2]]


def test_ball_patches_hold_the_points_within_the_radius():
    xyz = np.array([[0, 0, 0], [0.3, 0, 0], [0, 0.6, 0], [2, 0, 0]], float)
    masks = losses.ball_patches(xyz, np.array([0, 3]), 0.5)
    assert masks.tolist() == [[True, True, False, False], [False, False, False, True]]


def test_hungarian_matching_of_three_permuted_patches():
    fake = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0]], float)
    real = np.array([[0, 2.1, 0], [0, 0, 0.1], [1.2, 0, 0]], float)  # fake's centres permuted, moved a little
    rows, cols = losses.match_patches(fake, real)
    assert rows.tolist() == [0, 1, 2] and cols.tolist() == [1, 2, 0]
    # total L1 centre distance 0.1 + 0.2 + 0.1; a greedy pass would agree, the loss below checks the pairing
    means_fake, means_real = np.array([0.1, 0.5, 0.9]), np.array([0.8, 0.2, 0.4])
    # matched real means 0.2, 0.4, 0.8: 0.1 * (|0.1 - 0.2| + |0.5 - 0.4| + |0.9 - 0.8|) = 0.03
    assert losses.matched_patch_loss(means_fake, means_real, cols) == pytest.approx(0.03)


def test_matching_beats_a_greedy_choice():
    fake = np.array([[0, 0, 0], [1.0, 0, 0]])
    real = np.array([[0.1, 0, 0], [-1.0, 0, 0]])
    # L1 costs: f0-r0 0.1, f0-r1 1.0, f1-r0 0.9, f1-r1 2.0. Nearest first (f0-r0) totals 2.1;
    # the optimum crosses the pairs: 1.0 + 0.9 = 1.9
    assert losses.match_patches(fake, real)[1].tolist() == [1, 0]


def three_clusters(centres, intensities, seed):
    """Tight clusters of 10 points around each centre (3, 3), each of one intensity."""
    rng = np.random.default_rng(seed)
    xyz = np.concatenate([c + rng.uniform(-0.02, 0.02, (10, 3)) for c in np.asarray(centres, float)])
    return xyz, np.repeat(np.asarray(intensities, float), 10)


def test_group_intensity_loss_by_hand():
    centres = np.array([[-0.8, 0, 0], [0.8, 0, 0], [0, 0.8, 0.5]])
    xyz_fake, int_fake = three_clusters(centres, [0.1, 0.5, 0.9], 0)
    xyz_real, int_real = three_clusters(centres[[2, 0, 1]] + 0.05, [0.3, 0.2, 0.4], 1)  # permuted, shifted
    # cluster at -0.8 x: 0.1 vs 0.2; at +0.8 x: 0.5 vs 0.4; at +0.8 y: 0.9 vs 0.3 -> 0.1 * 0.8
    loss = losses.group_intensity_loss(xyz_fake, int_fake, xyz_real, int_real, patches=3, radius=0.3)
    assert loss == pytest.approx(0.1 * (0.1 + 0.1 + 0.6))
    order = np.random.default_rng(2).permutation(30)  # the points' order does not matter
    assert losses.group_intensity_loss(xyz_fake[order], int_fake[order], xyz_real, int_real, 3, 0.3) \
        == pytest.approx(loss)
    assert losses.group_intensity_loss(xyz_fake, int_fake, xyz_fake, int_fake, 3, 0.3) == 0.0


def test_patch_loss_is_the_same_on_torch_tensors():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(0)
    masks = rng.random((2, 4, 20)) < 0.5
    masks[:, :, 0] = True
    values, real = rng.random((2, 20)), rng.random((2, 4))
    cols = np.stack([rng.permutation(4) for _ in range(2)])
    expected = losses.matched_patch_loss(losses.patch_means(masks, values), real, cols)
    got = losses.matched_patch_loss(losses.patch_means(torch.from_numpy(masks.astype(float)), torch.from_numpy(values)),
                                    torch.from_numpy(real), torch.from_numpy(cols))
    assert float(got) == pytest.approx(expected, rel=1e-12)


# --- training ----------------------------------------------------------------------------

def loss_rows(folder: Path) -> list:
    with open(folder / "losses.csv", newline="") as stream:
        return list(csv.DictReader(stream))


def test_training_lowers_the_generator_loss_and_logs_every_step(trained):
    from pgt_blender.core.intensity.training import LOSS_COLUMNS

    rows = loss_rows(trained)
    assert tuple(rows[0]) == LOSS_COLUMNS and [int(r["step"]) for r in rows] == list(range(1, 31))
    generator = [float(r["generator"]) for r in rows]
    assert np.mean(generator[-5:]) < 0.9 * np.mean(generator[:5])
    assert all(0 <= float(r["group"]) for r in rows)


def test_checkpoint_round_trip(trained):
    import torch

    from pgt_blender.core.intensity.estimator import IntensityEstimator

    estimator = IntensityEstimator.load(trained / "intensity.pt", "kitti")
    assert estimator.classes == CLASSES and estimator.dataset == "kitti"
    assert estimator.config["lambda_group"] == 0.1 and estimator.config["points"] == 128
    state = torch.load(trained / "checkpoint.pt", weights_only=True)
    assert state["step"] == 30 and state["config"] == estimator.config
    for key, value in estimator.network.state_dict().items():
        assert torch.equal(value, state["networks"]["g"][key]), key


def test_resume_after_an_interruption_gives_the_same_bytes(sets, tmp_path, monkeypatch):
    pytest.importorskip("torch")
    from pgt_blender.core.intensity import training

    config = training.TrainConfig(**SMALL)
    training.train(*sets, config, tmp_path / "whole", progress=False)
    real_step, calls = training.train_step, []

    def interrupted(*args):
        calls.append(1)
        if len(calls) == 5:  # in step 5, after the checkpoint of step 3
            raise KeyboardInterrupt
        return real_step(*args)

    monkeypatch.setattr(training, "train_step", interrupted)
    with pytest.raises(KeyboardInterrupt):
        training.train(*sets, config, tmp_path / "resumed", progress=False)
    monkeypatch.setattr(training, "train_step", real_step)
    assert not (tmp_path / "resumed" / "intensity.pt").exists()
    assert len(loss_rows(tmp_path / "resumed")) == 3
    training.train(*sets, config, tmp_path / "resumed", resume=True, progress=False)
    for name in ("intensity.pt", "checkpoint.pt", "losses.csv", "config.json"):
        assert (tmp_path / "whole" / name).read_bytes() == (tmp_path / "resumed" / name).read_bytes(), name
    assert not list((tmp_path / "resumed").glob(".*partial"))


def test_same_seed_same_bytes_other_seed_other_bytes(sets, tmp_path):
    pytest.importorskip("torch")
    from pgt_blender.core.intensity.training import TrainConfig, train

    paths = [train(*sets, TrainConfig(**{**SMALL, "steps": 2, "seed": seed}), tmp_path / name, progress=False)
             for name, seed in (("a", 5), ("b", 5), ("c", 6))]
    first, again, other = (path.read_bytes() for path in paths)
    assert first == again and first != other


# --- inference and the fallback ----------------------------------------------------------

def an_object(count: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    dims = np.array([4.0, 2.0, 1.5])
    return box_surface(count, rng) * dims / 2, dims, rng.random((count, 3))


def test_predictions_are_per_point_in_range_and_batched_like_single(trained):
    from pgt_blender.core.intensity.estimator import IntensityEstimator

    estimator = IntensityEstimator.load(trained / "intensity.pt")
    objects = [(*an_object(count, seed), CLASSES[seed % 2]) for seed, count in enumerate((5, 128, 700, 3000))]
    batched = estimator.predict_many(objects)
    assert [len(v) for v in batched] == [5, 128, 700, 3000] and estimator.last_rate > 0
    for obj, values in zip(objects, batched):
        assert values.dtype == np.float32 and (values >= 0).all() and (values <= 1).all()
        np.testing.assert_allclose(estimator.predict(*obj), values, atol=1e-5)
        np.testing.assert_array_equal(estimator.predict(*obj), estimator.predict(*obj))  # deterministic
    scan, bounds, face_rgb = a_scan(700, 2)
    half = np.arange(700) % 2 == 0
    values, note = scan_intensity(scan, bounds, face_rgb, "car", trained / "intensity.pt", half)
    assert note.startswith("learned (")
    expected = estimator.predict(scan.box_frame_points(bounds)[half], bounds[1] - bounds[0], face_rgb[half], "car")
    np.testing.assert_array_equal(values, dataset_intensity(expected, "kitti"))


def a_scan(count: int, seed: int = 0, dataset: str = "kitti") -> tuple:
    """(scan, bounds, element sRGB): an_object's points as the returns of a two-sweep scan
    whose second sweep saw the object 1 m further along x; each return hit its own element."""
    xyz, dims, rgb = an_object(count, seed)
    rows = np.zeros(count, RETURN_DTYPE)
    rows["sweep"] = np.arange(count) % 2
    rows["x"], rows["y"], rows["z"] = (xyz + rows["sweep"][:, None] * [1.0, 0, 0]).T
    rows["face"] = np.arange(count)
    rows["intensity"] = 0.25
    shifted = np.eye(4)
    shifted[0, 3] = 1.0
    return Scan(rows, np.zeros(9), count, 0.0, dataset, [np.eye(4), shifted]), np.stack([-dims / 2, dims / 2]), rgb


def test_sweeps_go_to_the_box_frame_of_their_pose():
    scan, bounds, _ = a_scan(10)
    np.testing.assert_allclose(scan.box_frame_points(bounds), an_object(10)[0], atol=1e-12)


def test_without_a_checkpoint_the_scan_keeps_its_physical_intensities(tmp_path):
    scan, bounds, rgb = a_scan(50)
    values, note = scan_intensity(scan, bounds, rgb, "car")
    assert np.array_equal(values, scan.returns["intensity"]) and note == "physical law (no intensity checkpoint given)"
    missing = tmp_path / "none.pt"
    with pytest.raises(InputError, match="none.pt: no intensity-estimator checkpoint here"):
        scan_intensity(scan, bounds, rgb, "car", missing)


def test_without_torch_the_physical_law_and_a_reason(trained):
    code = ("import sys; sys.modules['torch'] = None; sys.path.insert(0, sys.argv[1])\n"
            "import numpy as np\n"
            "from pgt_blender.core.intensity.estimator import scan_intensity\n"
            "from pgt_blender.core.scan.returns import RETURN_DTYPE, Scan\n"
            "rows = np.zeros(1, RETURN_DTYPE); rows['intensity'] = 0.5\n"
            "scan = Scan(rows, np.zeros(9), 1, 0.0, 'kitti', [np.eye(4)])\n"
            "values, note = scan_intensity(scan, np.array([[-2, -1, 0], [2, 1, 1.5]]), np.ones((1, 3)), 'car', "
            "sys.argv[2])\n"
            "print(f'{values[0]:.3f}', note)\n")
    result = subprocess.run([sys.executable, "-c", code, str(ROOT / "addon"), str(trained / "intensity.pt")],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == (f"0.500 physical law: PyTorch (torch==2.13.0) is not installed, so "
                                     f"{trained / 'intensity.pt'} was not used")


# --- bad input ---------------------------------------------------------------------------

def test_training_rejects_mismatched_columns_and_nan_intensities(sets, tmp_path):
    pytest.importorskip("torch")
    from pgt_blender.core.intensity.training import TrainConfig, train

    real, rgb = sets
    config = TrainConfig(**SMALL)
    with pytest.raises(InputError, match=r"^real objects: values have shape \(6, 128, 3\), expected \(6, 128, 1\)"):
        train(rgb, rgb, config, tmp_path, progress=False)
    broken = ObjectSet(real.xyz, real.values.copy(), real.class_index, CLASSES, real.names, "kitti")
    broken.values[2, :3] = np.nan
    with pytest.raises(InputError, match=r"^object2: real values are NaN or infinite at 3 of 128 points$"):
        train(broken, rgb, config, tmp_path, progress=False)
    with pytest.raises(InputError, match="64 points each, the config says 128"):
        train(synthetic_set(6, 1, 0, points=64), rgb, config, tmp_path, progress=False)
    assert not (tmp_path / "checkpoint.pt").exists()


def test_a_folder_in_the_way_of_an_output_is_found_before_training(sets, tmp_path):
    from pgt_blender.core.intensity.training import TrainConfig, train

    (tmp_path / "intensity.pt").mkdir()
    with pytest.raises(InputError, match=f"{tmp_path / 'intensity.pt'}: is a folder; expected a file name"):
        train(*sets, TrainConfig(**SMALL), tmp_path, progress=False)
    assert [path.name for path in tmp_path.iterdir()] == ["intensity.pt"]


def test_resume_refuses_another_run_and_a_corrupt_checkpoint(sets, trained, tmp_path):
    import shutil

    from pgt_blender.core.intensity.training import TrainConfig, train

    folder = Path(shutil.copytree(trained, tmp_path / "copy"))
    config = TrainConfig(**{**SMALL, "steps": 40, "checkpoint_every": 10})
    losses = (folder / "losses.csv").read_bytes()
    for garbage, problem in ((b"\xff\xfe\x00", "codec"), (b"step,loss\n1,2\n", "the header is not step,generator"),
                             (losses + b"31,0.5\n", "line 32 has 2 values"), (losses + b"x" * 9 + losses[-20:], "")):
        (folder / "losses.csv").write_bytes(garbage)
        with pytest.raises(InputError, match=rf"losses.csv: damaged \(.*{problem}.*\); delete it to resume"):
            train(*sets, config, folder, resume=True, progress=False)
    (folder / "losses.csv").write_bytes(losses)
    with pytest.raises(InputError, match=r"checkpoint.pt: was written by a different run \(seed: 0 there, 1 now\)"):
        train(*sets, TrainConfig(**{**SMALL, "steps": 40, "checkpoint_every": 10, "seed": 1}), folder,
              resume=True, progress=False)
    other_objects = synthetic_set(6, 1, 5)  # a setting is named before the objects it draws
    with pytest.raises(InputError, match=r"run \(seed: 0 there, 1 now\)"):
        train(other_objects, sets[1], TrainConfig(**{**SMALL, "steps": 40, "checkpoint_every": 10, "seed": 1}),
              folder, resume=True, progress=False)
    with pytest.raises(InputError, match=r"run \(the training objects differ\); train without --resume"):
        train(other_objects, sets[1], config, folder, resume=True, progress=False)
    settings = (folder / "config.json").read_bytes()
    with pytest.raises(InputError, match=r"checkpoint.pt: is at step \d+, past the 5 steps asked for"):
        train(*sets, TrainConfig(**{**SMALL, "steps": 5, "checkpoint_every": 10}), folder, resume=True, progress=False)
    assert (folder / "config.json").read_bytes() == settings  # a refused resume changes nothing
    import torch

    state = torch.load(folder / "checkpoint.pt", weights_only=True)
    for damage in ({"step": "x"}, {"step": -5}, {"networks": None}, {"networks": {"g": {}}}):
        torch.save({**state, **damage}, folder / "checkpoint.pt")
        with pytest.raises(InputError, match=r"checkpoint.pt: damaged \(.*; train without --resume"):
            train(*sets, config, folder, resume=True, progress=False)
        assert (folder / "config.json").read_bytes() == settings
    (folder / "checkpoint.pt").write_bytes(b"PK\x03\x04 broken")
    with pytest.raises(InputError, match="not a readable intensity training checkpoint"):
        train(*sets, TrainConfig(**{**SMALL, "steps": 40, "checkpoint_every": 10}), folder, resume=True, progress=False)


def test_bad_checkpoints_classes_datasets_and_arrays(trained, tmp_path):
    import torch

    from pgt_blender.core.intensity.estimator import IntensityEstimator

    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a checkpoint at all")
    foreign = tmp_path / "heading.pt"
    torch.save({"format": "pgt_blender.heading_pointnet/1", "state_dict": {}}, foreign)
    for path in (corrupt, foreign):
        with pytest.raises(InputError, match="not a readable intensity-estimator checkpoint") as error:
            IntensityEstimator.load(path)
        assert str(error.value).startswith(f"{path}: ") and "\n" not in str(error.value)
    path = trained / "intensity.pt"
    saved = torch.load(path, weights_only=True)
    for field, value in (("dataset", None), ("points", -1), ("classes", "car"), ("config", None)):
        damaged = tmp_path / f"{field}.pt"
        config = None if field == "config" else {**saved["config"], field: value}
        torch.save({**saved, "config": config}, damaged)
        with pytest.raises(InputError, match=f"^{damaged}: not a readable intensity-estimator checkpoint "
                                             f"\\(ValueError: its config"):
            IntensityEstimator.load(damaged)
    with pytest.raises(InputError, match=f"^{path}: was trained on kitti intensities, not nuscenes's$"):
        IntensityEstimator.load(path, "nuscenes")
    xyz, dims, rgb = an_object(20)
    scan, bounds, face_rgb = a_scan(20)
    with pytest.raises(InputError, match=r"has no class 'bus' \(trained for car, truck\)"):
        scan_intensity(scan, bounds, face_rgb, "bus", path)
    for checkpoint in (path, IntensityEstimator.load(path)):
        with pytest.raises(InputError, match="not nuscenes's"):
            scan_intensity(a_scan(20, dataset="nuscenes")[0], bounds, face_rgb, "car", checkpoint)
    estimator = IntensityEstimator.load(path)
    bad_arrays = {
        r"colors have shape \(20, 4\), expected \(20, 3\)": (xyz, dims, np.ones((20, 4))),
        r"points have shape \(20, 2\)": (xyz[:, :2], dims, rgb),
        "points or colors are NaN or infinite": (np.where(np.arange(20)[:, None] == 3, np.nan, xyz), dims, rgb),
        r"colors span 0\.\.255": (xyz, dims, np.full((20, 3), 255.0) * (np.arange(20) > 0)[:, None]),
        "box dims must be three positive": (xyz, (4.0, 0.0, 1.0), rgb),
    }
    for message, (points, box, colors) in bad_arrays.items():
        with pytest.raises(InputError, match=f"^truck7: {message}"):
            estimator.predict(points, box, colors, "car", name="truck7")


# --- the script --------------------------------------------------------------------------

@pytest.fixture
def script(sets, monkeypatch):
    """The train_intensity command's module, reading the synthetic sets instead of data files."""
    module = importlib.import_module("pgt_blender.commands.train_intensity")
    monkeypatch.setattr(module, "load_sets", lambda args: sets)
    return module


def test_train_script_writes_and_resumes(script, tmp_path, capsys):
    pytest.importorskip("torch")
    out = tmp_path / "run"
    base = ["--out", out, "--points", "128", "--checkpoint-every", "2", "--threads", "1", "--real", tmp_path]
    assert script.main([str(a) for a in base + ["--steps", "2"]]) == 0
    assert script.main([str(a) for a in base + ["--steps", "4", "--resume"]]) == 0
    printed = capsys.readouterr().out
    assert "trained to step 4" in printed and "points/s" in printed
    assert [r["step"] for r in loss_rows(out)] == ["1", "2", "3", "4"]
    assert {p.name for p in out.iterdir()} == {"config.json", "losses.csv", "checkpoint.pt", "intensity.pt"}


def test_train_script_bad_input_is_one_line_and_exit_1(script, tmp_path, monkeypatch, capsys):
    def bad(args):
        raise InputError(tmp_path / "db.pkl", "not a ground-truth database pickle")

    monkeypatch.setattr(script, "load_sets", bad)
    assert script.cli.run_main(script.main, ["--out", str(tmp_path / "run"), "--real", str(tmp_path)]) == 1
    assert capsys.readouterr().err == f"error: {tmp_path / 'db.pkl'}: not a ground-truth database pickle\n"
    assert not (tmp_path / "run").exists()
