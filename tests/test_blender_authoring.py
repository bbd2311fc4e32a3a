"""The Align, Heading and Size operators in real headless Blender, against the core."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from pgt_blender.core.authoring import sizing
from pgt_blender.core.authoring.prepare import prepare
from pgt_blender.core.importing import load_reconstruction
from pgt_blender.core.samples import write_sample

from .conftest import datablock_counts

bpy = pytest.importorskip("bpy")

from pgt_blender.blender import authoring, objects  # noqa: E402  (needs bpy)


def imported(scene, path):
    obj = objects.add_reconstruction(scene, load_reconstruction(path))
    bpy.context.view_layer.objects.active = obj
    return obj


def vertices(obj):
    return authoring.positions(obj)


@pytest.fixture(scope="module")
def truck_file(tmp_path_factory):
    return write_sample(tmp_path_factory.mktemp("samples"), "truck", seed=2, points=6000)["reconstruction.ply"]


@pytest.fixture(scope="module")
def truck_mesh_file(tmp_path_factory):
    return write_sample(tmp_path_factory.mktemp("samples"), "truck", seed=2)["mesh.ply"]


def test_ui_and_headless_give_identical_objects(scene, truck_file, capfd):
    """Align, detect front (baseline), set a class size in the UI; prepare() on the same
    file with the same settings gives the same points, box and transform."""
    obj = imported(scene, truck_file)
    settings = scene.pgt_authoring
    settings.up, settings.heading_method = "pca", "baseline"
    settings.dataset, settings.class_name, settings.seed = "nuscenes", "truck", 9
    for operator in (bpy.ops.object.pgt_align, bpy.ops.object.pgt_auto_heading, bpy.ops.object.pgt_set_size):
        assert operator() == {"FINISHED"}
    headless = prepare(load_reconstruction(truck_file), "truck", up="pca", heading_method="baseline", seed=9)
    np.testing.assert_array_equal(vertices(obj), headless.positions)
    # the float64 product rounded once to the float32 property (not a float32 chain of products)
    np.testing.assert_array_equal(np.array(obj.pgt.object_from_source, np.float32),
                                  headless.object_from_source.astype(np.float32))
    np.testing.assert_allclose(obj.pgt.dims, headless.dims, rtol=1e-6)
    np.testing.assert_allclose(obj.pgt.dims, sizing.sample_dims("nuscenes", "truck", 9), rtol=1e-6)
    assert (obj.pgt.class_name, obj.pgt.dataset) == ("truck", "nuscenes")
    assert [s["step"] for s in json.loads(obj.pgt.steps_json)] == ["align", "heading", "size"]
    out = capfd.readouterr().out
    assert f"{obj.name}: detect front by baseline as truck (score " in out
    assert f"{obj.name}: align axes (up from planes), box " in out and " (source units)\n" in out
    dims = " x ".join(f"{d:.4g}" for d in obj.pgt.dims)
    assert f"{obj.name}: set size (class: nuscenes truck, seed 9), box {dims} m\n" in out


def test_detect_front_heads_a_trailer_by_its_running_gear(scene, tmp_path, capfd):
    """With the class set to trailer, Detect Front decides by the running gear, as
    prepare() does for that class, turns the object the same way and says so."""
    path = write_sample(tmp_path, "trailer", seed=1, points=6000)["reconstruction.ply"]
    obj = imported(scene, path)
    settings = scene.pgt_authoring
    settings.up, settings.heading_method = "auto", "classifier"
    settings.dataset, settings.class_name = "nuscenes", "trailer"
    for operator in (bpy.ops.object.pgt_align, bpy.ops.object.pgt_auto_heading):
        assert operator() == {"FINISHED"}
    headless = prepare(load_reconstruction(path), "trailer", heading_method="classifier", size="keep")
    step = json.loads(obj.pgt.steps_json)[1]
    assert step["decided_by"] == "running gear" == headless.steps[1].details["decided_by"]
    assert authoring.status(obj)["heading"] == "classifier/running gear"  # the status line says so
    turned = "turned 180" if step["turns"] == 2 else "front kept"
    assert (f"{obj.name}: detect front by classifier/running gear as trailer (score {step['score']:.3g}; {turned}), "
            "box" in capfd.readouterr().out)
    # the float64 product rounded once to the float32 property (not a float32 chain of products)
    np.testing.assert_array_equal(np.array(obj.pgt.object_from_source, np.float32),
                                  headless.object_from_source.astype(np.float32))


def test_status_and_box_follow_the_steps(scene, truck_file):
    from pgt_blender.blender.ui import status_icon, status_text

    obj = imported(scene, truck_file)
    assert status_text(obj) == "not aligned | heading unset | size unset"
    bpy.ops.object.pgt_align()
    assert authoring.status(obj) == {"aligned": True, "heading": "", "size": ""}
    dims = tuple(obj.pgt.dims)
    with pytest.raises(RuntimeError, match=f"{obj.name}: 0 quarter turns: nothing to turn"):
        bpy.ops.object.pgt_turn(turns=0)
    assert authoring.status(obj)["heading"] == ""
    bpy.ops.object.pgt_turn(turns=1)
    assert tuple(obj.pgt.dims) == pytest.approx((dims[1], dims[0], dims[2]))
    assert status_text(obj) == "aligned | heading: manual | size unset"
    scene.pgt_authoring.size_mode = "exact"
    scene.pgt_authoring.exact_dims = (5.0, 2.0, 2.5)
    bpy.ops.object.pgt_set_size()
    assert status_text(obj) == "aligned | heading: manual | size: exact, no class"
    assert status_icon(obj, "INFO") == "INFO"  # not ready for a bank
    box = next(child for child in obj.children if child.get(authoring.BOX_TAG))
    assert box.empty_display_type == "CUBE"
    np.testing.assert_allclose(box.scale, [2.5, 1.0, 1.25], rtol=1e-6)
    local = vertices(obj)
    record = json.loads(obj.pgt.steps_json)
    # the box is the surface's: the points' noise (3 sigma, scaled as the object) lies around it
    margin = 3 * record[0]["noise"] * np.abs(np.diag(record[-1]["transform"])[:3])
    inside = (np.abs(local) <= np.array([2.5, 1.0, 1.25]) * 1.01 + margin).all(axis=1)
    assert inside.mean() > 0.97  # the sample's 3 % floaters aside, the box holds the points
    bpy.ops.object.pgt_align()  # aligning again leaves the front to be confirmed again
    assert status_text(obj) == "aligned | heading unset | size: exact, no class"


def test_a_meshs_dimensions_follow_the_steps(scene, truck_mesh_file):
    """Blender's cached bounds of a mesh (Item > Dimensions, View Selected, culling) are
    those of its vertices after each step, not the imported ones."""
    obj = imported(scene, truck_mesh_file)
    scene.pgt_authoring.size_mode, scene.pgt_authoring.exact_dims = "exact", (1.0, 2.8, 1.1)  # turned: y is long
    for step in (bpy.ops.object.pgt_align, lambda: bpy.ops.object.pgt_turn(turns=1), bpy.ops.object.pgt_set_size):
        assert step() == {"FINISHED"}
        bpy.context.view_layer.update()
        np.testing.assert_allclose(obj.dimensions, np.ptp(vertices(obj), axis=0), rtol=1e-5)
    np.testing.assert_allclose(obj.dimensions, [1.0, 2.8, 1.1], rtol=0.02)


def test_a_steps_warning_is_reported_in_the_status_bar(scene, truck_mesh_file, capfd):
    """Set Size's stretch warning, one WARNING line of the operator (Blender prints those
    as "Warning: ..."), not a UserWarning on the console only."""
    obj = imported(scene, truck_mesh_file)
    assert bpy.ops.object.pgt_align() == {"FINISHED"}
    scene.pgt_authoring.size_mode, scene.pgt_authoring.exact_dims = "exact", (2.0, 2.0, 2.0)
    capfd.readouterr()
    assert bpy.ops.object.pgt_set_size() == {"FINISHED"}
    out, err = capfd.readouterr()
    assert f"Warning: {obj.name}: sizing stretches one axis 2.8x more than another" in out
    assert "UserWarning" not in err


def test_a_long_names_box_keeps_its_suffix(scene, truck_file):
    """The box child of a 63-byte object is "<name, shortened> Box", not the object's own
    name cut at Blender's 63 bytes and then ".001"."""
    obj = imported(scene, truck_file)
    obj.name = "T" * 63
    assert bpy.ops.object.pgt_align() == {"FINISHED"}
    (box,) = [child for child in obj.children if child.get(authoring.BOX_TAG)]
    assert box.name == "T" * 59 + " Box"


