"""The bad-input contract of every command, in one table (README "What the tools promise").

Each case builds a broken input in a fresh folder, runs the command as a user does (a
subprocess of the venv's Python) and checks the promise: exit status 1 and exactly one
stderr line ``error: <the file or folder at fault>: <the problem>``; nothing written
(the folder holds only the inputs afterwards, byte for byte); no code run from a data
file; no file outside the output folder. Usage mistakes argparse catches exit 2.

Deeper cases of each reader sit beside its module's tests: PLY headers (test_ply),
importers and COLMAP binaries (test_importing), sensor files (test_scan), bank configs,
damaged resume state and full disks (test_bank), info pickles (test_bank_merge,
test_heading_classifier), training (test_intensity_model), and the Blender operators'
CANCELLED reports with the scene unchanged (test_blender_import, test_blender_scan,
test_blender_authoring, test_blender_bank).
"""

import json
import os
import pickle
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pgt_blender.core.authoring.prepare import prepare, write_prepared
from pgt_blender.core.errors import InputError
from pgt_blender.core.files import TEXT_LIMIT
from pgt_blender.core.importing import load_reconstruction
from pgt_blender.core.importing.ply import read_vertices, write_ply
from pgt_blender.core.samples import write_sample

from .conftest import ROOT, CodeOnLoad, run_script



@pytest.fixture(scope="module")
def inputs(tmp_path_factory, shared_data) -> dict:
    """Good inputs the cases break: a sample truck (mesh, points, sidecar), a prepared
    bank object, real info pickles and the real COLMAP, splat and KITTI data."""
    samples = write_sample(tmp_path_factory.mktemp("samples"), "truck", points=3000)
    prepared = tmp_path_factory.mktemp("prepared")
    write_prepared(prepare(load_reconstruction(samples["reconstruction.ply"]), "truck", up="pca",
                           heading_method="baseline"), "truck", "nuscenes", prepared)
    return {"mesh": samples["mesh.ply"], "points": samples["reconstruction.ply"], "prepared": prepared,
            "infos": shared_data / "mmdet3d_kitti_gtdb" / "kitti_dbinfos_train.pkl",
            "statue": shared_data / "colmap_statue" / "sparse" / "0",
            "splat": shared_data / "gaussian_splat_donut" / "fused.ply", "kitti": shared_data / "kitti_scans"}


# --- builders: each takes (folder, inputs) and returns (command line, the path the error names, problem) ---

def ascii_ply(folder, header, body):
    path = folder / "cloud.ply"
    path.write_text("ply\nformat ascii 1.0\n" + header + "end_header\n" + body)
    return path


XYZ = "property float x\nproperty float y\nproperty float z\n"


def import_ply(header, body, problem):
    def build(folder, _):
        path = ascii_ply(folder, header, body)
        return ["import_reconstruction.py", path, "--out", folder / "scene.blend"], path, problem
    return build


def import_columns(change, problem):
    """A binary PLY of the first 10 donut splats, with ``change(columns)`` applied."""
    def build(folder, inputs):
        columns = {name: values[:10].copy() for name, values in read_vertices(inputs["splat"]).items()}
        change(columns)
        path = folder / "splat.ply"
        write_ply(path, columns)
        return ["import_reconstruction.py", path, "--out", folder / "scene.blend"], path, problem
    return build


