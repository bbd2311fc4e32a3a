"""Core importers on the real data in ../shared/data and on bad input (no bpy)."""

import io
import json
import os
import shutil
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pgt_blender.core.errors import InputError
from pgt_blender.core.importing import SUPPORTED, detect_kind, load_reconstruction
from pgt_blender.core.importing.ply import read_vertices, write_ply
from pgt_blender.core.importing.points import SH_C0
from pgt_blender.core.samples import sample_vehicle


def test_colmap_statue(statue):
    recon = load_reconstruction(statue)
    assert recon.kind == "colmap" and recon.name == "colmap_statue"
    assert recon.positions.shape == (1816, 3) and recon.positions.dtype == np.float32
    assert len(recon.cameras) == 40
    # README of the data: mean track length 4.27, mean reprojection error about 1.2 px.
    assert recon.attributes["track_length"].mean() == pytest.approx(4.273, abs=1e-3)
    assert recon.attributes["reprojection_error"].mean() == pytest.approx(1.15, abs=0.05)
    assert recon.colors.shape == (1816, 4) and 0.2 < recon.colors[:, :3].mean() < 0.6
    camera = recon.cameras[0]
    assert (camera.width, camera.height, camera.model) == (800, 1200, "SIMPLE_RADIAL")
    assert camera.fx == pytest.approx(2395.646389) and (camera.cx, camera.cy) == (400.0, 600.0)
    rotation = camera.world_from_camera[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-9)


def test_colmap_cameras_reproject_the_points(statue):
    """Each 3-D point seen in an image projects (pinhole + SIMPLE_RADIAL k1) onto its
    2-D observation within its reprojection error: poses and intrinsics are right."""
    import pycolmap

    recon = load_reconstruction(statue)
    model = pycolmap.Reconstruction(str(statue))
    by_name = {view.name: view for view in recon.cameras}
    errors = {}  # point id -> its observations' pixel errors
    for image in model.images.values():
        view = by_name[image.name]
        camera_from_world = np.linalg.inv(view.world_from_camera)
        for point2d in image.points2D:
            if not point2d.has_point3D():
                continue
            x, y, z = camera_from_world[:3, :3] @ model.points3D[point2d.point3D_id].xyz + camera_from_world[:3, 3]
            u, v = x / z, y / z
            radial = 1 + view.params[3] * (u * u + v * v)
            projected = np.array([view.fx * u * radial + view.cx, view.fy * v * radial + view.cy])
            errors.setdefault(point2d.point3D_id, []).append(np.linalg.norm(projected - point2d.xy))
    assert sum(map(len, errors.values())) == 7760  # observations in the model
    # COLMAP's mean reprojection error averages each point's mean error (summary: 1.14592).
    assert np.mean([np.mean(e) for e in errors.values()]) == pytest.approx(1.14592, abs=1e-4)


def test_colmap_text_and_binary_agree(statue, tmp_path):
    text_only = tmp_path / "text"
    text_only.mkdir()
    for name in ("cameras", "images", "points3D"):
        shutil.copy(statue / f"{name}.txt", text_only)
    text, binary = load_reconstruction(text_only), load_reconstruction(statue)
    order_t, order_b = np.lexsort(text.positions.T), np.lexsort(binary.positions.T)
    np.testing.assert_allclose(text.positions[order_t], binary.positions[order_b], atol=1e-5)
    np.testing.assert_array_equal(text.attributes["track_length"][order_t],
                                  binary.attributes["track_length"][order_b])
    np.testing.assert_allclose([c.world_from_camera for c in text.cameras],
                               [c.world_from_camera for c in binary.cameras], atol=2e-5)  # .txt rounds


