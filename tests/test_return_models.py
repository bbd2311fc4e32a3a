"""What returns look like: the ray-drop model and the intensity law (their maths against
synthetic ground truth, their use in scans, and the presets' fit on the shared KITTI frames)."""

from dataclasses import replace

import numpy as np
import pytest

from pgt_blender.core.scan import ray_drop
from pgt_blender.dev import CHRONO_VEHICLES
from pgt_blender.core.scan.physical_intensity import REFERENCE_RANGE, fit_intensity_law, relative_intensity
from pgt_blender.core.scan.raycast import ScanOptions, cast_rays
from pgt_blender.core.scan.sensors import PRESETS, Sensor, load_sensor_toml
from pgt_blender.core.scan.targets import mesh_target

from .conftest import run_script

KITTI = PRESETS["kitti"]


def wall(distance: float):
    """A 6 m x 5 m wall facing the sensor ``distance`` m ahead (x), sensor frame."""
    corners = np.array([[distance, -3, -2], [distance, 3, -2], [distance, 3, 3], [distance, -3, 3]], float)
    return mesh_target(corners, [[0, 1, 2], [0, 2, 3]], "wall")


def test_drop_probability_is_the_documented_logistic():
    # power = reflectivity * |cos| * (REFERENCE_RANGE / range)^2; logit p = a - k ln(power)
    p = ray_drop.drop_probability((0.0, 1.0), [1.0, 0.5, 0.5], [1.0, 1.0, 0.5], [REFERENCE_RANGE, REFERENCE_RANGE, 20.0])
    assert np.allclose(p, [0.5, 1 / 1.5, 1 / (1 + 0.5 * 0.5 / 4)])


def test_the_drop_fit_recovers_a_known_model():
    rng = np.random.default_rng(0)
    reflectivity, cos, ranges = rng.uniform(0.05, 1, 20000), rng.uniform(0.05, 1, 20000), rng.uniform(3, 80, 20000)
    truth = (-4.0, 0.9)
    dropped = rng.random(20000) < ray_drop.drop_probability(truth, reflectivity, cos, ranges)
    assert np.allclose(ray_drop.fit_drop_model(dropped, reflectivity, cos, ranges), truth, atol=0.15)
    with pytest.raises(ValueError, match="kept and dropped"):
        ray_drop.fit_drop_model(np.zeros(5, bool), np.ones(5), np.ones(5), np.ones(5))


def test_cell_outcomes_pair_simulated_hits_with_the_real_cells():
    columns = 100
    real_cells = np.array([5 * columns + 10, 5 * columns + 30, 6 * columns + 50])
    real_in_box = np.array([True, False, True])
    sim_cells = np.array([5 * columns + 11,   # a real box return one column over: kept
                          5 * columns + 30,   # the real return is not in the box: elsewhere
                          5 * columns + 70,   # no real return at all: dropped
                          6 * columns + 50])  # kept
    outcome = ray_drop.cell_outcomes(sim_cells, real_cells, real_in_box, columns)
    assert outcome.tolist() == [ray_drop.KEPT, ray_drop.ELSEWHERE, ray_drop.DROPPED, ray_drop.KEPT]


def test_scans_drop_rays_as_the_model_says_and_stay_seeded():
    target = wall(60.0)
    exact = cast_rays(target, KITTI, np.eye(4), ScanOptions())
    options = ScanOptions(ray_drop=True, seed=3)
    first, again = cast_rays(target, KITTI, np.eye(4), options), cast_rays(target, KITTI, np.eye(4), options)
    assert first.returns.tobytes() == again.returns.tobytes()
    cos = np.abs(KITTI.directions[exact.returns["ring"].astype(int) * KITTI.columns + exact.returns["column"], 0])
    expected = ray_drop.drop_probability(KITTI.ray_drop, np.full(exact.hits, 0.5), cos, exact.returns["range"]).mean()
    assert 0.15 < expected < 0.35  # the preset at 60 m
    assert abs(1 - first.hits / exact.hits - expected) < 4 * np.sqrt(expected * (1 - expected) / exact.hits)
    # Off (the default, or a sensor without a model): no ray dropped.
    assert cast_rays(target, KITTI, np.eye(4), ScanOptions(seed=3)).hits == exact.hits
    assert cast_rays(target, replace(KITTI, ray_drop=()), np.eye(4), options).hits == exact.hits


def test_the_intensity_spread_is_seeded_and_keeps_the_mean():
    target = wall(15.0)
    dim = replace(KITTI, intensity_law=(0.2, 0.0, KITTI.intensity_law[2]))  # the spread rarely clips at 1
    noisy = ScanOptions(range_noise=True, seed=1)
    first, again = cast_rays(target, dim, np.eye(4), noisy), cast_rays(target, dim, np.eye(4), noisy)
    assert first.returns.tobytes() == again.returns.tobytes()
    exact = cast_rays(target, dim, np.eye(4), ScanOptions())
    assert np.ptp(first.returns["intensity"]) > 5 * np.ptp(exact.returns["intensity"])
    # The log-normal factor has mean 1: the means agree within the clipping at 1 and sampling.
    assert abs(first.returns["intensity"].mean() / exact.returns["intensity"].mean() - 1) < 0.1


