"""The Scan section in real headless Blender, against the core scan on the same geometry."""

import math
import re
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from pgt_blender.core.reconstruction import Reconstruction
from pgt_blender.core.boxes import centred_bounds
from pgt_blender.core.scan.raycast import ScanOptions, cast_rays, placement
from pgt_blender.core.scan.returns import RETURN_DTYPE
from pgt_blender.core.scan.sensors import PRESETS
from pgt_blender.core.scan.targets import (embree_available, gaussian_target, mesh_target, reflectivity_from_srgb,
                                          surfel_target)

from .conftest import datablock_counts

bpy = pytest.importorskip("bpy")

from pgt_blender.blender import objects, scanning  # noqa: E402  (needs bpy)
from pgt_blender.blender.authoring import positions  # noqa: E402

BOX_HALF = np.array([2.0, 1.0, 0.75])


def box_geometry():
    """A 4 x 2 x 1.5 m box centred on the origin: (8, 3) vertices, (12, 3) triangles."""
    import trimesh

    box = trimesh.creation.box(2 * BOX_HALF)
    return box.vertices, box.faces


def mesh_object(scene, name, vertices, faces=()):
    """A new active mesh object with float32 ``vertices`` and (F, k) polygon ``faces``."""
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(vertices))
    mesh.vertices.foreach_set("co", np.asarray(vertices, np.float32).ravel())
    faces = np.asarray(faces, np.int32)
    if faces.size:
        mesh.loops.add(faces.size)
        mesh.polygons.add(len(faces))
        mesh.loops.foreach_set("vertex_index", faces.ravel())
        mesh.polygons.foreach_set("loop_start", np.arange(0, faces.size, faces.shape[1], dtype=np.int32))
    mesh.update(calc_edges=bool(faces.size))
    obj = bpy.data.objects.new(name, mesh)
    scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    return obj


def core_scan(target, settings, bounds=None):
    """The headless scan with the pose the operator derives from ``settings``, standing
    on ``bounds`` (2, 3) (default: the geometry's)."""
    x, y = settings.distance * math.cos(settings.azimuth), settings.distance * math.sin(settings.azimuth)
    sensor = PRESETS[settings.sensor]
    return cast_rays(target, sensor, placement(target.bounds if bounds is None else bounds, sensor, x, y,
                                               settings.heading), ScanOptions())


def result_objects(source_name):
    return {obj.name: obj for obj in bpy.data.objects if obj.get(scanning.SOURCE_TAG) == source_name}


def scan_columns(obj):
    """Every return column as stored on the scan object (float32 / int32)."""
    mesh = obj.data
    xyz = positions(obj)
    columns = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    for name in RETURN_DTYPE.names[3:]:
        attribute = mesh.attributes[name]
        values = np.empty(len(attribute.data), np.float32 if attribute.data_type == "FLOAT" else np.int32)
        attribute.data.foreach_get("value", values)
        columns[name] = values
    return columns


def assert_same_rows(obj, returns):
    """The scan object holds exactly ``returns``, each column cast to its stored type."""
    stored = scan_columns(obj)
    assert len(stored["x"]) == len(returns)
    for name in RETURN_DTYPE.names:
        expected = returns[name].astype(np.float32 if returns[name].dtype.kind == "f" else np.int32)
        np.testing.assert_array_equal(stored[name], expected, err_msg=name)


def color_values(attribute, field="color_srgb"):
    values = np.empty(len(attribute.data) * 4, np.float32)
    attribute.data.foreach_get(field, values)
    return values.reshape(-1, 4)


def test_box_scan_matches_the_core(scene):
    vertices, faces = box_geometry()
    obj = mesh_object(scene, "Box", vertices, faces)
    settings = scene.pgt_scan
    settings.azimuth = math.radians(30)
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    expected = core_scan(mesh_target(np.float32(vertices), faces, "Box"), settings)
    assert expected.hits > 100
    assert_same_rows(bpy.data.objects["Box Scan"], expected.returns)
    azimuths = np.degrees(np.arctan2(expected.returns["y"], expected.returns["x"]))
    assert azimuths.mean() == pytest.approx(30, abs=3)  # the object stands where the azimuth says
    assert re.fullmatch(rf"{expected.hits} points · {expected.rays} rays · \d+% hit · [\d.]+ ms", settings.stats)
    assert obj.name in scene.objects and bpy.context.view_layer.objects.active == obj