def colmap_points_cut_in_half(folder, inputs):
    model = Path(shutil.copytree(inputs["statue"], folder / "model"))
    for text in model.glob("*.txt"):
        text.unlink()
    points = model / "points3D.bin"
    points.write_bytes(points.read_bytes()[:points.stat().st_size // 2])  # pycolmap asked for 17 GB
    return ["import_reconstruction.py", model, "--out", folder / "scene.blend"], points, "claims 1,816 points but only"


def capture_run(folder, damage, problem, named, *options):
    """import_reconstruction.py of a small 3DGS output folder (8 orbit views, ball masks
    as .npy) after ``damage(run, masks)``; the error names ``named(run, masks)``."""
    from pgt_blender.core.capture import samples

    positions = samples.fibonacci_sphere(500).astype(np.float32)
    cameras = samples.orbit_cameras(8, 4.0, 20.0)
    run = folder / "run"
    samples.write_3dgs_run(run, samples.splat_columns(positions, np.zeros((500, 3, 4), np.float32),
                                                      np.full(500, 0.9), np.full((500, 3), 0.01)), cameras)
    masks = folder / "masks"
    masks.mkdir()
    for view, mask in zip(cameras, samples.ball_masks(cameras, (0, 0, 0), 1.0)):
        np.save(masks / view.name.replace(".png", ".npy"), mask)
    damage(run, masks)
    return (["import_reconstruction.py", run, *[masks if o == "MASKS" else o for o in options],
             "--out", folder / "scene.blend"], named(run, masks), problem)


def plenoxels(change, problem):
    """import_reconstruction.py of a 4^3 svox2 checkpoint with ``change(arrays)`` applied."""
    def build(folder, _):
        arrays = {"links": np.arange(64, dtype=np.int32).reshape(4, 4, 4), "density_data": np.ones((64, 1), np.float32),
                  "sh_data": np.zeros((64, 27), np.float16), "radius": np.ones(3, np.float32),
                  "center": np.zeros(3, np.float32), "basis_type": np.array(1)}
        change(arrays)
        np.savez(folder / "grid.npz", **arrays)
        return ["import_reconstruction.py", folder / "grid.npz", "--out", folder / "scene.blend"], folder / "grid.npz", problem
    return build


def import_pipe(folder, _):
    os.mkfifo(folder / "cloud.ply")  # a read would wait for a writer forever
    return ["import_reconstruction.py", folder / "cloud.ply", "--out", folder / "scene.blend"], folder / "cloud.ply", \
        "not a regular file (a pipe, socket or device)"


def colmap_nan_principal_point(folder, inputs):
    model = Path(shutil.copytree(inputs["statue"], folder / "model"))
    for text in model.glob("*.txt"):
        text.unlink()
    cameras = bytearray((model / "cameras.bin").read_bytes())
    struct.pack_into("<d", cameras, 40, np.nan)  # the first camera's cx (SIMPLE_RADIAL f, cx, cy, k from byte 32)
    (model / "cameras.bin").write_bytes(bytes(cameras))
    return ["import_reconstruction.py", model, "--out", folder / "scene.blend"], model, "principal point nan"


def reconstruct_file(name: str, content: bytes, problem):
    def build(folder, _):
        (folder / name).write_bytes(content)
        return ["reconstruct_frames.py", folder / name, "--out", folder / "model"], folder / name, problem
    return build


def latin1_image(folder, inputs):
    """An image named in Latin-1 ("café.jpg"): Python holds the byte as a surrogate escape,
    which the error line shows as \\udce9."""
    image = folder / "caf\udce9.jpg"
    image.write_bytes(b"\xff\xd8")
    shown = str(image).encode(errors="backslashreplace").decode()
    return (["reconstruct_frames.py", folder, "--out", folder / "model"], shown,
            "the file name is not UTF-8 text, which COLMAP stores; rename the image")


def scan(extra, problem, named=lambda folder, inputs: inputs["mesh"]):
    """scan_object.py of the sample truck at (10, 0) with ``extra(folder, inputs)`` arguments;
    the error names ``named(folder, inputs)``."""
    def build(folder, inputs):
        command = ["scan_object.py", "--object", inputs["mesh"], "--x", 10, "--y", 0, "--out", folder / "scan.bin"]
        return command + extra(folder, inputs), named(folder, inputs), problem
    return build


def in_folder(name):
    return lambda folder, inputs: folder / name


def sensor_file(body):
    def extra(folder, _):
        (folder / "sensor.toml").write_text('base = "nuscenes"\n' + body + "\n")
        return ["--sensor", folder / "sensor.toml"]
    return extra


def sidecar_scan(content: bytes, problem):
    def build(folder, inputs):
        mesh = folder / "truck.ply"
        mesh.write_bytes(inputs["mesh"].read_bytes())
        (folder / "truck.json").write_bytes(content)
        return (["scan_object.py", "--object", mesh, "--x", 10, "--y", 0, "--sweeps", 2, "--out", folder / "scan.bin"],
                folder / "truck.json", problem)
    return build


def crafted_pickle(script, flag, extra=(), out="out"):
    """An otherwise valid info pickle with a payload that would run a shell command."""
    def build(folder, inputs):
        infos = pickle.loads(inputs["infos"].read_bytes())
        infos["Pedestrian"][0]["score"] = CodeOnLoad(folder / "code_ran")
        crafted = folder / "crafted.pkl"
        crafted.write_bytes(pickle.dumps(infos))
        command = [script, flag, crafted, *[inputs.get(arg, arg) for arg in extra], "--out", folder / out]
        return command, crafted, "refused to load posix.system"
    return build


def spoiled_bank(key, value, problem):
    def build(folder, inputs):
        infos = pickle.loads(inputs["infos"].read_bytes())
        infos["Pedestrian"][0][key] = value
        bank = folder / "bank.pkl"
        bank.write_bytes(pickle.dumps(infos))
        return (["mix_bank.py", "--real", inputs["infos"], "--bank", bank, "--out", folder / "mixed.pkl"], bank,
                f"info 0 of 'Pedestrian': {problem}")
    return build


SMALL_GRID = {"grid": {"headings_deg": [0, 0, 1], "x": [10, 10, 1], "y": [0, 0, 1]}}


def bank(table: dict, problem, named="bank.toml", sidecar=None):
    """export_bank.py on a copy of the prepared truck with ``table`` as the config and
    ``sidecar(record)`` (if given) as its sidecar."""
    def build(folder, inputs):
        objects = Path(shutil.copytree(inputs["prepared"], folder / "objects"))
        if sidecar:
            path = objects / "truck_reconstruction.json"
            path.write_bytes(sidecar(json.loads(path.read_text())))
        config = folder / "bank.toml"
        config.write_text("".join(f"[{section}]\n" + "".join(f"{key} = {json.dumps(value)}\n"
                                                              for key, value in entries.items())
                                  for section, entries in table.items()))
        command = ["export_bank.py", "--objects", objects, "--config", config, "--out", folder / "bank",
                   "--workers", 1]
        return command, {"bank.toml": config, "sidecar": objects / "truck_reconstruction.json",
                         "out": folder / "bank"}[named], problem
    return build


def bank_with(extra, problem, named, table=SMALL_GRID):
    """export_bank.py as ``bank`` makes it (``table``), plus ``extra(folder, inputs)``
    arguments; the error names ``named(folder, inputs)``."""
    def build(folder, inputs):
        command, _, _ = bank(table, problem)(folder, inputs)
        return command + extra(folder, inputs), named(folder, inputs), problem
    return build


def cut_velodyne(folder, inputs):
    kitti = Path(shutil.copytree(inputs["kitti"], folder / "kitti"))
    scan_file = sorted((kitti / "velodyne").glob("*.bin"))[0]
    scan_file.write_bytes(scan_file.read_bytes() + b"\0\0")  # padded: the rows no longer line up
    return ["fit_ground.py", kitti], scan_file, "bytes are not whole rows of 4 float32 values"


def empty_labels(folder, inputs):
    """KITTI frames whose labels hold no box (empty, or DontCare only): no ground to fit."""
    kitti = Path(shutil.copytree(inputs["kitti"], folder / "kitti"))
    for label in (kitti / "label_2").glob("*.txt"):
        label.write_text("")
    return ["fit_ground.py", kitti], kitti, "none of its 0 labelled boxes has >= 50 ground returns around it"


def looping_label(folder, inputs):
    """A KITTI label that is a link to itself: named as such, not as missing."""
    kitti = Path(shutil.copytree(inputs["kitti"], folder / "kitti"))
    label = kitti / "label_2" / "000001.txt"
    label.unlink()
    label.symlink_to(label.name)
    return ["fit_ground.py", kitti], label, "a link that leads nowhere (its target is missing, or the links loop)"


def looping_ply(script):
    """A folder whose one .ply is a link to itself, given to ``script``."""
    def build(folder, inputs):
        objects = folder / "objects"
        objects.mkdir()
        (objects / "loop.ply").symlink_to("loop.ply")
        command = {"prepare_objects.py": ["--in", objects, "--class", "truck", "--out", folder / "out"],
                   "export_bank.py": ["--objects", objects, "--out", folder / "bank"]}[script]
        return [script, *command], objects / "loop.ply", "a link that leads nowhere"
    return build


def oversized(path: Path) -> Path:
    """``path`` made a sparse file one byte over the limit of a text input."""
    with open(path, "wb") as stream:
        stream.truncate(TEXT_LIMIT + 1)
    return path


def oversized_label(folder, inputs):
    kitti = Path(shutil.copytree(inputs["kitti"], folder / "kitti"))
    label = oversized(kitti / "label_2" / "000001.txt")
    return ["fit_ground.py", kitti], label, "too large for what is read from it (268,435,457 bytes, more than 256 MB)"


def pipe_material(folder, inputs):
    """A class mesh whose .mtl library is a named pipe, which a read would wait on forever."""
    meshes = folder / "meshes"
    meshes.mkdir()
    (meshes / "car.obj").write_text("mtllib car.mtl\nv 0 0 0\nv 4 0 0\nv 0 2 0\nf 1 2 3\n")
    os.mkfifo(meshes / "car.mtl")
    return (["fit_returns.py", inputs["kitti"], "--meshes", meshes], meshes / "car.mtl",
            "not a regular file (a pipe, socket or device)")


def shuffled_velodyne(folder, inputs):
    """A KITTI scan whose rows are shuffled: no longer stored laser by laser, as the ring fit needs."""
    kitti = Path(shutil.copytree(inputs["kitti"], folder / "kitti"))
    scan_file = kitti / "velodyne" / "000001.bin"
    rows = np.fromfile(scan_file, np.float32).reshape(-1, 4)
    np.random.default_rng(0).permutation(rows).tofile(scan_file)
    return ["fit_returns.py", kitti, "--meshes", "samples"], scan_file, "the fit needs 50"


def place(change, problem, named):
    """place_objects.py on a copy of KITTI frame 000001 with the real mmdet3d KITTI
    database (one pedestrian) as the bank, after ``change(folder, shared data, kitti copy)
    -> extra args``."""
    def build(folder, inputs):
        kitti = Path(shutil.copytree(inputs["kitti"], folder / "kitti"))
        extra = change(folder, inputs["kitti"].parent, kitti)
        command = ["place_objects.py", "--scan", kitti / "velodyne" / "000001.bin", "--info",
                   kitti / "label_2" / "000001.txt", "--bank", inputs["infos"], "--convention", "mmdet3d",
                   "--out", folder / "placed", *extra]
        return command, named(folder, kitti, inputs), problem
    return build


def sidewalk_map(folder) -> list:
    """--map-polygons of one sidewalk square 200 m a side about the sensor (class layers
    name a map's layers)."""
    (folder / "map.json").write_text('[{"layer": "sidewalk", "polygon": [[-100, -100], [100, -100], [100, 100], '
                                     '[-100, 100]]}]')
    return ["--map-polygons", folder / "map.json"]


def scan_of_one_object(folder, shared, kitti):
    """A ground-truth database file given as the scan (the pedestrian's 377 returns about
    its box bottom, the origin): nothing lies below the sensor."""
    shutil.copy(shared / "mmdet3d_kitti_gtdb" / "kitti_gt_database" / "0_Pedestrian_0.bin",
                kitti / "velodyne" / "000001.bin")
    return ["--objects", "Pedestrian=1"]


def map_elsewhere(folder, shared, kitti):
    image = np.zeros((100, 100, 3), np.float32)
    image[:, :50] = [0.5, 0.5, 0.5]
    import matplotlib.image

    matplotlib.image.imsave(folder / "map.png", image)
    (folder / "legend.json").write_text('{"road": [128, 128, 128]}')
    return ["--map", folder / "map.png", "--map-pose", "1000", "1000", "0.1", "--map-legend", folder / "legend.json"]


CASES = {
    # reading reconstructions
    "PLY body shorter than its header": import_ply("element vertex 2\n" + XYZ, "1 2 3\n", "declares 2 data rows"),
    "PLY property declared twice": import_ply("element vertex 1\n" + XYZ + "property float x\n", "1 2 3 4\n",
                                              "property 'x' appears twice in element 'vertex'"),
    "PLY uchar color of 300": import_ply(
        "element vertex 1\n" + XYZ + "property uchar red\nproperty uchar green\nproperty uchar blue\n",
        "0 0 0 300 0 0\n", "holds 300 in row 1: not a uint8 value"),
    "PLY property named like Blender's position": import_ply(
        "element vertex 1\n" + XYZ + "property float position\n", "1 2 3 4\n", "property 'position' has the name"),
    "PLY property named like a built-in Blender attribute": import_ply(
        "element vertex 1\n" + XYZ + "property float sharp_face\n", "1 2 3 4\n",
        "'sharp_face' has the name of a built-in Blender"),
    "mesh PLY with fewer faces than declared": import_ply(
        "element vertex 3\n" + XYZ + "element face 2\nproperty list uchar int vertex_indices\n",
        "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", "declares 3 vertices and 2 faces but the body holds 3 vertices and 1"),
    "splat with a NaN scale": import_columns(lambda c: c["scale_1"].__setitem__(3, np.nan),
                                             "have NaN or Inf values in scale_1"),
    "splat without opacity": import_columns(lambda c: c.pop("opacity"), "missing vertex properties opacity"),
    "COLMAP points3D.bin cut in half": colmap_points_cut_in_half,
    "COLMAP camera with a NaN principal point": colmap_nan_principal_point,
    "PLY that is a pipe": import_pipe,
    "3DGS cameras.json cut short": lambda folder, inputs: capture_run(
        folder, lambda run, masks: (run / "cameras.json").write_text('[{"id": 0, "img_name": "view_000", "wid'),
        "not a readable cameras.json (JSONDecodeError", lambda run, masks: run / "cameras.json"),
    "3DGS camera with a sheared rotation": lambda folder, inputs: capture_run(
        folder, lambda run, masks: (run / "cameras.json").write_text(json.dumps(
            [{"img_name": "a", "width": 8, "height": 8, "fx": 5, "fy": 5, "position": [0, 0, 0],
              "rotation": [[1, 0.5, 0], [0, 1, 0], [0, 0, 1]]}])),
        "camera 0: rotation is not a rotation matrix", lambda run, masks: run / "cameras.json"),
    "masks folder missing an image's mask": lambda folder, inputs: capture_run(
        folder, lambda run, masks: (masks / "view_005.npy").unlink(), "no mask for 1 of 8 images (view_005)",
        lambda run, masks: masks, "--foreground", "masks", "--masks", "MASKS"),
    "mask of another aspect ratio": lambda folder, inputs: capture_run(
        folder, lambda run, masks: np.save(masks / "view_002.npy", np.ones((10, 10), bool)),
        "is 10x10 pixels but its image view_002 is 320x240", lambda run, masks: masks / "view_002.npy",
        "--foreground", "masks", "--masks", "MASKS"),
    "Plenoxels checkpoint without sh_data": plenoxels(lambda a: a.pop("sh_data"), "no sh_data"),
    "Plenoxels links out of range": plenoxels(lambda a: a["links"].__setitem__((1, 2, 3), 64),
                                              "links out of range: 1 cells point outside the 64 data rows"),
    "Plenoxels learned basis": plenoxels(lambda a: a.__setitem__("basis_type", np.array(4)),
                                         "basis_type 4 (a learned 3D-texture basis)"),
    # structure from motion
    "reconstruct_frames of a folder without images": lambda folder, inputs: (
        ["reconstruct_frames.py", folder, "--out", folder / "model"], folder, "no images (.jpg, .jpeg, .png)"),
    "reconstruct_frames of a text file": reconstruct_file("notes.txt", b"frames", "not a folder of images nor a video"),
    "reconstruct_frames of an image named in Latin-1": latin1_image,
    "reconstruct_frames into its image folder": lambda folder, inputs: (
        ["reconstruct_frames.py", inputs["statue"].parents[1] / "images", "--out",
         inputs["statue"].parents[1] / "images"], inputs["statue"].parents[1] / "images", "is or holds the input"),
    "reconstruct_frames of a damaged video": reconstruct_file("orbit.mp4", b"\0\1garbage" * 100,
                                                              "not a decodable video"),
    # scanning
    "scan of a missing object": scan(lambda f, i: ["--object", f / "missing.obj"], "no such file",
                                     in_folder("missing.obj")),
    "scan of points as a mesh": scan(lambda f, i: ["--object", i["points"], "--surface", "mesh"],
                                     "has no faces to scan as a mesh",
                                     lambda folder, inputs: inputs["points"]),
    "scan out of the sensor's range": scan(lambda f, i: ["--x", 500], "no returns at x = 500 m, y = 0 m: the object is "
                                           "out of the nuscenes sensor's range or view there; nothing written"),
    "kitti sweeps merged into a .bin": scan(lambda f, i: ["--sensor", "kitti", "--sweeps", 3, "--speed", 5],
                                            "kitti .bin files have no time column to keep 3 merged sweeps apart",
                                            in_folder("scan.bin")),
    "unknown sensor preset": scan(lambda f, i: ["--sensor", "velodyne128"], "not a sensor preset",
                                  lambda folder, inputs: "velodyne128"),
    "sensor TOML unreadable": scan(sensor_file("columns = "), "not a readable TOML file", in_folder("sensor.toml")),
    "sensor TOML integer of 5,000 digits": scan(sensor_file("columns = 1" + "0" * 5000), "not a readable TOML file",
                                                in_folder("sensor.toml")),
    "sensor with 1e9 columns": scan(sensor_file("columns = 1000000000"), "exceeds 16,777,216 rays",
                                    in_folder("sensor.toml")),
    "sensor rate_hz = 'fast'": scan(sensor_file('rate_hz = "fast"'), "rate_hz must be a finite number",
                                    in_folder("sensor.toml")),
    "sensor mounted at infinity": scan(sensor_file("mounting_height = inf"), "mounting_height must be a finite",
                                       in_folder("sensor.toml")),
    "sidecar not UTF-8": sidecar_scan(b"\xe9{}", "UnicodeDecodeError"),
    "sidecar class without a motion model": sidecar_scan(b'{"class": "semi"}', "class 'semi' has no motion model"),
    # pickles that would run code, garbage inside databases
    "mix_bank --real crafted": crafted_pickle("mix_bank.py", "--real", ("--bank", "infos"), "out.pkl"),
    "mix_bank --bank crafted": crafted_pickle("mix_bank.py", "--bank", ("--real", "infos"), "out.pkl"),
    "train_intensity --real crafted": crafted_pickle("train_intensity.py", "--real"),
    "train_intensity --rgb of a mesh without its class": lambda folder, inputs: (
        ["train_intensity.py", "--real", inputs["kitti"], "--rgb", f"={inputs['mesh']}", "--out", folder / "model"],
        inputs["mesh"],
        f"'={inputs['mesh']}' names no class: give CLASS=MESH"),
    "mix_bank NaN box": spoiled_bank("box3d_lidar", np.array([0, 0, np.nan, 1, 1, 1, 0], np.float32),
                                     "box3d_lidar must be 7 or more finite numbers"),
    "mix_bank negative point count": spoiled_bank("num_points_in_gt", -3, "num_points_in_gt must be a count >= 0"),
    "score_bank of a bank folder that is not there": lambda folder, inputs: (
        ["score_bank.py", "--bank", folder / "bank", "--real", inputs["infos"]], folder / "bank", "no such folder"),
    # banks
    "class name leading out of the bank": bank({"classes": {"truck": "../../../../elsewhere/anywhere"}},
                                               "classes.truck = '../../../../elsewhere/anywhere'"),
    "class name with a slash": bank({"classes": {"truck": "sub/dir"}}, "expected a dataset class name"),
    "grid with no pose": bank({"grid": {"x": [0, 0, 1], "y": [0, 0, 1]}}, "the grid leaves no pose", "out"),
    "sidecar dims 'big'": bank(SMALL_GRID, "dims must be three positive lengths", "sidecar",
                               lambda record: json.dumps({**record, "dims": "big"}).encode()),
    "sidecar step without its transform": bank(SMALL_GRID, "steps[0]: transform must be a 4 x 4 list", "sidecar",
                                               lambda record: json.dumps({**record, "steps": [{"step": "size"}]}).encode()),
    "sidecar alignment with refine 'yes'": bank(SMALL_GRID, "steps[0]: refine must be true or false, got 'yes'",
                                               "sidecar", lambda record: json.dumps({**record, "steps": [
                                                   {**record["steps"][0], "refine": "yes"}, *record["steps"][1:]]
                                               }).encode()),
    "class mapped to a name without a motion model": bank(
        {**SMALL_GRID, "classes": {"semi": "Semi"}}, "no motion model for semi", "out",
        lambda record: json.dumps({**record, "class": "semi"}).encode()),
    "export_bank --real crafted": crafted_pickle("export_bank.py", "--real",
                                                 ("--objects", "prepared", "--workers", "1")),
    "export_bank with a dataset root that is no folder": bank_with(
        lambda folder, _: ["--data-root", folder / "no-root"], "the dataset root is not a folder",
        lambda folder, _: folder / "no-root"),  # named before any chunk is exported
    "export_bank on a Ray address nobody answers": bank_with(
        lambda folder, _: ["--executor", "ray", "--address", "127.0.0.1:1"], "no Ray cluster answers there",
        lambda folder, _: "127.0.0.1:1"),  # ray.init retried it without end
    "export_bank --real whose infos contradict --real-convention": bank_with(
        lambda _, inputs: ["--real", inputs["infos"], "--real-convention", "openpcdet"],
        "holds mmdetection3d infos (points about the box bottom, a group_id each), not openpcdet's",
        lambda _, inputs: inputs["infos"], {**SMALL_GRID, "bank": {"dataset": "kitti"}}),  # before the export
    # placement into real scenes
    "place_objects on a scan without ground": place(scan_of_one_object, "no ground found",
                                                    lambda folder, kitti, inputs: kitti / "velodyne" / "000001.bin"),
    "place_objects with a map that does not cover the scene": place(
        map_elsewhere, "the map image does not cover the scene", lambda folder, kitti, inputs: folder / "map.png"),
    "place_objects with a class layer table of letters": place(
        lambda folder, shared, kitti: (folder / "layers.json").write_text('{"Pedestrian": "sidewalk"}')
        and ["--class-layers", folder / "layers.json", *sidewalk_map(folder)],
        "class 'Pedestrian' has 'sidewalk': expected a list of layer names",
        lambda folder, kitti, inputs: folder / "layers.json"),
    "place_objects into a folder with a folder where its picture goes": place(  # found before the placement
        lambda folder, shared, kitti: (folder / "placed" / "birdseye.png").mkdir(parents=True) or [],
        "is a folder; expected a file name", lambda folder, kitti, inputs: folder / "placed" / "birdseye.png"),
    "place_objects asking for a class the bank lacks": place(
        lambda folder, shared, kitti: ["--objects", "Car=2"], "no 'Car' entry within 54 m",
        lambda folder, kitti, inputs: inputs["infos"]),
    # real scans
    "velodyne file padded by two bytes": cut_velodyne,
    "fit_ground on labels without a box": empty_labels,
    "fit_sensor on a folder without scans": lambda folder, inputs: (["fit_sensor.py", folder], folder,
                                                                    "holds no *.bin scans"),
    "fit_sensor of 64 lasers on the 16-beam preset": lambda folder, inputs: (
        ["fit_sensor.py", inputs["kitti"] / "velodyne", "--base", "vlp16"], inputs["kitti"] / "velodyne",
        "the scans have 64 lasers, the vlp16 preset 16: refine --base kitti"),
    "fit_returns on a scan not stored laser by laser": shuffled_velodyne,
    "a KITTI label that is a looping link": looping_label,
    "a KITTI label of 256 MB": oversized_label,
    "a class mesh whose material library is a pipe": pipe_material,
    "a sensor whose calibration is a link to nothing": scan(
        lambda folder, inputs: (folder / "gone.yaml").symlink_to("nothing.yaml")
        or sensor_file('calibration = "gone.yaml"')(folder, inputs), "a link that leads nowhere",
        in_folder("gone.yaml")),
    "a bank config of 256 MB": lambda folder, inputs: (
        ["export_bank.py", "--objects", inputs["prepared"], "--config", oversized(folder / "bank.toml"), "--out",
         folder / "bank"], folder / "bank.toml", "too large for what is read from it"),
    "a sensor file of 256 MB": scan(lambda folder, inputs: ["--sensor", oversized(folder / "sensor.toml")],
                                    "too large for what is read from it", in_folder("sensor.toml")),
    "place_objects with a class layer table of 256 MB": place(
        lambda folder, shared, kitti: ["--class-layers", oversized(folder / "layers.json"), *sidewalk_map(folder)],
        "too large for what is read from it", lambda folder, kitti, inputs: folder / "layers.json"),
    "prepare_objects on a looping link": looping_ply("prepare_objects.py"),
    "export_bank on a prepared object that is a looping link": looping_ply("export_bank.py"),
    "fit_returns with a meshes folder that is not there": lambda folder, inputs: (
        ["fit_returns.py", inputs["kitti"], "--meshes", folder / "meshes"], folder / "meshes", "no such folder"),
    "fit_returns on a folder without scans": lambda folder, inputs: (["fit_returns.py", folder, "--meshes", "samples"], folder,
                                                                     "no velodyne/*.bin scans"),
}


def contents(folder: Path) -> dict:
    return {path: path.read_bytes() if path.is_file() else None for path in sorted(folder.rglob("*"))}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_is_one_line_exit_1_and_writes_nothing(inputs, tmp_path, case):
    command, named, problem = CASES[case](tmp_path, inputs)
    before = contents(tmp_path)
    result = run_script(*command, cwd=tmp_path)
    errors = [line for line in result.stderr.splitlines() if line.startswith("error: ")]
    assert result.returncode == 1 and len(errors) == 1, result.stderr
    assert errors[0].startswith(f"error: {named}") and problem in errors[0], errors[0]
    assert contents(tmp_path) == before  # nothing written, nothing left half-written, no code ran
    assert not (tmp_path.parent / "elsewhere").exists()


def test_a_folder_that_cannot_be_read_is_named_not_taken_for_empty(inputs, tmp_path):
    """fit_sensor on a folder of scans it may not read: the folder and why, not 'holds no
    scans'. Run as root (whom no mode stops), the command runs without the capability to
    override file modes (setpriv)."""
    scans = tmp_path / "velodyne"
    scans.mkdir()
    shutil.copy(inputs["kitti"] / "velodyne" / "000001.bin", scans)
    scans.chmod(0)
    unprivileged = ["setpriv", "--bounding-set=-dac_override,-dac_read_search",
                    "--inh-caps=-dac_override,-dac_read_search"] if os.geteuid() == 0 else []
    try:
        result = subprocess.run([*unprivileged, sys.executable, ROOT / "headless_scripts" / "fit_sensor.py", scans,
                                 "--out", tmp_path / "sensor.toml"], capture_output=True, text=True)
    finally:
        scans.chmod(0o755)
    assert result.returncode == 1, result.stderr
    assert result.stderr.splitlines()[-1] == f"error: {scans}: cannot be read (Permission denied)"
    assert sorted(path.name for path in tmp_path.iterdir()) == ["velodyne"]


@pytest.mark.parametrize("flag, value", [("--x", "nan"), ("--heading", "inf"), ("--y", "-inf")])
def test_a_non_finite_pose_is_a_usage_error(inputs, tmp_path, flag, value):
    args = {"--x": "10", "--y": "0", "--heading": "0", flag: value}
    result = run_script("scan_object.py", "--object", inputs["mesh"], *[f"{key}={item}" for key, item in args.items()],
                        "--out", tmp_path / "scan.bin")
    assert result.returncode == 2 and f"argument {flag}: expected a finite number, got '{value}'" in result.stderr
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("command, problem", [
    ("mix_bank.py --seed=-1", "argument --seed: expected a whole number 0 .. 2,147,483,647, got '-1'"),
    ("demo.py --seed 99999999999", "argument --seed: expected a whole number 0 .. 2,147,483,647"),
    ("train_heading.py --points 1000000000", "argument --points: expected a whole number 1 .. 16,384"),
    ("train_heading.py --threads 0", "argument --threads: expected a whole number 1 .. 64"),
    ("train_intensity.py --steps " + "9" * 400, "argument --steps: expected a whole number 1 .. 10,000,000"),
    ("reconstruct_frames.py frames --every 1000000000", "argument --every: expected a whole number 1 .. 10,000"),
    ("reconstruct_frames.py frames --max-features 9223372036854775808", "argument --max-features"),
    ("scan_object.py --sweeps 1000000000", "argument --sweeps: expected a whole number 1 .. 100"),
    ("scan_object.py --speed 1e308", "argument --speed: expected a number -100 .. 100, got '1e308'"),
    ("fit_sensor.py scans --values-per-point 0", "argument --values-per-point: expected a whole number 3 .. 64"),
    ("fit_returns.py scans --values-per-point 3", "argument --values-per-point: expected a whole number 4 .. 64"),
    ("place_objects.py --max-distance 1e308", "argument --max-distance: expected a number 0 .. 1000"),
    ("place_objects.py --max-distance=inf", "argument --max-distance: expected a finite number, got 'inf'"),
    ("place_objects.py --seed=-1", "argument --seed: expected a whole number 0 .. 2,147,483,647"),
    ("place_objects.py --objects=Pedestrian=100000000", "argument --objects: expected CLASS=N (a class and a count "
                                                        "up to 1000)"),
    ("fit_ground.py kitti --mounting-height nan", "argument --mounting-height: expected a finite number"),
    ("prepare_objects.py --size 1e308,1e308,1e308", "argument --size: expected class, keep or three sizes"),
    ("mix_bank.py --ratio 1e-320:1", "ratio '1e-320:1': at most 1000 PGT entries per GT entry"),
    ("export_bank.py --workers 0", "argument --workers: expected a whole number 1 .. 1,024"),
    ("export_bank.py --out bank", "no input: give --blend FILE, --objects DIR, or run in Blender with a .blend"),
    ("score_bank.py --limit 0", "argument --limit: expected a whole number 1 .. 10,000,000"),
    # an option read only with another: said, not silently ignored
    ("place_objects.py --scan s.bin --info l.txt --bank b.pkl --out o --map-legend legend.json",
     "--map-pose and --map-legend describe a --map image; give it"),
    ("place_objects.py --scan s.bin --info l.txt --bank b.pkl --out o --class-layers layers.json",
     "--class-layers names layers of a map: give --map or --map-polygons"),
    ("import_reconstruction.py run --masks masks --out o.blend", "--masks is read with --foreground masks; give it"),
])
def test_out_of_range_arguments_are_usage_errors(tmp_path, command, problem):
    """Every count and quantity a command takes is bounded (cli.whole, cli.within): a
    typo is exit 2 and one line, not a MemoryError, an endless run or a traceback."""
    result = run_script(*command.split(), cwd=tmp_path)
    assert result.returncode == 2 and problem in result.stderr.splitlines()[-1], result.stderr
    assert not any(tmp_path.iterdir())


OUTPUTS = [("demo.py", "--out", None), ("export_bank.py", "--out", None), ("place_objects.py", "--out", None),
           ("prepare_objects.py", "--out", None), ("reconstruct_frames.py", "--out", None),
           ("train_intensity.py", "--out", None), ("fit_returns.py", "--out", ".toml"),
           ("fit_sensor.py", "--out", ".toml"), ("import_reconstruction.py", "--out", ".blend"),
           ("mix_bank.py", "--out", ".pkl"), ("scan_object.py", "--out", ".bin"), ("train_heading.py", "--out", ".pt"),
           ("score_bank.py", "--json", ".json")]


@pytest.mark.parametrize("script, flag, suffix", OUTPUTS)
def test_an_output_that_cannot_be_made_is_a_usage_error(tmp_path, script, flag, suffix):
    """An output under a file, a file where the output folder (``suffix`` None) goes, a
    folder where the output file goes, an output file named with another suffix than
    its format's, or one in a folder that takes no new file (/proc): exit 2 and one line
    naming the path and the problem, found while the arguments are read
    (cli.OUTPUT_FOLDER, cli.output_file), before any input is read or any training run;
    nothing written."""
    (tmp_path / "a_file").write_text("x")
    (tmp_path / "a_folder").mkdir()
    cases = {tmp_path / "a_file" / "out": f"cannot be made: it lies under the file {tmp_path / 'a_file'}",
             tmp_path / "a_file": "is a file, not an output folder",
             Path("/proc/out"): "cannot be written: /proc takes no new file"} if suffix is None else {
             tmp_path / "a_file" / f"out{suffix}": f"cannot be made: it lies under the file {tmp_path / 'a_file'}",
             tmp_path / "a_folder": "is a folder; expected a file name",
             tmp_path / "out.txt": f"expected a file name ending in {suffix}",
             Path(f"/proc/out{suffix}"): "cannot be written: /proc takes no new file"}
    before = contents(tmp_path)
    for out, problem in cases.items():
        result = run_script(script, flag, out, cwd=tmp_path)
        assert result.returncode == 2, result.stderr
        assert f"argument {flag}: {out}: {problem}" in result.stderr.splitlines()[-1], result.stderr
    assert contents(tmp_path) == before


@pytest.mark.parametrize("allocate, problem", [
    (lambda: np.empty(10**14), "out of memory: Unable to allocate 728. TiB"),
    (lambda: __import__("torch").empty(10**14), "out of memory: can't allocate memory: you tried to allocate "
                                                "400000000000000 bytes"),
])
def test_memory_running_out_is_one_line_exit_1(capsys, allocate, problem):
    """numpy's MemoryError and torch's allocator failure (a RuntimeError), both real,
    raised inside a command: one line, exit 1; any other RuntimeError stays a traceback."""
    from pgt_blender.cli import run_main

    assert run_main(lambda argv: allocate(), []) == 1
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {problem}"), lines
    with pytest.raises(RuntimeError, match="a bug"):
        run_main(lambda argv: (_ for _ in ()).throw(RuntimeError("a bug")), [])


def test_a_scan_larger_than_the_memory_is_named(tmp_path):
    """An 8 GiB scan (sparse: no disk used) under a 4 GiB address-space limit."""
    import resource

    velodyne = tmp_path / "velodyne"
    velodyne.mkdir()
    scan = velodyne / "000000.bin"
    with open(scan, "wb") as stream:
        stream.truncate(8 * 2**30)
    result = run_script("fit_sensor.py", velodyne,
                        preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (4 * 2**30, 4 * 2**30)))
    assert result.returncode == 1 and result.stderr == f"error: {scan}: too large to read (8.0 GiB)\n", result.stderr


def test_ctrl_c_is_one_line_exit_130(capsys):
    from pgt_blender.cli import run_main

    def main(argv):
        raise KeyboardInterrupt

    assert run_main(main, []) == 130 and capsys.readouterr().err == "error: interrupted\n"


def test_a_warning_is_one_line(capsys):
    """A warning raised inside a command, ours or numpy's: one line ``warning: <message>``,
    not Python's two (``file:line: Category: message``, then the source line)."""
    import warnings

    from pgt_blender.cli import run_main

    def main(argv):
        warnings.warn("mesh.obj: dropped 3 zero-area faces\nof 10", stacklevel=1)
        np.log(np.zeros(1))
        return 0

    assert run_main(main, []) == 0
    assert capsys.readouterr().err.splitlines() == ["warning: mesh.obj: dropped 3 zero-area faces of 10",
                                                    "warning: divide by zero encountered in log (RuntimeWarning)"]


def _intensity_label(path):
    from pgt_blender.core.intensity.objects import kitti_label_boxes

    return kitti_label_boxes(path, path)


def _mask(path):
    from pgt_blender.core.capture.masks import read_mask

    return read_mask(path, None)


# Every reader of a file a user names: (its module, function) or a wrapper, the suffix it expects.
FILE_READERS = {
    "reconstruction": (load_reconstruction, ".ply"),
    "cameras.json": (("pgt_blender.core.importing.cameras", "read_cameras_json"), ".json"),
    "nerfstudio transform": (("pgt_blender.core.importing.nerfstudio", "read_dataparser_transform"), ".json"),
    "sensor TOML": (("pgt_blender.core.scan.sensors", "load_sensor_toml"), ".toml"),
    "Velodyne calibration": (("pgt_blender.core.scan.sensors", "read_velodyne_calibration"), ".yaml"),
    "bank config": (("pgt_blender.core.bank.config", "load_config"), ".toml"),
    "info pickle": (("pgt_blender.core.safe_pickle", "load_pickle"), ".pkl"),
    "raw float32 scan": (("pgt_blender.core.files", "read_float32_rows"), ".bin"),
    "prepared sidecar": (("pgt_blender.core.authoring.prepare", "read_sidecar"), ".json"),
    "map polygons": (("pgt_blender.core.placement.maps", "read_polygons"), ".json"),
    "KITTI label and calib": (_intensity_label, ".txt"),
    "foreground mask": (_mask, ".npy"),
}


@pytest.mark.parametrize("special", ["pipe", "device"])
@pytest.mark.parametrize("reader", list(FILE_READERS))
def test_a_pipe_or_device_named_as_a_file_is_refused_unread(tmp_path, reader, special):
    """A pipe would block the read forever and a device such as /dev/zero never ends:
    both are refused before any read (an alarm turns a blocked read into a failure; the
    device here is /dev/null, whose read would end at once, so a missed check fails
    rather than fills the memory)."""
    import importlib
    import signal

    function, suffix = FILE_READERS[reader]
    if isinstance(function, tuple):
        function = getattr(importlib.import_module(function[0]), function[1])
    path = tmp_path / f"input{suffix}"
    os.mkfifo(path) if special == "pipe" else path.symlink_to("/dev/null")

    def blocked(*_):
        raise TimeoutError(f"{reader} read the {special}")

    previous = signal.signal(signal.SIGALRM, blocked)
    signal.alarm(10)
    try:
        with pytest.raises(InputError) as error:
            function(path)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    assert error.value.path == path and "not a regular file (a pipe, socket or device)" in error.value.problem


OUTPUT_IS_INPUT = [  # (command with IN / OUT placeholders, the output): each would overwrite what it reads
    # (an output file of another suffix than its inputs' is refused by its name first: test above)
    ("scan_object.py --object IN/truck.ply --x 10 --y 0 --out IN/truck.ply", "IN/truck.ply"),
    ("fit_returns.py IN --meshes samples --sensor IN/sensor.toml --out IN/sensor.toml", "IN/sensor.toml"),
    ("score_bank.py --bank IN --real IN/real.pkl --json IN/manifest.json", "IN/manifest.json"),
    ("place_objects.py --scan IN/scan.bin --info IN/label.txt --bank IN/real.pkl --out IN", "IN"),
    ("prepare_objects.py --in IN --class truck --out IN", "IN"),
    ("train_intensity.py --real IN --out IN", "IN"),
    ("train_intensity.py --real IN/elsewhere/real.pkl --rgb car=IN/truck.ply --out IN", "IN"),
    ("export_bank.py --objects IN --out IN", "IN"),
]


@pytest.mark.parametrize("command, output", OUTPUT_IS_INPUT)
def test_an_output_that_is_or_holds_an_input_is_refused(tmp_path, command, output):
    """Checked before anything is read: one line naming the output, exit 1, the input
    as it was (the inputs here are placeholders: no reader gets to them)."""
    inputs = tmp_path / "in"
    inputs.mkdir()
    for name in ("truck.ply", "scan.bin", "real.pkl", "label.txt", "sensor.toml", "manifest.json"):
        (inputs / name).write_bytes(b"input " + name.encode())
    before = {path.name: path.read_bytes() for path in inputs.iterdir()}
    result = run_script(*command.replace("IN", str(inputs)).split())
    assert result.returncode == 1 and result.stderr.count("\n") == 1, result.stderr
    assert result.stderr.startswith(f"error: {output.replace('IN', str(inputs))}: is or holds the input ")
    assert {path.name: path.read_bytes() for path in inputs.iterdir()} == before


def test_an_output_folder_above_its_inputs_is_allowed(tmp_path):
    """``place_objects --out .`` in a KITTI folder, ``prepare_objects --in proj/recons --out
    proj``: the output folder holds the inputs only further down, where nothing is written."""
    from pgt_blender.core.files import apart_from_inputs

    scan = tmp_path / "velodyne" / "000001.bin"
    scan.parent.mkdir()
    scan.write_bytes(b"")
    apart_from_inputs(tmp_path, [scan, scan.parent])
    with pytest.raises(InputError, match="is or holds the input"):
        apart_from_inputs(scan.parent, [scan])


def test_an_empty_input_setting_is_no_input(tmp_path, monkeypatch):
    """A setting left empty ("", Blender's unset path) names no file: it must not stand for
    the working folder, which may be the output or lie in it."""
    from pgt_blender.core.files import held_input

    monkeypatch.chdir(tmp_path)
    assert held_input(tmp_path, ["", None], anywhere=True) is None
    assert held_input(tmp_path, ["", "."], anywhere=True) == "."


@pytest.mark.parametrize("reader", ["sensor", "bank config"])
def test_a_toml_file_nested_too_deeply_is_named(tmp_path, reader):
    """5,000 nested arrays exhaust the TOML parser's recursion: one line, not a traceback."""
    from pgt_blender.core.bank.config import load_config
    from pgt_blender.core.scan.sensors import load_sensor_toml

    path = tmp_path / "deep.toml"
    path.write_text("elevations_deg = " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(InputError, match="^" + str(path) + ": not a readable TOML file: nested too deeply$"):
        (load_sensor_toml if reader == "sensor" else load_config)(path)


@pytest.mark.parametrize("obj, problem", [
    ("v 0 0 0\nv 1 0 0\nv 1e200 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n", "1 vertices are NaN or infinite or lie over"),
    ("v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n", "1 vertices are NaN or infinite or lie over"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", r"the mesh is flat \(extents \[1.0, 1.0, 0.0\] m\)"),
], ids=["far vertex", "NaN vertex", "flat"])
def test_a_training_mesh_no_scan_can_use_is_named(tmp_path, obj, problem):
    """train_heading --chrono scans its meshes: a vertex 1e200 m away or NaN (which
    trimesh's processing would drop with its face, silently) and a flat mesh are named
    with their file up front, not reported later as a collapsed network."""
    from pgt_blender.core.authoring.heading_classifier import mesh_folder_meshes

    (tmp_path / "car.obj").write_text(obj)
    with pytest.raises(InputError, match=f"^{tmp_path / 'car.obj'}: {problem}"):
        mesh_folder_meshes(tmp_path)


def test_a_legal_long_output_name_is_written(tmp_path):
    """A file name of 250 bytes is legal (NAME_MAX 255) though '.<name>.partial' is not:
    the temporary takes a shorter name, and nothing of it is left."""
    from pgt_blender.core.files import atomic_output

    path = tmp_path / ("c" * 245 + ".toml")
    with atomic_output(path) as stream:
        stream.write(b"[bank]\n")
    assert path.read_bytes() == b"[bank]\n" and [p.name for p in tmp_path.iterdir()] == [path.name]
