"""PCA axis alignment: analytic hard cases and property-based recovery of known poses."""

from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pgt_blender.core.authoring import alignment
from pgt_blender.core.authoring.alignment import (_deblurred_edge, align_axes, camera_up, density_inliers,
                                                   surface_estimate)
from pgt_blender.core.classes import MINORITY_CLASSES
from pgt_blender.core.errors import InputError
from pgt_blender.core.importing import load_reconstruction
from pgt_blender.core.samples import observed, random_rotation, sample_vehicle

# The documented symmetry with an up prior: the 180 degree turn about z (front/back).
FLIP = np.diag([-1.0, -1.0, 1.0])


def rotation_degrees(a, b) -> float:
    cosine = (np.trace(a @ b.T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cosine, -1, 1))))


def error_degrees(found, truth) -> float:
    """Angle between the recovered and true object_from_source rotations, up to FLIP."""
    return min(rotation_degrees(found, truth), rotation_degrees(FLIP @ found, truth))


def rotate_z(degrees) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def box_surface(extents, count, seed=0) -> np.ndarray:
    points, _ = trimesh.sample.sample_surface(trimesh.creation.box(extents=extents), count, seed=seed)
    return points


def aligned(points, found):
    return points @ found.transform[:3, :3].T + found.transform[:3, 3]


# ---- hard cases --------------------------------------------------------------------------

@pytest.mark.parametrize("yaw", [0.0, 17.0, 44.0, 73.0])
def test_square_footprint_snaps_to_an_edge(yaw):
    """Equal footprint eigenvalues: the fourth moment finds the square's edges; x is
    the edge nearest the source +x, so the box comes out tight, never diagonal."""
    points = box_surface((2.0, 2.0, 1.0), 20000) @ rotate_z(yaw).T
    found = align_axes(points, up=[0, 0, 1])
    assert found.yaw_from == "fourfold"
    np.testing.assert_allclose(found.dims, [2.0, 2.0, 1.0], atol=5e-3)
    snapped = ((yaw + 45) % 90) - 45  # the edge nearest +x
    assert rotation_degrees(found.transform[:3, :3], rotate_z(-snapped)) < 0.2


def test_exact_square_grid_is_deterministic():
    """A grid whose footprint eigenvalues are exactly equal: same bytes on every run."""
    u = np.linspace(-1, 1, 21)
    grid = np.array(np.meshgrid(u, u, [0.0, 0.5])).reshape(3, -1).T @ rotate_z(30).T
    runs = [align_axes(grid, up=[0, 0, 1]).transform.tobytes() for _ in range(3)]
    assert runs[0] == runs[1] == runs[2]
    assert rotation_degrees(np.frombuffer(runs[0]).reshape(4, 4)[:3, :3], rotate_z(-30)) < 1e-6


def test_cylinder_keeps_the_source_x():
    """A round footprint has no axis: x is the source +x projected, documented."""
    cylinder = trimesh.creation.cylinder(radius=1.0, height=3.0, sections=256)
    points, _ = trimesh.sample.sample_surface(cylinder, 20000, seed=2)
    found = align_axes(points, up=[0, 0, 1])
    assert found.yaw_from == "source"
    assert rotation_degrees(found.transform[:3, :3], np.eye(3)) < 1e-9


def test_lying_cylinder_without_prior_is_upright_towards_source_z():
    """Two equal minor eigenvalues: up is the direction perpendicular to the axis
    nearest the source +z, never a random one."""
    axis = np.array([1.0, 1.0, 0.3]) / np.linalg.norm([1.0, 1.0, 0.3])
    cylinder = trimesh.creation.cylinder(radius=0.5, height=6.0, sections=256,
                                         transform=trimesh.geometry.align_vectors([0, 0, 1], axis))
    points, _ = trimesh.sample.sample_surface(cylinder, 20000, seed=3)
    found = align_axes(points)
    rotation = found.transform[:3, :3]
    expected_up = np.array([0, 0, 1.0]) - axis * axis[2]
    assert found.up_from == "source"
    assert np.degrees(np.arccos(rotation[2] @ expected_up / np.linalg.norm(expected_up))) < 0.1
    assert abs(abs(rotation[0] @ axis) - 1) < 1e-3  # x along the cylinder


def test_sphere_keeps_the_source_axes():
    points = trimesh.sample.sample_surface(trimesh.creation.icosphere(5), 20000, seed=4)[0]
    found = align_axes(points)
    assert (found.up_from, found.yaw_from) == ("source", "source")
    assert rotation_degrees(found.transform[:3, :3], np.eye(3)) < 1e-9