def test_chrono_truck_scan_matches_the_core(scene, chrono_meshes):
    import trimesh

    path = next(p for p in chrono_meshes if p.stem == "truck_chassis")
    truck = trimesh.load(path, force="mesh", process=False)
    mesh_object(scene, "Truck", truck.vertices, truck.faces)
    settings = scene.pgt_scan
    settings.distance, settings.heading = 20.0, math.radians(-60)
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    expected = core_scan(mesh_target(np.float32(truck.vertices), truck.faces, "Truck"), settings)
    assert expected.hits > 500
    assert_same_rows(bpy.data.objects["Truck Scan"], expected.returns)


def test_face_column_is_the_blender_polygon(scene):
    """Quads are triangulated for the BVH; each return names the quad it hit."""
    bpy.ops.mesh.primitive_cube_add(size=2.0)
    cube = bpy.context.active_object
    mesh = cube.data
    mesh.calc_loop_triangles()
    count = len(mesh.loop_triangles)
    triangles, polygon = np.empty(count * 3, np.int32), np.empty(count, np.int32)
    mesh.loop_triangles.foreach_get("vertices", triangles)
    mesh.loop_triangles.foreach_get("polygon_index", polygon)
    settings = scene.pgt_scan
    settings.distance, settings.heading = 6.0, math.radians(20)
    bpy.ops.object.pgt_scan()
    expected = core_scan(mesh_target(positions(cube), triangles.reshape(-1, 3), cube.name), settings).returns
    expected["face"] = polygon[expected["face"]]
    assert_same_rows(bpy.data.objects["Cube Scan"], expected)
    assert len(np.unique(expected["face"])) >= 2 and expected["face"].max() < len(mesh.polygons)


def test_results_stand_where_the_object_stands(scene):
    """Scan points, sensor and ground are placed through the object's own matrix: in
    its local frame the points lie on its surface, the sensor is ``distance`` away and
    the ground touches its lowest point."""
    from mathutils import Euler, Matrix

    obj = mesh_object(scene, "Box", *box_geometry())
    obj.matrix_world = Matrix.Translation((3.0, 4.0, 0.5)) @ Euler((0.0, 0.0, 0.4)).to_matrix().to_4x4()
    settings = scene.pgt_scan
    settings.sensor, settings.distance = "kitti", 12.0
    bpy.ops.object.pgt_scan()
    results = result_objects("Box")
    assert set(results) == {"Box Scan", "PGT Sensor", "PGT Ground"}
    assert all(r.users_collection[0].name == scanning.SCAN_COLLECTION for r in results.values())
    assert bpy.data.collections[scanning.SCAN_COLLECTION] in scene.collection.children_recursive
    local_from_world = np.array(obj.matrix_world.inverted())

    def local(result, points):
        world = np.array(result.matrix_world) @ np.column_stack([points, np.ones(len(points))]).T
        return (local_from_world @ world)[:3].T

    on_box = local(results["Box Scan"], positions(results["Box Scan"])) / BOX_HALF
    np.testing.assert_allclose(np.abs(on_box).max(axis=1), 1.0, atol=1e-4)
    sensor = local(results["PGT Sensor"], np.zeros((1, 3)))[0]
    assert math.hypot(sensor[0], sensor[1]) == pytest.approx(12.0, abs=1e-4)
    assert sensor[2] == pytest.approx(PRESETS["kitti"].mounting_height - BOX_HALF[2], abs=1e-4)
    assert results["PGT Sensor"].empty_display_type == "PLAIN_AXES"
    ground = local(results["PGT Ground"], positions(results["PGT Ground"]))
    np.testing.assert_allclose(ground[:, 2], -BOX_HALF[2], atol=1e-4)
    assert np.ptp(ground[:, 0]) == pytest.approx(2 * 12.0 + 20.0, abs=1e-3)
    assert len(results["PGT Ground"].data.polygons) == 1


