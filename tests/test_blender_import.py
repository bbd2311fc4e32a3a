"""The Blender layer on real headless bpy: operators, menus, panel, bulk data, cameras."""

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from pgt_blender.core.importing import load_reconstruction
from pgt_blender.core.importing.ply import read_vertices, write_ply
from pgt_blender.core.samples import sample_vehicle

from .conftest import datablock_counts

bpy = pytest.importorskip("bpy")


def attribute_values(mesh, name, width):
    attribute = mesh.attributes[name]
    field = "vector" if attribute.data_type.startswith("FLOAT_VECTOR") or attribute.data_type == "FLOAT2" else "value"
    if attribute.data_type == "BYTE_COLOR":
        field = "color_srgb"
    values = np.empty(len(attribute.data) * width, np.int32 if attribute.data_type == "INT" else np.float32)
    attribute.data.foreach_get(field, values)
    return values.reshape(len(attribute.data), width) if width > 1 else values


def test_colmap_operator(scene, statue):
    assert bpy.ops.import_scene.pgt_colmap(directory=str(statue)) == {"FINISHED"}
    obj = bpy.context.active_object
    assert obj.name == "colmap_statue" and len(obj.data.vertices) == 1816
    assert obj.pgt.source_kind == "colmap" and obj.pgt.source_path == str(statue)
    assert obj.pgt.source_sha256 == load_reconstruction(statue).sha256 and obj.pgt.class_name == ""
    cameras = [child for child in obj.children if child.type == "CAMERA"]
    assert len(cameras) == 40 and len(bpy.data.cameras) == 40
    recon = load_reconstruction(statue)
    positions = attribute_values(obj.data, "position", 3)
    np.testing.assert_array_equal(positions, recon.positions)
    np.testing.assert_array_equal(attribute_values(obj.data, "track_length", 1), recon.attributes["track_length"])
    np.testing.assert_allclose(attribute_values(obj.data, "Col", 4), recon.colors, atol=1 / 255)
    assert obj.data.color_attributes.active_color.name == "Col"


def test_colmap_cameras_see_what_the_photos_saw(scene, statue):
    """Blender's own projection through each imported camera equals COLMAP's pinhole
    projection (u = fx x / z + cx, v = fy y / z + cy) of the points."""
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    bpy.ops.import_scene.pgt_colmap(directory=str(statue))
    recon = load_reconstruction(statue)
    assert (scene.render.resolution_x, scene.render.resolution_y) == (800, 1200)
    for view in recon.cameras[::8]:
        camera = bpy.data.objects[view.name]
        camera_from_world = np.linalg.inv(view.world_from_camera)
        local = recon.positions[::50].astype(np.float64) @ camera_from_world[:3, :3].T + camera_from_world[:3, 3]
        local = local[local[:, 2] > 0]
        expected = np.column_stack([view.fx * local[:, 0] / local[:, 2] + view.cx,
                                    view.fy * local[:, 1] / local[:, 2] + view.cy])
        world = local @ view.world_from_camera[:3, :3].T + view.world_from_camera[:3, 3]
        ndc = np.array([world_to_camera_view(scene, camera, Vector(p))[:] for p in world])
        blender = np.column_stack([ndc[:, 0] * view.width, (1 - ndc[:, 1]) * view.height])
        np.testing.assert_allclose(blender, expected, atol=1e-3)
        np.testing.assert_allclose(ndc[:, 2], local[:, 2], rtol=1e-5)  # depth along the optical axis


def test_point_clouds_are_drawn_as_points(scene, donut):
    """Loose vertices are invisible in Object Mode: the evaluated object is a point cloud."""
    bpy.ops.import_scene.pgt_gaussian_splat(filepath=str(donut))
    obj = bpy.context.active_object
    assert [m.type for m in obj.modifiers] == ["NODES"] and obj.modifiers[0].node_group.name == "PGT Points"
    evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    if hasattr(evaluated, "evaluated_geometry"):  # Blender 4.4+
        assert len(evaluated.evaluated_geometry().pointcloud.points) == 45624
    bpy.ops.import_scene.pgt_gaussian_splat(filepath=str(donut))
    assert len(bpy.data.node_groups) == 1  # one shared group


