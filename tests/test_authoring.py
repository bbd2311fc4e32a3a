"""Heading, sizing and the headless authoring chain (core and prepare_objects.py)."""

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from pgt_blender.core.authoring import heading, sizing
from pgt_blender.core.authoring.prepare import (AuthoredObject, apply_transform, prepare, size_step,
                                                up_vector, write_prepared)
from pgt_blender.core.classes import CLASS_SIZES, MINORITY_CLASSES
from pgt_blender.core.errors import InputError
from pgt_blender.core.importing import load_reconstruction
from pgt_blender.core.reconstruction import Reconstruction
from pgt_blender.core.samples import sample_vehicle, write_sample

from .conftest import run_script


def yawed_sample(class_name, yaw_degrees, offset=(3.0, -2.0, 1.0), count=20000) -> Reconstruction:
    """Surface points of a sample vehicle turned about z (up stays +z), as a recon."""
    points, _ = trimesh.sample.sample_surface(sample_vehicle(class_name).trimesh(), count, seed=21)
    c, s = np.cos(np.radians(yaw_degrees)), np.sin(np.radians(yaw_degrees))
    rotated = points @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + offset
    return Reconstruction(rotated.astype(np.float32), "point_ply", source=Path(f"{class_name}.ply"), sha256="0" * 64)


# ---- heading ----------------------------------------------------------------------------

def test_quarter_turns_are_exact():
    assert np.array_equal(heading.quarter_turns(4), np.eye(4))
    assert np.array_equal(heading.quarter_turns(1)[:3, :3] @ [1, 0, 0], [0, 1, 0])
    assert np.array_equal(heading.quarter_turns(2) @ heading.quarter_turns(2), np.eye(4))
    assert np.array_equal(heading.quarter_turns(-1), heading.quarter_turns(3))
    np.testing.assert_array_equal(heading.transformed_dims(heading.quarter_turns(1), [4, 2, 1]), [2, 4, 1])


@pytest.mark.parametrize("direction, front", [((5, 0.4, 9), (1, 0)), ((0.2, 3, 0), (0, 1)),
                                              ((-2, 1, 0), (-1, 0)), ((1, -3, 0), (0, -1))])
def test_front_towards_snaps_to_the_facing_side(direction, front):
    rotation = heading.front_towards(direction)
    np.testing.assert_array_equal(rotation[:3, :3] @ [*front, 0], [1, 0, 0])


def test_front_towards_needs_a_horizontal_direction():
    with pytest.raises(ValueError, match="horizontal component"):
        heading.front_towards((0, 0, 1))


@pytest.mark.parametrize("class_name", ["truck", "construction_vehicle"])
def test_baseline_finds_a_low_front(class_name):
    points, _ = trimesh.sample.sample_surface(sample_vehicle(class_name).trimesh(), 5000, seed=22)
    score = heading.profile_front_score(points)
    assert score > 0.05
    assert heading.profile_front_score(points * [-1, -1, 1]) == pytest.approx(-score)


@pytest.mark.parametrize("probability, score, front, decided_by", [
    (0.9, -0.5, True, "classifier"), (0.1, 0.5, False, "classifier"),
    (0.6, -0.2, False, "baseline"), (0.45, 0.1, True, "baseline"),
    (0.5 + heading.CLASSIFIER_DOUBT, -0.1, False, "baseline"), (0.5 - heading.CLASSIFIER_DOUBT - 1e-9, 0.3, False,
                                                                "classifier")])
def test_front_decision_defers_to_the_baseline_where_the_classifier_is_unsure(probability, score, front,
                                                                             decided_by):
    assert heading.front_decision(probability, score) == (front, decided_by)