def test_set_size_warns_of_an_unapplied_object_scale(scene, truck_mesh_file, capfd):
    """Set Size (Keep too) sizes the mesh data, as the scans and the bank read it: an object
    scale left on would show another size in the viewport, so it is a WARNING line; the
    step itself is the same as without the scale."""
    obj = imported(scene, truck_mesh_file)
    assert bpy.ops.object.pgt_align() == {"FINISHED"}
    scene.pgt_authoring.size_mode = "keep"
    capfd.readouterr()
    assert bpy.ops.object.pgt_set_size() == {"FINISHED"}
    assert "is not part of the size" not in capfd.readouterr().out
    kept = np.array(obj.pgt.dims)
    obj.scale = (2.0, 2.0, 1.5)
    bpy.context.view_layer.update()
    assert bpy.ops.object.pgt_set_size() == {"FINISHED"}
    assert (f"Warning: {obj.name}: its scale (2, 2, 1.5) is not part of the size, which is its mesh data's: apply it "
            "(Object > Apply > Scale) to see in the viewport the size the bank takes") in capfd.readouterr().out
    np.testing.assert_array_equal(obj.pgt.dims, kept)


def test_lengths_are_metres_whatever_the_unit_scale_and_bounded_as_on_the_command_lines(scene):
    """A centimetre scene (Unit Scale 0.01) would show and parse a length field through its
    unit while the core reads metres; the fields hold the command lines' bounds."""
    fields = [(bpy.types.Object, "pgt", "dims"), (bpy.types.Scene, "pgt_authoring", "exact_dims"),
              (bpy.types.Scene, "pgt_scan", "distance"), (bpy.types.Scene, "pgt_bank", "grid_step")]
    for owner, group, name in fields:
        assert owner.bl_rna.properties[group].fixed_type.properties[name].unit == "NONE", name
    scene.pgt_authoring.exact_dims, scene.pgt_scan.distance = (1e9, 1e9, 1e9), 1e30
    assert tuple(scene.pgt_authoring.exact_dims) == (1000.0,) * 3 and scene.pgt_scan.distance == 1e4


