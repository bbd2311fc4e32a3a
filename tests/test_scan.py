"""The scan core against analytic ground truth: sensors as data, windowed == full,
float64 exactness on sphere, box, cylinder and plane, no leaks, degenerate input,
determinism, range view, surfels, sweeps and the output files."""

import warnings
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from pgt_blender.core.boxes import box_frame
from pgt_blender.core.errors import InputError
from pgt_blender.core.importing.ply import read_vertices
from pgt_blender.core.samples import MINORITY_CLASSES, sample_vehicle, synthetic_reconstruction
from pgt_blender.core.scan.physical_intensity import REFERENCE_RANGE
from pgt_blender.core.scan.range_view import range_view_scan
from pgt_blender.core.scan import raycast
from pgt_blender.core.scan.raycast import ScanOptions, cast_rays, placement, scan_object, trace_rays
from pgt_blender.core.scan.returns import RETURN_DTYPE, write_scan
from pgt_blender.core.scan.sensors import PRESETS, Sensor, load_sensor_toml
from pgt_blender.core.scan.sweeps import Motion, sample_motion, scan_many, scan_sweeps
from pgt_blender.core.scan.targets import (blender_bvh, embree_scene, gaussian_target, mesh_target,
                                          surfel_target)

NUSCENES = PRESETS["nuscenes"]
FAR_NUSCENES = replace(NUSCENES, max_range=2000.0, name="nuscenes-far")


def pose(x, y, z=0.0, heading=0.0) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:2, :2] = [[np.cos(heading), -np.sin(heading)], [np.sin(heading), np.cos(heading)]]
    matrix[:3, 3] = [x, y, z]
    return matrix


def ray_directions(sensor, scan) -> np.ndarray:
    """Each return's float64 cell direction, sensor frame."""
    return sensor.directions[scan.returns["ring"].astype(np.int64) * sensor.columns + scan.returns["column"]]


