"""Sensors from real data: the per-laser fit (core/scan/sensor_fit.py, fit_sensor.py) on
KITTI's raw scans and on simulated scans with a known table, and Velodyne calibration
tables (ROS velodyne_pointcloud YAML) read as sensors."""

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from pgt_blender.core.errors import InputError
from pgt_blender.core.files import read_float32_rows
from pgt_blender.core.scan import sensor_fit
from pgt_blender.core.scan.raycast import ScanOptions, cast_rays
from pgt_blender.core.scan.sensors import PRESETS, load_sensor_toml, read_velodyne_calibration
from pgt_blender.core.scan.targets import mesh_target

from .conftest import run_script

KITTI = PRESETS["kitti"]


@pytest.fixture(scope="module")
def kitti_scans(shared_data) -> list:
    return [read_float32_rows(path, 4).astype(np.float64)
            for path in sorted((shared_data / "kitti_scans" / "velodyne").glob("*.bin"))]


def in_scan_order(scan) -> np.ndarray:
    """A simulated scan's points stored as KITTI stores them: laser by laser, each
    revolution from azimuth 0 counter-clockwise."""
    rows = scan.returns
    azimuth = np.mod(np.arctan2(rows["y"], rows["x"]), 2 * np.pi)
    order = np.lexsort((azimuth, rows["ring"]))
    return np.column_stack([rows[axis] for axis in "xyz"])[order]


def test_the_fit_recovers_a_known_table_from_a_simulated_scan():
    """A full revolution inside a 60 x 60 x 30 m room with the kitti preset: the fit
    gives back its elevations, vertical offsets and columns."""
    room = trimesh.creation.box(extents=(60.0, 60.0, 30.0))
    target = mesh_target(room.vertices, room.faces, "room")
    scan = cast_rays(target, replace(KITTI, max_range=200.0), np.eye(4), ScanOptions(window=False))
    fit = sensor_fit.fit_lasers([in_scan_order(scan)])
    assert fit.columns == KITTI.columns and fit.residual_m.max() < 1e-6
    assert np.abs(fit.elevations_deg - np.array(KITTI.elevations_deg)).max() < 1e-6
    assert np.abs(fit.vertical_offsets_m - np.array(KITTI.vertical_offsets_m)).max() < 1e-6


def test_the_kitti_preset_fits_every_real_scan_and_a_held_out_one(kitti_scans):
    for held_out in range(len(kitti_scans)):
        fit = sensor_fit.fit_lasers([scan for index, scan in enumerate(kitti_scans) if index != held_out])
        errors = sensor_fit.elevation_errors(fit, kitti_scans[held_out])
        assert np.sqrt(np.mean(errors**2)) < 0.01  # degrees; the target is 0.1
    fit = sensor_fit.fit_lasers(kitti_scans)
    assert fit.columns == KITTI.columns == 2000 and np.median(fit.residual_m) < 1e-3
    order = np.argsort(fit.elevations_deg)
    for scan in kitti_scans:  # the shipped table, laser by laser in the scans' order
        preset = sensor_fit.elevation_errors(fit, scan, np.array(KITTI.elevations_deg)[np.argsort(order)],
                                             np.array(KITTI.vertical_offsets_m)[np.argsort(order)])
        assert np.sqrt(np.mean(preset**2)) < 0.01


def test_a_scan_not_stored_laser_by_laser_is_refused():
    points = np.column_stack([np.cos(np.linspace(0, 3, 100)), np.sin(np.linspace(0, 3, 100)), np.zeros(100)])
    with pytest.raises(InputError, match="do not go round laser by laser"):
        sensor_fit.fit_lasers([points], ["flat.bin"])


def test_fit_sensor_script_writes_a_sensor_the_tools_take(shared_data, tmp_path):
    out = tmp_path / "kitti_fit.toml"
    velodyne = shared_data / "kitti_scans" / "velodyne"
    # a scan named again (beside its folder) counts once: it must not be held out against itself
    result = run_script("fit_sensor.py", velodyne, velodyne / "000000.bin", "--out", out, check=True)
    assert "columns per revolution: 2000" in result.stdout and result.stdout.count("held out") == 3
    sensor = load_sensor_toml(out)
    assert sensor.columns == 2000 and np.allclose(sensor.elevations_deg, KITTI.elevations_deg, atol=1e-3)
    assert np.allclose(sensor.vertical_offsets_m, KITTI.vertical_offsets_m, atol=1e-4)


# --------------------------------------------------------------- Velodyne calibration tables

def test_the_hdl32e_factory_table_is_the_nuscenes_preset(shared_data, tmp_path):
    (tmp_path / "hdl32e.toml").write_text(f'base = "nuscenes"\ncalibration = '
                                          f'"{shared_data / "velodyne_calibrations" / "32db.yaml"}"\n')
    sensor = load_sensor_toml(tmp_path / "hdl32e.toml")
    assert sensor.columns == 1080 and sensor.cell_origins is None
    assert np.abs(np.array(sensor.elevations_deg) - PRESETS["nuscenes"].elevations_deg).max() < 0.01


