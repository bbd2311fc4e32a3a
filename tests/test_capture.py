"""From a capture to a clean colored object (core, no bpy): the 3DGS, splatfacto and
Plenoxels readers, view-agnostic color (Algorithm 1) against analytic averages, and
foreground extraction on synthetic scenes with a known foreground and on the real statue."""

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from pgt_blender.core.capture import CaptureOptions, samples
from pgt_blender.core.capture.visibility import VisibilitySettings, element_spacing, view_hits
from pgt_blender.core.errors import InputError
from pgt_blender.core.importing import detect_kind, load_reconstruction
from pgt_blender.core.importing.cameras import write_cameras_json
from pgt_blender.core.importing.ply import write_ply
from pgt_blender.core.importing.sh import SH_C0, SH_C1, SH_C2, SH_C3, coefficients_from_attributes, sh_basis

VIEW_COLOR = CaptureOptions(view_color=True)


def splat_run(folder, positions, coefficients, cameras, opacity=0.9, extra=None):
    """A 3DGS output folder of splats at ``positions`` with ``coefficients`` (N, 3, K)."""
    columns = samples.splat_columns(positions, coefficients, np.full(len(positions), opacity),
                                    np.full((len(positions), 3), 0.005))
    columns.update(extra or {})
    samples.write_3dgs_run(folder, columns, cameras)
    return folder


def small_coefficients(rng, size, count):
    """SH fields whose per-view colors stay inside (0, 1), so no clipping bends the mean."""
    coefficients = rng.uniform(-0.03, 0.03, (size, 3, count)).astype(np.float32)
    coefficients[:, :, 0] = rng.uniform(-0.3, 0.3, (size, 3))
    return coefficients


# --- spherical harmonics ----------------------------------------------------------------------

def test_sh_basis_is_the_real_harmonics_with_the_condon_shortley_phase():
    """3DGS's basis k = l^2 + l + m is sqrt(2) Re Y_l^m (m > 0), sqrt(2) Im Y_l^|m| (m < 0),
    Y_l^0 (m = 0) of scipy's complex harmonics, an implementation independent of ours."""
    from scipy.special import sph_harm_y

    directions = samples.fibonacci_sphere(50)
    polar, azimuth = np.arccos(directions[:, 2]), np.arctan2(directions[:, 1], directions[:, 0])
    expected = np.empty((50, 16))
    for degree in range(4):
        for order in range(-degree, degree + 1):
            value = sph_harm_y(degree, abs(order), polar, azimuth)
            expected[:, degree * degree + degree + order] = (
                value.real if order == 0 else np.sqrt(2) * (value.real if order > 0 else value.imag))
    np.testing.assert_allclose(sh_basis(directions, 16), expected, atol=2e-6)


# --- view-agnostic color: analytic averages ----------------------------------------------------

def ring_cameras(axis: int, elevation_deg: float, count: int = 8, distance: float = 10.0) -> list:
    """``count`` cameras evenly around coordinate ``axis`` at ``elevation_deg`` from the
    plane across it, looking at the origin."""
    others = [i for i in range(3) if i != axis]
    elevation, azimuth = np.radians(elevation_deg), 2 * np.pi * (np.arange(count) + 0.25) / count
    centres = np.zeros((count, 3))
    centres[:, axis] = distance * np.sin(elevation)
    centres[:, others[0]] = distance * np.cos(elevation) * np.cos(azimuth)
    centres[:, others[1]] = distance * np.cos(elevation) * np.sin(azimuth)
    return [samples.look_at(centre, (0, 0, 0), f"view_{i}") for i, centre in enumerate(centres)]