def box_entry(origin, directions, low, high):
    """Float64 slab entry distance per ray (inf where the ray misses the box)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (low - origin) / directions, (high - origin) / directions
    enter, leave = np.fmin(t0, t1).max(axis=1), np.fmax(t0, t1).min(axis=1)
    return np.where((leave >= enter) & (leave > 0), enter, np.inf), leave - enter


@pytest.fixture(scope="module")
def sample_truck():
    vehicle = sample_vehicle("truck")
    return mesh_target(vehicle.vertices, vehicle.faces, "sample truck")


# ---------------------------------------------------------------- sensors as data

def test_presets_follow_the_reference():
    assert NUSCENES.beams == 32 and NUSCENES.columns == 1080 and NUSCENES.rate_hz == 20
    assert NUSCENES.elevations_deg[0] == -30.67 and NUSCENES.elevations_deg[-1] == 10.67
    assert np.allclose(np.diff(NUSCENES.elevations_deg), 4 / 3, atol=0.011)
    kitti = PRESETS["kitti"]
    assert kitti.beams == 64 and kitti.elevations_deg[-1] == 1.9367 and kitti.elevations_deg[0] == -24.9997
    assert kitti.columns == 2000 and 0.1 < min(kitti.vertical_offsets_m) < max(kitti.vertical_offsets_m) < 0.21
    assert np.diff(kitti.elevations_deg)[-1] < np.diff(kitti.elevations_deg)[0]  # upper block finer
    assert PRESETS["lyft"].beams == 40 and PRESETS["vlp16"].beams == 16
    for sensor in PRESETS.values():
        assert np.allclose(np.linalg.norm(sensor.directions, axis=1), 1.0)
        assert np.abs(sensor.cell_azimuths).max() <= np.pi


def test_paper_ablation_settings_are_expressible(tmp_path):
    (tmp_path / "ablation.toml").write_text('base = "nuscenes"\ncolumns = 3600\n')
    assert load_sensor_toml(tmp_path / "ablation.toml").columns == 3600
    (tmp_path / "uniform32.toml").write_text(
        "elevations_deg = [" + ", ".join(f"{e:.4f}" for e in np.linspace(-30, 10, 32)) + "]\n"
        "columns = 1080\nrate_hz = 20.0\nmin_range = 1.0\nmax_range = 70.0\nmounting_height = 1.84\n")
    custom = load_sensor_toml(tmp_path / "uniform32.toml")
    assert custom.beams == 32 and custom.elevations_deg[0] == -30 and custom.name == "uniform32"


@pytest.mark.parametrize("body, problem", [
    ("elevations_deg = []", "elevations_deg is empty"),
    ("elevations_deg = [0.0, -1.0]", "strictly increasing"),
    ("elevations_deg = [-95.0, 0.0]", "between -90 and 90"),
    ("columns = 0", "columns must be a positive integer"),
    ("columns = 10.5", "columns must be a positive integer"),
    ("rate_hz = -1.0", "rate_hz must lie between 0.1 and 1000, got -1.0"),
    ("rate_hz = 1e-300", "rate_hz must lie between 0.1 and 1000"),  # time lags beyond a float32
    ("max_range = 0.0", "max_range must be positive"),
    ("direction = true", "direction must be -1 (clockwise) or 1"),
    ("name = 7", "the sensor's name must be a non-empty text, got 7"),
    ('name = ""', "the sensor's name must be a non-empty text"),
    ("azimuth_offsets_deg = [1.0]", "azimuth_offsets_deg has 1 entries for 32 beams"),
    ("colums = 1080", "unknown sensor keys colums"),
    ("columns = ", "not a readable TOML file"),
    ('rate_hz = "fast"', "rate_hz must be a finite number, got 'fast'"),
    ("mounting_height = inf", "mounting_height must be a finite number"),
    ("columns = 1000000000", "exceeds 16,777,216 rays per revolution"),  # not a MemoryError
    ("columns = 1e9", "columns must be a positive integer"),
    ('elevations_deg = "12"', "elevations_deg must be a list of numbers"),
    ('firing_us = [0, "a"]', "firing_us must be a list of numbers"),
    ("firing_us = [1" + "0" * 400 + "]", "firing_us must be a list of numbers"),  # beyond a float
    ("intensity_law = [1, 0, 1e200]", "intensity_law needs 0 < scale <= 1e+06, 0 <= range_exponent <= 10 and "
                                      "0 <= spread <= 10"),  # exp(spread x normal) overflowed
    ("intensity_law = [1e308, 1, 0]", "intensity_law needs 0 < scale <= 1e+06"),
])
def test_bad_sensor_files_name_the_file_and_the_problem(tmp_path, body, problem):
    path = tmp_path / "bad.toml"
    path.write_text('base = "nuscenes"\n' + body + "\n")
    with pytest.raises(InputError) as caught:
        load_sensor_toml(path)
    assert str(path) in str(caught.value) and problem in str(caught.value)
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize("base", ['base = { name = "nuscenes" }', "base = 3", 'base = "waymo"'])
def test_a_base_that_is_no_preset_name_is_named(tmp_path, base):
    path = tmp_path / "bad.toml"
    path.write_text(base + "\ncolumns = 1080\n")
    with pytest.raises(InputError, match=f"^{path}: base .* is not a preset"):
        load_sensor_toml(path)


def test_firing_times_follow_the_column_and_the_beam_order():
    rings, columns = np.array([0, 16, 0]), np.array([0, 0, 1])
    times = NUSCENES.cell_times(rings, columns)
    assert times[0] == 0 and np.isclose(times[1], 1.152e-6) and np.isclose(times[2], 0.05 / 1080)


# ---------------------------------------------------------------- windowed == full

SENSOR_WITH_OFFSETS = Sensor("offsets", tuple(np.linspace(-25, 15, 20)), columns=900, rate_hz=10.0,
                             min_range=0.5, max_range=150.0, mounting_height=1.8,
                             azimuth_offsets_deg=tuple(np.tile([-1.2, 0.0, 1.9, 0.4], 5)))
# Lasers off the sensor origin, as a Velodyne calibration table places them (up to 0.2 m).
LASERS_OFF_ORIGIN = replace(SENSOR_WITH_OFFSETS, name="lasers-off-origin", max_range=2000.0,
                            vertical_offsets_m=tuple(np.tile([0.2, 0.05, -0.1, 0.12], 5)),
                            horizontal_offsets_m=tuple(np.tile([0.03, -0.026, 0.0, 0.01], 5)))


@pytest.mark.parametrize("case, sensor, matrix", [
    ("seam", NUSCENES, pose(-12.0, 0.05, -1.0, 0.3)),          # straddles azimuth +-180 deg
    ("seam offsets", SENSOR_WITH_OFFSETS, pose(-20.0, -0.4, -1.0, 1.2)),
    ("lasers off the origin, near", LASERS_OFF_ORIGIN, pose(2.4, 1.0, -1.0, 0.3)),
    ("lasers off the origin, seam", LASERS_OFF_ORIGIN, pose(-20.0, -0.4, -1.0, 1.2)),
    ("near", NUSCENES, pose(2.2, 1.0, -1.0, 0.0)),              # half a metre from the sensor
    ("far", NUSCENES, pose(48.0, -47.0, -1.0, 2.0)),
    ("footprint around the sensor", NUSCENES, pose(0.5, 0.2, -1.0, 0.7)),
    ("overhead", NUSCENES, pose(1.0, 0.0, 1.5, 0.4)),           # hanging above the sensor
    ("kitti", PRESETS["kitti"], pose(9.0, 6.0, -0.5, -0.8)),
])
def test_windowed_scan_returns_exactly_the_full_revolution(sample_truck, case, sensor, matrix):
    for options in (ScanOptions(), ScanOptions(range_noise=True, drop_rate=0.1, seed=5)):
        windowed = cast_rays(sample_truck, sensor, matrix, options)
        full = cast_rays(sample_truck, sensor, matrix, replace(options, window=False))
        assert windowed.hits > 0, case
        assert windowed.returns.tobytes() == full.returns.tobytes(), case
        assert windowed.rays <= full.rays == sensor.beams * sensor.columns
    # The window alone (Embree casts all of it), then with the BVH engine's slab test.
    around = "footprint" in case or "overhead" in case
    assert windowed.efficiency > (0.05 if around else 0.4)
    assert cast_rays(sample_truck, sensor, matrix, ScanOptions(engine="bvh")).efficiency > (0.05 if around else 0.5)


def test_windowed_equals_full_on_random_poses_of_an_open_real_mesh(chrono_meshes):
    sedan = trimesh.load(next(p for p in chrono_meshes if "sedan_chassis" in p.name), force="mesh", process=False)
    with pytest.warns(UserWarning, match="zero-area faces"):  # real meshes carry slivers
        target = mesh_target(sedan.vertices, sedan.faces, "sedan")
    rng = np.random.default_rng(11)
    for _ in range(6):
        distance, azimuth = rng.uniform(3, 60), rng.uniform(-np.pi, np.pi)
        matrix = placement(target.bounds, NUSCENES, distance * np.cos(azimuth), distance * np.sin(azimuth),
                           rng.uniform(-np.pi, np.pi))
        windowed = cast_rays(target, NUSCENES, matrix, ScanOptions())
        full = cast_rays(target, NUSCENES, matrix, ScanOptions(window=False))
        assert windowed.returns.tobytes() == full.returns.tobytes()


# ---------------------------------------------------------------- exactness

def tessellation_ranges(triangles: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Float64 Moller-Trumbore: nearest hit of rays from the origin on (T, 3, 3) triangles."""
    v0, e1, e2 = triangles[:, 0], triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    nearest = np.full(len(directions), np.inf)
    for i, direction in enumerate(directions):
        p = np.cross(direction, e2)
        inverse = 1.0 / np.einsum("ij,ij->i", e1, p)
        u = np.einsum("ij,ij->i", -v0, p) * inverse
        q = np.cross(-v0, e1)
        v = (q @ direction) * inverse
        t = np.einsum("ij,ij->i", e2, q) * inverse
        hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        nearest[i] = t[hit].min() if hit.any() else np.inf
    return nearest