def test_front_from_cursor(scene, truck_file):
    obj = imported(scene, truck_file)
    bpy.ops.object.pgt_align()
    before = vertices(obj).copy()
    scene.cursor.location = (0.3, -20.0, 0.0)  # beside the -y side
    assert bpy.ops.object.pgt_front_from_cursor() == {"FINISHED"}
    np.testing.assert_allclose(vertices(obj), before @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]]).T, atol=1e-6)


def test_colmap_cameras_follow_and_give_the_up(scene, statue):
    """Align (up from the cameras) and size the real statue: each camera still sees
    every point where it saw it before."""
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    obj = imported(scene, statue)
    cameras = [c for c in obj.children if c.type == "CAMERA"][:5]
    sample = np.arange(0, len(obj.data.vertices), 97)

    def views():
        bpy.context.view_layer.update()
        world = np.array(obj.matrix_world)
        points = vertices(obj)[sample] @ world[:3, :3].T + world[:3, 3]
        return np.array([[tuple(world_to_camera_view(scene, camera, Vector(p)))[:2] for p in points]
                         for camera in cameras])

    before = views()
    scene.pgt_authoring.up = "auto"
    assert bpy.ops.object.pgt_align() == {"FINISHED"}
    assert json.loads(obj.pgt.steps_json)[0]["up_from"] == "prior"
    assert obj.pgt.dims[2] == max(obj.pgt.dims)  # the statue stands
    scene.pgt_authoring.size_mode, scene.pgt_authoring.uniform = "exact", True
    scene.pgt_authoring.exact_dims = (2.0, 2.0, 6.0)
    assert bpy.ops.object.pgt_set_size() == {"FINISHED"}
    np.testing.assert_allclose(views(), before, atol=1e-4)
    headless = prepare(load_reconstruction(statue), "", up="auto", heading_method="none", size="exact",
                       exact=(2.0, 2.0, 6.0), uniform=True)
    np.testing.assert_allclose(np.array(obj.pgt.object_from_source), headless.object_from_source, atol=1e-4)