def ring_average(coefficients, axis: int, elevation_deg: float) -> np.ndarray:
    """The mean SH color over a ring of views around ``axis`` (directions camera -> origin:
    component a = -sin(elevation) along the axis, the rest on a circle of radius rho):
    only the terms invariant about the axis survive, with the circle's means of the
    squares rho^2 / 2 (the basis table in importing/sh.py)."""
    a, rho2 = -np.sin(np.radians(elevation_deg)), np.cos(np.radians(elevation_deg)) ** 2
    k = coefficients
    mean = SH_C0 * k[..., 0]
    if axis == 2:  # z ring: x, y on the circle
        mean += SH_C1 * a * k[..., 2] + SH_C2[2] * (2 * a * a - rho2) * k[..., 6] \
            + SH_C3[3] * a * (2 * a * a - 3 * rho2) * k[..., 12]
    elif axis == 0:  # x ring: y, z on the circle
        mean += -SH_C1 * a * k[..., 3] + SH_C2[2] * (rho2 / 2 - a * a) * k[..., 6] \
            + SH_C2[4] * (a * a - rho2 / 2) * k[..., 8] + SH_C3[4] * a * (1.5 * rho2 - a * a) * k[..., 13] \
            + SH_C3[6] * a * (a * a - 1.5 * rho2) * k[..., 15]
    else:  # y ring: x, z on the circle
        mean += -SH_C1 * a * k[..., 1] + SH_C2[2] * (rho2 / 2 - a * a) * k[..., 6] \
            + SH_C2[4] * (rho2 / 2 - a * a) * k[..., 8] + SH_C3[0] * a * (1.5 * rho2 - a * a) * k[..., 9] \
            + SH_C3[2] * a * (1.5 * rho2 - a * a) * k[..., 11]
    return mean + 0.5


TINY_CLUSTER = 1e-3 * np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_view_color_over_a_ring_of_views_is_the_analytic_mean(tmp_path, axis):
    """Four splats at the origin (degree 3), eight views around a coordinate axis at 35
    degrees: the mean color is the ring integral of the SH field, which checks the basis
    constants, their signs and the camera -> element direction."""
    rng = np.random.default_rng(axis)
    coefficients = small_coefficients(rng, 4, 16)
    run = splat_run(tmp_path / "run", TINY_CLUSTER, coefficients, ring_cameras(axis, 35.0))
    recon = load_reconstruction(run, capture=VIEW_COLOR)
    assert recon.attributes["view_hit"].all() and (recon.attributes["view_count"] == 8).all()
    np.testing.assert_allclose(recon.colors[:, :3], ring_average(coefficients, axis, 35.0), atol=2e-4)
    dc = np.clip(0.5 + SH_C0 * coefficients[:, :, 0], 0, 1)
    assert np.abs(recon.colors[:, :3] - dc).max() > 0.01  # the view terms do move the color


def test_view_color_refuses_to_replace_a_files_own_view_hit(tmp_path):
    run = splat_run(tmp_path / "run", TINY_CLUSTER, small_coefficients(np.random.default_rng(0), 4, 16),
                    ring_cameras(2, 35.0), extra={"view_hit": np.ones(len(TINY_CLUSTER), np.float32)})
    assert "view_hit" in load_reconstruction(run).attributes  # kept as the file has it ...
    with pytest.raises(InputError, match="has its own 'view_hit' property, which the view color makes; rename it"):
        load_reconstruction(run, capture=VIEW_COLOR)  # ... and not overwritten


def test_view_color_over_a_spherical_design_is_the_dc_color(tmp_path):
    """Views from the 12 vertices of an icosahedron (a spherical 5-design) average every
    SH term of degree 1-3 to zero: the mean is the DC color, though each view's is not."""
    golden = (1 + 5 ** 0.5) / 2
    vertices = np.array([(0, s1, s2 * golden) for s1 in (-1, 1) for s2 in (-1, 1)], float)
    vertices = np.concatenate([np.roll(vertices, shift, axis=1) for shift in range(3)])
    cameras = [samples.look_at(10 * v / np.linalg.norm(v), (0, 0, 0), f"v{i}") for i, v in enumerate(vertices)]
    coefficients = small_coefficients(np.random.default_rng(7), 4, 16)
    run = splat_run(tmp_path / "run", TINY_CLUSTER, coefficients, cameras)
    recon = load_reconstruction(run, capture=VIEW_COLOR)
    assert (recon.attributes["view_count"] == 12).all()
    np.testing.assert_allclose(recon.colors[:, :3], 0.5 + SH_C0 * coefficients[:, :, 0], atol=2e-4)
    directions = -vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    per_view = np.einsum("vk,ck->vc", sh_basis(directions, 16), coefficients[0]) + 0.5
    assert np.ptp(per_view, axis=0).max() > 0.05