@pytest.mark.parametrize("centre", [(6.0, 5.0, 0.2), (79.0, -4.0, 0.5), (-300.0, 640.0, 9.0)])
def test_sphere_hits_match_float64_intersections(centre):
    radius = 1.0 if np.linalg.norm(centre) < 100 else 12.0
    sphere = trimesh.creation.icosphere(subdivisions=6 if radius == 1.0 else 5, radius=radius)
    target = mesh_target(sphere.vertices, sphere.faces, "sphere")
    scan = cast_rays(target, FAR_NUSCENES, pose(*centre), ScanOptions())
    assert scan.hits >= 4
    directions, ranges = ray_directions(FAR_NUSCENES, scan), scan.returns["range"]
    assert np.allclose(scan.xyz, directions * ranges[:, None], atol=1e-9, rtol=0)
    # against the float64 intersection with the very same triangles
    exact = tessellation_ranges(sphere.triangles + np.asarray(centre), directions)
    assert np.abs(ranges - exact).max() < 1e-4
    # against the ideal sphere: off by at most the tessellation's sagitta / cos
    c = np.asarray(centre)
    along = directions @ c
    ideal = along - np.sqrt(along**2 - (c @ c - radius**2))
    normal = directions * ideal[:, None] - c
    cosine = np.abs(np.einsum("ij,ij->i", normal / radius, directions))
    sagitta = radius - (sphere.face_normals * sphere.triangles[:, 0]).sum(axis=1).min()
    assert np.all(np.abs(ranges - ideal) <= sagitta / cosine + 1e-5)
    facing = cosine > 0.8
    assert np.abs(ranges - ideal)[facing].max(initial=0) < 1e-4 * radius


@pytest.mark.parametrize("sensor", [FAR_NUSCENES, LASERS_OFF_ORIGIN], ids=lambda sensor: sensor.name)
@pytest.mark.parametrize("centre, heading", [((7.0, -3.0, -0.3), 0.4), ((80.0, 2.0, 0.0), -0.2),
                                             ((420.0, -250.0, 3.0), 1.0)])
def test_box_hits_match_the_analytic_box(centre, heading, sensor):
    size = np.array([4.0, 2.0, 1.6]) * (1 if abs(centre[0]) < 100 else 8)
    box = trimesh.creation.box(extents=size)
    target = mesh_target(box.vertices, box.faces, "box")
    matrix = pose(*centre, heading)
    full = cast_rays(target, sensor, matrix, ScanOptions(window=False))
    # every ray of the revolution from its laser's origin, intersected analytically in the box frame
    rotation, translation = matrix[:3, :3], matrix[:3, 3]
    local = sensor.directions @ rotation
    origins = np.zeros(3) if sensor.cell_origins is None else sensor.cell_origins
    entry, depth = box_entry((origins - translation) @ rotation, local, -size / 2, size / 2)
    hit_cells = full.returns["ring"].astype(np.int64) * sensor.columns + full.returns["column"]
    assert np.abs(full.returns["range"] - entry[hit_cells]).max() < 1e-4
    # a return is its laser's origin + range x direction, and lies on the box
    points = np.column_stack([full.returns[axis] for axis in "xyz"])
    laser = origins[hit_cells] if origins.ndim == 2 else origins
    assert np.allclose(points, laser + full.returns["range"][:, None] * sensor.directions[hit_cells], atol=1e-9)
    on_box = np.abs((points - translation) @ rotation) - size / 2
    assert np.abs(on_box.max(axis=1)).max() < 1e-3 * (1 + np.linalg.norm(centre) / 100)
    clear = np.isfinite(entry) & (depth > 1e-6)  # rays not merely grazing an edge
    assert set(np.flatnonzero(clear)) <= set(hit_cells) <= set(np.flatnonzero(np.isfinite(entry)))


def test_cylinder_hits_match_the_analytic_cylinder():
    radius, height, centre = 0.8, 3.0, np.array([9.0, 4.0, 0.0])
    cylinder = trimesh.creation.cylinder(radius=radius, height=height, sections=1024)
    target = mesh_target(cylinder.vertices, cylinder.faces, "cylinder")
    scan = cast_rays(target, NUSCENES, pose(*centre), ScanOptions())
    directions, ranges = ray_directions(NUSCENES, scan), scan.returns["range"]
    # side wall: |(o + t d - c)_xy| = r
    d, o = directions[:, :2], -centre[:2]
    a, b, c = (d * d).sum(1), (d @ o), o @ o - radius**2
    wall = (-b - np.sqrt(b * b - a * c)) / a
    z = directions[:, 2] * wall - centre[2]
    side = np.abs(z) < height / 2 - 1e-3
    normal = (d * wall[:, None] + o) / radius
    facing = np.abs(np.einsum("ij,ij->i", normal, d / np.linalg.norm(directions[:, :2], axis=1)[:, None])) > 0.5
    assert (side & facing).sum() > 20
    assert np.abs(ranges - wall)[side & facing].max() < 1e-4
    cap = ~side & (directions[:, 2] > 0)  # the top cap seen from below is impossible: sensor is below the top
    with np.errstate(divide="ignore"):
        top = (centre[2] + height / 2) / directions[:, 2]
    assert np.abs(ranges - np.where(cap, top, ranges)).max() < 1e-4


