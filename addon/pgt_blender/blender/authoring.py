"""Apply core authoring steps to Blender objects, in bulk.

The mesh data is rewritten in the object frame (``foreach_get`` -> the core's
``apply_transform`` -> ``foreach_set``; a splat's scale and rotation attributes with
``apply_to_splats``), exactly as ``prepare_objects.py`` does with the same arrays; an
object's own matrix (where the user put it) is left alone. Child
cameras follow the rigid part of each step. A child empty, "PGT Box", shows the box.
"""

import json
from contextlib import contextmanager

import bpy
import numpy as np
from mathutils import Matrix

from ..core.authoring.alignment import checked_points
from ..core.authoring.prepare import Step, apply_to_splats, apply_transform, checked_steps, heading_label
from ..core.boxes import centred_bounds
from ..core.errors import InputError
from .objects import _BLENDER_FROM_OPENCV, POINTS_GROUP, suffixed
from .scanning import splat_attributes

BOX_TAG = "pgt_box"


def is_reconstruction(obj) -> bool:
    """Whether ``obj`` is a mesh that pgt_blender imported (the authoring steps' input);
    a kind this version does not know (a stored index past its items reads "") is not."""
    return obj is not None and obj.type == "MESH" and obj.pgt.source_kind not in ("none", "")


@contextmanager
def object_mode(obj: bpy.types.Object):
    """Run the block with the active ``obj`` out of Edit Mode, where its mesh lives in an
    edit mesh (no attributes to read or write), and back in it after, with what the
    block wrote: a user can press Align right after picking the up faces."""
    if obj.mode != "EDIT":
        yield
        return
    bpy.ops.object.mode_set(mode="OBJECT")
    try:
        yield
    finally:
        bpy.ops.object.mode_set(mode="EDIT")


def require_authorable(obj: bpy.types.Object) -> None:
    """InputError when an authoring step cannot apply to ``obj``: it shares its mesh with
    other objects (a linked duplicate: rewriting the mesh would reshape them behind their
    records), its step record is damaged (``steps``), or it has no points, NaN/Inf ones or
    all at one place (nothing to align or size: checked before Author Selected changes
    any object)."""
    if obj.data.users > 1:
        raise InputError(obj.name, f"shares its mesh '{obj.data.name}' with {obj.data.users - 1} other user(s); "
                                   "authoring rewrites the mesh: make it single user first (Object > Relations > "
                                   "Make Single User > Object & Data)")
    steps(obj)
    if not len(obj.data.vertices):
        raise InputError(obj.name, "has no points to author")
    points, _ = checked_points(positions(obj), source=obj.name)
    if not np.ptp(points, axis=0).any():
        raise InputError(obj.name, f"its {len(points)} points all lie at one place: nothing to align or size")


def object_from_world(obj: bpy.types.Object) -> Matrix:
    """The inverse of ``obj``'s world matrix; InputError when it has none (a zero scale
    on an axis)."""
    inverse = obj.matrix_world.inverted(None)
    if inverse is None:
        raise InputError(obj.name, "has a zero scale on an axis: its frame cannot be inverted (fix the scale)")
    return inverse


def positions(obj: bpy.types.Object) -> np.ndarray:
    """(N, 3) float32 vertex positions of ``obj``'s mesh (its local frame)."""
    values = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.attributes["position"].data.foreach_get("vector", values)
    return values.reshape(-1, 3)


def weights(obj: bpy.types.Object):
    """(N,) float32 Gaussian-splat opacity of ``obj``, or None."""
    attribute = obj.data.attributes.get("opacity")
    if attribute is None or attribute.data_type != "FLOAT" or attribute.domain != "POINT":
        return None
    values = np.empty(len(attribute.data), np.float32)
    attribute.data.foreach_get("value", values)
    return values


def cameras(obj: bpy.types.Object) -> list:
    return [child for child in obj.children if child.type == "CAMERA"]