def test_scan_object_attributes_and_colors(scene):
    mesh_object(scene, "Box", *box_geometry())
    settings = scene.pgt_scan
    bpy.ops.object.pgt_scan()
    scan = bpy.data.objects["Box Scan"]
    assert scan.type == "MESH" and not scan.data.polygons
    names = {a.name: (a.data_type, a.domain) for a in scan.data.attributes}
    for column in RETURN_DTYPE.names[3:]:
        assert names[column] == ("FLOAT" if RETURN_DTYPE[column].kind == "f" else "INT", "POINT")
    colors = scan.data.color_attributes.active_color
    assert (colors.name, colors.data_type, colors.domain) == ("color", "FLOAT_COLOR", "POINT")
    assert scan.data.color_attributes.default_color_name == "color"
    assert scan.modifiers[objects.POINTS_GROUP].node_group.name == objects.POINTS_GROUP
    columns = scan_columns(scan)
    sensor = PRESETS[settings.sensor]
    by_intensity = color_values(colors, "color")
    np.testing.assert_array_equal(by_intensity, scanning.ramp(columns["intensity"] / sensor.intensity_max))

    settings.color_by = "RING"
    bpy.ops.object.pgt_scan()
    colors = bpy.data.objects["Box Scan"].data.color_attributes.active_color
    by_ring = color_values(colors, "color")
    np.testing.assert_array_equal(by_ring, scanning.ramp(columns["ring"] / (sensor.beams - 1)))
    assert not np.allclose(by_ring, by_intensity)


def test_second_scan_replaces_the_first(scene):
    mesh_object(scene, "Box", *box_geometry())
    mesh_object(scene, "Other", *box_geometry())
    bpy.ops.object.pgt_scan()
    bpy.context.view_layer.objects.active = bpy.data.objects["Box"]
    bpy.ops.object.pgt_scan()
    counts = datablock_counts(bpy) | {"collections": len(bpy.data.collections)}
    scene.pgt_scan.distance = 25.0
    bpy.ops.object.pgt_scan()
    assert datablock_counts(bpy) | {"collections": len(bpy.data.collections)} == counts
    # Sensor and ground of the second object scanned take Blender's ".001" names.
    assert sorted(result_objects("Box")) == ["Box Scan", "PGT Ground.001", "PGT Sensor.001"]
    assert sorted(result_objects("Other")) == ["Other Scan", "PGT Ground", "PGT Sensor"]
    ground = positions(bpy.data.objects["PGT Ground.001"])
    assert np.ptp(ground[:, 0]) == pytest.approx(2 * 25.0 + 20.0)


def test_a_copy_of_a_result_is_the_users_and_stays(scene):
    """Shift+D keeps the tags; the next scan replaces only what the last one made."""
    mesh_object(scene, "Box", *box_geometry())
    bpy.ops.object.pgt_scan()
    kept = bpy.data.objects["Box Scan"].copy()
    kept.data = kept.data.copy()
    scene.collection.objects.link(kept)
    renamed = bpy.data.objects["PGT Sensor"]
    renamed.name = "My sensor"
    bpy.context.view_layer.objects.active = bpy.data.objects["Box"]
    scene.pgt_scan.distance = 25.0
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    assert sorted(result_objects("Box")) == ["Box Scan", "Box Scan.001", "My sensor", "PGT Ground", "PGT Sensor"]
    assert bpy.data.objects["Box Scan.001"] == kept and bpy.data.objects["My sensor"] == renamed
    assert len(bpy.data.objects["Box Scan"].data.vertices) < len(kept.data.vertices)  # the new scan, from 25 m


def test_a_result_saved_without_its_name_tag_is_still_replaced(scene):
    mesh_object(scene, "Box", *box_geometry())
    bpy.ops.object.pgt_scan()
    for obj in result_objects("Box").values():
        del obj[objects.MADE_TAG]  # a .blend saved by an earlier version
    bpy.ops.object.pgt_scan()
    assert sorted(result_objects("Box")) == ["Box Scan", "PGT Ground", "PGT Sensor"]