def test_plenoxels_view_color_over_a_ring(tmp_path):
    """A Plenoxels grid (degree 2, svox2's default 9 coefficients, stored as float16) with
    a cameras.json beside it gets the same analytic ring mean."""
    rng = np.random.default_rng(3)
    links = np.arange(8, dtype=np.int32).reshape(2, 2, 2)
    sh = small_coefficients(rng, 8, 9).reshape(8, 27)
    samples.write_svox2(tmp_path / "grid.npz", links, np.full(8, 50.0), sh, radius=[1e-3] * 3, center=[0, 0, 0])
    write_cameras_json(tmp_path / "cameras.json", ring_cameras(2, 50.0))
    recon = load_reconstruction(tmp_path / "grid.npz", capture=VIEW_COLOR)
    assert recon.kind == "plenoxels" and recon.capture["view_color"]["sh_degree"] == 2
    stored = coefficients_from_attributes(recon.attributes)  # float16-rounded, as svox2 saved them
    padded = np.concatenate([stored, np.zeros((8, 3, 7), np.float32)], axis=2)
    np.testing.assert_allclose(recon.colors[:, :3], ring_average(padded, 2, 50.0), atol=2e-4)


def test_hidden_elements_keep_their_dc_color_and_are_flagged(tmp_path):
    """A shell of 20,000 splats around 50 splats inside it, 24 orbit views: the inside is
    never hit (DC color, view_hit False); on the shell the hits face the camera (the
    z-buffer sees surfaces, not everything in the frustum)."""
    rng = np.random.default_rng(0)
    shell = samples.fibonacci_sphere(20000)
    inside = 0.3 * samples.fibonacci_sphere(50)
    positions = np.concatenate([shell, inside]).astype(np.float32)
    coefficients = small_coefficients(rng, len(positions), 16)
    cameras = samples.orbit_cameras(24, 4.0, 20.0)
    recon = load_reconstruction(splat_run(tmp_path / "run", positions, coefficients, cameras), capture=VIEW_COLOR)
    hit = recon.attributes["view_hit"]
    assert not hit[20000:].any()
    np.testing.assert_array_equal(recon.colors[20000:, :3], np.clip(0.5 + SH_C0 * coefficients[20000:, :, 0], 0, 1))
    best_cosine = np.full(20000, -1.0)  # over the views, of the angle between normal and view
    for view in cameras:
        towards = view.centre - shell
        best_cosine = np.maximum(best_cosine, np.einsum("ij,ij->i", shell, towards) / np.linalg.norm(towards, axis=1))
    assert hit[:20000].sum() >= 0.97 * (best_cosine > 0).sum() and not hit[:20000][best_cosine < -0.1].any()
    report = recon.capture["view_color"]
    assert report["hit"] == hit.sum() and report["never_hit"] == (~hit).sum() and report["sh_degree"] == 3