def test_planar_cloud_gets_its_normal_as_up():
    rng = np.random.default_rng(5)
    flat = np.column_stack([rng.uniform(-3, 3, 20000), rng.uniform(-1, 1, 20000), np.zeros(20000)])
    rotation = random_rotation(rng)
    found = align_axes(flat @ rotation.T)
    axes = found.transform[:3, :3]
    assert found.up_from == "pca" and found.dims[2] < 1e-9
    assert abs(axes[2] @ rotation[:, 2]) == pytest.approx(1, abs=1e-12)  # z: the exact normal
    assert np.degrees(np.arccos(abs(axes[0] @ rotation[:, 0]))) < 0.5  # x: the long side


def test_collinear_cloud():
    direction = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    points = np.linspace(-2, 5, 50)[:, None] * direction + [10.0, 20.0, 30.0]
    found = align_axes(points)
    rotation = found.transform[:3, :3]
    assert abs(abs(rotation[0] @ direction) - 1) < 1e-12
    np.testing.assert_allclose(found.dims, [7.0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(aligned(points, found)[:, 1:], 0, atol=1e-9)  # on the x axis


@pytest.mark.parametrize("points", [
    [[1.0, 2.0, 3.0]],
    [[1.0, 2.0, 3.0], [4.0, 6.0, 3.0]],
    [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
], ids=["one", "two", "three"])
def test_one_two_three_points(points):
    points = np.array(points)
    found = align_axes(points)
    rotation = found.transform[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    local = aligned(points, found)
    np.testing.assert_allclose((local.min(axis=0) + local.max(axis=0)) / 2, 0, atol=1e-12)  # box centred
    if len(points) == 1:
        np.testing.assert_allclose(rotation, np.eye(3))
        np.testing.assert_allclose(found.dims, 0)
    if len(points) == 2:
        np.testing.assert_allclose(found.dims, [5.0, 0, 0], atol=1e-12)
    if len(points) == 3:
        assert found.dims[2] == pytest.approx(0, abs=1e-12) and found.up_from == "pca"


def test_duplicated_points_change_nothing():
    points = box_surface((4.0, 2.0, 1.5), 5000, seed=6) @ random_rotation(np.random.default_rng(6)).T
    once = align_axes(points)
    thrice = align_axes(np.repeat(points, 3, axis=0))
    np.testing.assert_allclose(thrice.transform, once.transform, atol=1e-9)
    np.testing.assert_allclose(thrice.dims, once.dims, atol=1e-9)


def test_float32_cloud_a_million_metres_away():
    """Moments are float64 after centring: only the float32 rounding of the input
    (6 cm at 1e6 m) remains."""
    vehicle = sample_vehicle("truck")
    points, _ = trimesh.sample.sample_surface(vehicle.trimesh(), 20000, seed=7)
    rotation = random_rotation(np.random.default_rng(7))
    offset = np.array([1e6, -2e6, 5e5])
    far = (points @ rotation.T + offset).astype(np.float32)
    found = align_axes(far, up=rotation[:, 2])
    assert error_degrees(found.transform[:3, :3], rotation.T) < 0.5
    np.testing.assert_allclose(found.dims, vehicle.dims, atol=0.15)
    centre = -found.transform[:3, :3].T @ found.transform[:3, 3]  # box centre, source frame
    assert np.linalg.norm(centre - offset) < 0.15


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_points_are_rejected(bad):
    points = box_surface((1.0, 1.0, 1.0), 100)
    points[17, 1] = bad
    with pytest.raises(InputError, match=r"^scan\.ply: 1 of 100 points have NaN or Inf coordinates$"):
        align_axes(points, source="scan.ply")


@pytest.mark.parametrize("points, weights, message", [
    (np.zeros((0, 3)), None, "expected \\(N, 3\\) points with N >= 1"),
    (np.zeros((5, 2)), None, "expected \\(N, 3\\) points"),
    (np.zeros((5, 3)), np.ones(4), "4 weights for 5 points"),
    (np.zeros((5, 3)), -np.ones(5), "weights must be finite, non-negative"),
    (np.zeros((5, 3)), np.zeros(5), "not all zero"),
])
def test_bad_shapes_and_weights_are_rejected(points, weights, message):
    with pytest.raises(InputError, match=message):
        align_axes(points, weights, source="x.ply")


def test_ten_percent_floaters():
    """10 % floaters in a box 1.5x the object's: the density test drops them and the
    axes and box stay true."""
    rng = np.random.default_rng(8)
    vehicle = sample_vehicle("bus")
    points, _ = trimesh.sample.sample_surface(vehicle.trimesh(), 20000, seed=80)  # not rng's stream
    floaters = rng.random(len(points)) < 0.1
    points[floaters] = rng.uniform(-0.75, 0.75, (floaters.sum(), 3)) * vehicle.dims
    rotation = random_rotation(rng)
    found = align_axes(points @ rotation.T, up=rotation[:, 2])
    assert error_degrees(found.transform[:3, :3], rotation.T) < 0.5
    assert (~found.inliers[floaters]).mean() > 0.7  # the rest lie close to the surface
    assert found.inliers[~floaters].mean() > 0.97  # few surface points lost
    # floaters within ~2 point spacings of the big side walls are indistinguishable from
    # surface noise and still widen the box a little
    assert (found.dims >= vehicle.dims - 0.01).all() and (found.dims <= vehicle.dims + 0.25).all()


def test_density_inliers_keep_small_and_duplicate_clouds():
    assert density_inliers(np.zeros((20, 3))).all()
    assert density_inliers(np.zeros((1000, 3))).all()


def test_weights_silence_floaters():
    """Zero-opacity splats (weight 0) take no part: the result is that of the rest."""
    rng = np.random.default_rng(9)
    core = box_surface((5.0, 2.0, 1.5), 10000, seed=9)
    junk = rng.normal(size=(3000, 3)) * [0.5, 4.0, 0.5]  # a sheet along y
    weights = np.r_[np.ones(len(core)), np.zeros(len(junk))]
    found, alone = align_axes(np.r_[core, junk], weights, up=[0, 0, 1]), align_axes(core, up=[0, 0, 1])
    np.testing.assert_allclose(found.transform, alone.transform, atol=1e-12)
    assert not found.inliers[len(core):].any()


def test_sign_follows_the_third_moment():
    """A shape with a long tail towards one end: x points along the tail whichever way
    the input is turned, so both inputs give the same object-frame points."""
    rng = np.random.default_rng(10)
    wedge = rng.uniform(0, 1, (20000, 3)) * [6.0, 2.0, 1.0]
    wedge = wedge[wedge[:, 1] < 2.0 * (1 - wedge[:, 0] / 6.0) + 0.2]
    turned = wedge @ rotate_z(180).T
    a, b = align_axes(wedge, up=[0, 0, 1]), align_axes(turned, up=[0, 0, 1])
    np.testing.assert_allclose(aligned(wedge, a), aligned(turned, b), atol=1e-9)
    assert skew(aligned(wedge, a)[:, 0]) > 0


def skew(values):
    centred = values - values.mean()
    return np.mean(centred**3)


def test_camera_up_of_the_real_statue(statue):
    """The Statue of Liberty photographed upright: with the cameras' up, the statue
    stands along +z, its tallest side."""
    recon = load_reconstruction(statue)
    up = camera_up(np.stack([c.world_from_camera for c in recon.cameras]))
    found = align_axes(recon.positions, up=up)
    assert found.up_from == "prior" and found.dims[2] == found.dims.max()


def test_camera_up_rejects_cancelling_cameras():
    poses = np.stack([np.eye(4), np.diag([1.0, -1.0, -1.0, 1.0])])
    with pytest.raises(ValueError, match="cancel out"):
        camera_up(poses)


# ---- property-based: known poses of real and built-in vehicles -------------------------

@lru_cache(maxsize=None)
def object_frame_points(name: str, count: int = 20000) -> tuple:
    """Surface points of a built-in sample or a Chrono mesh (X forward, Y left, Z up),
    centred on the box; and the box dims."""
    from .conftest import SHARED_DATA

    if name in MINORITY_CLASSES:
        mesh = sample_vehicle(name).trimesh()
    else:
        mesh = trimesh.load(SHARED_DATA / name, force="mesh")
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=11)
    centre = mesh.bounds.mean(axis=0)
    return points - centre, mesh.extents


def check_recovery(name, seed, noise, outliers):
    """Rotate, add noise and floaters, align with the up prior; compare with the truth
    up to FLIP, then align the result again: nothing may change."""
    source, rotation, dims, rng = posed_cloud(name, seed, noise, outliers, offset=10)
    found = align_axes(source, up=rotation[:, 2])
    assert error_degrees(found.transform[:3, :3], rotation.T) < 0.5
    once = aligned(source.astype(np.float64), found).astype(np.float32)
    again = align_axes(once, up=[0, 0, 1])
    assert rotation_degrees(again.transform[:3, :3], np.eye(3)) < 1e-3
    assert np.abs(again.transform[:3, 3]).max() < 1e-5 * np.linalg.norm(dims)


POSES = dict(seed=st.integers(0, 2**32 - 1), noise=st.floats(0.0, 0.005), outliers=st.floats(0.0, 0.1))
SETTINGS = settings(max_examples=15, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.mark.parametrize("class_name", MINORITY_CLASSES)
@SETTINGS
@given(**POSES)
def test_recovers_sample_vehicle_axes(class_name, seed, noise, outliers):
    check_recovery(class_name, seed, noise, outliers)


CHRONO = ("Nissan_Patrol/suv_chassis.obj", "sedan/sedan_chassis_vis.obj", "sedan/sedan_tire.obj",
          "MAN_Kat1/meshes/MAN_10t_chassis.obj", "VW_microbus/van_chassis.obj", "truck/truck_chassis.obj",
          "citybus/CityBus_Vis.obj")


@pytest.mark.parametrize("mesh", CHRONO)
@SETTINGS
@given(**POSES)
def test_recovers_chrono_mesh_axes(shared_data, mesh, seed, noise, outliers):
    check_recovery(f"chrono_vehicles/data/vehicle/{mesh}", seed, noise, outliers)


# ---- refinement to the surface planes (issue 18) -----------------------------------------

def up_axis_degrees(found, rotation) -> float:
    """Angle between the found and the true up axis, up to the up sign (the documented
    symmetry without a prior)."""
    return float(np.degrees(np.arccos(min(1.0, abs(found.transform[2, :3] @ rotation[:, 2])))))


def posed_cloud(name, seed, noise, outliers, offset=100, count=20000):
    """A sample or Chrono cloud of ``count`` points with noise (x box diagonal) and
    floaters, randomly posed (moved by N(0, ``offset``) m)."""
    points, dims = object_frame_points(name, count)
    rng = np.random.default_rng(seed)
    noisy = observed(points, dims, noise, outliers, rng)
    rotation = random_rotation(rng)
    return (noisy @ rotation.T + rng.normal(scale=offset, size=3)).astype(np.float32), rotation, dims, rng


def tilted(vector, degrees, rng) -> np.ndarray:
    """``vector`` turned by ``degrees`` about a random axis perpendicular to it."""
    axis = np.cross(vector, rng.normal(size=3))
    axis /= np.linalg.norm(axis)
    angle = np.radians(degrees)
    return vector * np.cos(angle) + np.cross(axis, vector) * np.sin(angle)


REFINE_SETTINGS = settings(max_examples=2, deadline=None, derandomize=True)


@pytest.mark.parametrize("class_name", MINORITY_CLASSES)
@REFINE_SETTINGS
@given(seed=st.integers(0, 2**32 - 1), prior_error=st.floats(0.0, 10.0), noise=st.sampled_from([0.0, 0.005]))
def test_refinement_corrects_a_prior_within_ten_degrees(class_name, seed, prior_error, noise):
    """A prior up to 10 degrees off, 10 % floaters: the refined axes are within 0.5
    degrees (up to the heading turn), and the tilt it reports is the prior's error."""
    source, rotation, _, rng = posed_cloud(class_name, seed, noise, 0.1)
    found = align_axes(source, up=tilted(rotation[:, 2], prior_error, rng), refine=True)
    assert found.refined and found.up_from == "prior"
    assert error_degrees(found.transform[:3, :3], rotation.T) < 0.5
    assert found.tilt_deg == pytest.approx(prior_error, abs=0.5)


@pytest.mark.parametrize("class_name", MINORITY_CLASSES)
@REFINE_SETTINGS
@given(seed=st.integers(0, 2**32 - 1), noise=st.sampled_from([0.0, 0.005]))
def test_refinement_finds_up_without_a_prior(class_name, seed, noise):
    """Arbitrary pose, no prior, 10 % floaters: the up axis within 1 degree."""
    source, rotation, _, _ = posed_cloud(class_name, seed, noise, 0.1)
    found = align_axes(source, refine=True)
    assert found.up_from == "planes"
    assert up_axis_degrees(found, rotation) < 1.0


@pytest.mark.parametrize("mesh", [m for m in CHRONO if "tire" not in m])
def test_refinement_of_chrono_meshes_by_face_normals(shared_data, mesh):
    """A real mesh, arbitrarily posed, no prior: its face normals give the axes exactly."""
    loaded = trimesh.load(shared_data / "chrono_vehicles/data/vehicle" / mesh, force="mesh")
    rotation = random_rotation(np.random.default_rng(len(mesh)))
    vertices = loaded.vertices @ rotation.T + 2000.0
    found = align_axes(vertices, faces=loaded.faces, refine=True)
    assert up_axis_degrees(found, rotation) < 0.5
    prior = align_axes(vertices, up=tilted(rotation[:, 2], 8.0, np.random.default_rng(1)), faces=loaded.faces,
                       refine=True)
    assert error_degrees(prior.transform[:3, :3], rotation.T) < 0.5


@pytest.mark.parametrize("mesh", [m for m in CHRONO if "tire" not in m])
@pytest.mark.parametrize("prior_error", [20.0, 30.0, 40.0])
def test_a_prior_far_off_is_overruled_by_the_planes(shared_data, mesh, prior_error):
    """A prior 20 to 40 degrees off (a 3D cursor placed roughly): started from it, the
    refinement locks onto the wrong planes (the truck's box came out 25 % too wide and
    high); the planes' own frame, labelled by the prior, gives the axes."""
    loaded = trimesh.load(shared_data / "chrono_vehicles/data/vehicle" / mesh, force="mesh")
    rotation = random_rotation(np.random.default_rng(len(mesh)))
    vertices = loaded.vertices @ rotation.T + 2000.0
    found = align_axes(vertices, up=tilted(rotation[:, 2], prior_error, np.random.default_rng(2)),
                       faces=loaded.faces, refine=True)
    assert error_degrees(found.transform[:3, :3], rotation.T) < 0.5
    assert found.tilt_deg == pytest.approx(prior_error, abs=0.5)


@pytest.mark.parametrize("class_name", MINORITY_CLASSES)
def test_a_prior_far_off_is_overruled_on_noisy_clouds(class_name):
    """As above on the built-in samples, 0.5 % noise and 10 % floaters, a prior 30
    degrees off: up within 1 degree."""
    source, rotation, _, rng = posed_cloud(class_name, 11, 0.005, 0.1)
    found = align_axes(source, up=tilted(rotation[:, 2], 30.0, rng), refine=True)
    assert found.refined and up_axis_degrees(found, rotation) < 1.0


def test_the_issue_truck_tilted_yawed_and_far_away(shared_data):
    """Issue 18's case: truck_chassis tilted 4 degrees about x, 37 degrees of yaw, 2 km
    away, prepared with the size kept: box within 1 %, axes within 0.5 degrees."""
    from scipy.spatial.transform import Rotation

    from pgt_blender.core.authoring.prepare import prepare
    from pgt_blender.core.reconstruction import Reconstruction

    mesh = trimesh.load(shared_data / "chrono_vehicles/data/vehicle/truck/truck_chassis.obj", force="mesh")
    rotation = Rotation.from_euler("x", 4, degrees=True).as_matrix() @ Rotation.from_euler("z", 37, degrees=True).as_matrix()
    vertices = (mesh.vertices @ rotation.T + [2000.0, 0, 0]).astype(np.float32)
    recon = Reconstruction(positions=vertices, kind="mesh", source=Path("truck_chassis.obj"), sha256="",
                           faces=np.asarray(mesh.faces, np.int32))
    authored = prepare(recon, "truck", up="auto", heading_method="baseline", size="keep")
    assert np.abs(authored.dims / mesh.extents - 1).max() < 0.01
    assert error_degrees(authored.object_from_source[:3, :3], rotation.T) < 0.5
    assert authored.steps[0].details["tilt_deg"] > 3.0


@pytest.mark.parametrize("class_name", MINORITY_CLASSES)
def test_refined_box_is_not_inflated_by_noise_and_floaters(class_name, monkeypatch):
    """0.5 % noise (x box diagonal) and 10 % floaters, three random poses: the refined
    box is the surface's, issue 18's target: the worst axis within 1 % in the median
    over the poses (what bench_alignment.py reports), no pose beyond 2.5 % (a bicycle's
    tubes) and, but for the two-wheelers (whose thin parts the noise widens about as
    much as the 0.1 % trim cuts), each tighter than the unrefined box of the noisy
    points. Every class has sides that are no wall (tyres, handlebar ends, a bucket's
    edge): they come from the deblurred edge. Noise-free, the box is exact to 0.5 %."""
    deblurred = []

    def counted(*args):
        deblurred.append(_deblurred_edge(*args))
        return deblurred[-1]

    monkeypatch.setattr(alignment, "_deblurred_edge", counted)
    worst = []
    for seed in (7, 8, 9):
        source, rotation, dims, _ = posed_cloud(class_name, seed, 0.005, 0.1)
        refined = align_axes(source, up=rotation[:, 2], refine=True)
        plain = align_axes(source, up=rotation[:, 2])
        worst.append(np.abs(refined.dims / dims - 1).max())
        if class_name not in ("motorcycle", "bicycle"):
            assert worst[-1] < np.abs(plain.dims / dims - 1).max()
    assert np.median(worst) < 0.01 and max(worst) < 0.025 and deblurred
    source, rotation, dims, _ = posed_cloud(class_name, 7, 0.0, 0.0)
    clean = align_axes(source, up=rotation[:, 2], refine=True)
    assert np.abs(clean.dims / dims - 1).max() < 0.005


@pytest.mark.parametrize("class_name", MINORITY_CLASSES)
def test_dense_cloud_box_is_as_tight(class_name):
    """100,000 points, 0.5 % noise (x box diagonal) and 10 % floaters, three random
    poses: the nearest neighbours of a dense cloud lie near each point's own offset
    from the surface, so the noise read from all of them came out 0.6-0.8 sigma and the
    box grew by 1-6 % in the median (up to 9 %); the box is read from a sample of ``BOX_POINTS`` instead, and is
    as tight as a 20,000-point cloud's: the worst axis within 1.2 % in the median over
    the poses (1 % but for the bicycle, 1.1 %), no pose beyond 2.5 %."""
    worst = []
    for seed in (7, 8, 9):
        source, rotation, dims, _ = posed_cloud(class_name, seed, 0.005, 0.1, count=100000)
        worst.append(np.abs(align_axes(source, up=rotation[:, 2], refine=True).dims / dims - 1).max())
    assert np.median(worst) < 0.012 and max(worst) < 0.025


def prism(profile, length) -> trimesh.Trimesh:
    """A closed prism along x: the convex (P, 2) ``profile`` in (y, z), ``length`` long,
    its ends fanned from the profile's mean."""
    n = len(profile)
    ring = np.arange(n)
    centre = profile.mean(axis=0)
    vertices = np.r_[np.c_[np.full(n, -length / 2), profile], np.c_[np.full(n, length / 2), profile],
                     [[-length / 2, *centre], [length / 2, *centre]]]
    sides = np.r_[np.c_[ring, (ring + 1) % n, n + ring], np.c_[(ring + 1) % n, n + (ring + 1) % n, n + ring]]
    ends = np.r_[np.c_[np.full(n, 2 * n), (ring + 1) % n, ring],
                 np.c_[np.full(n, 2 * n + 1), n + ring, n + (ring + 1) % n]]
    return trimesh.Trimesh(vertices, np.r_[sides, ends])


@pytest.mark.parametrize("seed", range(3))
def test_rounded_roof_is_not_cut(seed):
    """A 4 m prism, 1.8 m wide, flat walls and floor, a half-cylinder roof (radius 0.9 m,
    1.9 m high in all): 0.5 % noise, 10 % floaters, arbitrary pose with the up prior.
    At 20,000 points the roof's crest is broad enough to count as a wall (its crowd's
    median, not the plane fit's inward extreme): every dimension is within 1 % (the
    unrefined box is 6 % too high)."""
    angles = np.linspace(0, np.pi, 129)
    mesh = prism(np.r_[[[0.9, -0.5]], np.c_[0.9 * np.cos(angles), 0.5 + 0.9 * np.sin(angles)], [[-0.9, -0.5]]], 4.0)
    truth = np.array([4.0, 1.8, 1.9])
    rng = np.random.default_rng(seed)
    points, _ = trimesh.sample.sample_surface(mesh, 20000, seed=seed)
    points = observed(points, truth, 0.005, 0.1, rng, centre=mesh.bounds.mean(axis=0))
    rotation = random_rotation(rng)
    found = align_axes(points @ rotation.T + [30.0, 5.0, -2.0], up=rotation[:, 2], refine=True)
    np.testing.assert_allclose(found.dims, truth, rtol=0.01)


def test_thin_protrusions_are_kept_and_floaters_are_not():
    """A box body with two thin plates sticking out 0.25 m at the sides (mirrors: 0.4 %
    of the surface each), 0.5 % noise, 10 % floaters, arbitrary pose with the up prior:
    the width is the plates' span within 1 % (the trim and the wall median alone cut
    them off), and no side is widened by the floaters beyond 1 %."""
    body = trimesh.creation.box(extents=(4.0, 1.8, 1.4))
    plates = [trimesh.creation.box(extents=(0.1, 0.25, 0.15),
                                   transform=trimesh.transformations.translation_matrix((1.2, side * 1.025, 0.3)))
              for side in (-1, 1)]
    mesh = trimesh.util.concatenate([body, *plates])
    truth = np.array([4.0, 2.3, 1.4])
    rng = np.random.default_rng(12)
    points, _ = trimesh.sample.sample_surface(mesh, 20000, seed=12)
    points = observed(points, truth, 0.005, 0.1, rng)
    rotation = random_rotation(rng)
    found = align_axes(points @ rotation.T + [50.0, -20.0, 3.0], up=rotation[:, 2], refine=True)
    assert error_degrees(found.transform[:3, :3], rotation.T) < 0.5
    np.testing.assert_allclose(found.dims, truth, rtol=0.01)


@pytest.mark.parametrize("seed", range(6))
def test_a_walls_noise_tail_is_no_protrusion(seed):
    """A 4 x 2 x 1.5 m box, 20,000 surface points (spacing about 4 cm) with 1 % noise
    (4.7 cm, about the spacing, where the noise estimate reads 0.85 sigma), 10 %
    floaters, arbitrary pose with the up prior: hundreds of wall points cross a side's
    noise band, and some of them have neighbours there by chance, but no more than the
    same number spread over the side would; the box stays within 1 % (taking such
    chance neighbours for a protrusion widened it by up to 11 %)."""
    dims = np.array([4.0, 2.0, 1.5])
    rng = np.random.default_rng(seed)
    points = observed(box_surface(dims, 20000, seed=seed), dims, 0.01, 0.1, rng)
    rotation = random_rotation(rng)
    found = align_axes(points @ rotation.T, up=rotation[:, 2], refine=True)
    np.testing.assert_allclose(found.dims, dims, rtol=0.01)


@pytest.mark.parametrize("seed", range(3))
def test_deblurred_edge_of_analytic_marginals(seed):
    """The side of a surface seen through Gaussian noise (sigma 2 cm), 20,000 points
    with unit extent 1: a sphere's points are uniform along any axis (Archimedes), so
    its side is a blurred step; a wall is a blurred spike. The deblurred edge is
    within 0.6 sigma of the true side where the 0.1 % trimmed extreme lies 0.7 to 3
    sigma outside it; noise-free points give the trimmed extreme itself."""
    rng = np.random.default_rng(seed)
    sigma = 0.02
    step = rng.uniform(-1, 1, 20000)
    wall = np.r_[rng.uniform(-1, 1, 15000), np.ones(5000)]
    for clean in (step, wall):
        noisy = clean + rng.normal(scale=sigma, size=len(clean))
        assert abs(_deblurred_edge(noisy, sigma) - 1) < 0.6 * sigma
        assert np.partition(noisy, len(noisy) - 21)[len(noisy) - 21] - 1 > 0.6 * sigma
        assert _deblurred_edge(clean, 0.0) == np.partition(clean, len(clean) - 21)[len(clean) - 21]


@pytest.mark.parametrize("sigma", [0.0025, 0.01, 0.0235, 0.03])
def test_surface_noise_estimate_of_a_noisy_box(sigma):
    """A 4 x 2 x 1.5 m box (point spacing about 4 cm), 20,000 surface points with
    Gaussian noise sigma up to 0.6 % of its diagonal: the estimated surface noise is
    sigma within 6 % (chi-corrected, so not biased low; the nearest neighbours of a cloud
    whose noise nears the point spacing lie closer to the plane, so it then reads low:
    0.89 sigma at 4 cm)."""
    rng = np.random.default_rng(int(sigma * 1000))
    points = box_surface((4.0, 2.0, 1.5), 20000, seed=13) + rng.normal(scale=sigma, size=(20000, 3))
    estimate = surface_estimate(points - points.mean(axis=0)).noise
    assert estimate == pytest.approx(sigma, rel=0.06)


# ---- issue 18's targets, a seeded loop over random poses -------------------------------

def signed_up_degrees(found, rotation) -> float:
    """Angle between the found and the true up, the sign counted (upside down: 180)."""
    return float(np.degrees(np.arccos(np.clip(found.transform[2, :3] @ rotation[:, 2], -1, 1))))


TARGET_OBJECTS = (*MINORITY_CLASSES, *(f"chrono_vehicles/data/vehicle/{m}" for m in CHRONO if "tire" not in m))
# Clouds whose axes the refinement does not bring within 0.5 degrees of the mesh frame at
# 0.5 % noise: the SUV's underbody pitches 0.7 degrees against its level top, and the
# sharpened frame lands between them (docs/benchmarks.md); strict, so a fix shows.
CLOUD_SHORT = {"chrono_vehicles/data/vehicle/Nissan_Patrol/suv_chassis.obj"}


@pytest.mark.parametrize("name", TARGET_OBJECTS)
def test_targets_on_meshes_in_random_poses(shared_data, name):
    """The mesh itself (vertices and faces), three random poses 2 km away: with a prior
    up to 10 degrees off the axes within 0.5 degrees and the box within 1 %; without a
    prior up within 1 degree, its sign counted."""
    mesh = sample_vehicle(name).trimesh() if name in MINORITY_CLASSES else trimesh.load(shared_data / name, force="mesh")
    for seed in range(3):
        rng = np.random.default_rng([seed, 18])
        rotation = random_rotation(rng)
        vertices = mesh.vertices @ rotation.T + rng.normal(scale=2000.0, size=3)
        prior = align_axes(vertices, up=tilted(rotation[:, 2], rng.uniform(0, 10), rng), faces=mesh.faces, refine=True)
        assert error_degrees(prior.transform[:3, :3], rotation.T) < 0.5
        assert np.abs(np.sort(prior.dims[:2]) / np.sort(mesh.extents[:2]) - 1).max() < 0.01
        assert abs(prior.dims[2] / mesh.extents[2] - 1) < 0.01
        free = align_axes(vertices, faces=mesh.faces, refine=True)
        assert signed_up_degrees(free, rotation) < 1.0


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.xfail(strict=True, reason="issue 18: not reached"))
                                  if n in CLOUD_SHORT else n for n in TARGET_OBJECTS])
def test_axes_with_a_tilted_prior_on_noisy_clouds(shared_data, name):
    """20,000 surface points, 0.5 % noise (x box diagonal), 10 % floaters, three random
    poses, a prior up to 10 degrees off: the axes within 0.5 degrees."""
    for seed in range(3):
        source, rotation, _, rng = posed_cloud(name, 1800 + seed, 0.005, 0.1)
        prior = align_axes(source, up=tilted(rotation[:, 2], rng.uniform(0, 10), rng), refine=True)
        assert error_degrees(prior.transform[:3, :3], rotation.T) < 0.5


@pytest.mark.parametrize("name", TARGET_OBJECTS)
def test_up_without_a_prior_on_noisy_clouds(shared_data, name):
    """The same clouds and poses, no prior: up within 1 degree, its sign counted."""
    for seed in range(3):
        source, rotation, _, _ = posed_cloud(name, 1800 + seed, 0.005, 0.1)
        assert signed_up_degrees(align_axes(source, refine=True), rotation) < 1.0


def test_a_plain_box_stands_on_its_source_up_whatever_the_noise():
    """A box is mirror-symmetric across both of its shorter axes: up is the one nearer the
    source +z, not the one the sampling noise favours (6 of 10 boxes lay on their side)."""
    dims = np.array([4.5, 1.8, 1.5])
    for seed in range(10):
        noise = np.random.default_rng(seed).normal(scale=0.005, size=(20000, 3))
        points = (box_surface(dims, 20000, seed) + noise) @ rotate_z(40).T
        found = align_axes(points, refine=True)
        assert abs(found.transform[2, 2]) > np.cos(np.radians(1.0)), seed
        np.testing.assert_allclose(found.dims, dims, rtol=0.01)


@pytest.mark.parametrize("faces, problem", [
    (np.array([[0, 1, 2], [1, 2, 3]]), "every face has zero area: no surface to align"),  # a mesh collapsed to a line
    (np.array([[0.0, 1.0, 2.0]]), r"faces must be \(F, 3\) integer indices into 4 vertices"),
])
def test_a_mesh_without_surface_is_named(faces, problem):
    line = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
    with pytest.raises(InputError, match=f"^mesh.obj: {problem}"):
        align_axes(line, refine=True, faces=faces, source="mesh.obj")