def triangles(obj: bpy.types.Object):
    """(F, 3) int32 vertex indices of ``obj``'s faces, triangulated, or None for a point cloud."""
    mesh = obj.data
    if not len(mesh.polygons):
        return None
    mesh.calc_loop_triangles()
    values = np.empty(len(mesh.loop_triangles) * 3, np.int32)
    mesh.loop_triangles.foreach_get("vertices", values)
    return values.reshape(-1, 3)


FACES_AGREE = 0.5  # a flat part's faces sum to over 95 % of their area (the Chrono roofs: 96-99.5 %)


def selected_face_normal(obj: bpy.types.Object) -> np.ndarray:
    """(3,) area-weighted mean normal of the selected faces (local frame; the object out
    of Edit Mode: ``object_mode``); InputError when none is selected or their normals
    disagree: their area-weighted sum under FACES_AGREE x their area (a whole closed or
    nearly closed surface, as Edit Mode selects a freshly imported mesh, sums to 0-13 %)."""
    mesh = obj.data
    count = len(mesh.polygons)
    selected, normals, areas = np.empty(count, bool), np.empty(count * 3, np.float32), np.empty(count, np.float32)
    mesh.polygons.foreach_get("select", selected)
    mesh.polygons.foreach_get("normal", normals)
    mesh.polygons.foreach_get("area", areas)
    if not selected.any():
        raise InputError(obj.name, "has no selected faces to take up from (select them in Edit Mode)")
    mean = (normals.reshape(-1, 3)[selected] * areas[selected, None]).sum(axis=0)
    agreement = np.linalg.norm(mean) / max(areas[selected].sum(), np.finfo(np.float32).tiny)
    if not agreement >= FACES_AGREE:
        raise InputError(obj.name, f"the normals of its {int(selected.sum())} selected faces disagree (they sum to "
                                   f"{agreement:.0%} of their area, {FACES_AGREE:.0%} needed: all of a closed "
                                   "surface?): select the faces of one flat part, the bottom or the top")
    return mean


def camera_poses(obj: bpy.types.Object) -> np.ndarray:
    """(C, 4, 4) OpenCV world_from_camera of the child cameras, in ``obj``'s local frame."""
    poses = [np.array(_local_matrix(camera)) @ _BLENDER_FROM_OPENCV for camera in cameras(obj)]
    return np.array(poses).reshape(-1, 4, 4)


def _local_matrix(child) -> Matrix:
    return child.matrix_parent_inverse @ child.matrix_basis


def apply_step(obj: bpy.types.Object, step: Step) -> None:
    """Apply ``step`` to the mesh data, the child cameras and the record on ``obj.pgt``;
    ``require_authorable(obj)`` first, as the record is read after the mesh is written."""
    radius = _points_radius(obj)
    mesh = obj.data
    # through vertices, not the position attribute: only this tells Blender the bounds changed
    mesh.vertices.foreach_set("co", apply_transform(positions(obj), step.transform).ravel())
    splats = splat_attributes(mesh)
    if "scale" in splats and "rotation" in splats:  # Gaussian splats turn and stretch with their means
        scales, rotations = apply_to_splats(splats["scale"], splats["rotation"], step.transform)
        mesh.attributes["scale"].data.foreach_set("vector", scales.ravel())
        mesh.attributes["rotation"].data.foreach_set("value", rotations.ravel())
    mesh.update()
    linear = step.transform[:3, :3]
    scale = float(np.cbrt(abs(np.linalg.det(linear))))
    u, _, vt = np.linalg.svd(linear)
    rigid = np.eye(4)
    rigid[:3, :3] = u @ vt  # the rotation part; cameras do not take a scale
    for camera in cameras(obj):
        local = np.array(_local_matrix(camera))
        moved = rigid @ local
        moved[:3, 3] = apply_transform(local[None, :3, 3], step.transform)[0]
        camera.matrix_basis = camera.matrix_parent_inverse.inverted() @ Matrix(moved.tolist())
        camera.data.display_size *= scale
    if radius is not None:  # point radius in object units
        modifier, identifier = radius
        modifier[identifier] = modifier[identifier] * scale
    settings = obj.pgt
    record = steps(obj)
    record.append({"step": step.name, "transform": step.transform.tolist(), "dims": list(step.dims), **step.details})
    product = np.eye(4)
    for done in record:  # float64, as prepare() chains them; the float32 property rounds it once
        product = np.array(done["transform"]) @ product
    settings.object_from_source = Matrix(product.tolist())
    settings.dims = step.dims
    if step.name == "size":
        settings.dataset, settings.class_name = step.details["dataset"], step.details["class"]
    settings.steps_json = json.dumps(record)
    show_box(obj)