def test_detect_front_by_classifier_and_by_baseline_where_it_is_unsure():
    """The shipped classifier is sure about the sample truck; a plain box looks alike
    from both ends, so the baseline's score decides it."""
    from pgt_blender.core.authoring.heading_classifier import front_probability

    truck = sample_vehicle("truck").trimesh()
    points, _ = trimesh.sample.sample_surface(truck, 4000, seed=23)
    points -= truck.bounds.mean(axis=0)
    assert heading.automatic_front(points, truck.extents, "classifier")[::2] == (0, "classifier")
    assert heading.automatic_front(points * [-1, -1, 1], truck.extents, "classifier")[::2] == (2, "classifier")
    box, _ = trimesh.sample.sample_surface(trimesh.creation.box(extents=(4.0, 2.0, 1.5)), 4000, seed=24)
    box[:, 2] += np.where(box[:, 0] > 1.0, 0.05, 0.0)  # the +x quarter 5 cm higher: the baseline's rear
    box -= (box.max(axis=0) + box.min(axis=0)) / 2
    dims = np.ptp(box, axis=0)
    assert abs(front_probability(box, dims) - 0.5) <= heading.CLASSIFIER_DOUBT
    turns, score, decided_by = heading.automatic_front(box, dims, "classifier")
    assert (turns, score, decided_by) == (2, heading.profile_front_score(box), "baseline")


def test_running_gear_puts_a_trailers_front_ahead_of_its_wheels(tmp_path):
    """A box on stilts whose only low points are wheels 3 m behind the middle of its 10 m:
    the score is 0.3 exactly; the sample trailer (landing gear in front, tandem axle at
    the back) scores positive, and minus that turned 180 degrees."""
    rng = np.random.default_rng(3)
    body = rng.uniform([-5, -1.2, -1.0], [5, 1.2, 2.0], (500, 3))  # above the lowest quarter of 4 m
    wheels = np.column_stack([rng.uniform(-3.5, -2.5, 40), rng.uniform(-1.2, 1.2, 40), rng.uniform(-2, -1.2, 40)])
    wheels[:, 0] += -3.0 - wheels[:, 0].mean()
    dims = (10.0, 2.4, 4.0)
    assert heading.running_gear_front_score(np.r_[body, wheels], dims) == pytest.approx(0.3)
    assert heading.running_gear_front_score(body, dims) is None  # no wheels seen
    three = np.r_[body, wheels[:3]]
    assert heading.running_gear_front_score(three, dims) == pytest.approx(-wheels[:3, 0].mean() / 10)
    assert heading.running_gear_front_score(three[:-1], dims) is None  # below RUNNING_GEAR_MIN_POINTS
    assert heading.running_gear_front_score(np.r_[body, wheels] * [1, 1, 0], (10.0, 2.4, 1e-15)) is None  # flat
    assert heading.baseline_score(body, dims, "trailer") == (heading.profile_front_score(body), "baseline")
    trailer = sample_vehicle("trailer").trimesh()
    points, _ = trimesh.sample.sample_surface(trailer, 4000, seed=25)
    points -= trailer.bounds.mean(axis=0)
    score, rule = heading.baseline_score(points, trailer.extents, "trailer")
    assert score > 0.1 and rule == "running gear"
    assert heading.baseline_score(points * [-1, -1, 1], trailer.extents, "trailer")[0] == pytest.approx(-score)
    assert heading.baseline_score(points, trailer.extents, "truck")[1] == "baseline"  # the rule is the trailer's
    # Detect Front: a trailer's running gear decides, so neither torch nor the checkpoint is needed
    missing = tmp_path / "no_checkpoint.pt"
    assert heading.automatic_front(points * [-1, -1, 1], trailer.extents, "classifier", missing,
                                   class_name="trailer") == (2, pytest.approx(-score), "running gear")
    with pytest.raises(ValueError, match="no_checkpoint.pt"):
        heading.automatic_front(points, trailer.extents, "classifier", missing, class_name="truck")


@pytest.mark.parametrize("probability", [0.01, 0.5, 0.99])
def test_front_decision_leaves_a_trailer_to_its_running_gear(probability):
    assert heading.front_decision(probability, -0.2, "running gear") == (False, "running gear")


@pytest.mark.parametrize("seed", [0, 1])
def test_prepare_heads_a_sample_trailer_by_its_running_gear(tmp_path, seed):
    """A synthetic trailer reconstruction, randomly posed with floaters: prepared as a
    trailer, its front ends up at +x (the truth's), decided by the running gear."""
    paths = write_sample(tmp_path, "trailer", seed=seed, points=8000)
    truth = np.array(json.loads(paths["truth.json"].read_text())["source_from_object"])
    authored = prepare(load_reconstruction(paths["reconstruction.ply"]), "trailer", size="keep")
    assert authored.steps[1].details["decided_by"] == "running gear" and authored.steps[1].details["class"] == "trailer"
    forward = authored.object_from_source[:3, :3] @ truth[:3, 0]  # the true front, in the found object frame
    assert forward[0] / np.linalg.norm(forward) > 0.99


