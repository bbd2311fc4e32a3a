"""Built-in parametric vehicles and synthetic reconstructions (no bpy)."""

import json

import numpy as np
import pytest
import trimesh

from pgt_blender.core.classes import MINORITY_CLASSES, NUSCENES_SIZES
from pgt_blender.core.importing import load_reconstruction
from pgt_blender.core.samples import _inside_part, sample_vehicle, synthetic_reconstruction, write_sample


def surface_distance(mesh, points):
    """Exact unsigned distance from each point to the mesh surface (all point-triangle pairs)."""
    triangles = np.repeat(mesh.triangles[None], len(points), axis=0).reshape(-1, 3, 3)
    pairs = np.repeat(points, len(mesh.faces), axis=0)
    closest = trimesh.triangles.closest_point(triangles, pairs)
    return np.linalg.norm(closest - pairs, axis=1).reshape(len(points), -1).min(axis=1)


@pytest.mark.parametrize("class_name", MINORITY_CLASSES)
def test_vehicle_is_closed_and_class_sized(class_name):
    vehicle = sample_vehicle(class_name)
    mesh = vehicle.trimesh()
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    np.testing.assert_allclose(mesh.bounds, [-vehicle.dims / 2, vehicle.dims / 2], atol=1e-9)
    np.testing.assert_allclose(vehicle.dims, NUSCENES_SIZES[class_name][0])
    wheels = [p for p in vehicle.parts if p.kind == "wheel"]
    assert len(wheels) >= 2 and all(p.center[2] == pytest.approx(p.size[0] / 2) for p in wheels)  # on the ground


@pytest.mark.parametrize("class_name", MINORITY_CLASSES)
def test_front_differs_from_back(class_name):
    """A recognisable front: turned by 180 degrees, over 5 % of the surface lies more than
    5 cm (a LiDAR's resolving power at 10 m) away from the untouched surface."""
    mesh = sample_vehicle(class_name).trimesh()
    points, _ = trimesh.sample.sample_surface(mesh, 600, seed=0)
    distance = surface_distance(mesh, points * [-1, -1, 1])
    assert np.mean(distance > 0.05) > 0.05


@pytest.mark.parametrize("class_name", MINORITY_CLASSES)
def test_every_surface_point_gets_its_part_color(class_name):
    vehicle = sample_vehicle(class_name)
    points, _ = trimesh.sample.sample_surface(vehicle.trimesh(), 3000, seed=1)
    local = (points - vehicle.offset) / vehicle.scale
    assert np.any([_inside_part(local, part, 1e-3) for part in vehicle.parts], axis=0).all()


def test_synthetic_reconstruction_ground_truth():
    sample = synthetic_reconstruction("truck", seed=7, points=1000, noise=0.0, outlier_share=0.1)
    similarity = sample.source_from_object
    scale = np.cbrt(np.linalg.det(similarity[:3, :3]))
    np.testing.assert_allclose(similarity[:3, :3] @ similarity[:3, :3].T, scale**2 * np.eye(3), atol=1e-9)
    in_object = (sample.positions - similarity[:3, 3]) @ np.linalg.inv(similarity[:3, :3]).T
    inliers = in_object[~sample.is_outlier]
    distance = surface_distance(sample.vehicle.trimesh(), inliers)
    # float32 storage of source coordinates is the only error
    assert distance.max() < 1e-5 * np.abs(similarity[:3, 3]).max() / scale + 1e-5
    assert 0.07 < sample.is_outlier.mean() < 0.13


def test_same_seed_same_bytes(tmp_path):
    first = write_sample(tmp_path / "a", "motorcycle", seed=3, points=2000)
    second = write_sample(tmp_path / "b", "motorcycle", seed=3, points=2000)
    third = write_sample(tmp_path / "c", "motorcycle", seed=4, points=2000)
    for role in first:
        assert first[role].read_bytes() == second[role].read_bytes()
    assert first["reconstruction.ply"].read_bytes() != third["reconstruction.ply"].read_bytes()


def test_written_sample_imports(tmp_path):
    paths = write_sample(tmp_path, "bicycle", seed=0, points=1500)
    recon = load_reconstruction(paths["reconstruction.ply"])
    assert recon.kind == "point_ply" and len(recon.positions) == 1500 and recon.colors is not None
    mesh = load_reconstruction(paths["mesh.ply"])
    assert mesh.kind == "mesh"
    truth = json.loads(paths["truth.json"].read_text())
    assert truth["class"] == "bicycle" and truth["dims"] == list(NUSCENES_SIZES["bicycle"][0])
    assert np.asarray(truth["source_from_object"]).shape == (4, 4)