def test_the_intensity_fit_recovers_a_known_law():
    rng = np.random.default_rng(1)
    truth = (0.4, 1.0, 0.6)
    objects = np.repeat(np.arange(12), 400)
    object_range = np.linspace(12, 70, 12)
    power = rng.uniform(0.1, 0.9, len(objects)) * np.repeat(rng.uniform(0.5, 1.0, 12), 400)
    ranges = object_range[objects] + rng.normal(0, 0.5, len(objects))
    values = relative_intensity(power, np.ones(len(objects)), ranges, truth, rng.standard_normal(len(objects)))
    sim_power = rng.uniform(0.1, 0.9, len(objects)) * np.repeat(rng.uniform(0.5, 1.0, 12), 400)
    scale, exponent, spread = fit_intensity_law(values, ranges, objects, sim_power, objects, floor=1e-4)
    assert exponent == pytest.approx(truth[1], abs=0.2)
    assert spread == pytest.approx(truth[2], abs=0.1)
    assert scale == pytest.approx(truth[0], rel=0.2)  # carries the exponent's error at 12-70 m
    # Too few objects beyond REFERENCE_RANGE: no falloff is claimed.
    near = np.full(len(objects), 5.0)
    assert fit_intensity_law(values, near, objects, sim_power, objects, floor=1e-4)[1] == 0.0


@pytest.mark.parametrize("key, value, message", [
    ("ray_drop", "[1.0]", "ray_drop must be empty or \\(a, k\\)"),
    ("intensity_law", "[1.0, 0.0]", "intensity_law must be empty or"),
    ("intensity_law", "[0.0, 0.0, 1.0]", "0 < scale <= 1e\\+06"),
    ("ray_drop", '"high"', "ray_drop must be \\(a, k\\)"),
])
def test_bad_model_keys_in_a_sensor_toml_name_the_file(tmp_path, key, value, message):
    path = tmp_path / "bad.toml"
    path.write_text(f'base = "kitti"\n{key} = {value}\n')
    with pytest.raises(Exception, match=message) as caught:
        load_sensor_toml(path)
    assert "bad.toml" in str(caught.value)


def test_sensor_models_default_to_none():
    sensor = Sensor("plain", (0.0, 1.0), columns=100, rate_hz=10.0, min_range=1.0, max_range=50.0,
                    mounting_height=1.5)
    assert sensor.ray_drop == () and sensor.intensity_law == ()


def test_fit_returns_reproduces_the_presets(tmp_path, shared_data):
    out = tmp_path / "models.toml"
    result = run_script("fit_returns.py", str(shared_data / "kitti_scans"), "--meshes", CHRONO_VEHICLES, "--out", str(out))
    assert result.returncode == 0, result.stderr
    sensor = load_sensor_toml(out)
    assert np.allclose(sensor.ray_drop, KITTI.ray_drop, atol=1e-3)
    assert np.allclose(sensor.intensity_law, KITTI.intensity_law, atol=1e-3)
    assert "held out" in result.stdout
    nuscenes = run_script("fit_returns.py", str(shared_data / "kitti_scans"), "--meshes", CHRONO_VEHICLES, "--out", str(out),
                          "--intensity-points",
                          *map(str, sorted((shared_data / "nuscenes_format_sample").glob("*/LIDAR_TOP/*.bin"))))
    assert nuscenes.returncode == 0, nuscenes.stderr
    assert np.allclose(load_sensor_toml(out).intensity_law, PRESETS["nuscenes"].intensity_law, atol=1e-3)


def test_colors_set_contrast_and_the_law_the_level():
    # A wall whose left half is 4x as bright as its right: reflectivity keeps the 4:1
    # contrast with an area-weighted mean of 0.5, whatever the colors' absolute level.
    corners = np.array([[20, -3, -2], [20, 0, -2], [20, 0, 3], [20, -3, 3], [20, 3, -2], [20, 3, 3]], float)
    faces = [[0, 1, 2], [0, 2, 3], [4, 2, 1], [4, 5, 2]]
    for level in (0.05, 0.2):
        target = mesh_target(corners, faces, "two-tone", face_reflectivity=[level, level, 4 * level, 4 * level])
        assert np.allclose(target.reflectivity, [0.2, 0.2, 0.8, 0.8])
    black = mesh_target(corners, faces, "black", face_reflectivity=[0, 0, 0, 0])
    assert np.allclose(black.reflectivity, 0.5)