def test_point_cloud_scans_as_surfels(scene):
    rng = np.random.default_rng(0)
    count = 4000
    points = rng.uniform(-BOX_HALF, BOX_HALF, (count, 3))
    axis = rng.integers(0, 3, count)
    points[np.arange(count), axis] = np.where(rng.random(count) < 0.5, -1.0, 1.0) * BOX_HALF[axis]
    colors = np.column_stack([rng.random((count, 3)), np.ones(count)]).astype(np.float32)
    cloud = objects.add_reconstruction(scene, Reconstruction(points.astype(np.float32), "point_ply",
                                                             Path("cloud.ply"), "", colors=colors))
    bpy.context.view_layer.objects.active = cloud
    settings = scene.pgt_scan
    settings.surfel_scale = 0.8
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    stored_colors = color_values(cloud.data.color_attributes.active_color)
    target = surfel_target(positions(cloud), cloud.name, stored_colors, settings.surfel_scale)
    expected = core_scan(target, settings)
    assert expected.hits > 100
    assert_same_rows(bpy.data.objects[f"{cloud.name} Scan"], expected.returns)
    assert scanning.scan_target(cloud, settings.surfel_scale).kind == "surfels"
    assert "surfel_scale" in drawn_scan_panel()


def author_as_prepare_does(scene, class_name: str, seed: int) -> None:
    """Align (PCA), Detect Front (baseline) and Set Size (nuScenes class) on the active
    object: what prepare(..., up="pca", heading_method="baseline", seed=seed) does."""
    authoring = scene.pgt_authoring
    authoring.up, authoring.heading_method, authoring.size_mode = "pca", "baseline", "class"
    authoring.dataset, authoring.class_name, authoring.seed = "nuscenes", class_name, seed
    for operator in (bpy.ops.object.pgt_align, bpy.ops.object.pgt_auto_heading, bpy.ops.object.pgt_set_size):
        assert operator() == {"FINISHED"}


def test_an_authored_point_cloud_scans_as_scan_object_scans_it_prepared(scene, tmp_path):
    """Authored in the panels, a sample with floaters stands on its authored box, as
    scan_object.py stands the same object prepared (its sidecar's box) and as the bank
    does: the same rows. Its points' bounds, floaters and all, lie 0.3 m lower."""
    from pgt_blender.commands import scan_object as command
    from pgt_blender.core.authoring.prepare import prepare, write_prepared
    from pgt_blender.core.importing import load_reconstruction
    from pgt_blender.core.samples import write_sample

    path = write_sample(tmp_path, "bus", seed=3, points=6000)["reconstruction.ply"]
    assert bpy.ops.import_scene.pgt_point_cloud(filepath=str(path)) == {"FINISHED"}
    cloud = bpy.context.view_layer.objects.active
    author_as_prepare_does(scene, "bus", 3)
    settings = scene.pgt_scan
    settings.distance, settings.azimuth, settings.heading = 15.0, 0.0, 0.0
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}

    prepared = write_prepared(prepare(load_reconstruction(path), "bus", up="pca", heading_method="baseline", seed=3),
                              "bus", "nuscenes", tmp_path / "prepared")
    assert command.main(["--object", str(prepared[".ply"]), "--sensor", "nuscenes", "--x", "15", "--y", "0",
                         "--heading", "0", "--out", str(tmp_path / "scan.npy")]) == 0
    assert_same_rows(bpy.data.objects[f"{cloud.name} Scan"], np.load(tmp_path / "scan.npy"))
    assert positions(cloud)[:, 2].min() < -cloud.pgt.dims[2] / 2 - 0.3