def test_authoring_operators_are_undoable():
    from pgt_blender.blender.operators import AUTHORING

    assert all({"REGISTER", "UNDO"} <= operator.bl_options for operator in AUTHORING)


def test_operators_need_a_reconstruction(scene):
    bpy.ops.mesh.primitive_cube_add()
    with pytest.raises(RuntimeError, match="Select an imported reconstruction"):
        bpy.ops.object.pgt_align()


def test_heading_needs_alignment(scene, truck_file):
    imported(scene, truck_file)
    with pytest.raises(RuntimeError, match="Align the axes first"):
        bpy.ops.object.pgt_turn(turns=2)


@pytest.mark.parametrize("setting, value, message", [
    ("up", "cameras", "has no cameras to take the up direction from"),
])
def test_bad_align_settings_change_nothing(scene, truck_file, setting, value, message):
    obj = imported(scene, truck_file)
    before, counts = vertices(obj).copy(), datablock_counts(bpy)
    setattr(scene.pgt_authoring, setting, value)
    with pytest.raises(RuntimeError, match=f"{truck_file}: {message}"):
        bpy.ops.object.pgt_align()
    np.testing.assert_array_equal(vertices(obj), before)
    assert datablock_counts(bpy) == counts and not authoring.status(obj)["aligned"]


def test_empty_reconstruction_is_refused(scene):
    mesh = bpy.data.meshes.new("empty")
    obj = bpy.data.objects.new("empty", mesh)
    obj.pgt.source_kind, obj.pgt.source_path = "point_ply", "/data/empty.ply"
    scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    with pytest.raises(RuntimeError, match="empty: has no points to author"):
        bpy.ops.object.pgt_align()


def test_missing_checkpoint_is_reported(scene, truck_file, tmp_path):
    obj = imported(scene, truck_file)
    bpy.ops.object.pgt_align()
    before = vertices(obj).copy()
    scene.pgt_authoring.heading_method = "classifier"
    scene.pgt_authoring.checkpoint = str(tmp_path / "nowhere.pt")
    with pytest.raises(RuntimeError, match="nowhere.pt: "):
        bpy.ops.object.pgt_auto_heading()
    np.testing.assert_array_equal(vertices(obj), before)
    assert authoring.status(obj)["heading"] == ""


def test_flat_object_cannot_take_a_class_size(scene):
    from pgt_blender.core.reconstruction import Reconstruction

    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
    obj = objects.add_reconstruction(scene, Reconstruction(flat, "point_ply", Path("flat.ply"), ""))
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.pgt_align()
    scene.pgt_authoring.class_name = "car"
    with pytest.raises(RuntimeError, match="cannot scale a box"):
        bpy.ops.object.pgt_set_size()
    assert authoring.status(obj)["size"] == ""


