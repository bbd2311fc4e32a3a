"""The bank export: config, grid, the two frameworks' loading contracts for nuScenes and
KITTI, determinism over workers, executors and shards, resume after a kill, bad input."""

import ctypes
import json
import mmap
import os
import pickle
import re
import secrets
import shutil
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pgt_blender.core.authoring.prepare import prepare, write_prepared
from pgt_blender.core.bank import export, folder
from pgt_blender.core.bank.config import BankConfig, config_from_table, grid_values, load_config
from pgt_blender.core.boxes import inside_box
from pgt_blender.core.bank.formats import BOX_VALUES, DATABASE_CLASSES
from pgt_blender.core.bank.grid import footprint_distance, object_entries
from pgt_blender.core.bank.inputs import checked_objects, prepared_objects
from pgt_blender.core.bank.records import read_record
from pgt_blender.core.errors import InputError
from pgt_blender.core.importing import load_reconstruction
from pgt_blender.core.samples import write_sample
from pgt_blender.core.scan.sensors import PRESETS

from .conftest import CodeOnLoad, file_size_limit, run_script

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "headless_scripts" / "export_bank.py"
CHRONO_TRUCK = Path("data") / "vehicle" / "truck" / "truck_chassis.obj"
NOISE_MARGIN = 6 * PRESETS["nuscenes"].range_noise_sigma  # m: how far noise moves a kept return off its box
# A small grid: 5 headings x 3 x 3 positions (less the sensor's own) per object.
SMALL = {"grid": {"headings_deg": [-180, 180, 90], "x": [-20, 20, 20], "y": [-20, 20, 20]},
         "bank": {"chunk_size": 4}}