def test_an_authored_splat_scans_as_gaussians(scene, donut):
    """Align, heading and size move the splats' shapes as prepare() does; the Scan panel
    then scans the splat as Gaussians, row for row as the core does."""
    from pgt_blender.core.authoring.prepare import prepare
    from pgt_blender.core.importing import load_reconstruction

    assert bpy.ops.import_scene.pgt_gaussian_splat(filepath=str(donut)) == {"FINISHED"}
    splat = bpy.context.view_layer.objects.active
    author_as_prepare_does(scene, "car", 4)
    authored = prepare(load_reconstruction(donut), "car", up="pca", heading_method="baseline", seed=4)
    shapes = scanning.splat_attributes(splat.data)
    np.testing.assert_array_equal(positions(splat), authored.positions)
    np.testing.assert_array_equal(shapes["scale"], authored.splat_shapes[0])
    np.testing.assert_array_equal(shapes["rotation"], authored.splat_shapes[1])

    settings = scene.pgt_scan
    settings.distance, settings.azimuth = 12.0, math.radians(20)
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    assert scanning.scan_target(splat).kind == "gaussians"
    assert "surfel_scale" not in drawn_scan_panel()  # its own scales, not the point spacing
    stored_colors = color_values(splat.data.color_attributes.active_color)
    target = gaussian_target(authored.positions, *authored.splat_shapes, shapes["opacity"], splat.name, stored_colors)
    expected = core_scan(target, settings, centred_bounds(authored.dims))  # the authored box stands on the ground
    assert expected.hits > 100
    assert_same_rows(bpy.data.objects[f"{splat.name} Scan"], expected.returns)


@pytest.mark.parametrize("node_tree", [False, True])
def test_material_color_gives_the_reflectivity(scene, node_tree):
    """No color attribute: a face's reflectivity is its material's viewport color, on
    every Blender version, whatever its node tree says (5.0 gives every new material a
    Principled BSDF at 0.8), read without deprecated API; relative to the object's mean
    (targets.relative_reflectivity): a white and a dark material keep their contrast."""
    vertices, faces = box_geometry()
    obj = mesh_object(scene, "Box", vertices, faces)
    for name, linear in (("white", 0.9), ("dark", 0.1)):
        material = bpy.data.materials.new(name)
        material.diffuse_color = (linear, linear, linear, 1.0)  # scene-linear
        if node_tree:
            if material.node_tree is None:  # 4.x; 5.0 makes the tree itself and deprecates use_nodes
                material.use_nodes = True
            material.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.5, 0.5, 0.5, 1.0)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # the Scan operator shows the user every warning
            assert scanning.base_color(material) == pytest.approx((linear, linear, linear))
        obj.data.materials.append(material)
    corners = np.asarray(vertices)[faces]
    sides = np.round(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), 6)
    _, side = np.unique(np.sign(sides), axis=0, return_inverse=True)
    slots = np.zeros(len(faces), np.int32)
    for index in range(side.max() + 1):
        slots[np.flatnonzero(side == index)[1:]] = 1  # each side's two triangles: one white, one dark
    obj.data.polygons.foreach_set("material_index", slots)
    settings = scene.pgt_scan
    settings.sensor = "kitti"  # float intensities: no rounding to hide a difference
    bpy.ops.object.pgt_scan()
    albedo = reflectivity_from_srgb(np.array([[1.055 * 0.9 ** (1 / 2.4) - 0.055] * 3,
                                              [1.055 * 0.1 ** (1 / 2.4) - 0.055] * 3]))
    expected = core_scan(mesh_target(np.float32(vertices), faces, "Box", albedo[slots]), settings)
    stored = scan_columns(bpy.data.objects["Box Scan"])
    np.testing.assert_allclose(stored["intensity"], expected.returns["intensity"], rtol=1e-5)
    white = slots[stored["face"]] == 0
    assert white.any() and (~white).any()
    assert stored["intensity"][white].mean() > 4 * stored["intensity"][~white].mean()


@pytest.mark.parametrize("glass", ["named", "transparent"])
def test_glass_materials_are_seen_through(scene, glass):
    """Faces whose material is named like glass, or whose viewport color has an alpha
    below 1, return
    nothing; the rays go on to the far side of the box, as the core scans it."""
    vertices, faces = box_geometry()
    obj = mesh_object(scene, "Box", vertices, faces)
    paint, pane = bpy.data.materials.new("paint"), bpy.data.materials.new("Window" if glass == "named" else "clear")
    if glass == "transparent":
        pane.diffuse_color[3] = 0.2
    obj.data.materials.append(paint)
    obj.data.materials.append(pane)
    settings = scene.pgt_scan
    settings.distance, settings.azimuth = 8.0, 0.0
    panes = [index for index, polygon in enumerate(obj.data.polygons) if polygon.center.x < 0]  # facing the sensor
    for index in panes:
        obj.data.polygons[index].material_index = 1
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    stored = scan_columns(bpy.data.objects["Box Scan"])
    assert len(stored["face"]) > 50 and not set(stored["face"].tolist()) & set(panes)
    triangles = scanning.mesh_triangles(obj.data)[1]  # Blender polygon of each triangle
    see_through = np.isin(triangles, panes)
    expected = core_scan(mesh_target(np.float32(vertices), scanning.mesh_triangles(obj.data)[0], "Box",
                                     face_see_through=see_through), settings)
    assert len(stored["face"]) == expected.hits