def test_per_beam_hits_on_a_plane_equal_the_analytic_count():
    corners = np.array([[-0.013, -7.3, -1.7], [-0.013, 6.1, -1.7], [-0.013, 6.1, 2.9], [-0.013, -7.3, 2.9]])
    target = mesh_target(corners, [[0, 1, 2], [0, 2, 3]], "wall")
    matrix = pose(12.0, 1.0, 0.0, 0.0)
    scan = cast_rays(target, NUSCENES, matrix, ScanOptions())
    # analytic: the ray meets the plane x = 12 - 0.013 inside the rectangle
    directions = NUSCENES.directions.reshape(NUSCENES.beams, NUSCENES.columns, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (12.0 - 0.013) / directions[..., 0]
    y, z = directions[..., 1] * t + 0.0 - 1.0, directions[..., 2] * t
    inside = (t > 0) & (y > -7.3) & (y < 6.1) & (z > -1.7) & (z < 2.9)
    expected = inside.sum(axis=1)
    counted = np.bincount(scan.returns["ring"], minlength=NUSCENES.beams)
    assert expected.sum() > 500 and np.array_equal(counted, expected)
    assert np.abs(scan.returns["range"] - t[inside]).max() < 1e-6


@pytest.mark.parametrize("mesh", [trimesh.creation.box(extents=(2, 2, 2)), trimesh.creation.icosphere(2)],
                         ids=["cube", "icosphere"])
def test_rays_through_shared_edges_and_vertices_never_leak(mesh):
    target = mesh_target(mesh.vertices, mesh.faces, "closed", engine="bvh")
    from mathutils import Vector  # loaded with the BVH (the PyPI bpy registers it)

    rng = np.random.default_rng(3)
    aims = np.concatenate([mesh.vertices, mesh.vertices[mesh.edges_unique].mean(axis=1)])
    misses = 0
    for aim in aims:
        for inner in rng.uniform(-0.4, 0.4, (10, 3)):  # each ray goes on into the interior
            direction = (inner - aim) / np.linalg.norm(inner - aim)
            misses += target.bvh.ray_cast(Vector(aim - 9.0 * direction), Vector(direction))[0] is None
    assert misses == 0


# ---------------------------------------------------------------- degenerate input

def test_zero_area_faces_are_dropped_with_a_warning():
    box = trimesh.creation.box()
    faces = np.vstack([box.faces, [[0, 0, 1], [0, 1, 1]]])
    with pytest.warns(UserWarning, match="dropped 2 zero-area faces of 14"):
        target = mesh_target(box.vertices, faces, "with slivers")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        clean = mesh_target(box.vertices, box.faces, "clean")
    matrix = pose(5.0, 0.0, 0.0)
    assert cast_rays(target, NUSCENES, matrix, ScanOptions()).returns.tobytes() == \
        cast_rays(clean, NUSCENES, matrix, ScanOptions()).returns.tobytes()


@pytest.mark.parametrize("vertices, faces, problem", [
    (np.zeros((0, 3)), np.zeros((0, 3), int), "has no faces"),
    ([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]], [[0, 1, 2]], "1 vertices are NaN or infinite"),
    ([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], "every face has zero area"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]], "face indices out of range"),
])
def test_degenerate_meshes_are_clear_errors(vertices, faces, problem):
    with pytest.raises(InputError, match=problem):
        mesh_target(vertices, faces, "broken.obj")


def test_degenerate_point_clouds_are_clear_errors():
    with pytest.raises(InputError, match="point cloud is empty"):
        surfel_target(np.zeros((0, 3)), "empty.ply")
    with pytest.raises(InputError, match="2 points are NaN"):
        surfel_target([[0, 0, 0], [np.inf, 0, 0], [1, 1, np.nan], [0, 1, 0], [1, 0, 0]], "nan.ply")
    with pytest.raises(InputError, match="too few"):
        surfel_target(np.eye(3), "three.ply")


# ---------------------------------------------------------------- noise, drop, determinism, intensity

def test_same_seed_same_bytes_and_effects_do_what_they_say(sample_truck):
    matrix = placement(sample_truck.bounds, NUSCENES, 12.0, 4.0, 0.5)
    exact = cast_rays(sample_truck, NUSCENES, matrix, ScanOptions())
    noisy = ScanOptions(range_noise=True, drop_rate=0.2, seed=7)
    first, second = cast_rays(sample_truck, NUSCENES, matrix, noisy), cast_rays(sample_truck, NUSCENES, matrix, noisy)
    assert first.returns.tobytes() == second.returns.tobytes()
    assert first.returns.tobytes() != cast_rays(sample_truck, NUSCENES, matrix, replace(noisy, seed=8)).returns.tobytes()
    assert 0.7 < first.hits / exact.hits < 0.9
    kept = np.isin(exact.returns[["ring", "column"]], first.returns[["ring", "column"]])
    error = first.returns["range"] - exact.returns["range"][kept]
    assert 0.015 < error.std() < 0.025  # the sensor's 2 cm
    grazing = cast_rays(sample_truck, NUSCENES, matrix, ScanOptions(max_incidence_deg=60))
    assert 0 < grazing.hits < exact.hits
    dim = cast_rays(sample_truck, NUSCENES, matrix, ScanOptions(min_intensity=0.01))  # the law's scale: 0.064
    assert 0 < dim.hits < exact.hits and dim.returns["intensity"].min() >= 0.01 * 255 - 0.5