def write_config(path: Path, table: dict) -> Path:
    lines = []
    for section, entries in table.items():
        lines.append(f"[{section}]")
        lines += [f"{key} = {json.dumps(value)}" for key, value in entries.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def run_export(*args, check=True, **kwargs):
    """export_bank.py with ``args``; unless ``check`` is False it must succeed."""
    return run_script("export_bank.py", *args, check=check, **kwargs)


def bank_bytes(out: Path) -> dict:
    """Every file of a bank but the work records' folder, by relative path."""
    return {str(path.relative_to(out)): path.read_bytes() for path in sorted(out.rglob("*"))
            if path.is_file() and ".work" not in path.parts and not path.name.startswith("report")}


@pytest.fixture(scope="module")
def prepared(tmp_path_factory, shared_data) -> Path:
    """Prepared objects: the built-in sample truck and bicycle (points, so surfels) and
    the Chrono truck mesh (11k triangles), each authored to a nuScenes class size."""
    folder = tmp_path_factory.mktemp("prepared")
    samples = tmp_path_factory.mktemp("samples")
    for class_name, seed in (("truck", 1), ("bicycle", 2)):
        source = write_sample(samples, class_name, seed=seed, points=3000)["reconstruction.ply"]
        write_prepared(prepare(load_reconstruction(source), class_name, up="pca", heading_method="baseline",
                               seed=seed), class_name, "nuscenes", folder)
    chrono = load_reconstruction(shared_data / "chrono_vehicles" / CHRONO_TRUCK)
    write_prepared(prepare(chrono, "truck", up="+z", heading_method="none", size="keep"), "truck", "nuscenes",
                   folder)
    return folder


@pytest.fixture(scope="module")
def objects(prepared) -> list:
    found, incomplete = prepared_objects(prepared)
    return checked_objects(found, incomplete, False, prepared)


@pytest.mark.parametrize("damage, problem", [
    (lambda xyz: np.zeros_like(xyz), "truck_chassis: every face has zero area"),
    (lambda xyz: np.where(np.arange(len(xyz))[:, None] == 3, np.nan, xyz),
     "truck_chassis: 1 vertices are NaN or infinite"),
])
def test_geometry_no_scan_can_be_made_of_is_refused_up_front(objects, damage, problem):
    """What a chunk's ray target would refuse is named before the output folder is made,
    so a retry does not find a half-made bank."""
    mesh = next(obj for obj in objects if obj.geometry.kind == "mesh")
    broken = replace(mesh, geometry=replace(mesh.geometry, positions=damage(mesh.geometry.positions)))
    with pytest.raises(InputError, match=re.escape(f"scene.blend: {problem}")):
        checked_objects([broken], [], False, "scene.blend")


@pytest.mark.parametrize("field, value, problem", [
    ("scale", np.nan, "splat scale must be 3000 finite rows"),
    ("rotation", 0.0, "a splat has a zero-length rotation quaternion"),
])
def test_splat_fields_no_scan_can_use_are_refused_up_front(objects, field, value, problem):
    """Splat fields edited after import (a Blender attribute) are checked as the Gaussian
    target would, before the output folder is made."""
    cloud = next(obj for obj in objects if obj.name == "truck_reconstruction")
    count = len(cloud.geometry.positions)
    splats = {"scale": np.full((count, 3), 0.05, np.float32), "opacity": np.ones(count, np.float32),
              "rotation": np.tile(np.float32([1, 0, 0, 0]), (count, 1))}
    splats[field][7] = value
    broken = replace(cloud, geometry=replace(cloud.geometry, attributes={**cloud.geometry.attributes, **splats}))
    with pytest.raises(InputError, match=re.escape(f"scene.blend: truck_reconstruction: {problem}")):
        checked_objects([broken], [], False, "scene.blend")


@pytest.fixture(scope="module", params=["nuscenes", "kitti", "lyft"])
def bank(request, objects, tmp_path_factory):
    """(out folder, manifest) of a small bank of the three objects."""
    table = {**SMALL, "bank": {**SMALL["bank"], "dataset": request.param}}
    if request.param == "kitti":
        table["grid"] = {**table["grid"], "x": [0, 40, 20]}
        table["classes"] = {"bicycle": "Cyclist"}
    out = tmp_path_factory.mktemp(f"bank_{request.param}")
    return out, export.export_bank(objects, config_from_table(table), out, workers=2)


# --- config and grid -----------------------------------------------------------------


def test_default_config_is_the_papers_nuscenes_bank():
    config = BankConfig()
    assert len(grid_values(*config.headings_deg)) == 13
    assert len(grid_values(*config.x)) == len(grid_values(*config.y)) == 21
    assert (config.min_points, config.dataset, config.formats) == (16, "nuscenes", ("openpcdet", "mmdet3d"))
    assert BankConfig(dataset="kitti").x == (0.0, 70.0, 5.0) and BankConfig(dataset="kitti").y == (-40.0, 40.0, 5.0)
    assert BankConfig(dataset="lyft").x == (-80.0, 80.0, 5.0)
    # Lyft's released files carry a constant 100, so its banks do; the others the model's.
    assert BankConfig(dataset="lyft").constant_intensity == 100.0 and BankConfig().constant_intensity is None
    assert BankConfig(dataset="lyft", intensity="model").constant_intensity is None
    assert BankConfig(intensity=40).constant_intensity == 40.0


def test_the_sample_config_lists_every_key_at_its_default(tmp_path):
    """docs/bank.toml, the file a user copies, loads to the defaults and names every key;
    the grid's x and y are commented out, so that another dataset keeps its own, and
    uncommented they are nuScenes' defaults."""
    from pgt_blender.core.bank.config import _KEYS

    text = (ROOT / "docs" / "bank.toml").read_text()
    assert load_config(ROOT / "docs" / "bank.toml") == BankConfig()
    named = {f"{section}.{key}"
             for section, body in re.findall(r"^\[(\w+)\][^\n]*\n(.*?)(?=^\[|\Z)", text, re.M | re.S)
             for key in re.findall(r"^(?:# )?(\w+) = ", body, re.M) if section != "classes"}
    assert named == set(_KEYS)
    (tmp_path / "bank.toml").write_text(text.replace("# x = ", "x = ").replace("# y = ", "y = "))
    uncommented = load_config(tmp_path / "bank.toml")
    assert (uncommented.x, uncommented.y) == (BankConfig().x, BankConfig().y)


@pytest.mark.parametrize("text, named", [
    ("[grid]\nheadingz = [0, 1, 1]\n", "grid.headingz"),
    ("[bank]\nmin_points = 0\n", "bank.min_points"),
    ("[bank]\ndataset = \"kitti\"\nsweeps = 3\n", "bank.sweeps = 3: kitti files hold one sweep each"),
    ("[bank]\nformats = [\"openpcdet\", \"openpcdet\"]\n", "bank.formats = ['openpcdet', 'openpcdet']: expected "),
    ("[bank]\nseed = 99999999999999999999999\n", "bank.seed = 99999999999999999999999: expected an integer 0 .. "),
    ("[bank]\ndataset = \"waymo\"\n", "bank.dataset"),
    ("[grid]\nx = [0, 10]\n", "grid.x"),
    ("[jitter]\nsize = 0.9\n", "jitter.size"),
    ("[scan]\nrange_noise = 1\n", "scan.range_noise"),
    ("[sensors]\nx = 1\n", "unknown section [sensors]: a bank config has only the sections [bank], "),
    ("base = \"nuscenes\"\n[beams]\n", "unknown top-level key 'base'"),  # a sensor file given as the config
    ("[classes]\nbus = 3\n", "classes.bus"),
    ("[bank\n", "not a readable TOML"),
    ("[bank]\nintensity = \"bright\"\n", "bank.intensity"),
    ("[bank]\nintensity = 300\n", "above nuscenes's maximum 255"),
    ("[bank]\ndataset = \"lyft\"\nintensity_checkpoint = \"m.pt\"\n", "set bank.intensity = \"model\""),
    # values whose arrays or run would not fit a machine, numbers beyond a float
    ("[grid]\nx = [0, 1e9, 1e-9]\n", "grid.x"),
    ("[grid]\nx = [-1e4, 1e4, 0.1]\ny = [-1e4, 1e4, 0.1]\n", "the grid has 5.2e+11 headings x positions"),
    ("[grid]\nheadings_deg = [0, inf, 1]\n", "grid.headings_deg"),
    ("[bank]\nsweeps = 1000000\n", "bank.sweeps"),
    ("[jitter]\nsize_variants = 1000000000\n", "jitter.size_variants"),
    ("[jitter]\ncentre = 1" + "0" * 400 + "\n", "jitter.centre"),
    ("[bank]\nradius_scale = inf\n", "bank.radius_scale"),
    ("[bank]\nsensor = \"a\\u0000b.toml\"\n", "bank.sensor"),
    ("[classes]\ntruck = \"" + "T" * 300 + "\"\n", "classes.truck"),  # a file name too long for the disk
])
def test_a_bad_config_names_the_bad_key(tmp_path, text, named):
    path = tmp_path / "bank.toml"
    path.write_text(text)
    with pytest.raises(InputError, match="bank.toml") as error:
        load_config(path)
    assert named in str(error.value) and "\n" not in str(error.value)


def test_grid_entries_are_jittered_filtered_and_reproducible():
    dims = np.array([7.0, 2.5, 3.0])
    config = BankConfig(max_distance=30.0)
    entries = object_entries(config, 0, "truck", dims)
    assert np.array_equal(entries, object_entries(config, 0, "truck", dims))
    assert not np.array_equal(entries, object_entries(BankConfig(max_distance=30.0, seed=1), 0, "truck", dims))
    assert np.hypot(entries["x"], entries["y"]).max() <= 30.0
    nominal = np.round(entries["x"] / 5) * 5
    assert np.abs(entries["x"] - nominal).max() <= config.centre_jitter
    headings = np.degrees(np.unique(entries["heading"]))
    np.testing.assert_allclose(headings, np.arange(-180, 181, 30))
    assert 0 < entries["variant"].min() + 1 and entries["variant"].max() < config.size_variants
    assert (entries["speed"] == 0).mean() > 0.2 and entries["speed"].max() > 0  # still and moving trucks
    # The sensor stands on the ego vehicle: no box comes within the clearance.
    lengths = footprint_distance(entries["x"], entries["y"], entries["heading"], dims[0] * 0.95, dims[1] * 0.95)
    assert lengths.min() > config.ego_clearance
    assert footprint_distance(np.array([0.0]), np.array([0.0]), np.array([0.3]), 4.0, 2.0)[0] == 0.0




# --- the frameworks' loading contracts ----------------------------------------------


def load_like_openpcdet(root: Path, info: dict, columns: int) -> np.ndarray:
    """pcdet/datasets/augmentor/database_sampler.py: fromfile, reshape, the count check,
    then the points moved by the box centre."""
    points = np.fromfile(str(root / info["path"]), dtype=np.float32).reshape([-1, columns])
    assert points.shape[0] == info["num_points_in_gt"]
    points[:, :3] += info["box3d_lidar"][:3]
    return points


def load_like_mmdet3d(root: Path, info: dict, columns: int) -> tuple:
    """mmdet3d/datasets/transforms/dbsampler.py: fromfile, reshape to load_dim, translate by
    the (bottom-centre) box; the box back to a centre box for the inside test."""
    points = np.fromfile(os.path.join(root, info["path"]), dtype=np.float32).reshape(-1, columns)
    assert points.shape[0] == info["num_points_in_gt"]
    points[:, :3] += info["box3d_lidar"][:3]
    box = info["box3d_lidar"].astype(np.float64)
    box[2] += box[5] / 2
    return points, box


def test_every_entry_loads_through_both_frameworks(bank):
    out, manifest = bank
    dataset = manifest["config"]["dataset"]
    columns = 4 if dataset == "kitti" else 5
    sensor = PRESETS[dataset]
    loaded = {}
    for fmt in ("openpcdet", "mmdet3d"):
        root = out / fmt
        infos = pickle.loads((root / f"{dataset}_dbinfos_pgt.pkl").read_bytes())
        loaded[fmt] = infos
        for name, entries in infos.items():
            for info in entries:
                assert info["num_points_in_gt"] >= 16 and len(info["box3d_lidar"]) == BOX_VALUES[dataset]
                if fmt == "openpcdet":
                    points, box = load_like_openpcdet(root, info, columns), info["box3d_lidar"].astype(np.float64)
                else:
                    points, box = load_like_mmdet3d(root, info, columns)
                    assert info["group_id"] == info["image_idx"]
                assert isinstance(info["image_idx"], int) and info["image_idx"] >= 2**24  # never a real frame's
                # kept where the ray hit, then moved by range noise (sigma 2 cm): within 6 sigma
                assert inside_box(points[:, :3].astype(np.float64), box, NOISE_MARGIN).all()
                # standing on the ground model's ground: within 3 sigma of the road grade
                ground = np.hypot(*box[:2]) * np.tan(np.radians(3 * BankConfig().grade_deg)) + 0.01
                assert abs(box[2] - box[5] / 2 + sensor.mounting_height) < ground
                if dataset != "kitti":  # nuScenes and Lyft: 0..255 and 10 sweeps' time lags
                    assert np.array_equal(points[:, 3], np.round(points[:, 3])) and points[:, 3].max() <= 255
                    if dataset == "lyft":  # as the real Lyft files: a constant 100
                        assert (points[:, 3] == 100).all()
                    lags = points[:, 4] / (0.05 if dataset == "nuscenes" else 0.2)
                    np.testing.assert_allclose(lags, np.round(lags), atol=1e-4)
                    assert lags.max() <= 9 + 1e-4
                else:
                    assert 0 <= points[:, 3].min() and points[:, 3].max() <= 1
                    assert {"difficulty", "bbox", "score"} <= set(info) or fmt == "mmdet3d"
    assert set(loaded["openpcdet"]) == set(DATABASE_CLASSES[dataset])  # every class, empty or not
    assert {name for name, infos in loaded["openpcdet"].items() if infos} == set(manifest["counts"])
    for name, count in manifest["counts"].items():
        assert len(loaded["openpcdet"][name]) == len(loaded["mmdet3d"][name]) == count
    assert set(manifest["counts"]) == ({"Truck", "Cyclist"} if dataset == "kitti" else {"truck", "bicycle"})


def test_an_object_whose_faces_are_its_box_keeps_its_returns_under_range_noise(tmp_path):
    """Membership is decided where the ray hit, before range noise: a box-shaped object
    (every face on its box) keeps every return of an uncropped scan, noise or not, and
    its noisy points lie within the noise of the box."""
    import trimesh

    from pgt_blender.core.bank.entries import TargetCache, scan_entries
    from pgt_blender.core.bank.grid import ENTRY_DTYPE
    from pgt_blender.core.bank.inputs import BankObject
    from pgt_blender.core.reconstruction import Reconstruction
    from pgt_blender.core.scan.raycast import ScanOptions
    from pgt_blender.core.scan.sweeps import Motion, scan_sweeps

    dims = np.array([10.0, 2.5, 3.0])
    mesh = trimesh.creation.box(dims)
    geometry = Reconstruction(mesh.vertices.astype(np.float32), "mesh", tmp_path / "box.obj", "0" * 64,
                              faces=mesh.faces.astype(np.int32))
    config = config_from_table({"bank": {"sweeps": 1}, "jitter": {"size": 0.0, "centre": 0.0},
                                "scan": {"ray_drop": False}})
    cache = TargetCache([BankObject("box", "bus", dims, geometry)], config)
    for x, y, heading in ((15.0, 0.0, 0.0), (0.0, 15.0, 0.5), (-10.0, -12.0, 2.0)):
        entry = np.zeros(1, ENTRY_DTYPE)
        entry["x"], entry["y"], entry["heading"], entry["noise_seed"] = x, y, heading, 7
        scan, = scan_entries(cache, PRESETS["nuscenes"], entry, config)
        variant = cache.get(0, 0)
        uncropped = scan_sweeps(variant.target, PRESETS["nuscenes"], x, y, heading, Motion(), 1,
                                ScanOptions(range_noise=True, seed=7), variant.bounds, scale=variant.scale)
        assert scan.hits > 200 and scan.returns.dtype.names == ("x", "y", "z", "intensity", "time_lag")
        assert all(scan.returns[name].tobytes() == uncropped.returns[name].tobytes()
                   for name in scan.returns.dtype.names)
        assert inside_box(scan.xyz, scan.box, NOISE_MARGIN).all()
        assert not inside_box(scan.xyz, scan.box).all()  # the noise does reach out of the box


def test_a_prepared_splat_enters_the_bank_as_gaussians(shared_data, tmp_path):
    """A real 3DGS splat prepared as a car is scanned as Gaussians, its size variants
    with their splats stretched; its entries load as OpenPCDet loads them, inside their
    boxes."""
    from pgt_blender.core.bank.entries import TargetCache
    from pgt_blender.core.bank.grid import size_variants
    from pgt_blender.core.scan.gaussians import rotation_matrices

    folder = tmp_path / "prepared"
    splat = load_reconstruction(shared_data / "gaussian_splat_donut" / "fused.ply")
    write_prepared(prepare(splat, "car", up="pca", heading_method="baseline", seed=1), "car", "nuscenes", folder)
    found, incomplete = prepared_objects(folder)
    objects = checked_objects(found, incomplete, False, folder)
    config = config_from_table({"grid": {"headings_deg": [0, 90, 90], "x": [10, 20, 10], "y": [0, 0, 1]},
                                "bank": {"sweeps": 2}, "jitter": {"size_variants": 2}})
    cache = TargetCache(objects, config)
    attributes = objects[0].geometry.attributes
    shaped = rotation_matrices(attributes["rotation"]) * attributes["scale"][:, None, :].astype(np.float64)
    for variant, dims in enumerate(size_variants(config, 0, objects[0].dims)):
        target = cache.get(0, variant).target
        assert target.kind == "gaussians" and len(target.gaussians) == len(splat.positions)
        stretch = np.diag(dims / objects[0].dims)
        expected = stretch @ shaped @ shaped.transpose(0, 2, 1) @ stretch
        found = target.gaussians.axes * target.gaussians.scales[:, None, :]
        assert np.abs(found @ found.transpose(0, 2, 1) - expected).max() < 1e-6 * np.abs(expected).max()
    out = tmp_path / "bank"
    manifest = export.export_bank(objects, config, out, workers=1)
    infos = pickle.loads((out / "openpcdet" / "nuscenes_dbinfos_pgt.pkl").read_bytes())["car"]
    assert manifest["counts"] == {"car": len(infos)} and len(infos) >= 3
    for info in infos:
        points = load_like_openpcdet(out / "openpcdet", info, 5)
        assert info["num_points_in_gt"] >= 16
        assert inside_box(points[:, :3].astype(np.float64), info["box3d_lidar"].astype(np.float64), NOISE_MARGIN).all()


def test_a_chunk_of_mesh_and_splat_entries_is_the_bank_of_single_entry_chunks(objects, shared_data, tmp_path):
    """One chunk holding a mesh object's entries (its size variants cast in one call,
    each stretched) and a splat's (a target per variant) makes the bank that chunks of
    one entry each make, byte for byte."""
    folder = tmp_path / "prepared"
    splat = load_reconstruction(shared_data / "gaussian_splat_donut" / "fused.ply")
    write_prepared(prepare(splat, "car", up="pca", heading_method="baseline", seed=1), "car", "nuscenes", folder)
    found, incomplete = prepared_objects(folder)
    mixed = [next(obj for obj in objects if obj.geometry.kind == "mesh"), *checked_objects(found, incomplete, False,
                                                                                           folder)]
    table = {"grid": {"headings_deg": [0, 90, 90], "x": [10, 20, 10], "y": [0, 0, 1]}, "bank": {"sweeps": 2},
             "jitter": {"size_variants": 2}}
    banks = []
    for chunk_size in (64, 1):
        out = tmp_path / f"bank_{chunk_size}"
        manifest = export.export_bank(mixed, config_from_table({**table, "bank": {**table["bank"],
                                                                                 "chunk_size": chunk_size}}), out)
        assert set(manifest["counts"]) == {"car", "truck"}
        files = bank_bytes(out)
        del files["manifest.json"]  # its config records the chunk size; its checksums are compared below
        banks.append((files, manifest["files"], manifest["counts"]))
    assert banks[0] == banks[1]


def test_the_ground_model_places_and_tilts_objects_and_is_fitted_from_real_scans(shared_data):
    from pgt_blender.core.bank.ground import fit_ground, fit_kitti_frames, sample_ground
    from pgt_blender.core.scan.raycast import Ground, placement, placed_box

    sensor, bounds = PRESETS["kitti"], np.array([[-5.0, -1.25, -1.5], [5.0, 1.25, 1.5]])
    flat = placement(bounds, sensor, 20.0, 3.0, 0.4)
    assert np.array_equal(placement(bounds, sensor, 20.0, 3.0, 0.4, Ground()), flat)
    tilted = placement(bounds, sensor, 20.0, 3.0, 0.4, Ground(height=0.3, pitch=0.05, roll=-0.02))
    np.testing.assert_allclose(tilted[:3, :3] @ [0, 0, -1.5] + tilted[:3, 3], [20.0, 3.0, -1.73 + 0.3])
    np.testing.assert_allclose(tilted[2, :3] @ [1, 0, 0], np.sin(0.05))  # the nose is up by the pitch
    np.testing.assert_allclose(tilted[2, :3] @ [0, 1, 0], np.sin(-0.02) * np.cos(0.05))  # right side up
    assert placed_box(bounds, tilted)[6] == pytest.approx(0.4)  # the box keeps the heading, yaw only
    # The fit recovers a plane it is given (heights in the box frame's axes).
    rng = np.random.default_rng(0)
    around = rng.uniform(-8, 8, (4000, 2))
    centre, heading, dims = np.array([15.0, -4.0, -0.9]), 0.7, np.array([4.0, 2.0, 1.6])
    cos, sin = np.cos(heading), np.sin(heading)
    along, across = around @ [cos, sin], around @ [-sin, cos]
    z = -1.6 + np.tan(np.radians(2.0)) * along + np.tan(np.radians(-1.0)) * across
    fit = fit_ground(np.column_stack([around + centre[:2], z]), centre, dims, heading)
    assert fit["height"] == pytest.approx(-1.6) and fit["bottom_gap"] == pytest.approx(-0.9 - 0.8 + 1.6)
    assert fit["pitch"] == pytest.approx(2.0) and fit["roll"] == pytest.approx(-1.0)
    # Draws are seeded; the bank's defaults are this fit on the shared real KITTI frames.
    assert sample_ground(30, 0, 1, 1, np.random.default_rng(3)) == sample_ground(30, 0, 1, 1,
                                                                                np.random.default_rng(3))
    real = fit_kitti_frames(shared_data / "kitti_scans", sensor.mounting_height)
    assert real["used"] == 4 and (round(real["grade_deg"], 2), round(real["slope_deg"], 2)) == \
        (BankConfig().grade_deg, BankConfig().slope_deg)


def test_manifest_checksums_every_file(bank):
    import hashlib

    out, manifest = bank
    files = [path for path in out.rglob("*") if path.is_file() and ".work" not in path.parts
             and path.name != "manifest.json"]
    assert sorted(manifest["files"]) == sorted(str(path.relative_to(out)) for path in files)
    for relative, digest in list(manifest["files"].items())[:50]:
        assert hashlib.sha256((out / relative).read_bytes()).hexdigest() == digest
    assert manifest["entries"] == sum(manifest["counts"].values()) > 0
    assert {obj["name"] for obj in manifest["objects"]} == {"bicycle_reconstruction", "truck_chassis",
                                                           "truck_reconstruction"}


@pytest.mark.parametrize("change, problem", [
    (lambda m: m["config"].update(formats=[]), "bank.formats = []: expected a non-empty list"),
    (lambda m: m["config"].update(dataset="waymo"), "bank.dataset = 'waymo': expected one of"),
    (lambda m: m["config"].update(colour="red"), "config has unknown key 'colour'"),
    (lambda m: m.update(config=[]), "config must be an object, got list"),
    (lambda m: m["info_pickles"].pop("mmdet3d"), "info_pickles must name one pickle file per format"),
    (lambda m: m.update(data_root=7), "data_root must be a folder path or null"),
    (lambda m: m["info_pickles"].update(openpcdet="a\0b.pkl"), "info_pickles must name one pickle file per format"),
])
def test_a_manifest_is_read_with_the_checks_of_a_config_file(bank, tmp_path, change, problem):
    """What reads a finished bank (Preview Bank, place_objects, score_bank) indexes its
    config: a hand-edited one is named, not a KeyError."""
    from pgt_blender.core.bank.folder import read_manifest

    out, manifest = bank
    assert read_manifest(out) == manifest
    damaged = json.loads(json.dumps(manifest))
    change(damaged)
    (tmp_path / "manifest.json").write_text(json.dumps(damaged))
    with pytest.raises(InputError, match=re.escape(f"{tmp_path / 'manifest.json'}: {problem}")):
        read_manifest(tmp_path)


def test_openpcdet_and_mmdet3d_hold_the_same_points(bank):
    out, manifest = bank
    dataset = manifest["config"]["dataset"]
    columns = 4 if dataset == "kitti" else 5
    pcdet = pickle.loads((out / "openpcdet" / f"{dataset}_dbinfos_pgt.pkl").read_bytes())
    mmdet = pickle.loads((out / "mmdet3d" / f"{dataset}_dbinfos_pgt.pkl").read_bytes())
    for name in pcdet:
        for a, b in zip(pcdet[name][:20], mmdet[name][:20]):
            first = load_like_openpcdet(out / "openpcdet", a, columns)
            second, _ = load_like_mmdet3d(out / "mmdet3d", b, columns)
            np.testing.assert_allclose(first, second, atol=2e-5)


# --- determinism, executors, shards, resume -------------------------------------------


@pytest.fixture(scope="module")
def reference(objects, tmp_path_factory, prepared):
    """A nuScenes bank in one process, and its config file."""
    config_path = write_config(tmp_path_factory.mktemp("config") / "bank.toml", SMALL)
    out = tmp_path_factory.mktemp("reference") / "bank"
    export.export_bank(objects, load_config(config_path), out, workers=1)
    return out, config_path


def test_same_bank_whatever_the_workers(reference, prepared, tmp_path):
    out, config = reference
    run_export("--objects", prepared, "--config", config, "--out", tmp_path / "two", "--workers", "2")
    assert bank_bytes(tmp_path / "two") == bank_bytes(out)


def test_shards_assemble_to_the_same_bank(reference, prepared, tmp_path):
    out, config = reference
    for index in range(3):
        result = run_export("--objects", prepared, "--config", config, "--out", tmp_path / f"shard{index}",
                            "--shard", f"{index}/3", "--workers", "1")
        assert "--assemble" in result.stdout
    assert not (tmp_path / "shard0" / "manifest.json").exists()
    failed = run_export("--assemble", "--out", tmp_path / "shard0", check=False)
    assert failed.returncode == 1 and "not exported yet" in failed.stderr
    chunks = sorted((tmp_path / "shard0" / folder.WORK / "chunks").iterdir())
    with folder.exporting(tmp_path / "shard1", shared=True):  # that shard still exporting: said, nothing copied
        failed = run_export("--assemble", "--out", tmp_path / "shard0", "--from", tmp_path / "shard1",
                            tmp_path / "shard2", check=False)
    assert failed.returncode == 1 and last_line(failed) == f"error: {tmp_path / 'shard1'}: {folder.SHARD_BUSY}"
    assert sorted((tmp_path / "shard0" / folder.WORK / "chunks").iterdir()) == chunks
    run_export("--assemble", "--out", tmp_path / "shard0", "--from", tmp_path / "shard1", tmp_path / "shard2")
    assert bank_bytes(tmp_path / "shard0") == bank_bytes(out)


def test_ctrl_c_during_the_report_says_how_to_get_it(reference, prepared, tmp_path, monkeypatch, capsys):
    """Ctrl-C after the manifest, while the report is written (the quality score can take
    minutes): the bank is whole, and the one line says which command writes its report."""
    from pgt_blender.cli import run_main
    from pgt_blender.commands import export_bank
    from pgt_blender.core.bank import report

    out, config = tmp_path / "bank", reference[1]

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as patched:
        patched.setattr(report, "write_report", interrupted)
        code = run_main(export_bank.main, ["--objects", str(prepared), "--config", str(config), "--out", str(out),
                                           "--workers", "1"])
    assert code == 130 and capsys.readouterr().err.splitlines()[-1] == (
        f"error: interrupted; {out}: the bank is written but not its report; "
        f"export_bank.py --assemble --out {out} writes it")
    assert bank_bytes(out) == bank_bytes(reference[0]) and not (out / "report.md").exists()
    assert run_main(export_bank.main, ["--assemble", "--out", str(out)]) == 0 and (out / "report.md").is_file()


def test_a_folder_another_export_holds_is_refused_and_left_alone(reference, prepared, tmp_path):
    """An export holds its folder until it ends (folder.exporting, as in the export
    process): an export, resume, overwrite or assembly into it from another process is
    refused and writes nothing; shards of one array job hold it together."""
    out, config = reference
    busy, refusal = tmp_path / "busy", "another export is using this folder right now"
    with folder.exporting(busy):
        for args in ((), ("--resume",), ("--overwrite",), ("--shard", "0/1")):
            result = run_export("--objects", prepared, "--config", config, "--out", busy, *args, check=False)
            assert result.returncode == 1 and refusal in last_line(result)
        assert not any(busy.iterdir())
    with folder.exporting(busy, shared=True):  # another shard of the same array job is running
        run_export("--objects", prepared, "--config", config, "--out", busy, "--shard", "0/1")
        result = run_export("--assemble", "--out", busy, check=False)
        assert result.returncode == 1 and refusal in last_line(result)
        assert not (busy / "manifest.json").exists()
    run_export("--assemble", "--out", busy)
    assert bank_bytes(busy) == bank_bytes(out)


def test_a_process_forked_while_a_folder_is_held_does_not_keep_it(tmp_path):
    """A pool worker forked during an export and left running (its export killed) must
    not hold the folder: the next export can take it."""
    import multiprocessing

    forking = multiprocessing.get_context("fork")
    running = forking.Event()

    def work():  # runs after the fork's own steps, among them closing the copies
        running.set()
        time.sleep(60)

    with folder.exporting(tmp_path / "bank"):
        worker = forking.Process(target=work)
        worker.start()
        assert running.wait(30)
    try:
        with folder.exporting(tmp_path / "bank"):
            assert worker.is_alive()
    finally:
        worker.kill()
        worker.join()


def test_a_bank_outside_the_data_root_gets_paths_that_lead_out_of_it(reference, tmp_path):
    """--assemble --data-root ROOT with the bank kept elsewhere: the info paths start
    with ../ and the frameworks' joins (os.path.join(root, path)) reach the files."""
    out = Path(shutil.copytree(reference[0], tmp_path / "banks" / "bank"))
    root = tmp_path / "data" / "nuscenes"
    root.mkdir(parents=True)
    manifest = export.assemble(out, root)
    assert manifest["data_root"] == "../../data/nuscenes"
    for fmt, name in manifest["info_pickles"].items():
        infos = pickle.loads((out / name).read_bytes())
        paths = [info["path"] for entries in infos.values() for info in entries]
        assert paths and all(path.startswith(f"../../banks/bank/{fmt}/") for path in paths)
        assert all(os.path.isfile(os.path.join(root, path)) for path in paths)


def test_a_killed_run_resumes_to_the_same_bank(reference, prepared, tmp_path):
    out, config = reference
    target = tmp_path / "bank"
    process = subprocess.Popen([sys.executable, str(SCRIPT), "--objects", str(prepared), "--config", str(config),
                                "--out", str(target), "--workers", "2"], stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL, start_new_session=True)
    chunks = target / ".work" / "chunks"
    deadline = time.monotonic() + 120
    while len(list(chunks.glob("*.json"))) < 5 and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.05)
    os.killpg(process.pid, signal.SIGKILL)  # the whole run, workers too, mid-way
    process.wait()
    done = len(list(chunks.glob("*.json")))
    total = json.loads((target / ".work" / "identity.json").read_text())["chunks"]
    assert 0 < done < total and not (target / "manifest.json").exists()
    refused = run_export("--objects", prepared, "--config", config, "--out", target, check=False)
    assert refused.returncode == 1 and "not empty" in refused.stderr
    result = run_export("--objects", prepared, "--config", config, "--out", target, "--resume")
    assert f"{total - done} to do" in result.stdout
    assert bank_bytes(target) == bank_bytes(out)