def test_class_is_kept_by_name_and_cleared_when_the_dataset_lacks_it(scene, truck_file):
    """A dataset switch keeps a class the new dataset has and clears one it lacks, with
    the reason; Set Size then refuses instead of sizing to another class."""
    settings = scene.pgt_authoring
    settings.dataset, settings.class_name = "nuscenes", "truck"
    settings.dataset = "kitti"
    assert settings.class_name == "truck"  # KITTI has trucks: the same class, not the same position
    settings.dataset, settings.class_name = "nuscenes", "bus"
    settings.dataset = "kitti"
    assert settings.class_name == "" and settings.class_note.startswith("Cleared: 'bus' is not a KITTI class")
    settings.class_name = "lorry"  # typed, not picked from the search list
    assert settings.class_name == "" and "'lorry' is not a KITTI class" in settings.class_note
    obj = imported(scene, truck_file)
    bpy.ops.object.pgt_align()
    with pytest.raises(RuntimeError, match=f"{obj.name}: no class chosen: choose a KITTI class"):
        bpy.ops.object.pgt_set_size()
    assert authoring.status(obj)["size"] == "" and obj.pgt.class_name == ""
    settings.class_name = "van"
    assert bpy.ops.object.pgt_set_size() == {"FINISHED"}
    assert (obj.pgt.dataset, obj.pgt.class_name) == ("kitti", "van")


@pytest.fixture(scope="module")
def tilted_truck(tmp_path_factory, shared_data):
    """Issue 18's case as a file: truck_chassis tilted 4 degrees about x, 37 degrees of
    yaw, 2 km away; and the rotation applied."""
    import trimesh
    from scipy.spatial.transform import Rotation

    mesh = trimesh.load(shared_data / "chrono_vehicles/data/vehicle/truck/truck_chassis.obj", force="mesh")
    rotation = Rotation.from_euler("x", 4, degrees=True).as_matrix() @ Rotation.from_euler("z", 37, degrees=True).as_matrix()
    transform = np.eye(4)
    transform[:3, :3], transform[:3, 3] = rotation, (2000.0, 0, 0)
    mesh.apply_transform(transform)
    path = tmp_path_factory.mktemp("tilted") / "truck_chassis.obj"
    mesh.export(path)
    return path, rotation


def test_refinement_in_the_ui_matches_the_command_line(scene, tilted_truck):
    """Align with refinement in the UI = prepare() on the same file: the same transform and
    box, the 4 degree tilt removed and shown in the Align section."""
    from pgt_blender.blender.ui import refinement_text

    path, rotation = tilted_truck
    obj = imported(scene, path)
    scene.pgt_authoring.up, scene.pgt_authoring.refine = "auto", True
    assert bpy.ops.object.pgt_align() == {"FINISHED"}
    headless = prepare(load_reconstruction(path), "truck", up="auto", heading_method="none", size="keep")
    np.testing.assert_allclose(np.array(obj.pgt.object_from_source), headless.object_from_source, atol=1e-6)
    np.testing.assert_allclose(obj.pgt.dims, headless.dims, rtol=1e-6)
    align = json.loads(obj.pgt.steps_json)[0]
    assert align["refined"] and 3.0 < align["tilt_deg"] < 5.0
    assert refinement_text(obj) == (f"Refined: tilt removed {align['tilt_deg']:.2f}° from the PCA minor axis, "
                                    "noise 0 (source units)")
    up = np.array(obj.pgt.object_from_source)[2, :3]
    assert np.degrees(np.arccos(abs(up @ rotation[:, 2]))) < 0.5


def test_up_from_the_cursor_and_from_selected_faces(scene, tilted_truck):
    """The cursor above the object, or its picked roof faces, give up; refinement off
    keeps that up exactly, refinement on turns it onto the faces."""
    path, rotation = tilted_truck
    obj = imported(scene, path)
    settings = scene.pgt_authoring
    settings.up, settings.refine = "cursor", False
    points = authoring.positions(obj).astype(np.float64)
    middle = np.median(points, axis=0)
    scene.cursor.location = tuple(np.array(obj.matrix_world) @ np.r_[middle + 10 * rotation[:, 2], 1.0])[:3]
    assert bpy.ops.object.pgt_align() == {"FINISHED"}
    up = np.array(obj.pgt.object_from_source)[2, :3]
    assert up @ rotation[:, 2] > np.cos(np.radians(0.01))
    obj = imported(scene, path)
    normals = np.empty(len(obj.data.polygons) * 3, np.float32)
    obj.data.polygons.foreach_get("normal", normals)
    roofs = normals.reshape(-1, 3) @ rotation[:, 2] > 0.999  # the flat roof and floor tops
    obj.data.polygons.foreach_set("select", roofs)
    settings.up, settings.refine = "face", True
    assert bpy.ops.object.pgt_align() == {"FINISHED"}
    up = np.array(obj.pgt.object_from_source)[2, :3]
    assert up @ rotation[:, 2] > np.cos(np.radians(0.5))
    obj.data.polygons.foreach_set("select", np.zeros(len(obj.data.polygons), bool))
    with pytest.raises(RuntimeError, match="no selected faces"):
        bpy.ops.object.pgt_align()