def test_physical_intensity_on_a_wall_facing_the_sensor():
    corners = np.array([[0, -3, -2], [0, 3, -2], [0, 3, 3], [0, -3, 3]], float)
    for dataset, sensor, distance in (("nuscenes", NUSCENES, 5.0), ("kitti", PRESETS["kitti"], 20.0)):
        target = mesh_target(corners, [[0, 1, 2], [0, 2, 3]], "wall", face_reflectivity=[0.8, 0.8])
        scan = cast_rays(target, sensor, pose(distance, 0, 0), ScanOptions())
        directions = ray_directions(sensor, scan)
        scale, exponent, _ = sensor.intensity_law  # the fitted law; its spread needs range_noise
        expected = np.clip(scale * 0.5 * np.abs(directions[:, 0])  # one color: the mean reflectivity 0.5
                           * np.minimum(1, REFERENCE_RANGE / scan.returns["range"]) ** exponent, 0, 1)
        if dataset == "nuscenes":
            assert np.array_equal(scan.returns["intensity"], np.round(expected * 255))
        else:
            assert np.allclose(scan.returns["intensity"], expected, atol=1e-6)
            assert scan.returns["intensity"].max() <= 1.0


# ---------------------------------------------------------------- range view and surfels

def box_surface(size, count, seed):
    box = trimesh.creation.box(extents=size)
    points, faces = trimesh.sample.sample_surface(box, count, seed=seed)
    return box, points, box.face_normals[faces]


def test_range_view_keeps_the_nearest_point_per_cell_at_the_cell_centre_angles():
    box, points, normals = box_surface((4.0, 2.0, 1.6), 60000, seed=21)
    bounds = np.asarray(box.bounds)
    matrix = placement(bounds, NUSCENES, 10.0, 2.0, 0.6)
    view = range_view_scan(points, NUSCENES, matrix, bounds, normals=normals)
    assert view.returns.dtype == RETURN_DTYPE and view.hits > 100
    cells = view.returns["ring"].astype(np.int64) * NUSCENES.columns + view.returns["column"]
    assert len(np.unique(cells)) == len(cells)
    assert np.allclose(view.xyz, NUSCENES.directions[cells] * view.returns["range"][:, None], atol=1e-9)
    placed = points @ matrix[:3, :3].T + matrix[:3, 3]
    assert np.isin(view.returns["range"], np.linalg.norm(placed, axis=1)).all()  # ranges are kept as they were
    cast = cast_rays(mesh_target(box.vertices, box.faces, "box"), NUSCENES, matrix, ScanOptions())
    cast_cells = cast.returns["ring"].astype(np.int64) * NUSCENES.columns + cast.returns["column"]
    common, in_view, in_cast = np.intersect1d(cells, cast_cells, return_indices=True)
    assert len(common) > 0.9 * cast.hits  # dense input: range view sees what the rays see
    assert np.median(np.abs(view.returns["range"][in_view] - cast.returns["range"][in_cast])) < 0.05


def test_surfels_of_dense_points_scan_like_the_mesh():
    box, points, _ = box_surface((4.0, 2.0, 1.6), 40000, seed=22)
    matrix = placement(np.asarray(box.bounds), NUSCENES, 9.0, -3.0, 0.3)
    mesh_scan = cast_rays(mesh_target(box.vertices, box.faces, "box"), NUSCENES, matrix, ScanOptions())
    surfel_scan = cast_rays(surfel_target(points, "box points"), NUSCENES, matrix, ScanOptions())
    mesh_cells = mesh_scan.returns["ring"].astype(np.int64) * NUSCENES.columns + mesh_scan.returns["column"]
    surfel_cells = surfel_scan.returns["ring"].astype(np.int64) * NUSCENES.columns + surfel_scan.returns["column"]
    common, in_mesh, in_surfels = np.intersect1d(mesh_cells, surfel_cells, return_indices=True)
    assert len(common) > 0.97 * mesh_scan.hits and len(surfel_cells) < 1.03 * mesh_scan.hits
    error = np.abs(mesh_scan.returns["range"][in_mesh] - surfel_scan.returns["range"][in_surfels])
    assert np.median(error) < 0.01


@pytest.mark.parametrize("class_name", MINORITY_CLASSES)
def test_floaters_are_left_out_of_surfels(class_name):
    """A built-in sample's reconstruction (0.5 % noise, 3 % floaters in a box 1.5x the
    vehicle's) scanned as surfels: the floaters' disks, as wide as their distance to the
    surface, used to give 80-99 % of the returns; now under 5 %, with about the returns
    of the floater-free points, and the face column still indexes the given points.
    Floaters that landed on the surface stay: nothing tells them from it."""
    sample = synthetic_reconstruction(class_name, seed=3)
    object_from_source = np.linalg.inv(sample.source_from_object)
    points = sample.positions @ object_from_source[:3, :3].T + object_from_source[:3, 3]
    target = surfel_target(points, class_name, sample.colors)
    clean = surfel_target(points[~sample.is_outlier], class_name, sample.colors[~sample.is_outlier])
    kept = np.isin(np.arange(len(points)), target.source_index)
    assert (~kept & ~sample.is_outlier).sum() < 0.01 * len(points)  # the surface stays
    assert (kept & sample.is_outlier).sum() < 0.25 * sample.is_outlier.sum()  # the rest lie on it
    assert np.allclose(target.bounds, clean.bounds, atol=0.02 * np.ptp(clean.bounds, axis=0).max())
    matrix = placement(clean.bounds, NUSCENES, 12.0, 0.0, 0.6)
    scan = cast_rays(target, NUSCENES, matrix, ScanOptions())
    assert scan.hits > 20 and sample.is_outlier[scan.returns["face"]].mean() < 0.05
    assert abs(scan.hits / cast_rays(clean, NUSCENES, matrix, ScanOptions()).hits - 1) < 0.1


