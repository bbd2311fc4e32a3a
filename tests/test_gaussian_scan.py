"""Gaussian splats scanned as Gaussians (core/scan/gaussians.py): analytic cases, the
candidate blocks against a brute-force test of every cell, splat shapes through
authoring, and the command line on the real splat."""

import numpy as np
import pytest

from pgt_blender.core.authoring.prepare import prepare, write_prepared
from pgt_blender.core.importing import load_reconstruction
from pgt_blender.core.scan import gaussians
from pgt_blender.core.scan.raycast import ScanOptions, cast_rays
from pgt_blender.core.scan.sensors import PRESETS
from pgt_blender.core.scan.targets import gaussian_target

from .conftest import run_script

NUSCENES, KITTI = PRESETS["nuscenes"], PRESETS["kitti"]
IDENTITY = np.eye(4)  # object frame = sensor frame: splats placed where the test says
UPRIGHT = [[1.0, 0.0, 0.0, 0.0]]


def scan(target, sensor=NUSCENES, window=True):
    return cast_rays(target, sensor, IDENTITY, ScanOptions(window=window)).returns


def cell_of(sensor, ring: int, column: int) -> int:
    return ring * sensor.columns + column


def test_one_splat_head_on_returns_at_its_mean():
    cell = cell_of(NUSCENES, 20, 300)
    mean = 12.5 * NUSCENES.directions[cell]
    returns = scan(gaussian_target(mean[None], [[0.03, 0.03, 0.03]], UPRIGHT, [0.9]))
    assert len(returns) == 1 and (returns["ring"][0], returns["column"][0]) == (20, 300)
    assert returns["range"][0] == pytest.approx(12.5, abs=1e-9) and returns["face"][0] == 0
    assert len(scan(gaussian_target(mean[None], [[0.03, 0.03, 0.03]], UPRIGHT, [0.45]))) == 0  # below HIT_OPACITY


@pytest.mark.parametrize("near_opacity, far_opacity, expected", [
    (0.7, 0.9, 8.0),   # the nearer one alone crosses 0.5
    (0.3, 0.9, 12.0),  # 1 - 0.7 x 0.1 = 0.93 at the farther one
    (0.3, 0.2, None),  # 1 - 0.7 x 0.8 = 0.44: no return
    (0.3, 0.3, 12.0),  # two faint ones cross together: 1 - 0.7 x 0.7 = 0.51
])
def test_two_splats_in_line_composite_front_to_back(near_opacity, far_opacity, expected):
    direction = NUSCENES.directions[cell_of(NUSCENES, 22, 100)]
    means = np.array([12.0, 8.0])[:, None] * direction  # the farther listed first: order comes from depth
    target = gaussian_target(means, [[0.02] * 3] * 2, UPRIGHT * 2, [far_opacity, near_opacity])
    returns = scan(target)
    if expected is None:
        assert len(returns) == 0
    else:
        assert len(returns) == 1 and returns["range"][0] == pytest.approx(expected, abs=1e-9)
        assert returns["face"][0] == (1 if expected == 8.0 else 0)