def test_ray_executor_on_a_local_cluster(reference, prepared, tmp_path):
    pytest.importorskip("ray")
    out, config = reference
    # A local Ray (2.59+) authenticates with a token, kept here rather than in ~/.ray/auth_token
    # (where it would turn on authentication for every later `ray start --head` of the user).
    token = tmp_path / "auth_token"
    token.write_text(secrets.token_hex(32))
    run_export("--objects", prepared, "--config", config, "--out", tmp_path / "ray", "--executor", "ray",
               timeout=300, env=os.environ | {"RAY_AUTH_TOKEN_PATH": str(token)})
    assert bank_bytes(tmp_path / "ray") == bank_bytes(out)


# --- bad input ------------------------------------------------------------------------


def test_output_folder_rules(reference, prepared, tmp_path, shared_data):
    out, config = reference
    stranger = tmp_path / "photos"
    stranger.mkdir()
    (stranger / "holiday.jpg").write_bytes(b"jpeg")
    for flags in ((), ("--overwrite",), ("--resume",)):
        result = run_export("--objects", prepared, "--config", config, "--out", stranger, *flags, check=False)
        assert result.returncode == 1 and str(stranger) in result.stderr
    assert (stranger / "holiday.jpg").exists()
    other = write_config(tmp_path / "other.toml", {**SMALL, "bank": {"chunk_size": 4, "seed": 5}})
    copy = tmp_path / "copy"
    run_export("--objects", prepared, "--config", config, "--out", copy)
    mismatch = run_export("--objects", prepared, "--config", other, "--out", copy, "--resume", check=False)
    assert mismatch.returncode == 1 and "other objects or settings" in mismatch.stderr
    run_export("--objects", prepared, "--config", other, "--out", copy, "--overwrite")
    assert json.loads((copy / "manifest.json").read_text())["seed"] == 5
    (copy / "mine").mkdir()  # an input anywhere in the bank folder: --overwrite would delete it
    inside = write_config(copy / "mine" / "other.toml", {**SMALL, "bank": {"chunk_size": 4, "seed": 5}})
    refused = run_export("--objects", prepared, "--config", inside, "--out", copy, "--overwrite", check=False)
    assert refused.returncode == 1 and f"holds the input {inside}, which overwriting" in last_line(refused)
    assert inside.is_file() and (copy / "manifest.json").is_file()
    shutil.copy(shared_data / "velodyne_calibrations" / "32db.yaml", copy / "mine")  # read through a sensor file
    sensor = copy / "mine" / "sensor.toml"
    sensor.write_text('base = "nuscenes"\ncalibration = "32db.yaml"\n')
    beside = write_config(tmp_path / "beside.toml", {**SMALL, "bank": {"chunk_size": 4, "sensor": str(sensor)}})
    refused = run_export("--objects", prepared, "--config", beside, "--out", copy, "--overwrite", check=False)
    assert refused.returncode == 1 and f"holds the input {sensor}, which overwriting" in last_line(refused)
    (copy / "mine" / "32db.yaml").rename(copy / "32db.yaml")
    sensor.rename(tmp_path / "sensor.toml")
    (tmp_path / "sensor.toml").write_text(f'base = "nuscenes"\ncalibration = "{copy / "32db.yaml"}"\n')
    beside = write_config(tmp_path / "beside.toml", {**SMALL, "bank": {"chunk_size": 4,
                                                                       "sensor": str(tmp_path / "sensor.toml")}})
    refused = run_export("--objects", prepared, "--config", beside, "--out", copy, "--overwrite", check=False)
    assert refused.returncode == 1 and f"holds the input {copy / '32db.yaml'}, which overwriting" in last_line(refused)
    assert (copy / "32db.yaml").is_file()


