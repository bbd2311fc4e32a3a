"""Apply Intensity Model in real headless Blender: the estimator's values on the scan
preview, equal to the core's on the same returns; clear errors leave it untouched."""

import numpy as np
import pytest

from pgt_blender.core.intensity.objects import ObjectSet
from pgt_blender.core.scan.physical_intensity import dataset_intensity
from pgt_blender.core.scan.raycast import placement
from pgt_blender.core.scan.targets import srgb_from_linear

bpy = pytest.importorskip("bpy")
torch = pytest.importorskip("torch")

from pgt_blender.blender import properties, scanning  # noqa: E402
from pgt_blender.core.intensity.estimator import IntensityEstimator  # noqa: E402
from pgt_blender.core.intensity.training import TrainConfig, train  # noqa: E402

from .test_blender_scan import box_geometry, color_values, core_scan, mesh_object  # noqa: E402


def tiny_sets(dataset: str):
    """Two small domains of one class: real intensity rising with height, red-blue RGB."""
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-1, 1, (4, 256, 3)).astype(np.float32)
    intensity = ((xyz[..., 2:] + 1) / 2).astype(np.float32)
    rgb = np.concatenate([(xyz[..., :1] + 1) / 2, np.zeros_like(intensity), 1 - (xyz[..., :1] + 1) / 2], axis=-1)
    common = dict(class_index=np.zeros(4, np.int64), classes=("object",), names=[f"o{i}" for i in range(4)],
                  dataset=dataset)
    return ObjectSet(xyz, intensity, **common), ObjectSet(xyz[::-1].copy(), rgb.astype(np.float32), **common)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    real, rgb = tiny_sets("nuscenes")
    return train(real, rgb, TrainConfig(steps=2, batch=2, checkpoint_every=2, patches=4),
                 tmp_path_factory.mktemp("model"), progress=False)


@pytest.fixture
def preferences(registered):
    addon = bpy.context.preferences.addons.new()
    addon.module = properties.ADDON
    yield addon.preferences
    bpy.context.preferences.addons.remove(addon)


def colored_box(scene):
    vertices, faces = box_geometry()
    obj = mesh_object(scene, "Box", vertices, faces)
    colors = obj.data.color_attributes.new("Col", "FLOAT_COLOR", "POINT")
    shade = np.column_stack([(np.asarray(vertices)[:, 0] > 0) * 0.9, np.full(8, 0.2), np.full(8, 0.4), np.ones(8)])
    colors.data.foreach_set("color", shade.astype(np.float32).ravel())
    return obj, shade


def intensities(preview):
    values = np.empty(len(preview.data.vertices), np.float32)
    preview.data.attributes["intensity"].data.foreach_get("value", values)
    return values


def test_apply_intensity_model_matches_the_core(scene, preferences, checkpoint):
    obj, shade = colored_box(scene)
    bpy.ops.object.pgt_scan()
    preview = bpy.data.objects["Box Scan"]
    before = intensities(preview)
    preferences.intensity_checkpoint = str(checkpoint)
    bpy.context.view_layer.objects.active = preview
    assert bpy.ops.object.pgt_apply_intensity() == {"FINISHED"}
    after = intensities(preview)
    # the core on the same returns: box frame points, the color of the polygon hit
    settings = scene.pgt_scan
    target = scanning.scan_target(obj)
    result = core_scan(target, settings)
    x, y = settings.distance * np.cos(settings.azimuth), settings.distance * np.sin(settings.azimuth)
    matrix = placement(target.bounds, scanning.PRESETS[settings.sensor], x, y, settings.heading)
    local = (result.xyz - matrix[:3, 3]) @ matrix[:3, :3] - target.bounds.mean(axis=0)
    corner_srgb = srgb_from_linear(shade[:, :3])  # Blender stores float colors linear
    rgb = np.array([corner_srgb[list(p.vertices)].mean(axis=0) for p in obj.data.polygons])[result.returns["face"]]
    expected = dataset_intensity(IntensityEstimator.load(checkpoint).predict(local, target.size, rgb, "object"),
                                 "nuscenes")
    assert len(after) == len(expected) > 100
    assert np.abs(after - expected).max() <= 1.0  # float32 positions may flip a rounding
    assert not np.array_equal(after, before)


def test_with_a_checkpoint_every_scan_is_learned(scene, preferences, checkpoint):
    """A checkpoint in the preferences makes the learned intensity the Scan's default, the
    same values Apply Intensity Model gives."""
    colored_box(scene)
    preferences.intensity_checkpoint = str(checkpoint)
    bpy.ops.object.pgt_scan()
    learned = intensities(bpy.data.objects["Box Scan"])
    preferences.intensity_checkpoint = ""
    bpy.context.view_layer.objects.active = bpy.data.objects["Box"]
    bpy.ops.object.pgt_scan()
    physical = intensities(bpy.data.objects["Box Scan"])
    preferences.intensity_checkpoint = str(checkpoint)
    bpy.context.view_layer.objects.active = bpy.data.objects["Box Scan"]
    assert bpy.ops.object.pgt_apply_intensity() == {"FINISHED"}
    assert np.array_equal(learned, intensities(bpy.data.objects["Box Scan"]))
    assert not np.array_equal(learned, physical)