def test_gaussian_splat_donut(donut):
    recon = load_reconstruction(donut)
    raw = read_vertices(donut)
    assert recon.kind == "gaussian_splat" and recon.positions.shape == (45624, 3)
    assert {"opacity", "scale", "rotation", "f_dc_0", "f_dc_1", "f_dc_2"} <= set(recon.attributes)
    np.testing.assert_allclose(recon.attributes["opacity"], 1 / (1 + np.exp(-raw["opacity"])), rtol=1e-6)
    np.testing.assert_allclose(recon.attributes["scale"][:, 1], np.exp(raw["scale_1"]), rtol=1e-6)
    # Real files store unnormalised quaternions (README: lengths 0.61-2.72).
    stored = np.column_stack([raw[f"rot_{i}"] for i in range(4)])
    assert np.linalg.norm(stored, axis=1).min() < 0.7 and np.linalg.norm(stored, axis=1).max() > 2.5
    np.testing.assert_allclose(np.linalg.norm(recon.attributes["rotation"], axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(recon.attributes["rotation"] * np.linalg.norm(stored, axis=1)[:, None],
                               stored, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(recon.colors[:, 0], np.clip(0.5 + SH_C0 * raw["f_dc_0"], 0, 1), atol=1e-6)


def test_point_ply_with_colors_matches_splat_centres(donut):
    points = load_reconstruction(donut.with_name("color.ply"))
    assert points.kind == "point_ply" and points.colors is not None
    np.testing.assert_array_equal(points.positions, load_reconstruction(donut).positions)


def test_point_ply_normals_and_float_colors(tmp_path):
    rng = np.random.default_rng(3)
    xyz, normals = rng.normal(size=(2, 50, 3)).astype(np.float32)
    rgb = rng.uniform(size=(50, 3)).astype(np.float32)
    path = tmp_path / "n.ply"
    write_ply(path, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "nx": normals[:, 0], "ny": normals[:, 1],
                     "nz": normals[:, 2], "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2],
                     "confidence": np.arange(50, dtype=np.int32)}, binary=False)
    recon = load_reconstruction(path)
    np.testing.assert_allclose(recon.attributes["normal"], normals, rtol=1e-6)
    np.testing.assert_allclose(recon.colors[:, :3], rgb, rtol=1e-6)  # float colors kept as they are
    assert recon.attributes["confidence"].dtype == np.int32


def test_chrono_meshes(chrono_meshes):
    assert len(chrono_meshes) == 7
    for path in chrono_meshes:
        recon = load_reconstruction(path)
        assert recon.kind == "mesh" and len(recon.faces) > 100
        assert recon.faces.max() < len(recon.positions)
    truck = load_reconstruction(next(p for p in chrono_meshes if p.name == "truck_chassis.obj"))
    np.testing.assert_allclose(np.ptp(truck.positions, axis=0), [11.48, 3.64, 4.21], atol=0.01)


@pytest.mark.parametrize("suffix", [".stl", ".glb", ".obj", ".ply"])
def test_mesh_formats_round_trip(tmp_path, suffix):
    vehicle = sample_vehicle("bus")
    path = tmp_path / f"bus{suffix}"
    vehicle.trimesh().export(path)
    recon = load_reconstruction(path)
    assert detect_kind(path) == "mesh"
    assert len(recon.faces) == len(vehicle.faces)
    np.testing.assert_allclose(np.ptp(recon.positions, axis=0), vehicle.dims, rtol=1e-6)


# --- bad input: a one-line InputError naming the path -------------------------------------

def write_points(path, xyz, binary=True):
    write_ply(path, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}, binary=binary)
    return path


def break_truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])