def test_up_from_faces_whose_normals_cancel_is_named(scene):
    import trimesh
    from pgt_blender.core.reconstruction import Reconstruction

    box = trimesh.creation.box((4.0, 2.0, 1.5))
    obj = objects.add_reconstruction(scene, Reconstruction(box.vertices.astype(np.float32), "mesh", Path("box.ply"),
                                                           "", faces=box.faces.astype(np.int32)))
    bpy.context.view_layer.objects.active = obj
    obj.data.polygons.foreach_set("select", np.ones(len(obj.data.polygons), bool))  # a closed surface: all of it
    scene.pgt_authoring.up = "face"
    with pytest.raises(RuntimeError, match=f"{obj.name}: the normals of its 12 selected faces disagree \\(they sum "
                                           "to 0% of their area, 50% needed"):
        bpy.ops.object.pgt_align()


def test_the_align_section_says_when_the_planes_gave_up(scene, tmp_path):
    """A bus without a prior: PCA's minor axis is its width, and the planes give up; the
    section says so rather than calling 85 degrees a tilt."""
    from pgt_blender.blender.ui import refinement_text

    obj = imported(scene, write_sample(tmp_path, "bus", seed=3, points=6000)["reconstruction.ply"])
    scene.pgt_authoring.up, scene.pgt_authoring.refine = "auto", True
    assert bpy.ops.object.pgt_align() == {"FINISHED"}
    align = json.loads(obj.pgt.steps_json)[0]
    assert align["up_from"] == "planes" and align["tilt_deg"] > 45
    assert refinement_text(obj).startswith(f"Refined: up from the surface planes (the PCA minor axis lay "
                                           f"{align['tilt_deg']:.1f}° off), noise ")


def test_the_align_section_says_why_an_object_was_not_refined(scene, tmp_path):
    """Refine off, and refine on for a ball (no flat surface): each says so."""
    import trimesh
    from pgt_blender.blender.ui import refinement_text
    from pgt_blender.core.reconstruction import Reconstruction

    settings = scene.pgt_authoring
    truck = imported(scene, write_sample(tmp_path, "truck", seed=3, points=3000)["reconstruction.ply"])
    settings.up, settings.refine = "pca", False
    assert bpy.ops.object.pgt_align() == {"FINISHED"}
    assert refinement_text(truck) == "Not refined to the surface (Refine was off)"
    settings.refine = True
    points = trimesh.creation.icosphere(4, 2.0).sample(5000, seed=1).astype(np.float32)
    ball = objects.add_reconstruction(scene, Reconstruction(points, "point_ply", Path("ball.ply"), ""))
    bpy.context.view_layer.objects.active = ball
    assert bpy.ops.object.pgt_align() == {"FINISHED"}
    assert refinement_text(ball) == "Not refined to the surface: too little flat surface to refine to"


def test_up_from_every_face_of_an_open_mesh_is_named(scene, tilted_truck):
    """All of the Chrono truck, as Edit Mode first selects an imported mesh: an open
    surface whose normals sum to 1 % of its area gave an up 48 degrees off."""
    obj = imported(scene, tilted_truck[0])
    obj.data.polygons.foreach_set("select", np.ones(len(obj.data.polygons), bool))
    scene.pgt_authoring.up = "face"
    with pytest.raises(RuntimeError, match=f"{obj.name}: the normals of its 11028 selected faces disagree "
                                           r"\(they sum to 1% of their area"):
        bpy.ops.object.pgt_align()
    assert not obj.pgt.steps_json