def test_damaged_or_crafted_chunk_records_and_lost_files_are_redone_never_run(reference, prepared, tmp_path):
    out, config = reference
    copy = tmp_path / "bank"
    import shutil

    shutil.copytree(out, copy)
    marker = tmp_path / "code_ran"
    records = sorted((copy / ".work" / "chunks").glob("*.json"))
    records[1].write_bytes(pickle.dumps({"chunk": 1, "infos": {"x": [CodeOnLoad(marker)]}}))
    records[2].write_bytes(records[2].read_bytes()[:100])  # truncated
    crafted = json.loads(records[3].read_text())
    crafted["stats"] = {"numpy": "|O", "shape": [1], "bytes": "AAAAAAAAAAA="}  # an object array
    records[3].write_text(json.dumps(crafted))
    (copy / next(iter(json.loads(records[4].read_text())["files"]))).unlink()  # a lost entry file
    leading_out = json.loads(records[5].read_text())  # a file outside the bank, which exists
    (tmp_path / "leak.bin").write_bytes(b"")
    leading_out["files"]["../leak.bin"] = "0" * 64
    records[5].write_text(json.dumps(leading_out))
    records[6].write_text("[" * 100_000 + "]" * 100_000)  # deeper than the parser goes
    result = run_export("--assemble", "--out", copy, check=False)
    assert result.returncode == 1 and not marker.exists()
    assert last_line(result) == (f"error: {records[1]}: damaged or an entry file it lists is missing (6 chunk(s)); "
                                 f"--resume redoes them")
    run_export("--objects", prepared, "--config", config, "--out", copy, "--resume")
    assert not marker.exists() and bank_bytes(copy) == bank_bytes(out)