def test_repeated_points_scan_as_the_points_once():
    """A cloud given 12 times (a merge of captures, a writer's duplicates): each copy's
    nearest points were its own copies at 0 m, so its surfels shrank to nothing and the
    scan came back empty. Copies now count once: the same returns as the cloud alone."""
    sample = synthetic_reconstruction("truck", seed=3, points=4000, outlier_share=0.0)
    once = surfel_target(sample.positions, "once", sample.colors)
    repeated = surfel_target(np.tile(sample.positions, (12, 1)), "repeated", np.tile(sample.colors, (12, 1)))
    matrix = placement(once.bounds, NUSCENES, 12.0, 0.0, 0.6)
    expected, scan = (cast_rays(target, NUSCENES, matrix, ScanOptions()) for target in (once, repeated))
    assert expected.hits > 100 and scan.hits == expected.hits
    for column in ("x", "y", "z", "intensity"):
        np.testing.assert_array_equal(scan.returns[column], expected.returns[column])
    assert (scan.returns["face"] % len(sample.positions) == expected.returns["face"]).all()


def test_gaussian_splats_scan_as_ellipses(donut):
    from pgt_blender.core.importing import load_reconstruction

    splats = load_reconstruction(donut)
    scale = 20.0  # the donut is 0.22 units across: make it a 4 m object
    target = surfel_target(splats.positions * scale, "donut", splats.colors,
                           scales=splats.attributes["scale"] * scale, rotations=splats.attributes["rotation"])
    scan = scan_object(target, NUSCENES, 8.0, 0.0, 0.0)
    assert target.kind == "surfels" and scan.hits > 50
    assert (scan.returns["face"] < len(splats.positions)).all()


# ---------------------------------------------------------------- sweeps and files

def test_sweeps_move_the_object_back_along_its_heading(sample_truck):
    motion, heading = Motion(speed=10.0, acceleration=1.0), 0.25
    merged = scan_sweeps(sample_truck, NUSCENES, 15.0, 3.0, heading, motion, 10)
    assert np.array_equal(np.unique(merged.returns["sweep"]), np.arange(10))
    assert np.allclose(np.unique(merged.returns["time_lag"]), np.arange(10) * 0.05)
    assert np.allclose(merged.box[7:], 10.0 * np.array([np.cos(heading), np.sin(heading)]))
    lag = 0.35  # sweep 7: the truck was 10 * 0.35 - 0.5 * 0.35^2 metres back
    back = 10.0 * lag - 0.5 * lag**2
    expected = cast_rays(sample_truck, NUSCENES,
                         placement(sample_truck.bounds, NUSCENES, 15.0 - back * np.cos(heading),
                                   3.0 - back * np.sin(heading), heading), ScanOptions(), sweep=7)
    assert merged.returns[merged.returns["sweep"] == 7].tobytes() == expected.returns.tobytes()


def test_a_moving_ego_sees_a_still_object_anew_each_sweep_motion_compensated():
    """Sweep k is cast from where the sensor was k sweeps ago (nuScenes: forward = +y)
    and its returns are moved into the key frame: every noiseless return still lies on
    the still box's surface there, and the sweeps hit different points."""
    dims = np.array([6.0, 2.5, 3.0])
    mesh = trimesh.creation.box(dims)
    target = mesh_target(mesh.vertices, mesh.faces, name="box")
    ego = Motion(speed=12.0, acceleration=0.5)
    scan = scan_sweeps(target, NUSCENES, 8.0, 10.0, 0.3, Motion(), 10, ScanOptions(range_noise=True, seed=3),
                       ego=ego)
    lag = 0.45  # sweep 9: the sensor was 12 * 0.45 - 0.25 * 0.45^2 m back along +y
    np.testing.assert_allclose(scan.origins[9], [0.0, -(12.0 * lag - 0.25 * lag**2), 0.0])
    assert all(np.array_equal(pose, scan.poses[0]) for pose in scan.poses)  # the object stood still
    local = box_frame(scan.true_xyz, scan.box[:3], scan.box[6])
    on_a_face = np.abs(np.abs(local) - dims / 2).min(axis=1)
    assert np.abs(local).max(axis=0).max() <= dims.max() / 2 + 1e-6 and on_a_face.max() < 1e-6
    first, last = (scan.returns[scan.returns["sweep"] == k] for k in (0, 9))
    assert len(first) > 100 and len(last) > 100
    assert not np.array_equal(first[["ring", "column"]], last[["ring", "column"]])
    # A still ego: every sweep is the same cast (noise aside), as before.
    still = scan_sweeps(target, NUSCENES, 8.0, 10.0, 0.3, Motion(), 3)
    assert np.array_equal(*(still.returns[still.returns["sweep"] == k][["ring", "column"]] for k in (0, 2)))


def test_motion_draws_are_seeded():
    first = [sample_motion("truck", np.random.default_rng(4)) for _ in range(2)]
    assert first[0] == first[1]
    draws = [sample_motion("car", np.random.default_rng(seed)) for seed in range(200)]
    assert 0.3 < np.mean([d.speed == 0 for d in draws]) < 0.7
    assert all(0 <= d.speed <= 16 for d in draws)


def test_every_database_class_has_a_motion_model_and_user_classes_take_their_mapping():
    from pgt_blender.core.bank.formats import DATABASE_CLASSES
    from pgt_blender.core.scan.sweeps import motion_class

    assert all(motion_class(name) for names in DATABASE_CLASSES.values() for name in names)
    assert motion_class("semi", "Truck") == "truck"  # [classes] semi = "Truck": moves like a truck, not still
    assert motion_class("semi", "Semi") is None
    assert all(sample_motion("traffic_cone", np.random.default_rng(seed)).speed == 0 for seed in range(20))


