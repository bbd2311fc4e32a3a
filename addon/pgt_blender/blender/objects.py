"""Create Blender data from core results, in bulk (``foreach_set``, no per-point Python).

Frames: a reconstruction object keeps the source frame as its local frame (identity
matrix on import). Its cameras are children of it, so they follow when the
authoring steps move the object. Blender cameras look along their local -z with +y
up; COLMAP/OpenCV cameras look along +z with +y down, hence ``_BLENDER_FROM_OPENCV``.
"""

import bpy
import numpy as np
from mathutils import Matrix

from ..core.errors import InputError, printable
from ..core.reconstruction import CameraView, Reconstruction

_BLENDER_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
ROLE_TAG = "pgt_role"  # on a collection the add-on made: what it shows (replace_collection)
MADE_TAG = "pgt_made_as"  # on what the add-on made and replaces later: the name it was made with
_SENSOR_WIDTH_MM = 36.0
MAX_NAME_BYTES = 63  # Blender cuts a datablock's name to this many UTF-8 bytes
_ATTRIBUTE_TYPES = {  # (dtype kind, columns) -> (Blender type, foreach_set field)
    ("f", 1): ("FLOAT", "value"), ("i", 1): ("INT", "value"), ("b", 1): ("BOOLEAN", "value"),
    ("f", 2): ("FLOAT2", "vector"), ("f", 3): ("FLOAT_VECTOR", "vector"),
    ("f", 4): ("QUATERNION", "value"),
}


def add_reconstruction(scene: bpy.types.Scene, recon: Reconstruction, with_cameras: bool = True,
                       collection: bpy.types.Collection | None = None, made: list | None = None) -> bpy.types.Object:
    """Link a new object holding ``recon`` (and its cameras as children) into
    ``collection`` (default: the scene's master collection). With cameras, the scene's
    render resolution becomes the first camera's, so the camera views match the photos.
    The datablocks made are added to ``made``; on any failure every one in it is removed
    again (pass one list to several calls to take back them all)."""
    collection = collection or scene.collection
    made = [] if made is None else made
    try:
        mesh = _mesh(recon, made)
        obj = bpy.data.objects.new(printable(recon.name), mesh)
        made.append(obj)
        settings = obj.pgt
        settings.source_path = str(recon.source)
        settings.source_kind = recon.kind
        settings.source_sha256 = recon.sha256
        collection.objects.link(obj)
        extent = max(float(np.ptp(axis)) for axis in recon.positions.T)  # by column: 25x faster than axis=0
        if not len(recon.faces):
            show_as_points(obj, radius=0.5 * extent / np.sqrt(len(recon.positions)), made=made)
        if with_cameras and recon.cameras:
            scene.render.resolution_x, scene.render.resolution_y = recon.cameras[0].width, recon.cameras[0].height
            scene.render.resolution_percentage = 100
            for view in recon.cameras:
                camera = _camera(view, extent, made)
                camera.parent = obj
                collection.objects.link(camera)
        return obj
    except BaseException:
        remove_datablocks(made)
        raise


def box_empty(of: str, box: np.ndarray, made: list) -> bpy.types.Object:
    """A cube empty "<of> box" drawing a (>= 7,) centre box x y z dx dy dz heading (sensor frame)."""
    cube = bpy.data.objects.new(suffixed(of, " box"), None)
    made.append(cube)
    cube.empty_display_type = "CUBE"
    cube.location, cube.rotation_euler, cube.scale = box[:3], (0.0, 0.0, box[6]), np.asarray(box[3:6]) / 2
    return cube


def suffixed(name: str, suffix: str) -> str:
    """``printable(name)`` + ``suffix`` within Blender's MAX_NAME_BYTES: the name is
    shortened by whole characters so that the suffix stays (cut off, a long object's
    " Scan" would leave its result named like the object itself, then ".001")."""
    room = MAX_NAME_BYTES - len(suffix.encode())
    return printable(name).encode()[:room].decode(errors="ignore") + suffix


def mark_made(block) -> None:
    """Tag ``block`` (an ID) as made by the add-on under its current name (``made_here``)."""
    block[MADE_TAG] = block.name


def made_here(block, untagged: bool = False) -> bool:
    """Whether ``block`` is still what the add-on made, to replace at will: a copy of it
    (Shift+D, Duplicate Collection) or a renamed one has another name and is the user's.
    A block without the tag is the user's (an object they linked into the add-on's
    collection), unless ``untagged``: the caller knows it by another tag of the add-on's,
    saved before blocks carried this one (a scan result's source)."""
    return block.get(MADE_TAG, block.name if untagged else None) == block.name


def replace_collection(scene: bpy.types.Scene, role: str, objects: list) -> bpy.types.Collection:
    """A new collection named ``role`` in ``scene`` holding ``objects``, in place of the
    one made for ``role`` before, which goes with the objects made in it and their own
    meshes; what the user made, copied or renamed stays: their objects in it move to the
    scene's collection, their collection of that name makes the new one take Blender's
    next free name."""
    old = next((c for c in bpy.data.collections if c.get(ROLE_TAG) == role and made_here(c)), None)
    if old is not None:
        ours = [obj for obj in old.objects if made_here(obj)]
        for obj in old.objects:
            if not made_here(obj) and len(obj.users_collection) == 1:
                scene.collection.objects.link(obj)
        remove_datablocks(ours + [obj.data for obj in ours if obj.type == "MESH" and obj.data.users == 1])
        bpy.data.collections.remove(old)
    collection = bpy.data.collections.new(role)
    collection[ROLE_TAG] = role
    mark_made(collection)
    scene.collection.children.link(collection)
    for obj in objects:
        collection.objects.link(obj)
        mark_made(obj)
        # made while the old ones held their names: "entry.001" takes back "entry" once it is free
        base, dot, number = obj.name.rpartition(".")
        if dot and number.isdigit() and base not in bpy.data.objects:
            obj.name = base
    return collection