def test_the_cached_target_is_built_for_the_engine(scene):
    """Before any scan: the default engine's structure is built with the cached target
    (Embree's committed scene, where embreex is installed; else Blender's BVH)."""
    target = scanning.scan_target(mesh_object(scene, "Engine box", *box_geometry()))
    if embree_available():
        assert target.bvh is None and target.embree_scene.is_committed
    else:
        assert target.bvh is not None and target.embree_scene is None


def test_bvh_is_built_once_per_object_and_rebuilt_after_an_edit(scene, monkeypatch):
    built = []

    def counting(*args, **kwargs):
        built.append(args[2])
        return mesh_target(*args, **kwargs)

    monkeypatch.setattr(scanning, "mesh_target", counting)
    obj = mesh_object(scene, "Box", *box_geometry())
    bpy.ops.object.pgt_scan()
    first = scanning.scan_target(obj)
    scene.pgt_scan.heading = math.radians(10)
    bpy.ops.object.pgt_scan()
    assert built == ["Box"] and scanning.scan_target(obj) is first
    top = int(np.argmax(positions(obj)[:, 2]))
    obj.data.vertices[top].co.z += 0.5
    bpy.ops.object.pgt_scan()
    assert built == ["Box", "Box"]
    assert scanning.scan_target(obj) is not first
    assert scanning.scan_target(obj).bounds[1, 2] == pytest.approx(1.25)


def _missing_toml(scene, tmp_path):
    scene.pgt_scan.sensor, scene.pgt_scan.sensor_file = "CUSTOM", str(tmp_path / "nowhere.toml")
    return "nowhere.toml: cannot read the file (No such file or directory)"