def test_a_file_name_that_is_not_utf8_imports_and_reports(scene, donut, tmp_path, capfd):
    """Bytes 0xff 0xfe in a file name: Blender names and reports take only UTF-8, so both
    show the bytes escaped."""
    path = Path(os.fsdecode(bytes(tmp_path) + b"/bad\xff\xfe.ply"))
    path.write_bytes(donut.read_bytes())
    assert bpy.ops.import_scene.pgt_gaussian_splat(filepath=str(path)) == {"FINISHED"}
    assert bpy.context.active_object.name == "bad\\udcff\\udcfe" and "Imported bad\\udcff" in capfd.readouterr().out
    folder = Path(os.fsdecode(bytes(tmp_path) + b"/d\xff"))
    folder.mkdir()
    with pytest.raises(RuntimeError, match=r"d\\udcff: no COLMAP model files"):
        bpy.ops.import_scene.pgt_colmap(directory=str(folder))


def test_gaussian_splat_operator(scene, donut):
    assert bpy.ops.import_scene.pgt_gaussian_splat(filepath=str(donut)) == {"FINISHED"}
    mesh = bpy.context.active_object.data
    recon = load_reconstruction(donut)
    assert len(mesh.vertices) == 45624
    assert mesh.attributes["opacity"].data_type == "FLOAT"
    assert mesh.attributes["scale"].data_type == "FLOAT_VECTOR"
    assert mesh.attributes["rotation"].data_type == "QUATERNION"
    np.testing.assert_array_equal(attribute_values(mesh, "rotation", 4), recon.attributes["rotation"])
    np.testing.assert_array_equal(attribute_values(mesh, "scale", 3), recon.attributes["scale"])
    np.testing.assert_array_equal(attribute_values(mesh, "opacity", 1), recon.attributes["opacity"])


def capture_run(folder, views=8):
    """A 3DGS output folder of the table scene (SH degree 1), its cameras and ball masks (.npy)."""
    from pgt_blender.core.capture import samples

    scene_data = samples.table_scene(np.random.default_rng(0), 3000, 3000, 500)
    cameras = samples.orbit_cameras(views, 4.0, 30.0, target=scene_data["ball_centre"])
    count = len(scene_data["positions"])
    coefficients = np.random.default_rng(1).uniform(-0.2, 0.2, (count, 3, 4)).astype(np.float32)
    samples.write_3dgs_run(folder / "run", samples.splat_columns(scene_data["positions"], coefficients,
                                                                 np.full(count, 0.9), np.full((count, 3), 0.01)), cameras)
    masks = folder / "masks"
    masks.mkdir()
    for view, mask in zip(cameras, samples.ball_masks(cameras, scene_data["ball_centre"], 0.5)):
        np.save(masks / view.name.replace(".png", ".npy"), mask)
    return folder / "run" / "point_cloud" / "iteration_30000" / "point_cloud.ply", masks


def test_gaussian_splat_operator_with_view_color_and_masks(scene, tmp_path):
    """The operator's capture settings give the core's result: view colors, the view_hit
    BOOLEAN attribute, only the foreground, the training cameras, the report."""
    import json

    from pgt_blender.core.capture import CaptureOptions

    ply, masks = capture_run(tmp_path)
    assert bpy.ops.import_scene.pgt_gaussian_splat(filepath=str(ply), view_color=True, foreground="masks",
                                                   masks_directory=str(masks), with_cameras=True) == {"FINISHED"}
    obj = bpy.context.active_object
    recon = load_reconstruction(ply, capture=CaptureOptions(view_color=True, foreground="masks", masks=masks))
    assert obj.name == "run" and len(obj.data.vertices) == len(recon.positions) < 6500
    assert obj.data.attributes["view_hit"].data_type == "BOOLEAN"
    hit = np.zeros(len(recon.positions), bool)
    obj.data.attributes["view_hit"].data.foreach_get("value", hit)
    np.testing.assert_array_equal(hit, recon.attributes["view_hit"])
    np.testing.assert_allclose(attribute_values(obj.data, "Col", 4), recon.colors, atol=1 / 255)
    assert sum(child.type == "CAMERA" for child in obj.children) == 8
    report = json.loads(obj["pgt_capture"])
    assert report["foreground"] == recon.capture["foreground"]
    assert report["view_color"]["hit"] == recon.capture["view_color"]["hit"] >= hit.sum()  # counted before the cut