BAD_INPUTS = {
    "nan coordinates": (lambda d: write_points(d / "nan.ply", np.array([[0, 0, 0], [np.nan, 1, 2.0]], np.float32)),
                        r"1 of 2 points have NaN/Inf coordinates \(first at index 1\)"),
    "inf coordinates": (lambda d: write_points(d / "inf.ply", np.array([[np.inf, 0, 0.0]]), binary=False),
                        "NaN/Inf coordinates"),
    "empty cloud": (lambda d: write_points(d / "empty.ply", np.zeros((0, 3), np.float32)), "empty cloud"),
    "unsupported format": (lambda d: (d / "scan.xyz").write_text("1 2 3\n") and d / "scan.xyz", "unsupported format '.xyz'"),
    "missing file": (lambda d: d / "nothing.ply", "no such file or folder"),
    "corrupt mesh": (lambda d: (d / "bad.glb").write_bytes(b"glTF\x02\x00\x00\x00garbage") and d / "bad.glb",
                     "could not be read as a mesh"),
    "mesh without faces": (lambda d: (d / "v.obj").write_text("v 0 0 0\nv 1 0 0\n") and d / "v.obj", "no faces"),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input(tmp_path, case):
    make, problem = BAD_INPUTS[case]
    path = make(tmp_path)
    with pytest.raises(InputError, match=problem) as error:
        load_reconstruction(path)
    assert str(error.value).startswith(f"{path}: ") and "\n" not in str(error.value)


def test_truncated_gaussian_splat(donut, tmp_path):
    path = tmp_path / "splat.ply"
    shutil.copy(donut, path)
    break_truncate(path)
    with pytest.raises(InputError, match=f"{path}: truncated: the header declares 45624 vertex"):
        load_reconstruction(path)


def test_splat_with_wrong_sh_count(donut, tmp_path):
    columns = {name: values[:10] for name, values in read_vertices(donut).items()}
    columns.update({f"f_rest_{i}": np.zeros(10, np.float32) for i in range(5)})
    write_ply(tmp_path / "sh.ply", columns)
    with pytest.raises(InputError, match="5 f_rest_\\* fields"):
        load_reconstruction(tmp_path / "sh.ply")


@pytest.mark.parametrize("field, value", [("scale_1", np.nan), ("opacity", np.inf), ("f_dc_0", -np.inf)])
def test_splats_with_nan_or_inf_fields_are_refused(donut, tmp_path, field, value):
    columns = {name: values[:10].copy() for name, values in read_vertices(donut).items()}
    columns[field][3] = value
    write_ply(tmp_path / "splat.ply", columns)
    with pytest.raises(InputError, match=rf"1 of 10 splats have NaN or Inf values in {field} \(1\)"):
        load_reconstruction(tmp_path / "splat.ply")


def test_ascii_colors_out_of_their_type_are_refused(tmp_path):
    path = tmp_path / "colors.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
                    "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
                    "0 0 0 300 0 0\n1 1 1 0 0 0\n")
    with pytest.raises(InputError, match=r"property red \(uint8\) holds 300 in row 1: not a uint8 value"):
        load_reconstruction(path)  # it wrapped to 44 before


def test_kind_mismatch(donut, tmp_path):
    with pytest.raises(InputError, match="expected Gaussian splats but this is a point cloud"):
        load_reconstruction(donut.with_name("color.ply"), kind="gaussian_splat")
    with pytest.raises(InputError, match="expected a point cloud but this is a folder$"):
        load_reconstruction(tmp_path, kind="point_ply")  # not "a colmap": any folder would be one


def test_an_undecodable_file_name_is_printable_in_the_error(tmp_path):
    """A name that is not UTF-8 (bytes 0xff 0xfe) reaches Blender's reports escaped."""
    path = Path(os.fsdecode(bytes(tmp_path) + b"/bad\xff\xfe.xyz"))
    path.write_text("")
    error = pytest.raises(InputError, load_reconstruction, path).value
    assert str(error).encode("utf-8").endswith(b"bad\\udcff\\udcfe.xyz: unsupported format '.xyz' (supported: "
                                               + SUPPORTED.encode() + b")")


def test_a_line_break_in_a_file_name_keeps_the_error_on_one_line(tmp_path):
    path = tmp_path / "two\nlines.xyz"
    path.write_text("")
    error = pytest.raises(InputError, load_reconstruction, path).value
    assert "\n" not in str(error) and str(error).startswith(f"{tmp_path}/two\\nlines.xyz: unsupported format")


@pytest.mark.parametrize("missing", ["points3D.bin", "cameras.bin"])
def test_colmap_missing_file(statue_copy, missing):
    for text in statue_copy.glob("*.txt"):
        text.unlink()
    (statue_copy / missing).unlink()
    with pytest.raises(InputError, match=f"COLMAP model is missing {missing}"):
        load_reconstruction(statue_copy)


def _cut(fraction):
    def damage(path):
        path.write_bytes(path.read_bytes()[:int(path.stat().st_size * fraction)])
    return damage


def _huge_track(path):  # the first point's track length (after id, xyz, rgb, error) says 2**40
    data = bytearray(path.read_bytes())
    data[8 + 8 + 24 + 3 + 8:8 + 8 + 24 + 3 + 8 + 8] = (2**40).to_bytes(8, "little")
    path.write_bytes(bytes(data))