@pytest.mark.parametrize("placement", ["even", "random"])
@pytest.mark.parametrize("count", [5000, 100_000])
def test_view_hits_see_the_front_surface(placement, count):
    """Per view on a unit sphere: no hit lies more than 2 depth tolerances behind the
    sphere's first surface along its ray (a leak through a gap in the z-buffer would lie
    a chord behind: 5 to 30 tolerances here); most hits face the camera, most facing
    elements are hit."""
    rng = np.random.default_rng(1)
    points = samples.fibonacci_sphere(count) if placement == "even" else rng.normal(size=(count, 3))
    points = (points / np.linalg.norm(points, axis=1, keepdims=True)).astype(np.float32)
    cameras = samples.orbit_cameras(24, 4.0, 20.0)
    settings = VisibilitySettings()
    counts = np.zeros(3)
    for hits in view_hits(points, cameras, element_spacing(points, rng), settings=settings):
        view = cameras[hits.view]
        seen = points[hits.framed].astype(np.float64)
        towards = view.centre - seen
        distance = np.linalg.norm(towards, axis=1)
        along = -(towards / distance[:, None]) @ view.centre
        first = -along - np.sqrt(np.maximum(along ** 2 - (view.centre @ view.centre - 1), 0))  # ray enters the sphere
        tolerance = settings.depth_tolerance * hits.cell_px * (seen - view.centre) @ view.world_from_camera[:3, 2] / view.fx
        assert ((distance - first)[hits.hit] <= 2 * tolerance[hits.hit]).all()
        facing = np.einsum("ij,ij->i", seen, towards) > 0
        counts += [(hits.hit & facing).sum(), hits.hit.sum(), facing.sum()]
    assert counts[0] / counts[1] >= 0.9 and counts[0] / counts[2] >= 0.85


def test_translucent_elements_do_not_hide_what_is_behind():
    """A patch in front of another, seen head-on: the back patch is hit only while the
    front one is less opaque than the occluder threshold (0.5)."""
    grid = np.stack(np.meshgrid(np.linspace(-0.2, 0.2, 41), np.linspace(-0.2, 0.2, 41)), -1).reshape(-1, 2)
    front = np.column_stack([grid, np.full(len(grid), 0.5)])
    back = np.column_stack([grid, np.zeros(len(grid))])
    points = np.concatenate([front, back]).astype(np.float32)
    camera = [samples.look_at((0, 0, 3), (0, 0, 0), "top")]
    for front_opacity, back_hit in ((0.1, True), (0.9, False)):
        opacity = np.concatenate([np.full(len(grid), front_opacity), np.full(len(grid), 0.9)])
        hits = next(view_hits(points, camera, 0.01, opacity))
        hit = np.zeros(len(points), bool)
        hit[hits.framed[hits.hit]] = True
        assert hit[:len(grid)].all() and (hit[len(grid):].mean() > 0.99 if back_hit else not hit[len(grid):].any())


# --- readers ----------------------------------------------------------------------------------------

def test_3dgs_run_reads_the_last_iteration_and_its_cameras(tmp_path):
    rng = np.random.default_rng(2)
    positions = rng.normal(size=(300, 3)).astype(np.float32)
    cameras = samples.orbit_cameras(5, 4.0, 10.0)
    run = splat_run(tmp_path / "truck_run", positions, small_coefficients(rng, 300, 16), cameras)
    assert detect_kind(run) == "gaussian_splat"
    for source in (run, run / "point_cloud" / "iteration_30000" / "point_cloud.ply"):
        recon = load_reconstruction(source)
        assert recon.name == "truck_run" and len(recon.positions) == 300  # iteration_7000 holds 150
        assert [view.name for view in recon.cameras] == [f"view_{i:03d}" for i in range(5)]
        for read, written in zip(recon.cameras, cameras):
            np.testing.assert_allclose(read.world_from_camera, written.world_from_camera, atol=1e-12)
            assert (read.fx, read.cx, read.cy, read.model) == (written.fx, written.cx, written.cy, "PINHOLE")
    assert load_reconstruction(run, with_cameras=False).cameras == []


@pytest.mark.parametrize("spoil, problem", [
    (lambda path: path.symlink_to(path.with_name("gone.ply")), "a link that leads nowhere"),
    (os.mkfifo, "not a regular file"),
    (Path.mkdir, "is a folder; expected a file"),
])
@pytest.mark.parametrize("spoilt", ["point_cloud/iteration_30000/point_cloud.ply", "cameras.json"])
def test_3dgs_run_with_its_newest_splats_or_cameras_spoilt_names_them(tmp_path, spoilt, spoil, problem):
    """Not an older iteration, nor a run without cameras, in silence."""
    run = splat_run(tmp_path / "run", np.zeros((10, 3), np.float32) + np.arange(10)[:, None],
                    small_coefficients(np.random.default_rng(0), 10, 1), samples.orbit_cameras(2, 4.0, 0.0))
    (run / spoilt).unlink()
    spoil(run / spoilt)
    with pytest.raises(InputError, match=problem) as error:
        load_reconstruction(run)
    assert error.value.path == run / spoilt