def test_align_from_faces_picked_in_edit_mode(scene, tilted_truck):
    """Pick the roof in Edit Mode and press Align there: the step runs (out of Edit Mode
    and back), the object stays in Edit Mode, and Scan there sees the same mesh."""
    path, rotation = tilted_truck
    import bmesh

    obj = imported(scene, path)
    obj.select_set(True)
    bpy.ops.object.mode_set(mode="EDIT")
    edited = bmesh.from_edit_mesh(obj.data)
    for face in edited.faces:  # the roof and floor tops, picked as a user picks them
        face.select_set(face.normal.dot(rotation[:, 2]) > 0.999)
    bmesh.update_edit_mesh(obj.data)
    scene.pgt_authoring.up, scene.pgt_authoring.refine = "face", True
    assert bpy.ops.object.pgt_align() == {"FINISHED"} and obj.mode == "EDIT"
    assert np.array(obj.pgt.object_from_source)[2, :3] @ rotation[:, 2] > np.cos(np.radians(0.5))
    assert bpy.ops.object.pgt_scan() == {"FINISHED"} and obj.mode == "EDIT"
    in_edit_mode = len(bpy.data.objects[f"{obj.name} Scan"].data.vertices)
    bpy.ops.object.mode_set(mode="OBJECT")
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    assert len(bpy.data.objects[f"{obj.name} Scan"].data.vertices) == in_edit_mode > 0


def test_a_linked_duplicate_is_refused(scene, truck_file):
    """Alt+D shares the mesh: authoring one would reshape the other behind its record."""
    obj = imported(scene, truck_file)
    twin = obj.copy()
    scene.collection.objects.link(twin)
    before, counts = vertices(obj).copy(), datablock_counts(bpy)
    with pytest.raises(RuntimeError, match=f"{obj.name}: shares its mesh '{obj.data.name}' with 1 other user"):
        bpy.ops.object.pgt_align()
    np.testing.assert_array_equal(vertices(obj), before)
    assert datablock_counts(bpy) == counts and not authoring.status(obj)["aligned"]
    twin.data = twin.data.copy()  # Make Single User: now it aligns
    assert bpy.ops.object.pgt_align() == {"FINISHED"}


def test_a_zero_scale_is_named_not_a_traceback(scene, truck_file):
    obj = imported(scene, truck_file)
    bpy.ops.object.pgt_align()
    obj.scale = (1.0, 0.0, 1.0)
    bpy.context.view_layer.update()
    before = vertices(obj).copy()
    with pytest.raises(RuntimeError, match=f"{obj.name}: has a zero scale on an axis") as error:
        bpy.ops.object.pgt_front_from_cursor()
    assert "Traceback" not in str(error.value)
    np.testing.assert_array_equal(vertices(obj), before)


IDENTITY = np.eye(4).tolist()


@pytest.mark.parametrize("record, problem", [
    ("nope {", r"pgt.steps_json is not JSON \(Expecting value"),
    ('{"step": "align"}', "pgt.steps_json must be a list of steps, got dict"),
    ("[1, 2]", r"pgt.steps_json\[0\]: expected an object, got int"),
    (json.dumps([{"step": "size", "transform": IDENTITY, "mode": "keep"}]),
     r"pgt.steps_json\[0\]: dims must be three finite lengths >= 0, got None"),
    (json.dumps([{"step": "heading", "transform": IDENTITY, "dims": [4, 2, 2], "by": 3}]),
     r"pgt.steps_json\[0\]: by must be a string, got 3"),
])
def test_a_damaged_step_record_is_named_and_changes_nothing(scene, truck_file, record, problem):
    """A hand-edited record: every authoring operator names it (poll or report), the
    panels show it, nothing changes; cleared, the object authors again."""
    from pgt_blender.blender.ui import status_icon, status_text

    obj = imported(scene, truck_file)
    obj.select_set(True)
    obj.pgt.steps_json = record
    scene.pgt_authoring.dataset, scene.pgt_authoring.class_name = "nuscenes", "truck"
    before, counts = vertices(obj).copy(), datablock_counts(bpy)
    for operator in (bpy.ops.object.pgt_align, bpy.ops.object.pgt_set_size, bpy.ops.object.pgt_author_selected):
        with pytest.raises(RuntimeError, match=f"{obj.name}: {problem}.*the authoring record is damaged") as error:
            operator()
        assert "Traceback" not in str(error.value)
    assert re.match(problem, status_text(obj)) and status_icon(obj, "INFO") == "ERROR"
    np.testing.assert_array_equal(vertices(obj), before)
    assert datablock_counts(bpy) == counts and obj.pgt.steps_json == record and tuple(obj.pgt.dims) == (0, 0, 0)
    obj.pgt.steps_json = ""
    assert bpy.ops.object.pgt_align() == {"FINISHED"}