def test_without_a_checkpoint_the_scan_keeps_its_physical_intensities(scene, preferences):
    colored_box(scene)
    bpy.ops.object.pgt_scan()
    preview = bpy.data.objects["Box Scan"]
    before = intensities(preview)
    bpy.context.view_layer.objects.active = preview
    with pytest.raises(RuntimeError, match="No intensity checkpoint: set one in Preferences"):
        bpy.ops.object.pgt_apply_intensity()
    preferences.intensity_checkpoint = "/nowhere/intensity.pt"
    with pytest.raises(RuntimeError, match="/nowhere/intensity.pt: no intensity-estimator checkpoint here"):
        bpy.ops.object.pgt_apply_intensity()
    assert np.array_equal(intensities(preview), before)


def test_another_dataset_or_class_is_refused(scene, preferences, checkpoint):
    obj, _ = colored_box(scene)
    preferences.intensity_checkpoint = str(checkpoint)
    scene.pgt_scan.sensor = "kitti"
    bpy.ops.object.pgt_scan()
    preview = bpy.data.objects["Box Scan"]
    bpy.context.view_layer.objects.active = preview
    with pytest.raises(RuntimeError, match="trained on nuscenes intensities, not kitti's"):
        bpy.ops.object.pgt_apply_intensity()
    scene.pgt_scan.sensor = "nuscenes"
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.pgt_scan()
    obj.pgt.class_name = "bus"
    bpy.context.view_layer.objects.active = bpy.data.objects["Box Scan"]
    with pytest.raises(RuntimeError, match="has no class 'bus'"):
        bpy.ops.object.pgt_apply_intensity()


def _delete_faces(obj, preview):
    import bmesh

    edited = bmesh.new()
    edited.from_mesh(obj.data)
    bmesh.ops.delete(edited, geom=edited.faces[:6], context="FACES_ONLY")
    edited.to_mesh(obj.data)
    edited.free()


def _delete_faces_of_an_unstamped_scan(obj, preview):
    del preview[scanning.GEOMETRY_TAG]  # a preview saved before previews carried the stamp
    _delete_faces(obj, preview)


def _give_the_name_to_another_mesh(obj, preview):
    obj.name = "Old box"
    mesh_object(bpy.context.scene, "Box", *box_geometry()).scale = (0.1, 0.1, 0.1)
    bpy.context.scene.objects["Box"].data.vertices[0].co.x += 0.5


@pytest.mark.parametrize("edit, problem", [
    (_delete_faces, r"Box: changed since the scan \(its vertices or faces differ, or another object took its name\)"),
    (_give_the_name_to_another_mesh, "Box: changed since the scan"),
    (_delete_faces_of_an_unstamped_scan,
     r"Box: has 6 faces but the scan hit number \d+: it changed since the scan; scan it again"),
    (lambda obj, preview: preview.data.attributes.remove(preview.data.attributes["face"]),
     "Box Scan: has no per-point int attribute 'face': scan Box again"),
    (lambda obj, preview: preview.data.color_attributes.remove(preview.data.color_attributes["color"]),
     "Box Scan: has no per-point color attribute 'color': scan Box again"),
    (lambda obj, preview: setattr(obj, "scale", (1.0, 1.0, 0.0)) or preview.pop(scanning.POSE_TAG),
     "Box: has a zero scale on an axis"),  # a preview made before the pose stamp
    (lambda obj, preview: preview.__setitem__(scanning.POSE_TAG, [0.0] * 15),
     "Box Scan: pgt_sensor_from_object must be 16 finite numbers: scan Box again"),
    (lambda obj, preview: preview.__setitem__(scanning.DATASET_TAG, "waymo"),
     "Box Scan: pgt_dataset = 'waymo' is not one of nuscenes, kitti, lyft"),
])
def test_an_object_or_preview_changed_since_the_scan_is_named(scene, preferences, checkpoint, edit, problem):
    """The preview's face column addresses the source as it was scanned: an edit since is
    named, and the preview keeps every value it had."""
    obj, _ = colored_box(scene)
    bpy.ops.object.pgt_scan()
    preview = bpy.data.objects["Box Scan"]
    edit(obj, preview)
    bpy.context.view_layer.update()
    colors = {attribute.name: color_values(attribute) for attribute in preview.data.color_attributes}
    before = intensities(preview)
    preferences.intensity_checkpoint = str(checkpoint)
    bpy.context.view_layer.objects.active = preview
    with pytest.raises(RuntimeError, match=problem) as error:
        bpy.ops.object.pgt_apply_intensity()
    assert "Traceback" not in str(error.value)
    assert np.array_equal(intensities(preview), before)
    after = {attribute.name: color_values(attribute) for attribute in preview.data.color_attributes}
    assert after.keys() == colors.keys() and all(np.array_equal(after[name], colors[name]) for name in colors)