def test_a_damaged_identity_names_the_fix_and_overwrite_replaces_it(reference, prepared, tmp_path):
    out, config = reference
    copy = tmp_path / "bank"
    import shutil

    shutil.copytree(out, copy)
    identity = copy / ".work" / "identity.json"
    for damaged, problem in ((identity.read_text()[:40], "JSONDecodeError"), ("[" * 100_000, "RecursionError"),
                             ('{"chunks": 1' + "0" * 5000 + "}", "ValueError: Exceeds the limit")):
        identity.write_text(damaged)
        for args in (("--assemble",), ("--objects", prepared, "--config", config, "--resume")):
            result = run_export(*args, "--out", copy, check=False)
            assert result.returncode == 1
            assert last_line(result).startswith(f"error: {identity}: damaged ({problem}")
            assert last_line(result).endswith("--overwrite starts the bank anew")
    run_export("--objects", prepared, "--config", config, "--out", copy, "--overwrite")
    assert bank_bytes(copy) == bank_bytes(out)


def test_overwrite_removes_a_link_in_the_bank_not_what_it_points_to(reference, prepared, tmp_path):
    out, config = reference
    copy = Path(shutil.copytree(out, tmp_path / "bank"))
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "notes.txt").write_text("mine")
    (copy / "linked").symlink_to(kept, target_is_directory=True)
    run_export("--objects", prepared, "--config", config, "--out", copy, "--overwrite")
    assert bank_bytes(copy) == bank_bytes(out) and not (copy / "linked").exists()
    assert (kept / "notes.txt").read_text() == "mine"