def test_3dgs_run_without_cameras_json_takes_the_colmap_model_it_trained_on(tmp_path, statue):
    run = splat_run(tmp_path / "run", np.zeros((10, 3), np.float32) + np.arange(10)[:, None],
                    small_coefficients(np.random.default_rng(0), 10, 1), samples.orbit_cameras(2, 4.0, 0.0))
    (run / "cameras.json").unlink()
    assert load_reconstruction(run).cameras == []
    shutil.copytree(statue, tmp_path / "dataset" / "sparse" / "0")
    (run / "cfg_args").write_text(f"Namespace(source_path='{tmp_path / 'dataset'}', sh_degree=3)")
    cameras = load_reconstruction(run).cameras
    assert len(cameras) == 40 and cameras[0].model == "SIMPLE_RADIAL"


def test_splatfacto_exports(tmp_path):
    """nerfstudio's gaussian-splat export: with SH it reads as the 3DGS file does (its
    zero normals dropped); with rgb colors it is a splat cloud without SH."""
    rng = np.random.default_rng(4)
    positions = rng.normal(size=(200, 3)).astype(np.float32)
    columns = samples.splat_columns(positions, small_coefficients(rng, 200, 16), rng.uniform(0.1, 0.9, 200),
                                    rng.uniform(0.01, 0.1, (200, 3)))
    write_ply(tmp_path / "inria.ply", columns)
    write_ply(tmp_path / "splat.ply", samples.splatfacto_columns(columns))
    write_ply(tmp_path / "rgb.ply", samples.splatfacto_columns(columns, rgb=True))
    inria, splat, rgb = (load_reconstruction(tmp_path / f"{name}.ply") for name in ("inria", "splat", "rgb"))
    assert splat.kind == rgb.kind == "gaussian_splat"
    assert set(splat.attributes) == set(inria.attributes) and "nx" not in splat.attributes
    for name in ("opacity", "scale", "rotation", "f_rest_44"):
        np.testing.assert_array_equal(splat.attributes[name], inria.attributes[name])
    np.testing.assert_array_equal(splat.colors, inria.colors)
    np.testing.assert_allclose(rgb.colors, inria.colors, atol=1 / 255)
    assert not any(name.startswith("f_") for name in rgb.attributes)
    write_cameras_json(tmp_path / "cameras.json", samples.orbit_cameras(6, 6.0, 20.0))
    colored = load_reconstruction(tmp_path / "rgb.ply", capture=VIEW_COLOR)
    assert colored.capture["view_color"]["sh_degree"] is None and colored.attributes["view_hit"].any()
    np.testing.assert_array_equal(colored.colors, rgb.colors)  # nothing view-dependent to average