# ---- sizing -----------------------------------------------------------------------------

def test_class_size_noise_is_seeded_and_clipped():
    mean = sizing.class_dims("nuscenes", "truck")
    draws = np.array([sizing.sample_dims("nuscenes", "truck", seed) for seed in range(300)])
    ratios = draws / mean
    assert ratios.min() >= 0.9 - 1e-12 and ratios.max() <= 1.1 + 1e-12
    assert np.isclose(ratios, 1.1).any() and np.isclose(ratios, 0.9).any()  # the clip is hit
    assert 0.065 < np.std(ratios - 1) < 0.078  # N(0, 0.1) clipped at 1 sigma: std 0.0718
    assert np.array_equal(sizing.sample_dims("nuscenes", "truck", 7), sizing.sample_dims("nuscenes", "truck", 7))
    uniform = sizing.sample_dims("lyft", "bus", 7, uniform=True) / sizing.class_dims("lyft", "bus")
    assert np.ptp(uniform) < 1e-12


@pytest.mark.parametrize("dataset", sorted(CLASS_SIZES))
def test_every_preset_has_positive_sizes(dataset):
    for class_name in CLASS_SIZES[dataset]:
        assert (sizing.class_dims(dataset, class_name) > 0).all()


def test_unknown_dataset_or_class():
    with pytest.raises(ValueError, match="unknown dataset 'waymo'"):
        sizing.class_dims("waymo", "truck")
    with pytest.raises(ValueError, match="kitti has no class 'bus' \\(have: car, pedestrian, cyclist, truck, van\\)"):
        sizing.class_dims("kitti", "bus")
    np.testing.assert_allclose(sizing.class_dims("kitti", "truck"), [10.14, 2.59, 3.25])  # KITTI's Truck labels


def test_scale_to_anisotropic_and_uniform():
    scale, dims = sizing.scale_to([2.0, 1.0, 0.5], [8.0, 2.0, 2.0])
    np.testing.assert_allclose(dims, [8.0, 2.0, 2.0])
    np.testing.assert_allclose(np.diag(scale)[:3], [4.0, 2.0, 4.0])
    scale, dims = sizing.scale_to([2.0, 1.0, 0.5], [8.0, 2.0, 2.0], uniform=True)
    np.testing.assert_allclose(np.diag(scale)[:3], np.cbrt(32.0))
    assert np.prod(dims) == pytest.approx(32.0)
    for flat in ([2.0, 1.0, 0.0], [2.0, 1.0, 1e-16]):  # 1e-16: a flat cloud's float noise after Align
        with pytest.raises(ValueError, match="sizes must be positive .* is flat"):
            sizing.scale_to(flat, [8.0, 2.0, 2.0])


def test_sizing_that_reshapes_an_object_is_a_warning(recwarn):
    """A sedan's tyre (0.7 x 0.25 x 0.7 m) sized as a car is stretched 3.2x more along
    its length than up: a part, not a car. A whole vehicle is sized without a word."""
    with pytest.warns(UserWarning, match=r"tyre.obj: sizing stretches one axis 3.2x more than another"):
        sizing.scale_to([0.7, 0.25, 0.7], [4.63, 1.95, 1.73], source="tyre.obj")
    sizing.scale_to([4.89, 1.85, 1.47], [4.63, 1.95, 1.73], source="sedan.obj")
    assert not recwarn.list


# ---- the chain --------------------------------------------------------------------------

@pytest.mark.parametrize("class_name", ["truck", "construction_vehicle"])
@pytest.mark.parametrize("yaw", [0.0, 150.0, -100.0])
def test_prepare_recovers_pose_heading_and_size(class_name, yaw):
    recon = yawed_sample(class_name, yaw)
    authored = prepare(recon, class_name, up="+z", heading_method="baseline", seed=5)
    target = sizing.sample_dims("nuscenes", class_name, 5)
    np.testing.assert_allclose(authored.dims, target)
    c, s = np.cos(np.radians(-yaw)), np.sin(np.radians(-yaw))
    rotation = authored.object_from_source[:3, :3] / (target / sample_vehicle(class_name).dims)[:, None]
    np.testing.assert_allclose(rotation, [[c, -s, 0], [s, c, 0], [0, 0, 1]], atol=0.01)  # front at +x
    # the transform reproduces the written points; the steps multiply to it
    np.testing.assert_array_equal(authored.positions, apply_transform(
        apply_transform(apply_transform(recon.positions, authored.steps[0].transform),
                        authored.steps[1].transform), authored.steps[2].transform))
    product = authored.steps[2].transform @ authored.steps[1].transform @ authored.steps[0].transform
    np.testing.assert_allclose(product, authored.object_from_source)
    local = apply_transform(recon.positions, authored.object_from_source)
    np.testing.assert_allclose((local.min(axis=0) + local.max(axis=0)) / 2, 0, atol=0.02)