def remove_datablocks(datablocks) -> None:
    """Remove objects, meshes, cameras and node groups (objects first, so data has no users)."""
    for block in sorted(datablocks, key=lambda b: not isinstance(b, bpy.types.Object)):
        collection = {bpy.types.Object: bpy.data.objects, bpy.types.Mesh: bpy.data.meshes,
                      bpy.types.Camera: bpy.data.cameras,
                      bpy.types.GeometryNodeTree: bpy.data.node_groups}[type(block)]
        collection.remove(block)


POINTS_GROUP = "PGT Points"


def show_as_points(obj: bpy.types.Object, radius: float, made: list) -> None:
    """Blender does not draw loose vertices in Object Mode: a Mesh to Points geometry
    nodes modifier shows the cloud (viewport and render, color attributes carried
    over) while the mesh keeps the imported data untouched."""
    group = bpy.data.node_groups.get(POINTS_GROUP)
    if group is None:
        group = bpy.data.node_groups.new(POINTS_GROUP, "GeometryNodeTree")
        made.append(group)
        group.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
        group.interface.new_socket("Radius", in_out="INPUT", socket_type="NodeSocketFloat")
        group.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
        inputs, outputs = group.nodes.new("NodeGroupInput"), group.nodes.new("NodeGroupOutput")
        to_points = group.nodes.new("GeometryNodeMeshToPoints")
        group.links.new(inputs.outputs["Geometry"], to_points.inputs["Mesh"])
        group.links.new(inputs.outputs["Radius"], to_points.inputs["Radius"])
        group.links.new(to_points.outputs["Points"], outputs.inputs["Geometry"])
    modifier = obj.modifiers.new(POINTS_GROUP, "NODES")
    modifier.node_group = group
    modifier[group.interface.items_tree["Radius"].identifier] = max(radius, 1e-6)


def _mesh(recon: Reconstruction, made: list) -> bpy.types.Mesh:
    mesh = bpy.data.meshes.new(printable(recon.name))
    made.append(mesh)
    mesh.vertices.add(len(recon.positions))
    mesh.attributes["position"].data.foreach_set("vector", recon.positions.ravel())
    if len(recon.faces):
        corners = recon.faces.ravel()
        mesh.loops.add(len(corners))
        mesh.polygons.add(len(recon.faces))
        mesh.loops.foreach_set("vertex_index", corners)
        mesh.polygons.foreach_set("loop_start", np.arange(0, len(corners), 3, dtype=np.int32))
    if recon.colors is not None:
        colors = mesh.color_attributes.new("Col", "BYTE_COLOR", "POINT")
        colors.data.foreach_set("color_srgb", recon.colors.ravel())
        mesh.color_attributes.active_color = colors
    for name, values in recon.attributes.items():
        if name in mesh.attributes or name.startswith("."):
            raise InputError(recon.source, f"property '{name}' has the name of a Blender attribute the mesh "
                                           f"already has; rename it")
        add_attribute(mesh, name, values, recon.source)
    mesh.update(calc_edges=bool(len(recon.faces)))
    return mesh


def add_attribute(mesh: bpy.types.Mesh, name: str, values: np.ndarray, source=None) -> None:
    """A new per-point attribute ``name`` holding ``values`` (N,) or (N, k); InputError
    naming ``source`` when Blender reserves the name for a built-in attribute of
    another type or domain (``id``, ``sharp_face``, ``material_index``, ...) or the
    name is longer than Blender keeps (67 bytes in 4.5)."""
    columns = 1 if values.ndim == 1 else values.shape[1]
    data_type, field = _ATTRIBUTE_TYPES[(values.dtype.kind, columns)]
    attribute = mesh.attributes.new(name, data_type, "POINT")
    if attribute is None or attribute.name != name:
        size = len(name.encode())
        reason = (f"is {size} bytes long, too long for a Blender attribute name" if size > 63
                  else "has the name of a built-in Blender attribute")
        raise InputError(source or mesh.name, f"property '{name}' {reason}; rename it")
    attribute.data.foreach_set(field, np.ascontiguousarray(values).ravel())


def camera_intrinsics(view: CameraView) -> dict:
    """Blender camera settings reproducing the pinhole (fx, cx, cy) of ``view``.

    Horizontal sensor fit: ``lens`` / ``sensor_width`` = fx / width. Shifts are in
    units of the image width; +x shift moves the principal point right, +y up (the
    image's v axis points down, hence the sign flip).
    """
    return {
        "sensor_fit": "HORIZONTAL",
        "sensor_width": _SENSOR_WIDTH_MM,
        "lens": view.fx * _SENSOR_WIDTH_MM / view.width,
        "shift_x": (view.cx - view.width / 2) / view.width,
        "shift_y": (view.height / 2 - view.cy) / view.width,
    }


def _camera(view: CameraView, extent: float, made: list) -> bpy.types.Object:
    data = bpy.data.cameras.new(printable(view.name))
    made.append(data)
    for key, value in camera_intrinsics(view).items():
        setattr(data, key, value)
    data.display_size = max(extent * 0.05, 1e-3)
    camera = bpy.data.objects.new(data.name, data)
    made.append(camera)
    camera.matrix_world = Matrix((view.world_from_camera @ _BLENDER_FROM_OPENCV).tolist())
    # What Blender cannot represent stays readable on the object.
    camera["pgt_resolution"] = (view.width, view.height)
    camera["pgt_focal_px"] = (view.fx, view.fy)
    camera["pgt_camera_model"] = view.model
    camera["pgt_camera_params"] = list(view.params)
    return camera