def plane_disc(normal, centre, radius: float, spacing: float):
    """Flat splats (normal scale 0) on a hexagonal-ish grid covering a disc in the plane
    through ``centre`` with ``normal``: positions, scales, rotations (w x y z)."""
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    u = np.cross(normal, [0.0, 0.0, 1.0] if abs(normal[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    grid = np.arange(-radius, radius + spacing / 2, spacing)
    a, b = (values.ravel() for values in np.meshgrid(grid, grid))
    inside = np.hypot(a, b) <= radius
    positions = centre + a[inside, None] * u + b[inside, None] * v
    rotation = gaussians.quaternions(np.stack([u, v, normal], axis=1)[None])  # columns: the splat's axes
    count = len(positions)
    return positions, np.tile([spacing, spacing, 0.0], (count, 1)), np.repeat(rotation, count, axis=0)


@pytest.mark.parametrize("sensor", [NUSCENES, KITTI], ids=["nuscenes", "kitti lasers off the origin"])
def test_a_flat_disc_of_splats_scans_as_its_plane(sensor):
    normal, centre, radius = np.array([-1.0, -0.3, 0.2]), np.array([9.0, 2.0, -0.5]), 1.5
    positions, scales, rotations = plane_disc(normal, centre, radius, 0.05)
    returns = scan(gaussian_target(positions, scales, rotations, np.full(len(positions), 0.6)), sensor)
    cells = returns["ring"].astype(np.int64) * sensor.columns + returns["column"]
    origins = np.zeros((len(cells), 3)) if sensor.cell_origins is None else sensor.cell_origins[cells]
    directions = sensor.directions[cells]
    unit = normal / np.linalg.norm(normal)
    exact = ((centre - origins) @ unit) / (directions @ unit)  # the ray meets the plane there
    assert len(returns) > 100 and np.abs(returns["range"] - exact).max() < 1e-9
    # Every ray that meets the plane well inside the disc returns, none well outside it.
    all_cells = np.arange(sensor.beams * sensor.columns)
    all_origins = np.zeros((len(all_cells), 3)) if sensor.cell_origins is None else sensor.cell_origins
    depth = ((centre - all_origins) @ unit) / (sensor.directions @ unit)
    meet = all_origins + depth[:, None] * sensor.directions
    off_centre = np.linalg.norm(meet - centre, axis=1)
    front = depth > 0
    hit = np.isin(all_cells, cells)
    assert hit[front & (off_centre < radius - 0.1)].all()
    assert not hit[~front | (off_centre > radius + 0.15)].any()


def test_windowed_scan_equals_the_full_revolution():
    positions, scales, rotations = plane_disc([0.0, -1.0, 0.1], np.array([-3.0, 11.0, 0.0]), 1.0, 0.05)
    target = gaussian_target(positions, scales, rotations, np.full(len(positions), 0.3))  # composited in depth
    assert np.array_equal(scan(target), scan(target, window=False))


@pytest.mark.parametrize("sensor", [NUSCENES, KITTI, PRESETS["vlp16"]], ids=lambda s: s.name)
def test_cell_blocks_hold_every_cell_whose_ray_meets_a_splat(sensor):
    """Random splats (some flat, some around the sensor) against a brute-force exact test
    of every cell of the revolution."""
    rng = np.random.default_rng(7)
    count = 120
    scales = np.exp(rng.uniform(np.log(0.01), np.log(1.0), (count, 3)))
    scales[:, 2] *= rng.choice([1.0, 1e-4], count)
    splats = gaussians.Gaussians.from_splats(rng.normal(size=(count, 3)) * [8, 8, 1.5], scales,
                                             rng.normal(size=(count, 4)), np.full(count, 0.9))
    first_ring, rings, first_column, columns = gaussians._cell_blocks(splats, sensor, IDENTITY)
    origins = np.zeros(3) if sensor.cell_origins is None else sensor.cell_origins
    all_rings, all_columns = np.divmod(np.arange(sensor.beams * sensor.columns), sensor.columns)
    met = 0
    for index in range(count):  # per splat, vectorised over the cells
        a = ((origins - splats.means[index]) @ splats.axes[index]) / splats.scales[index]
        b = (sensor.directions @ splats.axes[index]) / splats.scales[index]
        depth = -np.einsum("ij,ij->i", np.broadcast_to(a, b.shape), b) / np.einsum("ij,ij->i", b, b)
        closest = a + depth[:, None] * b
        hit = (np.einsum("ij,ij->i", closest, closest) <= gaussians.CUTOFF_SIGMAS ** 2) & (depth > 0)
        in_rings = (all_rings >= first_ring[index]) & (all_rings < first_ring[index] + rings[index])
        in_columns = (all_columns - first_column[index]) % sensor.columns < columns[index]
        assert (in_rings & in_columns)[hit].all(), index
        met += hit.sum()
    assert met > 1000


def test_quaternions_and_transformed_shapes():
    rng = np.random.default_rng(3)
    wxyz = rng.normal(size=(500, 4))
    wxyz /= np.linalg.norm(wxyz, axis=1, keepdims=True)
    wxyz *= np.sign(wxyz[:, :1])
    assert np.abs(gaussians.quaternions(gaussians.rotation_matrices(wxyz)) - wxyz).max() < 1e-12
    scales = np.exp(rng.normal(size=(500, 3)))
    linear = np.diag([2.0, 0.5, 1.5]) @ gaussians.rotation_matrices(rng.normal(size=(1, 4)))[0]
    new_scales, new_rotations = gaussians.transform_gaussians(scales, wxyz, linear)

    def covariance(s, q):
        shaped = gaussians.rotation_matrices(q) * np.asarray(s, np.float64)[:, None]
        return shaped @ shaped.transpose(0, 2, 1)

    expected = linear @ covariance(scales, wxyz) @ linear.T
    assert np.abs(covariance(new_scales, new_rotations) - expected).max() < 1e-6 * np.abs(expected).max()
    assert (np.diff(new_scales, axis=1) <= 0).all()


def test_prepared_splat_is_a_splat_in_the_object_frame(shared_data, tmp_path):
    source = load_reconstruction(shared_data / "gaussian_splat_donut" / "fused.ply")
    authored = prepare(source, "car", up="pca", heading_method="baseline")
    paths = write_prepared(authored, "car", "nuscenes", tmp_path)
    reloaded = load_reconstruction(paths[".ply"])
    assert reloaded.kind == "gaussian_splat" and len(reloaded.positions) == len(source.positions)
    np.testing.assert_allclose(reloaded.attributes["opacity"], source.attributes["opacity"], atol=1e-6)
    np.testing.assert_array_equal(reloaded.colors, source.colors)
    linear = authored.object_from_source[:3, :3]
    before = gaussians.rotation_matrices(source.attributes["rotation"]) * source.attributes["scale"][:, None, :]
    after = gaussians.rotation_matrices(reloaded.attributes["rotation"]) * reloaded.attributes["scale"][:, None, :]
    expected = linear @ before @ before.transpose(0, 2, 1) @ linear.T
    scale = np.abs(expected).max(axis=(1, 2), keepdims=True)
    assert np.abs(after @ after.transpose(0, 2, 1) - expected).max() < 1e-5 * scale.max()


def test_scan_object_scans_a_splat_as_gaussians(shared_data, tmp_path):
    authored = prepare(load_reconstruction(shared_data / "gaussian_splat_donut" / "fused.ply"), "car", up="pca",
                       heading_method="baseline")
    splat = write_prepared(authored, "car", "nuscenes", tmp_path)[".ply"]
    rows = {}
    for surface in ("auto", "gaussians", "surfels"):
        out = tmp_path / f"{surface}.npy"
        result = run_script("scan_object.py", "--object", splat, "--x", 12, "--y", 3, "--surface", surface,
                            "--out", out)
        assert result.returncode == 0, result.stderr
        rows[surface] = np.load(out)
    assert np.array_equal(rows["auto"], rows["gaussians"]) and len(rows["auto"]) > 100
    assert not np.array_equal(rows["auto"]["range"], rows["surfels"]["range"][:len(rows["auto"])])
    refused = run_script("scan_object.py", "--object", shared_data / "chrono_vehicles" / "data" / "vehicle" / "truck"
                         / "truck_chassis.obj", "--x", 12, "--y", 3, "--surface", "gaussians", "--out",
                         tmp_path / "truck.npy")
    assert refused.returncode == 1 and "is not a Gaussian splat" in refused.stderr