def test_scan_files_hold_the_dataset_columns(sample_truck, tmp_path):
    for dataset, sensor, width in (("nuscenes", NUSCENES, 5), ("kitti", PRESETS["kitti"], 4)):
        scan = scan_sweeps(sample_truck, sensor, 10.0, 5.0, 1.0, Motion(5.0), 2)
        write_scan(scan, tmp_path / f"{dataset}.bin")
        rows = np.fromfile(tmp_path / f"{dataset}.bin", np.float32).reshape(-1, width)
        assert np.array_equal(rows[:, 3], scan.returns["intensity"])
        assert np.allclose(rows[:, :3], scan.xyz, atol=1e-5)
        if width == 5:
            assert np.allclose(rows[:, 4], scan.returns["time_lag"])
        write_scan(scan, tmp_path / f"{dataset}.ply")
        columns = read_vertices(tmp_path / f"{dataset}.ply")
        assert set(columns) == set(RETURN_DTYPE.names) and np.array_equal(columns["ring"], scan.returns["ring"])
        write_scan(scan, tmp_path / f"{dataset}.npy")
        assert np.load(tmp_path / f"{dataset}.npy").tobytes() == scan.returns.tobytes()
    with pytest.raises(ValueError, match="must end in"):
        write_scan(scan, tmp_path / "scan.txt")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        f"{d}.{s}" for d in ("nuscenes", "kitti") for s in ("bin", "ply", "npy"))


# ---------------------------------------------------------------- see-through surfaces

def _pane(x, half=2.0):
    """Two triangles of a 4 x 4 m square facing the sensor at distance x."""
    return (np.array([[x, -half, -half], [x, half, -half], [x, half, half], [x, -half, half]]),
            np.array([[0, 1, 2], [0, 2, 3]]))


@pytest.mark.parametrize("engine", ["bvh", "embree"])
def test_rays_pass_glass_and_return_from_what_lies_behind(engine):
    """A glass pane 5 m ahead and a wall at 7 m: every return is on the wall, at the
    wall's analytic range; glass alone returns nothing."""
    (glass, glass_faces), (wall, wall_faces) = _pane(5.0), _pane(7.0, half=3.0)
    vertices, faces = np.vstack([glass, wall]), np.vstack([glass_faces, wall_faces + 4])
    see_through = np.array([True, True, False, False])
    target = mesh_target(vertices, faces, "window", face_see_through=see_through, engine=engine)
    scan = cast_rays(target, FAR_NUSCENES, np.eye(4), ScanOptions(engine=engine))
    directions = ray_directions(FAR_NUSCENES, scan)
    assert scan.hits > 50 and set(scan.returns["face"]) <= {2, 3}
    assert np.abs(scan.returns["range"] - 7.0 / directions[:, 0]).max() < 1e-6
    only_glass = mesh_target(glass, glass_faces, "glass", face_see_through=[True, True], engine=engine)
    assert cast_rays(only_glass, FAR_NUSCENES, np.eye(4), ScanOptions(engine=engine)).hits == 0


def test_a_target_is_built_for_its_engine():
    """A target built for Embree holds a committed scene (Embree builds its BVH on a
    scene's first query: built with the target, a cached target's first scan costs what
    the others do) and no Blender BVH; cast with the BVH engine it builds that on first
    use, with the very returns of a target built for the BVH. Gaussian
    targets have no polygons for either; an unknown engine name is an error."""
    vertices, faces = _pane(5.0)
    target = mesh_target(vertices, faces, "pane", engine="embree")
    scene = target.embree_scene
    assert target.bvh is None and scene is not None and scene.is_committed
    by_embree = cast_rays(target, FAR_NUSCENES, np.eye(4), ScanOptions(engine="embree"))
    by_bvh = cast_rays(target, FAR_NUSCENES, np.eye(4), ScanOptions(engine="bvh"))
    assert target.embree_scene is scene and target.bvh is not None and by_embree.hits > 50
    plain = mesh_target(vertices, faces, "pane", engine="bvh")
    assert plain.bvh is not None and plain.embree_scene is None
    assert cast_rays(plain, FAR_NUSCENES, np.eye(4), ScanOptions(engine="bvh")).returns.tobytes() == \
        by_bvh.returns.tobytes()
    with pytest.raises(ValueError, match="engine must be one of"):
        mesh_target(vertices, faces, "pane", engine="optix")
    splats = gaussian_target(vertices, np.full((4, 3), 0.1), np.tile([1.0, 0.0, 0.0, 0.0], (4, 1)), np.ones(4))
    for build in (embree_scene, blender_bvh):
        with pytest.raises(ValueError, match="no polygons|no triangles"):
            build(splats)


def test_glass_is_named_or_transparent_and_faint_splats_are_seen_through(donut):
    from pgt_blender.core.importing import load_reconstruction
    from pgt_blender.core.scan.targets import see_through_materials, target_from_reconstruction

    assert see_through_materials(["Material_Window.000", "GLASS", "Windshield", "paint", "", None]).tolist() == \
        [True, True, True, False, False, False]
    assert see_through_materials(["paint", "paint"], [1.0, 0.3]).tolist() == [False, True]
    splats = load_reconstruction(donut)
    splats.positions = splats.positions * 20  # a 4 m donut
    target = target_from_reconstruction(splats, gaussians=False)  # splats as surfels
    faint = splats.attributes["opacity"] < 0.5
    assert target.see_through is not None and target.see_through.sum() == faint.sum() > 0
    scan = cast_rays(target, FAR_NUSCENES, pose(6.0, 0.0, 0.0), ScanOptions())
    assert scan.hits > 100 and not faint[scan.returns["face"]].any()