def test_a_real_hdl64e_table_keeps_its_two_blocks_of_laser_origins(shared_data, tmp_path):
    table = read_velodyne_calibration(shared_data / "velodyne_calibrations" / "64e_s2.1-sztaki.yaml")
    assert len(table["elevations_deg"]) == 64 and list(table["elevations_deg"]) == sorted(table["elevations_deg"])
    offsets = np.array(table["vertical_offsets_m"])
    assert offsets.min() > 0.1 and offsets.max() - offsets.min() > 0.05  # lower and upper block
    assert 0 < np.abs(table["horizontal_offsets_m"]).max() < 0.03
    (tmp_path / "sztaki.toml").write_text('base = "kitti"\ncalibration = "64e.yaml"\n')
    (tmp_path / "64e.yaml").write_bytes((shared_data / "velodyne_calibrations" / "64e_s2.1-sztaki.yaml").read_bytes())
    sensor = load_sensor_toml(tmp_path / "sztaki.toml")
    box = trimesh.creation.box(extents=(4.0, 2.0, 1.6))
    matrix = np.eye(4)
    matrix[:3, 3] = (8.0, 2.0, -0.9)
    scan = cast_rays(mesh_target(box.vertices, box.faces, "box"), sensor, matrix, ScanOptions())
    assert scan.hits > 100


@pytest.mark.parametrize("text, problem", [
    ("lasers: 7\n", "'lasers' must list 1 to 1024 lasers"),
    ("cameras: []\n", "not a velodyne_pointcloud calibration (KeyError"),
    ("lasers:\n- {rot_correction: 0.1}\n", "(KeyError: 'vert_correction')"),
    ("lasers:\n- {vert_correction: .nan}\n", "calibration values must be finite numbers"),
    ("lasers: [\n", "not a readable YAML file"),
    ("lasers:\n- {vert_correction: 1" + "0" * 400 + "}\n", "(OverflowError"),  # beyond a float
    ("lasers: " + "[" * 20_000 + "\n", "not a readable YAML file"),  # RecursionError in the parser
])
def test_bad_calibration_tables_name_the_file(tmp_path, text, problem):
    (tmp_path / "bad.yaml").write_text(text)
    with pytest.raises(InputError) as caught:
        read_velodyne_calibration(tmp_path / "bad.yaml")
    assert caught.value.path == tmp_path / "bad.yaml" and problem in str(caught.value)


def test_a_calibration_that_does_not_fit_its_base_is_refused(shared_data, tmp_path):
    (tmp_path / "vlp16.yaml").write_bytes((shared_data / "velodyne_calibrations" / "VLP16db.yaml").read_bytes())
    (tmp_path / "wrong.toml").write_text('base = "kitti"\ncalibration = "vlp16.yaml"\n')
    with pytest.raises(InputError, match="the calibration has 16 lasers, the kitti preset 64 beams"):
        load_sensor_toml(tmp_path / "wrong.toml")
    (tmp_path / "far.toml").write_text('base = "kitti"\nvertical_offsets_m = [' + ", ".join(["2.0"] * 64) + "]\n")
    with pytest.raises(InputError, match="vertical_offsets_m must lie within"):
        load_sensor_toml(tmp_path / "far.toml")


def test_range_view_sees_points_from_their_lasers():
    """Dense points on a wall 10 m ahead through the kitti preset (lasers 0.1-0.2 m above
    the origin): each kept point moves only to its cell's centre angles as its own laser
    sees them, a few centimetres, never by the laser's offset."""
    from pgt_blender.core.scan.range_view import range_view_scan

    rng = np.random.default_rng(0)
    wall = np.column_stack([np.zeros(40000), rng.uniform(-3, 3, 40000), rng.uniform(0, 3, 40000)])
    matrix = np.eye(4)
    matrix[:3, 3] = (10.0, 0.0, -KITTI.mounting_height)
    scan = range_view_scan(wall, KITTI, matrix, np.array([[-0.1, -3, 0], [0.1, 3, 3]]),
                           normals=np.tile([1.0, 0.0, 0.0], (len(wall), 1)))
    moved = np.column_stack([scan.returns[axis] for axis in "xyz"]) - (wall @ matrix[:3, :3].T + matrix[:3, 3])[
        scan.returns["face"]]
    half_cell = np.radians(max(np.diff(KITTI.elevations_deg)) / 2 + KITTI.azimuth_step_deg / 2)
    assert scan.hits > 1000 and (np.linalg.norm(moved, axis=1) < scan.returns["range"] * half_cell + 1e-3).all()