def test_prepare_size_keep_and_exact():
    recon = yawed_sample("bus", 30.0)
    kept = prepare(recon, "bus", up="+z", heading_method="none", size="keep")
    np.testing.assert_allclose(kept.dims, sample_vehicle("bus").dims, atol=0.06)  # 0.25 deg of a bus
    assert np.linalg.det(kept.object_from_source[:3, :3]) == pytest.approx(1.0)
    exact = prepare(recon, "bus", up="+z", heading_method="none", size="exact", exact=(10.0, 2.5, 3.0))
    np.testing.assert_allclose(exact.dims, [10.0, 2.5, 3.0])


def test_size_of_a_flat_object_is_a_clear_error():
    flat = Reconstruction(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32), "point_ply",
                          source=Path("flat.ply"), sha256="")
    with pytest.raises(InputError, match="^flat.ply: cannot scale a box of"):
        prepare(flat, "truck", heading_method="none")


def test_up_choices(statue):
    poses = np.array([c.world_from_camera for c in load_reconstruction(statue).cameras])
    assert up_vector("auto", poses) is not None and up_vector("auto", ()) is None
    np.testing.assert_array_equal(up_vector("-y"), [0, -1, 0])
    with pytest.raises(InputError, match="^x.ply: has no cameras"):
        up_vector("cameras", (), "x.ply")
    with pytest.raises(ValueError, match="unknown up"):
        up_vector("north")


def test_size_step_rejects_unknown_mode():
    with pytest.raises(ValueError, match="unknown size mode"):
        size_step([1, 1, 1], "huge")