@pytest.mark.parametrize("engine", ["bvh", "embree"])
def test_a_stretched_target_scans_as_the_mesh_stretched(sample_truck, engine):
    """A size variant is the target's rays stretched (trace_rays' ``scale``), not a new
    target: it returns the hits of the mesh whose vertices are scaled, on the same cells,
    with the same ranges and incidences (float32 geometry apart), from every side and
    over moving sweeps."""
    scale = np.array([1.08, 0.93, 1.04])
    mesh = sample_vehicle("truck").trimesh()
    stretched = mesh_target(mesh.vertices * scale, mesh.faces, name="stretched")
    rng = np.random.default_rng(3)
    for _ in range(6):
        distance, azimuth, heading = rng.uniform(5, 40), rng.uniform(-np.pi, np.pi), rng.uniform(-np.pi, np.pi)
        x, y = distance * np.cos(azimuth), distance * np.sin(azimuth)
        by_rays = scan_sweeps(sample_truck, NUSCENES, x, y, heading, Motion(6.0), 3, ScanOptions(engine=engine),
                              scale=scale)
        by_mesh = scan_sweeps(stretched, NUSCENES, x, y, heading, Motion(6.0), 3, ScanOptions(engine=engine))
        assert by_rays.hits > 100
        np.testing.assert_allclose(by_rays.box, by_mesh.box, atol=1e-12)
        same = np.isin(by_rays.returns[["sweep", "ring", "column"]], by_mesh.returns[["sweep", "ring", "column"]])
        assert same.mean() > 0.995  # a ray through a shared edge may pick the other side
        rows, others = by_rays.returns[same], by_mesh.returns[np.isin(
            by_mesh.returns[["sweep", "ring", "column"]], by_rays.returns[["sweep", "ring", "column"]])]
        assert np.abs(rows["range"] - others["range"]).max() < 1e-5
        assert np.abs(rows["intensity"] - others["intensity"]).max() <= 1.0  # whole numbers, the cosine's rounding


@pytest.mark.parametrize("lasers_off_the_origin", [False, True])
def test_a_rays_bits_do_not_depend_on_the_runs_it_is_worked_in(sample_truck, monkeypatch, lasers_off_the_origin):
    """trace_rays works through a batch's rays in runs of about RAY_BLOCK (whole poses,
    for the rays' frames): in tiny runs, with every pose split across several, the
    trace of stretched targets seen by lasers on or off the origin is the same, bit for
    bit, as in the default runs."""
    sensor = NUSCENES
    if lasers_off_the_origin:
        sensor = replace(NUSCENES, vertical_offsets_m=tuple(np.linspace(-0.1, 0.1, NUSCENES.beams)),
                         horizontal_offsets_m=tuple(np.linspace(0.03, -0.03, NUSCENES.beams)))
    rng = np.random.default_rng(5)
    poses = np.stack([pose(x, y, heading=h) for x, y, h in zip(rng.uniform(-25, 25, 6), rng.uniform(-25, 25, 6),
                                                               rng.uniform(-np.pi, np.pi, 6))])
    scales = rng.uniform(0.9, 1.1, (6, 3))
    default = trace_rays(sample_truck, sensor, poses, scale=scales)
    monkeypatch.setattr(raycast, "RAY_BLOCK", 97)
    small = trace_rays(sample_truck, sensor, poses, scale=scales)
    assert default.rays.min() > 97 and len(default.cells) > 1000
    for name in ("rays", "pose", "cells", "ranges", "cos_incidence", "polygons"):
        assert getattr(small, name).tobytes() == getattr(default, name).tobytes(), name


@pytest.mark.parametrize("engine", ["bvh", "embree"])
def test_size_variants_cast_together_scan_as_each_alone(sample_truck, engine):
    """scan_many casts objects of different sizes (one ``scale`` and box per object) in
    one engine call; each object's scan is the one it gets alone, bit for bit, and a
    scan asking for fewer columns holds the same values in those."""
    rng = np.random.default_rng(11)
    count = 5
    scales = rng.uniform(0.9, 1.1, (count, 3))
    x, y = rng.uniform(-30, 30, count), rng.uniform(-30, 30, count)
    heading, seeds = rng.uniform(-np.pi, np.pi, count), np.arange(count) + 40
    bounds = sample_truck.bounds * scales[:, None]
    options = ScanOptions(range_noise=True, drop_rate=0.1, engine=engine)
    motion, ego = Motion(np.linspace(0.0, 8.0, count)), Motion(np.full(count, 4.0))
    together = scan_many(sample_truck, NUSCENES, x, y, heading, motion, 3, options, seeds, bounds, 0.01, ego,
                         scale=scales)
    lean = scan_many(sample_truck, NUSCENES, x, y, heading, motion, 3, replace(options, columns=("time_lag",)),
                     seeds, bounds, 0.01, ego, scale=scales)
    for index in range(count):
        alone = scan_sweeps(sample_truck, NUSCENES, x[index], y[index], heading[index],
                            Motion(motion.speed[index]), 3, replace(options, seed=int(seeds[index])), bounds[index],
                            0.01, Motion(ego.speed[index]), scale=scales[index])
        assert alone.hits > 20 and together[index].returns.tobytes() == alone.returns.tobytes()
        assert together[index].box.tobytes() == alone.box.tobytes()
        assert lean[index].returns.dtype.names == ("x", "y", "z", "time_lag")
        assert all(lean[index].returns[name].tobytes() == alone.returns[name].tobytes()
                   for name in lean[index].returns.dtype.names)
    with pytest.raises(ValueError, match="no return column colour"):
        ScanOptions(columns=("intensity", "colour"))