def test_a_bank_folder_named_in_another_encoding_gets_its_report(reference, prepared, tmp_path):
    """A folder name that is not UTF-8 (bytes from another system): the whole bank and
    its report, which names the folder with those bytes."""
    out, config = reference
    odd = tmp_path / os.fsdecode(b"bank\xff")
    run_export("--objects", prepared, "--config", config, "--out", odd, errors="surrogateescape")
    assert bank_bytes(odd) == bank_bytes(out) and b"bank\xff" in (odd / "report.md").read_bytes()


@pytest.mark.parametrize("table, problem", [
    ({"grid": {"x": [0, 0, 1], "y": [0, 0, 1]}}, "the grid leaves no pose"),
    ({"grid": {"x": [60, 60, 1], "y": [0, 0, 1], "headings_deg": [0, 0, 1]}, "bank": {"min_points": 100000}},
     "no entry kept: all 3 poses had fewer than 100000 points"),  # one pose of each of the 3 objects
])
def test_an_empty_bank_is_an_error_not_an_empty_database(prepared, tmp_path, table, problem):
    config = write_config(tmp_path / "bank.toml", table)
    out = tmp_path / "bank"
    result = run_export("--objects", prepared, "--config", config, "--out", out, "--workers", 1, check=False)
    assert result.returncode == 1 and problem in last_line(result)
    assert not out.exists()  # nothing left behind: there is no bank to resume
    out.mkdir()  # a folder that existed stays, empty
    result = run_export("--objects", prepared, "--config", config, "--out", out, "--workers", 1, check=False)
    assert result.returncode == 1 and problem in last_line(result) and not any(out.iterdir())
    out.rmdir()
    objects = checked_objects(*prepared_objects(prepared), False, prepared)
    with pytest.raises(InputError, match=problem):  # the library call, too
        export.export_bank(objects, load_config(config), out)
    assert not out.exists()


def test_a_bank_folder_with_a_file_in_the_way_is_refused_by_the_library_call(objects, tmp_path):
    """The Bank panel's call: a file at --out or among its parents is named, nothing made."""
    (tmp_path / "a_file").write_text("x")
    for out, problem in ((tmp_path / "a_file", "is a file, not an output folder"),
                         (tmp_path / "a_file" / "bank", f"lies under the file {tmp_path / 'a_file'}")):
        with pytest.raises(InputError, match=problem):
            export.export_bank(objects, BankConfig(x=(0, 0, 1), y=(10, 10, 1)), out)
    assert [path.name for path in tmp_path.iterdir()] == ["a_file"] and (tmp_path / "a_file").read_text() == "x"


@pytest.mark.parametrize("flags", [(), ("--resume",), ("--overwrite",)])
def test_a_start_cut_short_before_its_identity_does_not_block_the_folder(reference, prepared, tmp_path, flags):
    """A full disk right at the start leaves only .work/chunks: any run continues there."""
    out, config = reference
    cut = tmp_path / "bank"
    (cut / ".work" / "chunks").mkdir(parents=True)
    run_export("--objects", prepared, "--config", config, "--out", cut, *flags)
    assert bank_bytes(cut) == bank_bytes(out)