def test_plenoxels_cells_density_and_coefficients(tmp_path):
    """Cell centres at center + radius (2 (index + 0.5) / resolution - 1) (svox2's
    grid2world), cells of zero density dropped, opacity over one cell side, SH as 3DGS
    names them; the legacy single ``data`` array reads the same."""
    rng = np.random.default_rng(5)
    resolution, radius, center = (6, 5, 4), np.array([1.0, 0.8, 0.6]), np.array([0.2, -0.1, 0.3])
    occupied = rng.random(resolution) < 0.4
    links = np.full(resolution, -1, np.int32)
    links[occupied] = rng.permutation(occupied.sum())
    rows = int(occupied.sum())
    density = rng.uniform(-1, 30, rows)
    sh = rng.normal(0, 0.3, (rows, 48))
    samples.write_svox2(tmp_path / "grid.npz", links, density, sh, radius, center)
    recon = load_reconstruction(tmp_path / "grid.npz")
    index = np.argwhere(occupied)
    row = links[occupied]
    filled = density[row] > 0
    expected = center + radius * (2 * (index + 0.5) / np.array(resolution) - 1)
    np.testing.assert_allclose(recon.positions, expected[filled], atol=1e-6)
    np.testing.assert_allclose(recon.attributes["density"], density[row][filled], rtol=1e-6)
    side = np.mean(2 * radius / np.array(resolution))
    np.testing.assert_allclose(recon.attributes["opacity"], 1 - np.exp(-density[row][filled] * side), rtol=1e-5)
    stored = sh.astype(np.float16).astype(np.float32)[row][filled].reshape(-1, 3, 16)
    np.testing.assert_array_equal(coefficients_from_attributes(recon.attributes), stored)
    np.testing.assert_allclose(recon.colors[:, :3], np.clip(0.5 + SH_C0 * stored[:, :, 0], 0, 1), atol=1e-6)
    np.savez(tmp_path / "legacy.npz", links=links, radius=radius, center=center,
             data=np.column_stack([density, sh.astype(np.float16).astype(np.float32)]))
    np.testing.assert_allclose(load_reconstruction(tmp_path / "legacy.npz").positions, recon.positions, atol=1e-6)


# --- foreground ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def table_capture(tmp_path_factory):
    """A 3DGS run of the table scene (a ball on a table, clutter beside it), 16 orbit
    views, with the truth as a per-splat ``foreground`` property."""
    folder = tmp_path_factory.mktemp("table")
    scene = samples.table_scene(np.random.default_rng(11))
    cameras = samples.orbit_cameras(16, 4.0, 30.0, target=scene["ball_centre"])
    positions = scene["positions"]
    run = splat_run(folder / "run", positions, small_coefficients(np.random.default_rng(1), len(positions), 4),
                    cameras, extra={"foreground": scene["foreground"].astype(np.uint8)})
    return {"run": run, "cameras": cameras, **scene}


