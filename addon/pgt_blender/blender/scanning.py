"""The Scan section: one simulated LiDAR sweep of a Blender object, shown in the scene.

Frames: an object's mesh data (its local coordinates) is the core's object frame
(+x forward, +y left, +z up, m, what authoring writes). The core places the object in
the sensor frame (sensor at the origin, ground at z = -mounting_height) by
``sensor_from_object``. The results are made in the sensor frame and put where the
object stands: ``matrix_world = object.matrix_world @ inverse(sensor_from_object)``.

Geometry is read and results are written in bulk (``foreach_get`` / ``foreach_set``).
Each object's ScanTarget (its BVH, or its Gaussians for a splat) is built once and cached under the object's name
with a fingerprint of everything that went into it, so scans from other poses reuse
it and an edited mesh, color or material rebuilds it.
"""

import math
import warnings
import zlib
from dataclasses import replace

import bpy
import numpy as np
from mathutils import Matrix

from ..core.errors import InputError, printable
from ..core.scan.raycast import ScanOptions, cast_rays, placement
from ..core.scan.returns import Scan
from ..core.scan.sensors import PRESETS, Sensor, load_sensor_toml
from ..core.scan.targets import (DEFAULT_REFLECTIVITY, ScanTarget, gaussian_target, has_gaussians, mesh_target,
                                 reflectivity_from_linear, reflectivity_from_srgb, resolve_engine,
                                 see_through_materials, surfel_target)
from .objects import (POINTS_GROUP, add_attribute, made_here, mark_made, remove_datablocks, show_as_points,
                      suffixed)
from .properties import field_path

CUSTOM = "CUSTOM"
SCAN_COLLECTION = "PGT Scan"
SOURCE_TAG = "pgt_scan_of"  # on every result object: the name of the object scanned
DATASET_TAG = "pgt_dataset"  # on the points object: whose intensity scale its returns use
GEOMETRY_TAG = "pgt_scanned_geometry"  # on the points object: scanned_geometry of the object scanned
POSE_TAG = "pgt_sensor_from_object"  # on the points object: the scan's 4x4 pose, row by row (16 floats)
POINT_RADIUS = 0.03  # m: a visible dot per return at street distances
GROUND_MARGIN = 10.0  # m beyond the object's distance on each side
CACHE_SIZE = 4  # objects whose BVH stays in memory
# Colormap stops (scene-linear RGB), low to high: dark blue, azure, green, yellow, red.
_RAMP = np.array([[0.004, 0.004, 0.17], [0.0, 0.26, 1.0], [0.01, 0.6, 0.03], [1.0, 0.69, 0.0], [0.79, 0.01, 0.005]])

_cache: dict = {}  # object name -> ((geometry fingerprint, other inputs' fingerprint), ScanTarget)


def sensor_of(settings) -> Sensor:
    """The preset chosen in ``settings`` (``Scene.pgt_scan``), or the custom sensor read
    from its ``sensor_file`` (InputError when that is not a usable sensor TOML)."""
    if settings.sensor in PRESETS:
        return PRESETS[settings.sensor]
    if settings.sensor != CUSTOM:  # "": a stored index this version has no item for
        raise InputError("Scan", "no sensor chosen: choose one in the Scan panel")
    if not settings.sensor_file:
        raise InputError("Custom sensor", "no .toml file chosen")
    return load_sensor_toml(field_path(settings.sensor_file))


def scan(obj: bpy.types.Object, settings, box=None) -> tuple[Scan, Sensor, np.ndarray]:
    """One sweep of ``obj`` standing ``settings.distance`` m from the sensor towards
    ``settings.azimuth`` (rad, from +x counter-clockwise), turned to ``settings.heading``
    (rad), its box ``box`` (2, 3) object frame (authoring.authored_bounds; None: the
    geometry's bounds) on the ground. Returns the scan (sensor frame), the sensor and the
    (4, 4) float64 sensor_from_object. Bad input raises InputError before any Blender
    data is made."""
    not_finite = [name for name in ("distance", "azimuth", "heading") if not math.isfinite(getattr(settings, name))]
    if not_finite:  # min/max do not hold NaN off a property that a script or driver set
        raise InputError("Scan", f"{not_finite[0]} must be a finite number, got {getattr(settings, not_finite[0])}")
    sensor, options = sensor_of(settings), ScanOptions()
    warn_unscanned(obj)
    target = scan_target(obj, settings.surfel_scale, options.engine)
    x, y = settings.distance * math.cos(settings.azimuth), settings.distance * math.sin(settings.azimuth)
    sensor_from_object = placement(target.bounds if box is None else box, sensor, x, y, settings.heading)
    return cast_rays(target, sensor, sensor_from_object, options), sensor, sensor_from_object