def test_class_names_cannot_lead_files_out_of_the_bank(tmp_path):
    for name in ("../../../../elsewhere/anywhere", "sub/dir", "/abs", "a b"):
        with pytest.raises(InputError, match="classes.truck = .*expected a dataset class name"):
            config_from_table({"classes": {"truck": name}}, tmp_path / "bank.toml")


def test_the_report_compares_with_a_real_database(prepared, tmp_path, shared_data):
    real = shared_data / "mmdet3d_kitti_gtdb" / "kitti_dbinfos_train.pkl"
    config = write_config(tmp_path / "kitti.toml", {**SMALL, "bank": {"chunk_size": 4, "dataset": "kitti"},
                                                     "grid": {**SMALL["grid"], "x": [0, 40, 20]}})
    result = run_export("--objects", prepared, "--config", config, "--out", tmp_path / "bank", "--real", real)
    report = (tmp_path / "bank" / "report.md").read_text()
    assert "report.md" in result.stdout and "kitti_dbinfos_train.pkl" in report and "| Pedestrian |" in report


def test_incomplete_objects_are_listed_and_refused(prepared, tmp_path, reference):
    _, config = reference
    folder = tmp_path / "objects"
    folder.mkdir()
    for path in prepared.glob("truck_reconstruction.*"):
        (folder / path.name).write_bytes(path.read_bytes())
    (folder / "loose.ply").write_bytes((prepared / "bicycle_reconstruction.ply").read_bytes())
    unsized = json.loads((prepared / "bicycle_reconstruction.json").read_text())
    unsized["steps"] = [step for step in unsized["steps"] if step["step"] != "size"]
    (folder / "unsized.ply").write_bytes((prepared / "bicycle_reconstruction.ply").read_bytes())
    (folder / "unsized.json").write_text(json.dumps(unsized))
    result = run_export("--objects", folder, "--config", config, "--out", tmp_path / "bank", check=False)
    assert result.returncode == 1 and "2 incomplete" in result.stderr
    assert "loose.ply: no sidecar" in result.stderr and "unsized.ply: no size set" in result.stderr
    assert not (tmp_path / "bank").exists()
    run_export("--objects", folder, "--config", config, "--out", tmp_path / "bank", "--skip-incomplete")
    manifest = json.loads((tmp_path / "bank" / "manifest.json").read_text())
    assert [obj["name"] for obj in manifest["objects"]] == ["truck_reconstruction"]


@pytest.mark.parametrize("damage, problem", [
    (lambda record: json.dumps({**record, "dims": "big"}).encode(), "dims must be three positive lengths"),
    (lambda record: json.dumps({**record, "dims": [4, 2, -1]}).encode(), "dims must be three positive lengths"),
    (lambda record: json.dumps({**record, "dims": [4, 2, 10**400]}).encode(), "dims must be three positive lengths"),
    (lambda record: json.dumps({**record, "class": 7}).encode(), "class must be a string, got 7"),
    (lambda record: json.dumps([record]).encode(), "expected a JSON object"),
    (lambda record: "\N{LATIN SMALL LETTER E WITH ACUTE}".encode("latin-1") + b"{}", "UnicodeDecodeError"),
])
def test_a_damaged_sidecar_is_one_line_in_both_scripts(prepared, tmp_path, reference, damage, problem):
    """One sidecar reader (authoring.prepare.read_sidecar) for export_bank.py and scan_object.py."""
    _, config = reference
    folder = tmp_path / "objects"
    folder.mkdir()
    (folder / "truck.ply").write_bytes((prepared / "truck_reconstruction.ply").read_bytes())
    record = json.loads((prepared / "truck_reconstruction.json").read_text())
    (folder / "truck.json").write_bytes(damage(record))
    result = run_export("--objects", folder, "--config", config, "--out", tmp_path / "bank", check=False)
    assert result.returncode == 1 and last_line(result).startswith(f"error: {folder / 'truck.json'}: ")
    assert problem in last_line(result) and not (tmp_path / "bank").exists()
    scan = subprocess.run([sys.executable, str(ROOT / "headless_scripts" / "scan_object.py"), "--object",
                           str(folder / "truck.ply"), "--x", "10", "--y", "0", "--sweeps", "2", "--out",
                           str(tmp_path / "scan.bin")], capture_output=True, text=True)
    assert scan.returncode == 1 and scan.stderr.strip().startswith(f"error: {folder / 'truck.json'}: ")
    assert not (tmp_path / "scan.bin").exists()


def test_a_class_without_a_dataset_name_is_refused(objects, tmp_path):
    trailer = [replace(objects[0], class_name="trailer")]
    with pytest.raises(InputError, match="no kitti class for trailer"):
        export.new_job(trailer, BankConfig(dataset="kitti"), tmp_path)
    assert export.new_job(trailer, BankConfig(dataset="kitti", classes={"trailer": "Truck"}), tmp_path).class_names \
        == ["Truck"]
    with pytest.raises(InputError, match="every object's class is skipped"):
        export.new_job(trailer, BankConfig(dataset="kitti", classes={"trailer": ""}), tmp_path)


@contextmanager
def read_only_folder(path: Path):
    """A folder nobody may write into, root included (root ignores mode bits, not the
    immutable attribute)."""
    path.mkdir(mode=0o555)
    if os.getuid() == 0:
        if subprocess.run(["chattr", "+i", str(path)], capture_output=True).returncode:
            pytest.skip("running as root on a file system without chattr +i: cannot make a read-only folder")
        try:
            yield path
        finally:
            subprocess.run(["chattr", "-i", str(path)])
    else:
        yield path


def last_line(result) -> str:
    return result.stderr.strip().splitlines()[-1]


def test_write_errors_end_cleanly(reference, prepared, tmp_path):
    """A full disk (writes past a file-size limit fail), while scanning and while
    assembling: a one-line error naming the file, exit 1, no manifest, no partial file
    and no broken pickle. A folder the user may not write is found as the arguments are
    read (exit 2)."""
    out, config = reference
    full = tmp_path / "full"
    result = run_export("--objects", prepared, "--config", config, "--out", full, "--workers", "1", check=False,
                        preexec_fn=file_size_limit(64_000))
    assert result.returncode == 1 and "File too large" in last_line(result) and str(full) in last_line(result)
    assert not (full / "manifest.json").exists() and not list(full.rglob("*dbinfos*"))
    assert not [path for path in full.rglob("*") if path.name.endswith(".partial")]
    for record in (full / ".work" / "chunks").glob("*.json"):
        assert isinstance(read_record(record), dict)  # the chunks that finished are whole
    run_export("--objects", prepared, "--config", config, "--out", full, "--resume")
    for name in ("manifest.json", "openpcdet/nuscenes_dbinfos_pgt.pkl", "mmdet3d/nuscenes_dbinfos_pgt.pkl"):
        (full / name).unlink()
    result = run_export("--assemble", "--out", full, check=False, preexec_fn=file_size_limit(4_000))
    assert result.returncode == 1 and "dbinfos_pgt.pkl: File too large" in last_line(result)
    assert not (full / "manifest.json").exists() and not list(full.rglob("*dbinfos*"))
    assert not [path for path in full.rglob("*") if path.name.endswith(".partial")]
    run_export("--assemble", "--out", full)
    assert bank_bytes(full) == bank_bytes(out)
    with read_only_folder(tmp_path / "locked") as locked:
        result = run_export("--objects", prepared, "--config", config, "--out", locked / "bank", check=False)
        assert result.returncode == 2 and f"{locked} takes no new file" in last_line(result)
        assert "Permission denied" in last_line(result) or "Operation not permitted" in last_line(result)
        assert not (locked / "bank").exists()