def _points_radius(obj: bpy.types.Object):
    """(modifier, input identifier) of the radius the point display draws ``obj`` with,
    or None: no display, or one the user emptied or rewired (it is theirs then)."""
    modifier = obj.modifiers.get(POINTS_GROUP)
    group = getattr(modifier, "node_group", None)
    socket = group.interface.items_tree.get("Radius") if group is not None else None
    if socket is None or not isinstance(modifier.get(getattr(socket, "identifier", "")), float):
        return None
    return modifier, socket.identifier


def show_box(obj: bpy.types.Object) -> bpy.types.Object:
    """The wire cube child showing the object's box (made on first use)."""
    box = next((child for child in obj.children if child.get(BOX_TAG)), None)
    if box is None:
        box = bpy.data.objects.new(suffixed(obj.name, " Box"), None)
        box[BOX_TAG] = True
        box.empty_display_type = "CUBE"
        box.hide_select = True
        for collection in obj.users_collection:
            collection.objects.link(box)
        box.parent = obj
    box.matrix_parent_inverse.identity()
    box.matrix_basis = Matrix.Diagonal((*(max(d, 1e-6) / 2 for d in obj.pgt.dims), 1.0))
    return box


def authored_bounds(obj: bpy.types.Object):
    """(2, 3) float64 the box of ``obj``'s last authoring step, centred on its origin (what
    stands on the ground in the bank and in scan_object.py with a sidecar), or None
    before any step (a scan then takes the geometry's bounds)."""
    record = steps(obj)
    return centred_bounds(record[-1]["dims"]) if record else None


def current_dims(obj: bpy.types.Object) -> np.ndarray:
    """(3,) float64 box of the last step, from the step record: ``pgt.dims`` is float32
    and would make the next step differ from the headless chain in the last bit."""
    record = steps(obj)
    return np.array(record[-1]["dims"]) if record else np.array(obj.pgt.dims, np.float64)


def steps(obj: bpy.types.Object) -> list:
    """The authoring steps applied to ``obj``, oldest first (``pgt.steps_json``);
    InputError when a hand edit left something else there (prepare.checked_steps)."""
    try:
        return checked_steps(json.loads(obj.pgt.steps_json or "[]"), obj.name, "pgt.steps_json")
    except (ValueError, RecursionError) as error:  # bad JSON, or an InputError of checked_steps
        problem = error.problem if isinstance(error, InputError) else f"pgt.steps_json is not JSON ({error})"
        raise InputError(obj.name, f"{problem}; the authoring record is damaged: clear it "
                                   "(pgt.steps_json = '') and author the object again") from None


def record_problem(obj: bpy.types.Object) -> str:
    """What is wrong with ``obj``'s step record (``steps``), or "" when it reads."""
    try:
        steps(obj)
    except InputError as error:
        return error.problem
    return ""


def status(obj: bpy.types.Object) -> dict:
    """What is done and what is left, read off the step record: aligned; how the heading
    was decided since the last alignment (heading_label; a new PCA may turn the
    front away); the last size mode."""
    done = {"aligned": False, "heading": "", "size": ""}
    for step in steps(obj):
        if step["step"] == "align":
            done.update(aligned=True, heading="")
        elif step["step"] == "heading":
            done["heading"] = heading_label(step)
        else:
            done["size"] = step["mode"]
    return done