def test_plenoxels_operator(scene, tmp_path):
    from pgt_blender.core.capture import samples

    links = np.arange(27, dtype=np.int32).reshape(3, 3, 3)
    samples.write_svox2(tmp_path / "grid.npz", links, np.linspace(-2, 20, 27), np.zeros((27, 27)), [1, 2, 3], [0, 0, 1])
    assert bpy.ops.import_scene.pgt_plenoxels(filepath=str(tmp_path / "grid.npz")) == {"FINISHED"}
    obj = bpy.context.active_object
    recon = load_reconstruction(tmp_path / "grid.npz")
    assert obj.pgt.source_kind == "plenoxels" and len(obj.data.vertices) == len(recon.positions) == 24
    np.testing.assert_array_equal(attribute_values(obj.data, "position", 3), recon.positions)
    np.testing.assert_array_equal(attribute_values(obj.data, "density", 1), recon.attributes["density"])
    np.testing.assert_array_equal(attribute_values(obj.data, "opacity", 1), recon.attributes["opacity"])


def test_point_cloud_operator_keeps_normals(scene, tmp_path):
    xyz = np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32)
    path = tmp_path / "cloud.ply"
    write_ply(path, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                     "nx": xyz[:, 2], "ny": xyz[:, 0], "nz": xyz[:, 1]}, binary=False)
    assert bpy.ops.import_scene.pgt_point_cloud(filepath=str(path)) == {"FINISHED"}
    mesh = bpy.context.active_object.data
    np.testing.assert_array_equal(attribute_values(mesh, "normal", 3), xyz[:, [2, 0, 1]])
    assert "Col" not in mesh.attributes


@pytest.mark.parametrize("suffix", [".obj", ".glb", ".stl"])
def test_mesh_operator(scene, tmp_path, suffix):
    vehicle = sample_vehicle("truck")
    path = tmp_path / f"truck{suffix}"
    vehicle.trimesh().export(path)
    assert bpy.ops.import_scene.pgt_mesh(filepath=str(path)) == {"FINISHED"}
    mesh = bpy.context.active_object.data
    assert len(mesh.polygons) == len(vehicle.faces)
    assert all(p.loop_total == 3 for p in mesh.polygons)
    assert not mesh.validate()  # nothing to fix
    corners = np.empty(len(mesh.loops), np.int32)
    mesh.loops.foreach_get("vertex_index", corners)
    np.testing.assert_array_equal(corners.reshape(-1, 3), load_reconstruction(path).faces)


def test_chrono_mesh_operator(scene, chrono_meshes):
    path = next(p for p in chrono_meshes if p.name == "CityBus_Vis.obj")
    assert bpy.ops.import_scene.pgt_mesh(filepath=str(path)) == {"FINISHED"}
    assert bpy.context.active_object.pgt.source_kind == "mesh"
    assert len(bpy.context.active_object.data.polygons) == len(load_reconstruction(path).faces)


def test_add_sample_operator(scene, capfd):
    assert bpy.ops.object.pgt_add_sample(class_name="trailer", seed=2, points=3000) == {"FINISHED"}
    obj = bpy.context.active_object
    assert obj.name == "sample_trailer_seed2" and len(obj.data.vertices) == 3000
    assert "Added sample_trailer_seed2: 3,000 points of a sample trailer, " in capfd.readouterr().out


# --- bad input: ERROR report, CANCELLED, scene untouched ----------------------------------
# bpy.ops raises RuntimeError carrying the report when an operator reports an ERROR;
# the importers only do so on the path that returns {'CANCELLED'}.