@pytest.mark.parametrize("moved", [0.0, 1.0])
def test_an_authored_object_is_checked_against_its_scan_in_a_new_session(scene, preferences, checkpoint, tmp_path,
                                                                           moved):
    """An aligned mesh, scanned, then Apply in a new session (no ray target held): the
    scan's values again, or, its vertices moved 1 m up since, the one-line refusal."""
    from pgt_blender.core.samples import write_sample

    path = write_sample(tmp_path, "truck", seed=0)["mesh.ply"]
    assert bpy.ops.import_scene.pgt_mesh(filepath=str(path)) == {"FINISHED"}
    obj = bpy.context.view_layer.objects.active
    assert bpy.ops.object.pgt_align() == {"FINISHED"}
    preferences.intensity_checkpoint = str(checkpoint)
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    preview = bpy.data.objects[f"{obj.name} Scan"]
    learned = intensities(preview)
    for vertex in obj.data.vertices:
        vertex.co.z += moved
    scanning._cache.clear()  # what a reopened file starts with
    bpy.context.view_layer.objects.active = preview
    if not moved:
        assert bpy.ops.object.pgt_apply_intensity() == {"FINISHED"}
        assert np.array_equal(intensities(preview), learned)
        return
    with pytest.raises(RuntimeError, match=f"{obj.name}: changed since the scan") as error:
        bpy.ops.object.pgt_apply_intensity()
    assert "Traceback" not in str(error.value) and np.array_equal(intensities(preview), learned)


def test_moving_the_object_or_its_preview_since_the_scan_changes_nothing(scene, preferences, checkpoint):
    """Apply takes the scan's own pose (stamped on the preview), not the one the two
    objects' placements imply now."""
    obj, _ = colored_box(scene)
    preferences.intensity_checkpoint = str(checkpoint)
    assert bpy.ops.object.pgt_scan() == {"FINISHED"}
    preview = bpy.data.objects["Box Scan"]
    learned = intensities(preview)
    obj.location, obj.rotation_euler.z, preview.location.x = (3.0, -2.0, 0.5), 0.7, 5.0
    bpy.context.view_layer.update()
    bpy.context.view_layer.objects.active = preview
    assert bpy.ops.object.pgt_apply_intensity() == {"FINISHED"}
    assert np.array_equal(intensities(preview), learned)


def test_a_preview_whose_object_name_went_to_a_camera_is_not_a_preview(scene, preferences, checkpoint):
    obj, _ = colored_box(scene)
    bpy.ops.object.pgt_scan()
    bpy.data.objects.remove(obj)
    camera = bpy.data.objects.new("Box", bpy.data.cameras.new("Box"))
    scene.collection.objects.link(camera)
    preferences.intensity_checkpoint = str(checkpoint)
    bpy.context.view_layer.objects.active = bpy.data.objects["Box Scan"]
    with pytest.raises(RuntimeError, match="Select a scan preview .* whose object still exists"):
        bpy.ops.object.pgt_apply_intensity()


def test_apply_intensity_on_a_preview_in_edit_mode(scene, preferences, checkpoint):
    """Edit Mode holds the preview's points in an edit mesh: the operator leaves it for the
    step and returns, with the same values as in Object Mode."""
    colored_box(scene)
    bpy.ops.object.pgt_scan()
    preview = bpy.data.objects["Box Scan"]
    preferences.intensity_checkpoint = str(checkpoint)
    bpy.context.view_layer.objects.active = preview
    assert bpy.ops.object.pgt_apply_intensity() == {"FINISHED"}
    expected = intensities(preview)
    bpy.ops.object.mode_set(mode="EDIT")
    assert bpy.ops.object.pgt_apply_intensity() == {"FINISHED"} and preview.mode == "EDIT"
    bpy.ops.object.mode_set(mode="OBJECT")
    assert np.array_equal(intensities(preview), expected)


def test_a_preview_tag_that_is_no_name_is_no_preview(scene, preferences, checkpoint):
    colored_box(scene)
    bpy.ops.object.pgt_scan()
    preview = bpy.data.objects["Box Scan"]
    preview[scanning.SOURCE_TAG] = 5
    bpy.context.view_layer.objects.active = preview
    with pytest.raises(RuntimeError, match="Select a scan preview"):
        bpy.ops.object.pgt_apply_intensity()