def warn_unscanned(obj: bpy.types.Object) -> None:
    """Warn of what the scans and the bank leave out of ``obj``: they read its mesh data in
    metres, not its modifiers (but the PGT Points display) nor its object scale."""
    modifiers = [modifier.name for modifier in obj.modifiers if not (
        modifier.type == "NODES" and modifier.node_group and modifier.node_group.name == POINTS_GROUP)]
    left_out = [f"its modifiers ({', '.join(modifiers)})"] if modifiers else []
    scale = unapplied_scale(obj)
    if scale:
        left_out.append(scale)
    if left_out:
        warnings.warn(printable(f"{obj.name}: {' and '.join(left_out)} are not scanned, only its mesh data: apply "
                                f"them (Object > Apply) to scan what the viewport shows"), stacklevel=2)


def unapplied_scale(obj: bpy.types.Object) -> str:
    """'its scale (2, 2, 2)' when ``obj``'s world scale is not 1, else '': the scans, the
    bank and Set Size read its mesh data, in metres, not what the scale makes of it."""
    scale = obj.matrix_world.to_scale()
    if max(abs(value - 1.0) for value in scale) <= 1e-6:
        return ""
    return f"its scale ({', '.join(f'{value:.4g}' for value in scale)})"


def scan_target(obj: bpy.types.Object, radius_scale: float = 1.0, engine: str = "auto") -> ScanTarget:
    """The (cached) ScanTarget of ``obj``'s mesh data, object frame, m, for ``engine``
    (raycast.ENGINES; built with Blender's BVH for "bvh", its Embree scene for "embree").
    With faces: its triangles, ``source_index`` = the Blender polygon index of each.
    Without: Gaussians when it carries the splat attributes (scale, rotation, opacity:
    splat_attributes), else surfels of ``radius_scale`` x the point spacing;
    ``source_index`` = the vertex index."""
    geometry, rest, build = _target_inputs(obj, radius_scale, resolve_engine(engine))
    fingerprint = (_fingerprint(geometry), _fingerprint(rest))
    cached = _cache.pop(obj.name, None)
    if cached is None or cached[0] != fingerprint:
        cached = (fingerprint, build())
    _cache[obj.name] = cached  # re-inserted: the dict's order is least recently used first
    while len(_cache) > CACHE_SIZE:
        del _cache[next(iter(_cache))]
    return cached[1]


def scanned_geometry(obj: bpy.types.Object) -> str:
    """What a scan's ``face`` column addresses in ``obj``'s mesh, stamped: the fingerprint
    of its vertex positions and, with faces, its triangles and their polygons, as held
    for the target scan_target last made of ``obj`` (call it first; the mesh is not read
    again)."""
    return repr(_cache[obj.name][0][0])


def _target_inputs(obj: bpy.types.Object, radius_scale: float, engine: str):
    """Everything the target is made of (the cache's fingerprint covers it all): the
    geometry a return's ``face`` addresses and the rest; and the function that builds
    the target from them."""
    mesh = obj.data
    vertices = mesh_vertices(mesh)
    if not len(mesh.polygons):
        colors = point_colors(mesh)
        splats = splat_attributes(mesh)
        if has_gaussians(splats):
            return (vertices,), ("gaussians", colors, splats["scale"], splats["rotation"], splats["opacity"]), \
                lambda: gaussian_target(vertices, splats["scale"], splats["rotation"], splats["opacity"], obj.name,
                                        colors)
        opacities = splats.get("opacity")  # faint points are seen through
        return (vertices,), ("surfels", colors, radius_scale, opacities, engine), \
            lambda: surfel_target(vertices, obj.name, colors, radius_scale, engine=engine, opacities=opacities)
    corners, polygon_index = _triangle_corners(mesh)
    triangles = _corner_vertices(mesh)[corners]
    slots = _triangle_slots(obj, polygon_index)
    reflectivity = _face_reflectivity(obj, triangles, corners, slots)
    see_through = _face_see_through(obj, slots)

    def build():
        target = mesh_target(vertices, triangles, obj.name, reflectivity, engine=engine,
                             face_see_through=see_through)
        return replace(target, source_index=polygon_index[target.source_index])

    return (vertices, triangles, polygon_index), ("mesh", reflectivity, see_through, engine), build