def test_write_prepared_round_trip(tmp_path):
    recon = yawed_sample("truck", 60.0)
    recon.colors = np.random.default_rng(1).random((len(recon.positions), 4)).astype(np.float32)
    recon.attributes = {"opacity": np.linspace(0, 1, len(recon.positions), dtype=np.float32)}
    authored = prepare(recon, "truck", up="+z", heading_method="baseline")
    paths = write_prepared(authored, "truck", "nuscenes", tmp_path)
    sidecar = json.loads(paths[".json"].read_text())
    assert sidecar["class"] == "truck" and sidecar["source_sha256"] == "0" * 64
    np.testing.assert_allclose(sidecar["dims"], authored.dims)
    np.testing.assert_allclose(sidecar["transform"], authored.object_from_source)
    assert [s["step"] for s in sidecar["steps"]] == ["align", "heading", "size"]
    back = load_reconstruction(paths[".ply"])
    np.testing.assert_array_equal(back.positions, authored.positions)
    np.testing.assert_allclose(back.attributes["opacity"], recon.attributes["opacity"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["truck.json", "truck.ply"]


def test_authored_object_apply_accumulates():
    recon = yawed_sample("bicycle", 0.0, count=500)
    authored = AuthoredObject.from_reconstruction(recon)
    authored.dims = np.array([1.0, 2.0, 3.0])
    from pgt_blender.core.authoring.prepare import turn_step

    authored.apply(turn_step(1, authored.dims)).apply(turn_step(1, authored.dims))
    np.testing.assert_array_equal(authored.object_from_source, heading.quarter_turns(2))
    np.testing.assert_array_equal(authored.dims, [1.0, 2.0, 3.0])


# ---- prepare_objects.py -----------------------------------------------------------------

@pytest.fixture(scope="module")
def sample_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("reconstructions")
    for class_name in ("truck", "bus"):
        paths = write_sample(folder, class_name, seed=4, points=4000)
        paths["mesh.ply"].unlink()
        paths["truth.json"].unlink()
    return folder


def test_prepare_objects_cli(sample_folder, tmp_path):
    out = tmp_path / "out"
    result = run_script("prepare_objects.py", "--in", sample_folder, "--class", "truck", "--out", out,
                        "--heading", "baseline", "--seed", "3")
    assert result.returncode == 0, result.stderr
    names = sorted(p.name for p in out.iterdir())
    assert names == ["bus_reconstruction.json", "bus_reconstruction.ply",
                     "truck_reconstruction.json", "truck_reconstruction.ply"]
    for index, stem in enumerate(("bus_reconstruction", "truck_reconstruction")):
        sidecar = json.loads((out / f"{stem}.json").read_text())
        assert {"class", "dims", "transform", "source_sha256"} <= set(sidecar)
        np.testing.assert_allclose(sidecar["dims"], sizing.sample_dims("nuscenes", "truck", 3 + index))
        recon = load_reconstruction(sample_folder / f"{stem}.ply")
        assert sidecar["source_sha256"] == recon.sha256
        written = load_reconstruction(out / f"{stem}.ply").positions
        np.testing.assert_allclose(written, apply_transform(recon.positions, np.array(sidecar["transform"])),
                                   atol=1e-5)


def test_prepare_objects_names_a_trailers_running_gear(tmp_path):
    paths = write_sample(tmp_path / "in", "trailer", seed=2, points=4000)
    paths["mesh.ply"].unlink()
    paths["truth.json"].unlink()
    result = run_script("prepare_objects.py", "--in", tmp_path / "in", "--class", "trailer", "--out", tmp_path / "out",
                        "--heading", "baseline", "--size", "keep")
    assert result.returncode == 0, result.stderr
    assert "baseline/running gear" in result.stdout


def test_prepare_objects_keep_size(sample_folder, tmp_path):
    result = run_script("prepare_objects.py", "--in", sample_folder, "--class", "bus", "--out", tmp_path,
                        "--heading", "none", "--size", "keep", "--up", "pca")
    assert result.returncode == 0, result.stderr
    sidecar = json.loads((tmp_path / "bus_reconstruction.json").read_text())
    assert sidecar["steps"][-1]["mode"] == "keep"
    assert np.linalg.det(np.array(sidecar["transform"])[:3, :3]) == pytest.approx(1.0)


def test_prepare_objects_kitti_truck(sample_folder, tmp_path):
    """KITTI labels trucks (its database has a Truck list): sized from KITTI's Truck mean."""
    result = run_script("prepare_objects.py", "--in", sample_folder, "--class", "truck", "--dataset", "kitti",
                        "--out", tmp_path, "--heading", "baseline", "--seed", "5")
    assert result.returncode == 0, result.stderr
    sidecar = json.loads((tmp_path / "truck_reconstruction.json").read_text())
    assert sidecar["class"] == "truck"
    np.testing.assert_allclose(sidecar["dims"], sizing.sample_dims("kitti", "truck", 6))  # second input: seed + 1


def test_prepare_objects_bad_inputs(sample_folder, tmp_path):
    broken = tmp_path / "in"
    broken.mkdir()
    (broken / "broken.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n1\n")
    out = tmp_path / "out"
    result = run_script("prepare_objects.py", "--in", broken, "--class", "truck", "--out", out, "--heading", "baseline")
    assert result.returncode == 1
    assert f"error: {broken / 'broken.ply'}:" in result.stderr
    assert not out.exists() or not any(out.iterdir())
    for args, message in [(("--in", tmp_path / "missing"), "not a folder"),
                          (("--in", tmp_path), "no reconstructions found")]:
        result = run_script("prepare_objects.py", *args, "--class", "truck", "--out", out)
        assert result.returncode == 1 and message in result.stderr
    result = run_script("prepare_objects.py", "--in", sample_folder, "--class", "bus", "--out", out,
                        "--dataset", "kitti")
    assert result.returncode == 2 and "kitti has no class 'bus'" in result.stderr
    result = run_script("prepare_objects.py", "--in", sample_folder, "--class", "truck", "--out", out,
                        "--size", "4,2")
    assert result.returncode == 2 and "three sizes L,W,H of 0.001 .. 1000 m; got '4,2'" in result.stderr


def test_minority_classes_have_nuscenes_presets():
    assert set(MINORITY_CLASSES) <= set(CLASS_SIZES["nuscenes"])