def _trailing(path):
    path.write_bytes(path.read_bytes() + b"\0" * 5)


@pytest.mark.parametrize("name, damage, problem", [
    ("points3D.bin", _cut(0.5), "claims 1,816 points but only"),  # was a 17 GB allocation in pycolmap
    ("points3D.bin", _cut(0.9), "truncated"),
    ("points3D.bin", _huge_track, "claims 1,099,511,627,776 track elements"),
    ("images.bin", _cut(0.7), "truncated"),
    ("cameras.bin", _trailing, "5 bytes after the last record"),
])
def test_colmap_damaged_binaries_are_refused_before_pycolmap_reads_them(statue_copy, name, damage, problem):
    for text in statue_copy.glob("*.txt"):
        text.unlink()
    damage(statue_copy / name)
    with pytest.raises(InputError) as caught:
        load_reconstruction(statue_copy)
    assert caught.value.path == statue_copy / name and problem in str(caught.value)


# --- malformed inputs found by fuzzing the importers: each (folder, donut, statue) ->
# (the input, the path the error names) ----------------------------------------------------

def _splat(change):
    """The first 10 donut splats with ``change(columns)`` applied."""
    def build(folder, donut, statue):
        columns = {name: values[:10].copy() for name, values in read_vertices(donut).items()}
        change(columns)
        write_ply(folder / "splat.ply", columns)
        return folder / "splat.ply", folder / "splat.ply"
    return build


def _file(name, content: bytes):
    def build(folder, donut, statue):
        (folder / name).write_bytes(content)
        return folder / name, folder / name
    return build


def _fifo(folder, donut, statue):
    os.mkfifo(folder / "cloud.ply")  # reading it would wait for a writer forever
    return folder / "cloud.ply", folder / "cloud.ply"


CAMERA = {"img_name": "a", "width": 8, "height": 8, "fx": 5, "fy": 5, "position": [0, 0, 0],
          "rotation": np.eye(3).tolist()}


def _cameras_json(text: str):
    """A splat with ``text`` as the cameras.json beside it."""
    def build(folder, donut, statue):
        splat, _ = _splat(lambda columns: None)(folder, donut, statue)
        (folder / "cameras.json").write_text(text)
        return splat, folder / "cameras.json"
    return build


def _svox2(change):
    """A 2^3 svox2 checkpoint with ``change(arrays)`` applied."""
    def build(folder, donut, statue):
        arrays = {"links": np.arange(8, dtype=np.int32).reshape(2, 2, 2), "density_data": np.ones((8, 1), np.float32),
                  "sh_data": np.zeros((8, 3), np.float32), "basis_type": np.array(1)}
        change(arrays)
        np.savez(folder / "grid.npz", **arrays)
        return folder / "grid.npz", folder / "grid.npz"
    return build


def _npz_member_claiming_petabytes(folder, donut, statue):
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<i4", "fortran_order": False, "shape": (10**5,) * 3})
    with zipfile.ZipFile(folder / "grid.npz", "w") as archive:
        archive.writestr("links.npy", header.getvalue() + bytes(64))
    return folder / "grid.npz", folder / "grid.npz"


def _colmap(file: str, change):
    """A binary copy of the statue model with ``change(path of file)`` applied; -> (model, model / file)."""
    def build(folder, donut, statue):
        model = Path(shutil.copytree(statue, folder / "model"))
        for text in model.glob("*.txt"):
            text.unlink()
        change(model / file)
        return model, model / file
    return build


def _packed(offset: int, layout: str, value):
    def change(path):
        data = bytearray(path.read_bytes())
        struct.pack_into("<" + layout, data, offset, value)
        path.write_bytes(bytes(data))
    return change


def _replaced_by(make):
    def change(path):
        path.unlink()
        make(path)
    return change


def _named_folder(build):
    """``build`` whose error names the model folder (a camera's problem) rather than the file."""
    def named(folder, donut, statue):
        model, _ = build(folder, donut, statue)
        return model, model
    return named