def test_points_made_nan_after_alignment_are_refused_by_every_step(scene, truck_file):
    obj = imported(scene, truck_file)
    bpy.ops.object.pgt_align()
    broken = vertices(obj).copy()
    broken[:3] = np.nan
    obj.data.attributes["position"].data.foreach_set("vector", broken.ravel())
    record = obj.pgt.steps_json
    for operator in (bpy.ops.object.pgt_turn, bpy.ops.object.pgt_auto_heading, bpy.ops.object.pgt_set_size):
        with pytest.raises(RuntimeError, match=f"{obj.name}: 3 of {len(broken)} points have NaN or Inf coordinates"):
            operator()
    assert obj.pgt.steps_json == record


def test_up_from_a_cursor_at_the_median_is_named(scene, truck_file):
    obj = imported(scene, truck_file)
    scene.cursor.location = np.median(vertices(obj), axis=0)
    scene.pgt_authoring.up = "cursor"
    with pytest.raises(RuntimeError, match=f"{obj.name}: the 3D cursor is at the points' median: put it above"):
        bpy.ops.object.pgt_align()


@pytest.mark.parametrize("points, problem", [(0, "has no points to author"),
                                             (5, "its 5 points all lie at one place: nothing to align or size")])
def test_author_selected_checks_every_object_before_changing_any(scene, truck_file, points, problem):
    good = imported(scene, truck_file)
    bad = bpy.data.objects.new("ZZZ bad", bpy.data.meshes.new("ZZZ bad"))
    bad.data.vertices.add(points)
    bad.pgt.source_kind = "point_ply"
    scene.collection.objects.link(bad)
    for obj in (good, bad):
        obj.select_set(True)
    scene.pgt_authoring.dataset, scene.pgt_authoring.class_name = "nuscenes", "truck"
    before = vertices(good).copy()
    with pytest.raises(RuntimeError, match=f"ZZZ bad: {problem}"):
        bpy.ops.object.pgt_author_selected()
    np.testing.assert_array_equal(vertices(good), before)
    assert good.pgt.steps_json == ""


def test_author_selected_checks_the_heading_checkpoint_before_changing_any(scene, truck_file, tmp_path):
    objects_chosen = [imported(scene, truck_file) for _ in range(2)]
    for obj in objects_chosen:
        obj.select_set(True)
    settings = scene.pgt_authoring
    settings.dataset, settings.class_name = "nuscenes", "truck"
    settings.heading_method, settings.checkpoint = "classifier", str(tmp_path / "missing.pt")
    with pytest.raises(RuntimeError, match="missing.pt"):
        bpy.ops.object.pgt_author_selected()
    assert all(obj.pgt.steps_json == "" for obj in objects_chosen)


def test_a_point_display_the_user_emptied_does_not_stop_a_step(scene, truck_file):
    """The Points modifier is display only: cleared (X in its panel), the step still applies
    whole, once."""
    obj = imported(scene, truck_file)
    obj.modifiers[objects.POINTS_GROUP].node_group = None
    assert bpy.ops.object.pgt_align() == {"FINISHED"}
    assert [step["step"] for step in authoring.steps(obj)] == ["align"]