SPLAT_ATTRIBUTES = {"opacity": ("FLOAT", "value", 1), "scale": ("FLOAT_VECTOR", "vector", 3),
                    "rotation": ("QUATERNION", "value", 4)}  # name -> (type, field, values per point)


def splat_attributes(mesh: bpy.types.Mesh) -> dict:
    """The Gaussian-splat point attributes the mesh carries, as the importer made them
    (objects.add_attribute): ``opacity`` (N,), ``scale`` (N, 3) m and ``rotation``
    (N, 4) w x y z, float32; absent ones (or of another type or domain) are left out."""
    found = {}
    for name, (attribute, field, width) in _splat_layers(mesh).items():
        values = read(attribute.data, field, len(mesh.vertices) * width, np.float32)
        found[name] = values if width == 1 else values.reshape(-1, width)
    return found


def is_splat(mesh: bpy.types.Mesh) -> bool:
    """Whether a mesh without faces carries every splat attribute (it scans as Gaussians),
    told without reading them: cheap enough for a panel's redraw."""
    return not len(mesh.polygons) and len(_splat_layers(mesh)) == len(SPLAT_ATTRIBUTES)


def _splat_layers(mesh: bpy.types.Mesh) -> dict:
    """name -> (attribute, field, values per point) of the splat attributes ``mesh``
    carries with the importer's type and domain."""
    layers = {}
    for name, (data_type, field, width) in SPLAT_ATTRIBUTES.items():
        attribute = mesh.attributes.get(name)
        if attribute is not None and attribute.data_type == data_type and attribute.domain == "POINT":
            layers[name] = attribute, field, width
    return layers


def _fingerprint(inputs: tuple) -> tuple:
    """What tells a changed target input: arrays by dtype, shape and CRC-32 of their bytes
    (zlib's runs at memory speed; a cache key, not a security check), the rest by repr."""
    return tuple((part.dtype.str, part.shape, zlib.crc32(np.ascontiguousarray(part).data))
                 if isinstance(part, np.ndarray) else repr(part) for part in inputs)


def read(collection, field: str, count: int, dtype) -> np.ndarray:
    values = np.empty(count, dtype)
    collection.foreach_get(field, values)
    return values


def mesh_vertices(mesh: bpy.types.Mesh) -> np.ndarray:
    """(V, 3) float32 vertex positions, object frame, from the "position" attribute (a
    bulk copy, 50x faster than ``vertices``' "co"; an empty mesh has none)."""
    position = mesh.attributes.get("position")
    if position is None:
        return np.zeros((0, 3), np.float32)
    return read(position.data, "vector", len(mesh.vertices) * 3, np.float32).reshape(-1, 3)


def mesh_triangles(mesh: bpy.types.Mesh) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) int32 vertex indices of the mesh's triangulation and (T,) int32 polygon
    each triangle belongs to."""
    corners, polygons = _triangle_corners(mesh)
    return _corner_vertices(mesh)[corners], polygons


def _triangle_corners(mesh: bpy.types.Mesh) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) int32 corner (loop) indices of each triangle of the mesh's triangulation
    and (T,) int32 its polygon. A mesh of triangles only is its own triangulation (the
    usual reconstruction: read in bulk); others go through Blender's loop triangles,
    whose per-element reads are slow on millions of faces."""
    polygons = len(mesh.polygons)
    if len(mesh.loops) == 3 * polygons:  # every polygon has >= 3 corners: all are triangles, in corner order
        return np.arange(3 * polygons, dtype=np.int32).reshape(-1, 3), np.arange(polygons, dtype=np.int32)
    mesh.calc_loop_triangles()
    count = len(mesh.loop_triangles)
    corners = read(mesh.loop_triangles, "loops", count * 3, np.int32).reshape(-1, 3)
    return corners, read(mesh.loop_triangle_polygons, "value", count, np.int32)


def _corner_vertices(mesh: bpy.types.Mesh) -> np.ndarray:
    """(L,) int32 vertex of each corner (loop), from Blender's ".corner_vert" attribute
    (a bulk copy; ``loops``' "vertex_index" is 50x slower)."""
    corner_vert = mesh.attributes.get(".corner_vert")
    if corner_vert is None:
        return read(mesh.loops, "vertex_index", len(mesh.loops), np.int32)
    return read(corner_vert.data, "value", len(mesh.loops), np.int32)


def srgb(attribute) -> np.ndarray:
    """(N, 4) float32 sRGB 0..1 of a color attribute (byte or float, any domain)."""
    return read(attribute.data, "color_srgb", len(attribute.data) * 4, np.float32).reshape(-1, 4)