# Byte offsets in the statue's binaries: cameras.bin (count, then id i32, model i32,
# width u64, height u64, SIMPLE_RADIAL f cx cy k), images.bin (count, id u32, qvec 4d,
# tvec 3d), points3D.bin (count, id u64, xyz 3d, rgb 3B, error d).
MALFORMED = {
    "PLY element with rows but no properties": (
        _file("cloud.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nend_header\n"),
        "PLY element 'vertex' declares 1 rows but no properties"),
    "PLY that is a pipe": (_fifo, "not a regular file (a pipe, socket or device)"),
    "splat f_rest_ field not numbered": (_splat(lambda c: c.update(f_rest_a=c["x"])), "1 f_rest_* fields"),
    "splat log-scale overflowing": (_splat(lambda c: c["scale_0"].__setitem__(3, 100.0)),
                                    "1 splats have a log-scale beyond float32"),
    "splat f_dc beyond float32 (a double property)": (_splat(lambda c: c.update(f_dc_0=np.full(10, 1e300))),
                                                      "10 of 10 splats have NaN or Inf values in f_dc_0 (10)"),
    "splat NaN normal": (_splat(lambda c: c.update(nx=np.where(np.arange(10) == 3, np.nan, 1).astype(np.float32),
                                                   ny=np.zeros(10, np.float32), nz=np.zeros(10, np.float32))),
                         "NaN or Inf values in nx (1)"),
    "point PLY with float colors written 0..255": (
        _file("cloud.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                           b"property float z\nproperty float red\nproperty float green\nproperty float blue\n"
                           b"end_header\n0 0 0 0.5 0.5 0.5\n1 0 0 200 10 0\n"),
        "1 of 2 points have colors outside float 0..1 in 'red' (values 0.5 to 200)"),
    "splat rgb as ushort": (_splat(lambda c: [c.pop(f"f_dc_{i}") for i in range(3)] and c.update(
        red=np.full(10, 60000, np.uint16), green=np.zeros(10, np.uint16), blue=np.zeros(10, np.uint16))),
        "10 of 10 points have colors outside uchar 0..255 in 'red'"),
    "point PLY extra property beyond int32": (
        _file("cloud.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                           b"property float z\nproperty uint label\nend_header\n0 0 0 7\n1 0 0 4000000000\n"),
        "vertex property 'label' holds 4000000000 in row 2: beyond a Blender int32 attribute"),
    "point PLY extra double beyond float32": (
        _file("cloud.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                           b"property float z\nproperty double weight\nend_header\n0 0 0 1e300\n1 0 0 1\n"),
        "vertex property 'weight' holds 1e+300 in row 1: beyond a Blender float32 attribute"),
    "OBJ vertex with a vertical tab": (_file("v.obj", b"v 0 0 0\nv 0 \x0b 1\nf 1 1 2\n"),
                                       "vertices are not 3-D coordinates"),
    "OBJ face index 0": (_file("zero.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n# f 0 1 2 is not read\nf 1/1 2/0 3/3\n"),
                         "line 5: a face index is 0; OBJ indices count from 1"),  # trimesh: the last vertex
    "OBJ face index past the vertices": (_file("past.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n"),
                                        "a face refers to a vertex the file does not have"),
    "cameras.json nested 100,000 deep": (_cameras_json("[" * 100_000), "RecursionError"),
    "cameras.json width Infinity": (_cameras_json(json.dumps([{**CAMERA, "width": float("inf")}])),
                                    "camera 0: width, height, fx, fy must be numbers"),
    "cameras.json width 1e20 px": (_cameras_json(json.dumps([{**CAMERA, "width": 10**20}])),
                                   "width and height must be whole numbers of pixels, 1 .. 65536"),
    "cameras.json fx of 400 digits": (_cameras_json(json.dumps([{**CAMERA, "fx": 10**400}])),
                                      "camera 0: width, height, fx, fy must be numbers"),
    "npz that is a .npy": (_file("grid.npz", b"\x93NUMPY\x01\x00v\x00{'descr': '<f8', 'fortran_order': False, "
                                             b"'shape': (10**9,), }" + b" " * 60 + b"\n"),
                           "not an .npz archive"),
    "npz basis_type a vector": (_svox2(lambda a: a.update(basis_type=np.array([1, 1]))),
                                "basis_type must be one integer, not int64 (2,)"),
    "npz basis_type a string": (_svox2(lambda a: a.update(basis_type=np.array("sh"))), "basis_type must be one integer"),
    "npz density as text": (_svox2(lambda a: a.update(density_data=np.full((8, 1), "x"))),
                            "arrays that must hold numbers do not: density_data (<U1)"),
    "npz old data array 0-d": (_svox2(lambda a: [a.pop("density_data"), a.pop("sh_data"), a.update(data=np.array(1.0))]),
                               "data () must be (C, 1 + 3 K)"),
    "npz member claiming petabytes": (_npz_member_claiming_petabytes,
                                      "member links.npy declares (100000, 100000, 100000) int32"),
    "COLMAP focal length -inf": (_named_folder(_colmap("cameras.bin", _packed(32, "d", -np.inf))),
                                 "focal lengths -inf, -inf px must be positive numbers up to 1e+08"),
    "COLMAP focal length 1e300": (_named_folder(_colmap("cameras.bin", _packed(32, "d", 1e300))),
                                  "focal lengths 1e+300, 1e+300 px must be positive numbers up to 1e+08"),
    "COLMAP principal point NaN": (_named_folder(_colmap("cameras.bin", _packed(40, "d", np.nan))),
                                   "principal point nan"),
    "COLMAP image width 0": (_named_folder(_colmap("cameras.bin", _packed(16, "Q", 0))), "image size 0 x"),
    "COLMAP translation NaN": (_named_folder(_colmap("images.bin", _packed(60, "d", np.nan))), "its pose is not finite"),
    "COLMAP translation beyond float32": (_named_folder(_colmap("images.bin", _packed(60, "d", 1e300))),
                                          "its pose is not finite (as float32)"),
    "COLMAP reprojection error overflowing float32": (_colmap("points3D.bin", _packed(43, "d", 1e308)),
                                                      "1 of 1816 points have a reprojection error that is NaN or beyond float32"),
    "COLMAP cameras.bin a folder": (_colmap("cameras.bin", _replaced_by(Path.mkdir)), "is a folder; expected a file"),
    "COLMAP images.bin a pipe": (_colmap("images.bin", _replaced_by(os.mkfifo)), "not a regular file"),
    "COLMAP points3D.bin a link to a device": (_colmap("points3D.bin", _replaced_by(lambda p: p.symlink_to("/dev/null"))),
                                               "not a regular file"),  # /dev/zero would never end
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_input_is_one_input_error_naming_the_file(tmp_path, donut, statue, case):
    build, problem = MALFORMED[case]
    path, named = build(tmp_path, donut, statue)
    with pytest.raises(InputError) as error:
        load_reconstruction(path)
    assert error.value.path == named and problem in error.value.problem, str(error.value)


def test_colmap_folder_without_model(statue, tmp_path):
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    with pytest.raises(InputError, match=r"no COLMAP model files .* \(try its sparse/0 sub-folder\)"):
        load_reconstruction(tmp_path)


def test_material_meshes_carry_colors_and_glass(shared_data, tmp_path):
    from pgt_blender.core.importing.mesh import read_material_mesh

    sedan = read_material_mesh(shared_data / "chrono_vehicles/data/vehicle/sedan/sedan_chassis_vis.obj")
    assert len(sedan.faces) == len(sedan.face_srgb) == len(sedan.see_through) > 30000
    assert 0 < sedan.see_through.mean() < 0.5  # windows and lights (dissolve d < 1), not the body
    red = np.isclose(sedan.face_srgb, np.array([0.400594, 0.022045, 0.003914]), atol=1 / 255).all(axis=1)
    assert red.any() and not sedan.see_through[red].any()  # the body paint (Material.001, d 1)
    (tmp_path / "part.obj").write_text("mtllib part.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl paint\nf 1 2 3\n")
    (tmp_path / "part.mtl").write_text("newmtl paint\nKd 0.5 0.5 0.5\nd half\n")
    with pytest.raises(InputError, match="part.mtl: material paint: dissolve 'd' must be a number"):
        read_material_mesh(tmp_path / "part.obj")
    (tmp_path / "part.mtl").write_text("newmtl paint\nKd 0.5 0.5 0.5\n")
    plain = read_material_mesh(tmp_path / "part.obj")
    assert plain.faces.tolist() == [[0, 1, 2]] and not plain.see_through.any()