def broken_inputs(tmp_path, statue, donut):
    nan = tmp_path / "nan.ply"
    write_ply(nan, {"x": np.array([0, np.nan], np.float32), "y": np.zeros(2, np.float32), "z": np.zeros(2, np.float32)})
    truncated = tmp_path / "truncated.ply"
    truncated.write_bytes(donut.read_bytes()[:100000])
    mismatched = tmp_path / "mismatched.ply"
    mismatched.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                          "property float z\nend_header\n0 0 0\n1 1 1\n")
    empty = tmp_path / "empty.ply"
    empty.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                     "property float z\nend_header\n")
    no_points = shutil.copytree(statue, tmp_path / "model")
    for name in ("points3D.bin", "points3D.txt"):
        (no_points / name).unlink()
    unsupported = tmp_path / "scan.las"
    unsupported.write_bytes(b"LASF")
    corrupt = tmp_path / "corrupt.stl"
    corrupt.write_bytes(b"solid x\nfacet normal 0 0 nan\nendsolid\n")
    clashes = {}
    for name in ("position", "sharp_face"):  # Blender's own attribute names: refused, not renamed .001
        clashes[name] = tmp_path / f"{name}.ply"
        write_ply(clashes[name], {axis: np.zeros(2, np.float32) for axis in ("x", "y", "z", name)})
    long_name = tmp_path / "long_name.ply"  # longer than an attribute name Blender keeps
    write_ply(long_name, {axis: np.zeros(2, np.float32) for axis in ("x", "y", "z", "a" * 70 + "1")})
    no_opacity = tmp_path / "no_opacity.ply"
    write_ply(no_opacity, {name: values[:5] for name, values in read_vertices(donut).items() if name != "opacity"})
    splats, masks = capture_run(tmp_path)
    (masks / "view_003.npy").unlink()
    no_links = tmp_path / "no_links.npz"
    np.savez(no_links, density_data=np.zeros((1, 1)), sh_data=np.zeros((1, 3)))
    bad_cameras = tmp_path / "cameras.json"
    bad_cameras.write_text('[{"img_name": "a", "width": 10}]')
    half_good = tmp_path / "half_good"  # a.ply is built, then Blender refuses b.ply: a goes too
    half_good.mkdir()
    write_ply(half_good / "a.ply", {axis: np.arange(3, dtype=np.float32) for axis in ("x", "y", "z")})
    shutil.copy(clashes["sharp_face"], half_good / "b.ply")
    return [
        ("pgt_folder", {"directory": str(half_good)}, half_good / "b.ply", "property 'sharp_face' has the name"),
        ("pgt_gaussian_splat", {"filepath": str(splats), "foreground": "masks", "masks_directory": str(masks)},
         masks, "no mask for 1 of 8 images (view_003)"),
        ("pgt_gaussian_splat", {"filepath": str(splats), "foreground": "masks"}, splats,
         "Foreground Masks needs a masks folder"),
        ("pgt_gaussian_splat", {"filepath": str(splats), "view_color": True, "cameras_file": str(bad_cameras)},
         bad_cameras, "camera 0 has no height, position, rotation, fx, fy"),
        ("pgt_plenoxels", {"filepath": str(no_links)}, no_links, "no links"),
        *[("pgt_point_cloud", {"filepath": str(path)}, path, f"property '{name}' has the name")
          for name, path in clashes.items()],
        ("pgt_point_cloud", {"filepath": str(long_name)}, long_name, "is 71 bytes long, too long for a Blender"),
        ("pgt_gaussian_splat", {"filepath": str(no_opacity)}, no_opacity, "missing vertex properties opacity"),
        ("pgt_point_cloud", {"filepath": str(nan)}, nan, "NaN/Inf coordinates"),
        ("pgt_gaussian_splat", {"filepath": str(truncated)}, truncated, "truncated"),
        ("pgt_point_cloud", {"filepath": str(mismatched)}, mismatched, "declares 3 data rows"),
        ("pgt_point_cloud", {"filepath": str(empty)}, empty, "empty cloud"),
        ("pgt_colmap", {"directory": str(no_points)}, no_points, "missing points3D.bin"),
        ("pgt_mesh", {"filepath": str(unsupported)}, unsupported, "unsupported format"),
        ("pgt_mesh", {"filepath": str(corrupt)}, corrupt, "mesh"),
        ("pgt_gaussian_splat", {"filepath": str(donut.with_name("color.ply"))}, donut.with_name("color.ply"),
         "expected Gaussian splats but this is a point cloud"),
    ]