def color_attribute(mesh: bpy.types.Mesh):
    colors = mesh.color_attributes
    return colors.active_color or next(iter(colors), None)


def point_colors(mesh: bpy.types.Mesh):
    """(N, 4) sRGB per vertex from the color attribute when it is per point, else None."""
    attribute = color_attribute(mesh)
    return srgb(attribute) if attribute is not None and attribute.domain == "POINT" else None


def _triangle_slots(obj: bpy.types.Object, polygons: np.ndarray):
    """(T,) int32 material slot of each triangle (``polygons``: its polygon), or None when
    no slot holds a material."""
    if not any(slot.material for slot in obj.material_slots):
        return None
    slots = read(obj.data.polygons, "material_index", len(obj.data.polygons), np.int32)[polygons]
    return np.clip(slots, 0, len(obj.material_slots) - 1)


def _face_reflectivity(obj: bpy.types.Object, triangles: np.ndarray, corners: np.ndarray, slots):
    """(T,) reflectivity per triangle: the mean over its corners of the color
    attribute (``triangles`` its vertices, ``corners`` its loops), else its material's
    base color (``slots``: _triangle_slots), else None (the core's default)."""
    mesh = obj.data
    attribute = color_attribute(mesh)
    if attribute is not None:
        per_element = triangles if attribute.domain == "POINT" else corners
        return reflectivity_from_srgb(srgb(attribute))[per_element].mean(axis=1)
    return None if slots is None else _material_reflectivity(obj)[slots]


def _face_see_through(obj: bpy.types.Object, slots):
    """(T,) bool per triangle whose material is glass (targets.see_through_materials: by
    name, or an alpha below 1), or None when none is."""
    if slots is None:
        return None
    materials = [slot.material for slot in obj.material_slots]
    per_slot = see_through_materials([material.name if material else "" for material in materials],
                                     [material_alpha(material) if material else 1.0 for material in materials])
    return per_slot[slots] if per_slot[slots].any() else None


def _material_reflectivity(obj: bpy.types.Object) -> np.ndarray:
    """(S,) float32 reflectivity per material slot (the core's default for an empty slot)."""
    materials = [slot.material for slot in obj.material_slots]
    used = [index for index, material in enumerate(materials) if material]
    reflectivity = np.full(len(materials), DEFAULT_REFLECTIVITY, np.float32)
    linear = np.array([base_color(materials[index]) for index in used], np.float64)
    reflectivity[used] = reflectivity_from_linear(linear)
    return reflectivity


def base_color(material: bpy.types.Material) -> tuple:
    """Linear RGB: the material's viewport color (Material > Viewport Display > Color).
    One rule on every Blender version: the node tree is not read, because Blender 5.0
    gives every new material a Principled BSDF (Base Color 0.8) and deprecates
    ``use_nodes``, the switch that told 4.x which color the user meant."""
    return tuple(material.diffuse_color)[:3]


def material_alpha(material: bpy.types.Material) -> float:
    """The viewport color's alpha (the same rule as ``base_color``)."""
    return float(material.diffuse_color[3])


def ramp(values: np.ndarray) -> np.ndarray:
    """(N, 4) float32 linear RGBA of (N,) values in [0, 1] through the colormap _RAMP."""
    stops = np.linspace(0.0, 1.0, len(_RAMP))
    rgb = [np.interp(values, stops, _RAMP[:, channel]) for channel in range(3)]
    return np.column_stack([*rgb, np.ones(len(values))]).astype(np.float32)


def return_colors(returns: np.ndarray, sensor: Sensor, color_by: str) -> np.ndarray:
    """(N, 4) linear RGBA per return: intensity over the dataset's maximum, or ring over
    the beam count, through the colormap."""
    if color_by == "RING":
        values = returns["ring"] / max(sensor.beams - 1, 1)
    else:
        values = returns["intensity"] / sensor.intensity_max
    return ramp(np.clip(values, 0.0, 1.0))


def stats_text(result: Scan) -> str:
    """The panel's statistics line: returns, rays cast, hit rate, core time."""
    return (f"{result.hits} points · {result.rays} rays · {100 * result.efficiency:.0f}% hit · "
            f"{result.seconds * 1e3:.1f} ms")