def _bad_toml(scene, tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text('base = "nuscenes"\ncolumns = -5\n')
    scene.pgt_scan.sensor, scene.pgt_scan.sensor_file = "CUSTOM", str(path)
    return f"{path}: sensor 'bad': columns must be a positive integer"


def _no_toml(scene, tmp_path):
    scene.pgt_scan.sensor = "CUSTOM"
    return "Custom sensor: no .toml file chosen"


def _empty_mesh(scene, tmp_path):
    mesh_object(scene, "Empty", np.zeros((0, 3)))
    return "Empty: point cloud is empty"


def _flat_faces(scene, tmp_path):
    mesh_object(scene, "Flat", [[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]])
    return "Flat: every face has zero area"


def _distance_not_a_number(scene, tmp_path):
    scene.pgt_scan.distance = float("nan")  # a script or driver: the field's min does not hold NaN off
    return "Scan: distance must be a finite number, got nan"


def _points_at_float32_max(scene, tmp_path):
    mesh_object(scene, "Far", np.random.default_rng(0).random((60, 3)) * 3e38)
    return "Far: 60 points are NaN or infinite or lie over 1e+08 m from the origin"


def _stale_sensor(scene, tmp_path):
    scene.pgt_scan["sensor"] = 99  # a .blend of a version with more sensors: reads as ""
    return "Scan: no sensor chosen"


@pytest.mark.parametrize("setup", [_missing_toml, _bad_toml, _no_toml, _empty_mesh, _flat_faces, _distance_not_a_number,
                                   _points_at_float32_max, _stale_sensor])
def test_bad_input_is_reported_and_changes_nothing(scene, tmp_path, setup):
    from pgt_blender.blender.operators import OBJECT_OT_pgt_scan

    mesh_object(scene, "Box", *box_geometry())
    bpy.ops.object.pgt_scan()  # earlier results must survive a failed scan
    before = {name: obj.as_pointer() for name, obj in result_objects("Box").items()}
    message = setup(scene, tmp_path)
    counts = datablock_counts(bpy) | {"collections": len(bpy.data.collections),
                                      "materials": len(bpy.data.materials)}
    stats = scene.pgt_scan.stats
    with pytest.raises(RuntimeError, match=re.escape(message)):
        bpy.ops.object.pgt_scan()
    reports = []
    self = SimpleNamespace(report=lambda kind, text: reports.append((kind, text)))
    assert OBJECT_OT_pgt_scan.execute(self, bpy.context) == {"CANCELLED"}
    assert reports == [({"ERROR"}, reports[0][1])] and message in reports[0][1]
    assert datablock_counts(bpy) | {"collections": len(bpy.data.collections),
                                    "materials": len(bpy.data.materials)} == counts
    assert {name: obj.as_pointer() for name, obj in result_objects("Box").items()} == before
    assert scene.pgt_scan.stats == stats


def test_a_scan_with_no_returns_is_a_warning_and_changes_nothing(scene):
    """Out of range (500 m): legal but empty; the operator says why and cancels."""
    from pgt_blender.blender.operators import OBJECT_OT_pgt_scan

    mesh_object(scene, "Box", *box_geometry())
    scene.pgt_scan.distance = 500.0
    counts = datablock_counts(bpy)
    reports = []
    self = SimpleNamespace(report=lambda kind, text: reports.append((kind, text)))
    assert OBJECT_OT_pgt_scan.execute(self, bpy.context) == {"CANCELLED"}
    assert reports == [({"WARNING"}, "Box: no returns at this pose, out of the nuScenes sensor's range or view; "
                                     "no scan preview made")]
    assert datablock_counts(bpy) == counts and not result_objects("Box")


def test_a_sensor_inside_the_object_is_a_warning(scene, capfd):
    """Distance 0 puts the sensor inside a 3 m tall box: the scan is made, with a warning."""
    vertices, faces = box_geometry()
    mesh_object(scene, "Box", vertices * [1, 1, 2], faces)
    scene.pgt_scan.distance = 0.0
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    assert "Warning: Box: the sensor lies inside the object's box (centre 0.00, 0.00 m)" in capfd.readouterr().out
    assert len(result_objects("Box")) == 3
    scene.pgt_scan.distance = 15.0
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    assert "inside the object's box" not in capfd.readouterr().out


@pytest.mark.parametrize("name", ["B" * 63, "Bé" * 21])
def test_a_long_names_results_keep_their_suffix(scene, name):
    """Blender cuts names at 63 bytes: a 63-byte object's scan is still "<name, shortened
    by whole characters> Scan" (cut off, it was the object's own name and then ".001"),
    and a second scan replaces it."""
    vertices, faces = box_geometry()
    obj = mesh_object(scene, name, vertices, faces)
    assert len(obj.name.encode()) > 60
    for _ in range(2):
        bpy.context.view_layer.objects.active = obj
        assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    results = [o.name for o in bpy.data.objects if o.get(scanning.SOURCE_TAG) == obj.name and scanning.DATASET_TAG in o]
    assert results == [objects.suffixed(obj.name, " Scan")]
    assert results[0].endswith(" Scan") and results[0][:-5] in obj.name and len(results[0].encode()) <= 63


def test_a_long_names_box_empty_keeps_its_suffix(scene):
    """The bank preview's and the placement's cubes are "<name> box" by the same rule, a
    file name's undecodable byte written as its escape."""
    made = []
    cube = objects.box_empty("E" * 62 + "\udcff", np.zeros(7), made)
    assert cube.name == "E" * 59 + " box" and made == [cube]
    assert objects.box_empty("bin\udcff", np.zeros(7), made).name == "bin\\udcff box"
    objects.remove_datablocks(made)


def test_a_rescans_meshes_keep_their_names(scene):
    """Each scan builds its results before it removes the last ones (a failed scan leaves
    them): the new meshes' names, taken while the old ones still held them, are the
    results' own again ("Box Scan", "PGT Ground"), not ".001" on every second scan."""
    vertices, faces = box_geometry()
    obj = mesh_object(scene, "Box", vertices, faces)
    for _ in range(2):
        bpy.context.view_layer.objects.active = obj
        assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    for name in ("Box Scan", "PGT Ground"):
        assert bpy.data.objects[name].data.name == name
    assert not [mesh.name for mesh in bpy.data.meshes if "." in mesh.name]


def test_modifiers_and_an_object_scale_are_a_warning_and_not_scanned(scene, capfd):
    """The scan reads the mesh data in metres: an Array modifier and a scale of 2 change
    nothing in it, and a warning says they are left out."""
    vertices, faces = box_geometry()
    obj = mesh_object(scene, "Box", vertices, faces)
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    plain = scan_columns(bpy.data.objects["Box Scan"])
    assert "not scanned" not in capfd.readouterr().out
    obj.modifiers.new("Array", "ARRAY")
    obj.scale = (2.0, 2.0, 2.0)
    bpy.context.view_layer.update()
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    assert ("Warning: Box: its modifiers (Array) and its scale (2, 2, 2) are not scanned, only its mesh data: apply "
            "them (Object > Apply) to scan what the viewport shows") in capfd.readouterr().out
    scanned = scan_columns(bpy.data.objects["Box Scan"])
    assert all(np.array_equal(scanned[name], plain[name]) for name in plain)


def test_zero_area_faces_are_a_warning(scene, capfd):
    vertices, faces = box_geometry()
    vertices = np.vstack([vertices, [[0, 0, 5], [1, 0, 5], [2, 0, 5]]])
    mesh_object(scene, "Box", vertices, np.vstack([faces, [[8, 9, 10]]]))
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    assert "Warning: Box: dropped 1 zero-area faces of 13" in capfd.readouterr().out
    assert len(result_objects("Box")) == 3


def test_scan_needs_a_mesh(scene):
    bpy.ops.object.empty_add()
    with pytest.raises(RuntimeError, match="Select a mesh or point-cloud object"):
        bpy.ops.object.pgt_scan()


def test_scan_is_undoable_and_registered():
    from pgt_blender.blender.operators import OBJECT_OT_pgt_scan, classes
    from pgt_blender.blender.properties import PGT_PG_scan
    from pgt_blender.blender.properties import classes as property_classes
    from pgt_blender.blender.ui import VIEW3D_PT_pgt_scan
    from pgt_blender.blender.ui import classes as panel_classes

    assert {"REGISTER", "UNDO"} <= OBJECT_OT_pgt_scan.bl_options
    assert OBJECT_OT_pgt_scan in classes and PGT_PG_scan in property_classes
    assert VIEW3D_PT_pgt_scan in panel_classes


def drawn_scan_panel() -> list:
    """What the Scan panel draws for the active object (_Layout's record)."""
    from pgt_blender.blender.ui import VIEW3D_PT_pgt_scan

    drawn = []
    VIEW3D_PT_pgt_scan.draw(SimpleNamespace(layout=_Layout(drawn)), bpy.context)
    return drawn


class _Layout:
    """Stands in for UILayout: records what a panel draws, checking property names."""

    def __init__(self, drawn):
        self.drawn = drawn

    def prop(self, data, name, **options):
        assert name in data.bl_rna.properties, name
        self.drawn.append(name)

    def operator(self, idname, **options):
        self.drawn.append(idname)

    def label(self, text="", **options):
        self.drawn.append(text)

    def column(self, **options):
        return self


@pytest.mark.parametrize("sensor", ["nuscenes", "CUSTOM"])
def test_panel_draws_the_settings_button_and_stats(scene, sensor):
    mesh_object(scene, "Box", *box_geometry())
    scene.pgt_scan.sensor = sensor
    if sensor == "nuscenes":
        bpy.ops.object.pgt_scan()
    drawn = drawn_scan_panel()
    assert drawn[:1] == ["sensor"] and "object.pgt_scan" in drawn
    assert {"distance", "azimuth", "heading", "color_by"} <= set(drawn)
    assert ("sensor_file" in drawn) == (sensor == "CUSTOM")
    assert (f"Box at 15 m: {scene.pgt_scan.stats}" in drawn) == bool(scene.pgt_scan.stats)
    # surfel scale only where it means something: a point cloud, not a mesh or a splat
    assert "surfel_scale" not in drawn