def write_masks(folder, cameras, masks, half_size=()):
    """Masks as PNG files named after the images (some at half size, some as .npy)."""
    from PIL import Image

    folder.mkdir(exist_ok=True)
    for index, (view, mask) in enumerate(zip(cameras, masks)):
        stem = view.name.removesuffix(".png")
        if index % 5 == 4:
            np.save(folder / f"{stem}.npy", mask.astype(np.uint8))
        else:
            image = Image.fromarray((mask * 255).astype(np.uint8))
            if index in half_size:
                image = image.resize((view.width // 2, view.height // 2), Image.NEAREST)
            image.save(folder / f"{stem}.png")
    return folder


def npy_claiming(shape: tuple, descr="|u1") -> bytes:
    """An .npy header declaring ``shape`` of ``descr`` and no data."""
    header = repr({"descr": descr, "fortran_order": False, "shape": shape}).encode()
    header += b" " * (63 - len(header) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header


@pytest.mark.parametrize("name, content, problem", [
    ("huge.npy", npy_claiming((300_000, 400_000)), "is 400000x300000 pixels but its image view.png is 320x240"),
    ("empty.npy", b"", "not a readable .npy header"),
    ("flat.npy", npy_claiming((0, 0)), "is 0x0 pixels"),
    ("table.npy", npy_claiming((240, 320), [("a", "<f4")]), "a .npy mask must be a 2-D array of numbers"),
    ("text.npy", npy_claiming((240, 320), "<U1"), "a .npy mask must be a 2-D array of numbers"),
    ("dot.png", "1x1", "is 1x1 pixels but its image view.png is 320x240"),
    ("cut.npy", npy_claiming((240, 320)), "not a readable mask (ValueError"),
])
def test_masks_that_are_not_the_image_s_are_named(tmp_path, name, content, problem):
    """Before numpy or Pillow allocate what a header declares (112 GiB for the first)."""
    from PIL import Image

    from pgt_blender.core.capture.masks import read_mask
    from pgt_blender.core.reconstruction import CameraView

    path = tmp_path / name
    if content == "1x1":
        Image.fromarray(np.full((1, 1), 255, np.uint8)).save(path)
    else:
        path.write_bytes(content)
    view = CameraView("view.png", 320, 240, 300.0, 300.0, 160.0, 120.0, np.eye(4))
    with pytest.raises(InputError) as error:
        read_mask(path, view)
    assert error.value.path == path and problem in error.value.problem


def precision_recall(recon, total_foreground):
    kept_truth = recon.attributes["foreground"].astype(bool)
    return kept_truth.mean(), kept_truth.sum() / total_foreground


def test_foreground_from_masks(table_capture, tmp_path):
    """Perfect ball masks (some at half size, some .npy): the ball stays, the table and
    the clutter go, also where the table shows inside the ball's silhouette."""
    masks = samples.ball_masks(table_capture["cameras"], table_capture["ball_centre"], 0.5)
    folder = write_masks(tmp_path / "masks", table_capture["cameras"], masks, half_size=(1, 6))
    recon = load_reconstruction(table_capture["run"], capture=CaptureOptions(foreground="masks", masks=folder))
    precision, recall = precision_recall(recon, table_capture["foreground"].sum())
    assert precision >= 0.99 and recall >= 0.98, (precision, recall)
    report = recon.capture["foreground"]
    assert report["kept"] == len(recon.positions) and report["elements"] == len(table_capture["positions"])
    assert report["judged_by_hits"] + report["judged_by_framing"] + report["never_framed"] == report["elements"]


def test_foreground_from_masks_with_view_color_in_one_pass(table_capture, tmp_path):
    masks = samples.ball_masks(table_capture["cameras"], table_capture["ball_centre"], 0.5)
    folder = write_masks(tmp_path / "masks", table_capture["cameras"], masks)
    options = CaptureOptions(view_color=True, foreground="masks", masks=folder)
    recon = load_reconstruction(table_capture["run"], capture=options)
    assert {"view_color", "foreground"} <= set(recon.capture)
    assert len(recon.attributes["view_hit"]) == len(recon.positions)


def test_foreground_without_masks_removes_the_table(table_capture):
    recon = load_reconstruction(table_capture["run"], capture=CaptureOptions(foreground="plane"))
    precision, recall = precision_recall(recon, table_capture["foreground"].sum())
    assert precision == 1.0 and recall >= 0.97, (precision, recall)
    report = recon.capture["foreground"]
    np.testing.assert_allclose(report["plane"]["normal"], [0, 0, 1], atol=1e-3)
    assert abs(report["plane"]["offset"]) < 0.25 * recon.capture["spacing"] and report["centre_from"] == "camera axes"
    np.testing.assert_allclose(report["centre"], table_capture["ball_centre"], atol=1e-6)


def test_foreground_without_masks_or_cameras(table_capture, tmp_path):
    """A plain point cloud of the scene: the centre is the median element (on the
    table under the ball), the plane the dominant one."""
    path = tmp_path / "scene.ply"
    positions = table_capture["positions"]
    write_ply(path, {"x": positions[:, 0], "y": positions[:, 1], "z": positions[:, 2],
                     "foreground": table_capture["foreground"].astype(np.uint8)})
    recon = load_reconstruction(path, capture=CaptureOptions(foreground="plane"))
    precision, recall = precision_recall(recon, table_capture["foreground"].sum())
    assert precision == 1.0 and recall >= 0.97 and recon.capture["foreground"]["centre_from"] == "median element"


def test_foreground_is_seeded(table_capture):
    runs = [load_reconstruction(table_capture["run"], capture=CaptureOptions(foreground="plane", seed=seed))
            for seed in (3, 3)]
    np.testing.assert_array_equal(runs[0].positions, runs[1].positions)
    assert json.dumps(runs[0].capture) == json.dumps(runs[1].capture)


def test_statue_foreground_without_masks(statue):
    """The real COLMAP statue (1,816 points of the Statue of Liberty and the top of its
    pedestal from 40 web photos): up comes out along the statue (the photos look up at
    it from the ground); its sparse points hold no flat support plane (the pedestal's
    are its walls), so nothing is cut; the statue with the pedestal top is one
    component, and the stray points around it go (docs/user_guide.md)."""
    full = load_reconstruction(statue)
    recon = load_reconstruction(statue, capture=CaptureOptions(foreground="plane"))
    report = recon.capture["foreground"]
    print(json.dumps(report))
    up = np.array(report["up"])
    axis = np.linalg.svd(full.positions - np.median(full.positions, axis=0), full_matrices=False)[2][0]
    assert report["centre_from"] == "camera axes" and abs(axis @ up) > np.cos(np.radians(15))
    assert report["plane"] is None and report["removed_with_plane"] == 0
    assert 0.95 * len(full.positions) < report["kept"] == len(recon.positions) < len(full.positions)
    assert (recon.positions @ up).max() >= np.percentile(full.positions @ up, 99)  # the torch stays


def test_capture_needs_cameras_and_points(donut, tmp_path):
    with pytest.raises(InputError, match=f"^{donut}: has no cameras: view color and mask foreground need"):
        load_reconstruction(donut, capture=VIEW_COLOR)
    from pgt_blender.core.samples import sample_vehicle

    sample_vehicle("bus").trimesh().export(tmp_path / "bus.obj")
    with pytest.raises(InputError, match="not on a mesh"):
        load_reconstruction(tmp_path / "bus.obj", capture=CaptureOptions(foreground="plane"))


def test_splatfacto_export_with_its_run_transform_sees_through_the_colmap_cameras(statue, tmp_path):
    """A splatfacto export lives in nerfstudio's frame, s (R x + t) of the COLMAP world
    (the run's dataparser_transforms.json); the COLMAP cameras given with it are moved
    the same way, so each camera sees every point at the pixel COLMAP saw it."""
    original = load_reconstruction(statue)
    rotation = samples.look_at((1, 2, 3), (0, 0, 0), "r").world_from_camera[:3, :3]
    translation, scale = np.array([0.3, -1.2, 2.0]), 0.37
    moved = (scale * (original.positions @ rotation.T + translation)).astype(np.float32)
    count = len(moved)
    columns = samples.splat_columns(moved, np.zeros((count, 3, 16), np.float32), np.full(count, 0.5),
                                    np.full((count, 3), 0.01))
    write_ply(tmp_path / "splat.ply", samples.splatfacto_columns(columns))
    (tmp_path / "dataparser_transforms.json").write_text(json.dumps(
        {"transform": np.column_stack([rotation, translation]).tolist(), "scale": scale}))
    recon = load_reconstruction(tmp_path / "splat.ply", cameras=statue)

    def pixels(view, points):
        transform = view.camera_from_world()
        local = points @ transform[:3, :3].T + transform[:3, 3]
        return view.project(local[local[:, 2] > 0])[0]

    for before, after in zip(original.cameras[::7], recon.cameras[::7]):
        np.testing.assert_allclose(pixels(after, recon.positions), pixels(before, original.positions), atol=2e-2)
    (tmp_path / "dataparser_transforms.json").write_text('{"transform": [[2, 0, 0, 0]], "scale": 1}')
    with pytest.raises(InputError, match="dataparser_transforms.json: not a nerfstudio dataparser transform"):
        load_reconstruction(tmp_path / "splat.ply", cameras=statue)
    overflowing = {"transform": np.eye(3, 4).tolist(), "scale": 1e300}  # finite in float64, not in Blender's float32
    (tmp_path / "dataparser_transforms.json").write_text(json.dumps(overflowing))
    with pytest.raises(InputError, match="dataparser_transforms.json: moves camera .* beyond the floating-point range"):
        load_reconstruction(tmp_path / "splat.ply", cameras=statue)
    vanishing = {"transform": np.eye(3, 4).tolist(), "scale": 1e-320}
    (tmp_path / "dataparser_transforms.json").write_text(json.dumps(vanishing))
    with pytest.raises(InputError, match="dataparser_transforms.json: moves every camera onto one point"):
        load_reconstruction(tmp_path / "splat.ply", cameras=statue)