def resident_pages(path: Path) -> int:
    """How many of ``path``'s pages are in the page cache (mincore on a mapping that
    touches none of them)."""
    size = path.stat().st_size
    pages = (ctypes.c_ubyte * -(-size // mmap.PAGESIZE))()
    with open(path, "rb") as stream, mmap.mmap(stream.fileno(), size, access=mmap.ACCESS_COPY) as mapping:
        start = ctypes.c_char.from_buffer(mapping)
        code = ctypes.CDLL(None, use_errno=True).mincore(ctypes.c_void_p(ctypes.addressof(start)),
                                                          ctypes.c_size_t(size), pages)
        del start  # the mapping closes only without exported pointers
    assert code == 0, os.strerror(ctypes.get_errno())
    return sum(page & 1 for page in pages)


@pytest.mark.skipif(sys.platform != "linux", reason="posix_fadvise and mincore as Linux has them")
def test_written_entry_files_leave_the_page_cache(tmp_path):
    """A chunk's entry files leave the page cache once written back (folder.drop_cached,
    which skips a file removed meanwhile); their bytes stay, and a file written the
    usual way stays cached (what the check would otherwise see)."""
    from pgt_blender.core.bank.folder import drop_cached, write_entry_file

    data = np.arange(100_000, dtype=np.float32)
    usual, entry = tmp_path / "usual.bin", tmp_path / "entry.bin"
    usual.write_bytes(data.tobytes())
    write_entry_file(entry, data)
    for path in (usual, entry):
        with open(path, "rb") as stream:
            os.fsync(stream.fileno())
    drop_cached([entry, tmp_path / "gone.bin"])
    assert resident_pages(usual) == -(-data.nbytes // mmap.PAGESIZE) and resident_pages(entry) == 0
    assert entry.read_bytes() == data.tobytes()


def test_a_file_system_that_refuses_the_cache_advice_still_gets_the_files(tmp_path, monkeypatch):
    """posix_fadvise is advice: where it fails (EINVAL on some file systems), the entry
    file is written whole and dropping the cache does nothing."""
    from pgt_blender.core.bank.folder import drop_cached, write_entry_file

    def refuse(*args):
        raise OSError(22, "Invalid argument")

    monkeypatch.setattr(os, "posix_fadvise", refuse, raising=False)
    data = np.arange(1000, dtype=np.float32)
    write_entry_file(tmp_path / "entry.bin", data)
    drop_cached([tmp_path / "entry.bin"])
    assert (tmp_path / "entry.bin").read_bytes() == data.tobytes()


def test_learned_intensity_paints_the_bank(objects, tmp_path):
    """A (tiny) trained estimator replaces the physical intensities, the same bytes on
    one worker or two (spawned: PyTorch does not survive a fork)."""
    pytest.importorskip("torch")
    from pgt_blender.core.intensity.estimator import IntensityEstimator
    from pgt_blender.core.intensity.objects import ObjectSet
    from pgt_blender.core.intensity.training import TrainConfig, train

    rng = np.random.default_rng(0)
    xyz = rng.uniform(-1, 1, (4, 128, 3)).astype(np.float32)
    classes, names = ("truck", "bicycle"), [f"object{i}" for i in range(4)]
    real = ObjectSet(xyz, rng.uniform(0, 1, (4, 128, 1)).astype(np.float32), np.arange(4) % 2, classes, names,
                     "nuscenes")
    rgb = ObjectSet(xyz, rng.uniform(0, 1, (4, 128, 3)).astype(np.float32), np.arange(4) % 2, classes, names,
                    "nuscenes")
    checkpoint = train(real, rgb, TrainConfig(points=128, batch=2, steps=3, checkpoint_every=3, threads=1),
                       tmp_path / "model", progress=False)
    two_objects = [obj for obj in objects if obj.name != "truck_chassis"]
    physical = BankConfig(x=(-20.0, 20.0, 20.0), y=(-20.0, 20.0, 20.0), headings_deg=(0.0, 90.0, 90.0), chunk_size=4)
    learned = replace(physical, intensity_checkpoint=str(checkpoint))
    # a config file names the training's folder (or its intensity.pt) relative to itself
    config = write_config(tmp_path / "bank.toml", {"bank": {"intensity_checkpoint": "model"}})
    assert load_config(config).intensity_checkpoint == str(tmp_path / "model")
    assert IntensityEstimator.load(tmp_path / "model").path == checkpoint
    banks = {name: export.export_bank(two_objects, config, tmp_path / name, workers=workers)
             for name, config, workers in (("physical", physical, 1), ("one", learned, 1), ("two", learned, 2))}
    assert bank_bytes(tmp_path / "one") == bank_bytes(tmp_path / "two")
    assert banks["one"]["counts"] == banks["physical"]["counts"]
    info = pickle.loads((tmp_path / "one" / "openpcdet" / "nuscenes_dbinfos_pgt.pkl").read_bytes())["truck"][0]
    learned_points = np.fromfile(tmp_path / "one" / "openpcdet" / info["path"], np.float32).reshape(-1, 5)
    physical_points = np.fromfile(tmp_path / "physical" / "openpcdet" / info["path"], np.float32).reshape(-1, 5)
    np.testing.assert_array_equal(learned_points[:, [0, 1, 2, 4]], physical_points[:, [0, 1, 2, 4]])
    assert not np.array_equal(learned_points[:, 3], physical_points[:, 3])
    assert np.array_equal(learned_points[:, 3], np.round(learned_points[:, 3])) and learned_points[:, 3].max() <= 255
    # a class the checkpoint lacks is named before the folder is made, not in the first chunk
    with pytest.raises(InputError, match=r"has no class 'bus' \(trained for truck, bicycle\)"):
        export.export_bank([replace(two_objects[0], class_name="bus")], learned, tmp_path / "refused")
    assert not (tmp_path / "refused").exists()


def test_the_embree_engine_gives_the_same_bank_but_for_shared_edges(reference, objects, tmp_path):
    """The default engine ("auto": Embree, installed with the package) casts the same rays
    as Blender's BVH in one batch; at most a handful of rows differ, where a ray meets an
    edge two polygons share. Compared without noise and drops: an entry's noise is one
    stream over its returns, so one different hit would shift the noise of the rest."""
    out, config = reference
    assert json.loads((out / "manifest.json").read_text())["config"]["engine"] == "embree"  # auto, resolved
    exact = replace(load_config(config), range_noise=False, ray_drop=False)
    manifests = {engine: export.export_bank(objects, replace(exact, engine=engine), tmp_path / engine)
                 for engine in ("embree", "bvh")}
    assert manifests["bvh"]["counts"] == manifests["embree"]["counts"]
    rows = differing = 0
    for info in pickle.loads((tmp_path / "embree" / "openpcdet" / "nuscenes_dbinfos_pgt.pkl").read_bytes())["truck"]:
        ours = np.fromfile(tmp_path / "embree" / "openpcdet" / info["path"], np.float32).reshape(-1, 5)
        theirs = np.fromfile(tmp_path / "bvh" / "openpcdet" / info["path"], np.float32).reshape(-1, 5)
        rows += len(ours)
        differing += abs(len(ours) - len(theirs)) if len(ours) != len(theirs) else int((ours != theirs).any(1).sum())
    assert differing <= 1e-4 * rows