def show_scan(scene: bpy.types.Scene, source: bpy.types.Object, result: Scan, sensor: Sensor,
              sensor_from_object: np.ndarray, settings) -> bpy.types.Object:
    """Replace ``source``'s previous results in the "PGT Scan" collection by the returns
    ("<name> Scan", a point per return with every column as an attribute), the sensor
    origin ("PGT Sensor") and the ground ("PGT Ground"), all placed where ``source``
    stands. The previous results go only once the new ones are built. ``result`` is the
    scan just made of ``source`` (scanned_geometry reads what its target was made of).
    Returns the points object."""
    world = source.matrix_world @ Matrix(np.linalg.inv(sensor_from_object).tolist())
    scan_name = suffixed(source.name, " Scan")
    made = []
    try:
        points = points_object(scan_name, result.returns,
                               return_colors(result.returns, sensor, settings.color_by), made)
        origin = bpy.data.objects.new("PGT Sensor", None)
        made.append(origin)
        origin.empty_display_type = "PLAIN_AXES"
        ground = _ground_object(sensor.mounting_height, settings.distance + GROUND_MARGIN, made)
        collection = _collection(scene)
    except BaseException:
        remove_datablocks(made)
        raise
    remove_results(source.name)
    points[DATASET_TAG], points[GEOMETRY_TAG] = sensor.dataset, scanned_geometry(source)
    points[POSE_TAG] = np.asarray(sensor_from_object, np.float64).ravel().tolist()
    for obj, name in ((points, scan_name), (origin, "PGT Sensor"), (ground, "PGT Ground")):
        obj.name = name  # the earlier result's name, free now
        if obj.data is not None:  # and its mesh's, which went with it
            obj.data.name = name
        obj[SOURCE_TAG] = source.name
        mark_made(obj)
        obj.matrix_world = world
        collection.objects.link(obj)
    return points


def remove_results(source_name: str) -> None:
    """Remove the result objects of ``source_name``'s last scan and their own meshes; a
    copy of one (Shift+D) or one renamed is the user's and stays (objects.made_here)."""
    old = [obj for obj in bpy.data.objects if obj.get(SOURCE_TAG) == source_name and made_here(obj, untagged=True)]
    meshes = [obj.data for obj in old if obj.type == "MESH" and obj.data.users == 1]
    remove_datablocks(old + meshes)


def _collection(scene: bpy.types.Scene) -> bpy.types.Collection:
    collection = bpy.data.collections.get(SCAN_COLLECTION) or bpy.data.collections.new(SCAN_COLLECTION)
    if collection not in scene.collection.children_recursive:
        scene.collection.children.link(collection)
    return collection


def points_object(name: str, returns: np.ndarray, rgba: np.ndarray, made: list) -> bpy.types.Object:
    """A vertex-only mesh object: positions = the returns' x, y, z (sensor frame, stored
    float32), every other column a point attribute (float32 or int32), and the (N, 4)
    linear ``rgba`` as the active color attribute "color"."""
    name = printable(name)
    mesh = bpy.data.meshes.new(name)
    made.append(mesh)
    mesh.vertices.add(len(returns))
    if len(returns):  # a mesh without vertices has no "position" attribute
        xyz = np.column_stack([returns["x"], returns["y"], returns["z"]]).astype(np.float32)
        mesh.attributes["position"].data.foreach_set("vector", xyz.ravel())
    for column in returns.dtype.names:
        if column not in ("x", "y", "z"):
            values = returns[column]
            add_attribute(mesh, column, values.astype(np.float32 if values.dtype.kind == "f" else np.int32))
    colors = mesh.color_attributes.new("color", "FLOAT_COLOR", "POINT")
    colors.data.foreach_set("color", rgba.ravel())
    mesh.color_attributes.active_color = colors
    mesh.color_attributes.default_color_name = colors.name
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    made.append(obj)
    show_as_points(obj, POINT_RADIUS, made)
    return obj


def _ground_object(mounting_height: float, half_side: float, made: list) -> bpy.types.Object:
    """A square of side 2 ``half_side`` m centred under the sensor at z = -mounting_height
    (sensor frame)."""
    mesh = bpy.data.meshes.new("PGT Ground")
    made.append(mesh)
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half_side
    mesh.vertices.add(4)
    mesh.attributes["position"].data.foreach_set(
        "vector", np.column_stack([corners, np.full(4, -mounting_height)]).astype(np.float32).ravel())
    mesh.loops.add(4)
    mesh.polygons.add(1)
    mesh.loops.foreach_set("vertex_index", np.arange(4, dtype=np.int32))
    mesh.polygons.foreach_set("loop_start", np.zeros(1, np.int32))
    mesh.update(calc_edges=True)
    ground = bpy.data.objects.new("PGT Ground", mesh)
    made.append(ground)
    return ground