def test_bad_input_is_cancelled_and_leaves_nothing(scene, tmp_path, statue, donut):
    bpy.ops.import_scene.pgt_colmap(directory=str(statue))  # something already in the scene
    before = datablock_counts(bpy)
    for operator, arguments, path, problem in broken_inputs(tmp_path, statue, donut):
        with pytest.raises(RuntimeError) as error:
            getattr(bpy.ops.import_scene, operator)(**arguments)
        message = str(error.value).removeprefix("Error: ").strip()
        assert message.startswith(f"{path}: ") and problem in message and "\n" not in message
        assert datablock_counts(bpy) == before, operator


def test_failure_while_building_removes_partial_data(scene, statue):
    """A failure after some Blender data exists (here: a camera that cannot be made)
    removes the points object, its mesh, its display node group and the cameras already built."""
    from pgt_blender.blender import objects

    recon = load_reconstruction(statue)
    recon.cameras[5].name = 7  # not a string: no camera can take it as a name
    before = datablock_counts(bpy)
    with pytest.raises(AttributeError):
        objects.add_reconstruction(scene, recon)
    assert datablock_counts(bpy) == before


# --- registration, menus, panel -----------------------------------------------------------

def test_menu_panel_and_properties_registered(registered):
    from pgt_blender.blender.ui import menu_import

    assert menu_import in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize()
    assert hasattr(bpy.types, "VIEW3D_PT_pgt_import")
    for name in ("pgt_colmap", "pgt_gaussian_splat", "pgt_plenoxels", "pgt_point_cloud", "pgt_mesh"):
        assert hasattr(bpy.ops.import_scene, name)
    assert {"source_path", "source_kind", "source_sha256", "class_name", "object_from_source"} <= set(
        bpy.types.Object.bl_rna.properties["pgt"].fixed_type.properties.keys())


def test_register_unregister_twice(registered):
    import pgt_blender

    for _ in range(2):
        pgt_blender.unregister()
        assert not hasattr(bpy.types.Object, "pgt") and not hasattr(bpy.types, "VIEW3D_PT_pgt_import")
        pgt_blender.register()
        assert hasattr(bpy.types.Object, "pgt") and hasattr(bpy.types, "VIEW3D_PT_pgt_import")


def test_importers_without_a_file_say_so(scene):
    """Run with nothing picked (a script, or Redo), each importer names what is missing."""
    before = datablock_counts(bpy)
    for name, missing in (("pgt_colmap", "model folder"), ("pgt_gaussian_splat", "file"), ("pgt_plenoxels", "file"),
                          ("pgt_point_cloud", "file"), ("pgt_mesh", "file"), ("pgt_folder", "folder"),
                          ("pgt_placed_scene", "placement folder")):
        with pytest.raises(RuntimeError, match=f"Import .*: no {missing} chosen$"):
            getattr(bpy.ops.import_scene, name)()
    assert datablock_counts(bpy) == before


def test_every_property_has_a_tooltip(registered):
    """Each visible property of the add-on's settings, preferences and operators has a
    description, Blender's tooltip (HIDDEN ones are never shown)."""
    from pgt_blender.blender import operators, properties

    def own(struct, base):  # the add-on's properties, not Blender's inherited ones
        return [prop for prop in struct.properties if prop.identifier not in base.properties.keys()]

    props = {f"{cls.__name__}.{prop.identifier}": prop for cls in properties.classes
             for prop in own(cls.bl_rna, cls.bl_rna.base)}
    for cls in operators.classes:
        category, name = cls.bl_idname.split(".")
        rna = getattr(getattr(bpy.ops, category), name).get_rna_type()
        props.update({f"{cls.bl_idname}.{prop.identifier}": prop for prop in rna.properties
                      if prop.identifier != "rna_type"})
    assert len(props) > 30
    missing = [name for name, prop in props.items() if not prop.is_hidden and not prop.description]
    assert missing == []


def test_blend_relative_paths_are_accepted(scene):
    """"//" paths (relative to the .blend) are set without a warning on every version."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene.pgt_scan.sensor_file = "//sensors/custom.toml"
        scene.pgt_authoring.checkpoint = "//heading.pt"
