"""What a scan hits: one object's surface in its object frame, with its ray structure (Embree
scene or Blender BVH) built once.

Object frame: +x forward, +y left, +z up, metres (what authoring writes). Meshes are
used as they are (open, non-manifold and self-intersecting meshes are fine: a ray
takes the nearest triangle). Gaussian splats (scales, rotations and opacities) are
scanned as Gaussians (gaussians.py: each ray composites the splats it meets). Point
clouds, and splats when asked, become *surfels*: one flat hexagon per point with the
area of its disk, so a reconstruction is scanned without meshing.

A LiDAR sees through glass: rays pass see-through polygons (glass and window
materials, transparent ones, splats fainter than SEE_THROUGH_OPACITY) and return from
what lies behind, as a car's windows return the seats or nothing.
"""

import importlib
import re
import warnings
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..authoring.alignment import density_inliers
from ..errors import InputError
from .gaussians import Gaussians, rotation_matrices

SURFEL_SIDES = 6
# A hexagon with the disk's area: circumradius = r * sqrt(2 pi / (3 sqrt 3)).
_HEXAGON_FOR_DISK = np.sqrt(2 * np.pi / (3 * np.sqrt(3)))
SPLAT_SIGMAS = 2.0  # a splat's disk reaches 2 sigma along its two larger axes
DEFAULT_REFLECTIVITY = 0.5
MAX_COORDINATE = 1e8  # m, per axis: 100,000 km from the origin is a unit or import mistake, not an object
SEE_THROUGH_NAMES = re.compile(r"glass|window|windshield|windscreen", re.IGNORECASE)
SEE_THROUGH_OPACITY = 0.5  # a splat fainter than this is seen through


def bvhtree_class():
    """``mathutils.bvhtree.BVHTree``. Blender has mathutils built in; the PyPI ``bpy``
    wheel registers it only once bpy has loaded, so outside Blender load that first.
    Nothing here touches bpy's data API."""
    try:
        from mathutils.bvhtree import BVHTree
    except ModuleNotFoundError:
        importlib.import_module("bpy")
        from mathutils.bvhtree import BVHTree
    return BVHTree


# What a mesh or surfel target is cast with: Blender's BVH or an Embree scene.
TARGET_ENGINES = ("bvh", "embree")


def resolve_engine(engine: str) -> str:
    """The engine ``engine`` names: "auto" is "embree" when embreex imports, else "bvh"."""
    return ("embree" if embree_available() else "bvh") if engine == "auto" else engine


@lru_cache(maxsize=None)
def embree_available() -> bool:
    try:
        import embreex  # noqa: F401  (only whether it imports)
    except ImportError:
        return False
    return True


@dataclass
class ScanTarget:
    """One object ready to be scanned from any pose.

    bvh:          mathutils BVHTree over the polygons (float32 inside), built by
                  blender_bvh for the "bvh" engine; None until then, and for Gaussians.
    bounds:       (2, 3) float64 [min, max] corners of the object's box, object frame,
                  m: of the mesh's vertices or the cloud's points. Placement and the
                  output box use it.
    cast_bounds:  (2, 3) float64 box around every polygon (surfels reach past their
                  points); the ray window uses it.
    planes:       (P, 4) float64 per polygon: unit normal n and offset n . v, so a hit's
                  range is refined in float64 on its polygon's plane.
    reflectivity: (P,) float32 in [0, 1] per polygon, relative to the object (its
                  area-weighted mean is DEFAULT_REFLECTIVITY: relative_reflectivity),
                  for the physical intensity and the ray drop.
    source_index: (P,) int32: the mesh face (or point) each polygon came from; the
                  scan's ``face`` column.
    kind:         "mesh", "surfels" or "gaussians".
    see_through:  (P,) bool per polygon, or None: glass and faint splats, which a ray
                  passes on to what lies behind (raycast.trace_rays).
    triangle_vertices (V, 3) float32, triangle_faces (T, 3) int32: the polygons as an
                  indexed triangle mesh, and triangle_polygon (T,) int32 the polygon of
                  each triangle: what the Embree scene and the BVH are built from.
    embree_scene: the Embree scene (embree_scene), None until built.
    """

    bvh: object
    bounds: np.ndarray
    cast_bounds: np.ndarray
    planes: np.ndarray
    reflectivity: np.ndarray
    source_index: np.ndarray
    kind: str
    name: str = "object"
    triangle_vertices: np.ndarray | None = None
    triangle_faces: np.ndarray | None = None
    triangle_polygon: np.ndarray | None = None
    embree_scene: object = None
    see_through: np.ndarray | None = None
    gaussians: Gaussians | None = None

    @property
    def size(self) -> np.ndarray:
        return self.bounds[1] - self.bounds[0]


def embree_scene(target: ScanTarget):
    """The Embree scene of ``target``'s triangles, built and committed on first use and
    kept on the target (one per object, reused by every cast). ImportError without
    embreex; ValueError for a Gaussian target (no triangles: its own compositing)."""
    if target.triangle_vertices is None:
        raise ValueError(f"{target.name}: a {target.kind} target has no triangles for Embree")
    if target.embree_scene is None:
        try:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh
        except ImportError:
            raise ImportError("the embree engine needs embreex (pip install embreex)") from None
        scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene, target.triangle_vertices, target.triangle_faces)
        # Embree builds its BVH on a scene's first query and embreex has no commit call
        scene.run(np.zeros((1, 3), np.float32), np.array([[0.0, 0.0, 1.0]], np.float32), output=1)
        target.embree_scene = scene
    return target.embree_scene


def blender_bvh(target: ScanTarget):
    """Blender's BVH over ``target``'s polygons (its triangles; a surfel's hexagon), built
    on first use and kept on the target, like embree_scene."""
    if target.triangle_vertices is None:
        raise ValueError(f"{target.name}: a {target.kind} target has no polygons for a BVH")
    if target.bvh is None:
        surfels = target.kind == "surfels"
        polygons = np.arange(len(target.triangle_vertices)).reshape(-1, SURFEL_SIDES) if surfels \
            else target.triangle_faces
        target.bvh = bvhtree_class().FromPolygons(target.triangle_vertices.tolist(), polygons.tolist(),
                                                  all_triangles=not surfels, epsilon=0.0)
    return target.bvh


def ready_for(target: ScanTarget, engine: str) -> ScanTarget:
    """``target`` with what ``engine`` casts on built ("auto" resolved): Blender's BVH or
    the Embree scene, so a cached target's first scan costs what the others do (Gaussians
    have their own compositing). ValueError for an unknown engine name."""
    if target.gaussians is None:
        (embree_scene if _checked_engine(engine) == "embree" else blender_bvh)(target)
    return target


def _checked_engine(engine: str) -> str:
    resolved = resolve_engine(engine)
    if resolved not in TARGET_ENGINES:
        raise ValueError(f"engine must be one of auto, {', '.join(TARGET_ENGINES)}, got {engine!r}")
    return resolved


def reflectivity_from_linear(rgb: np.ndarray) -> np.ndarray:
    """(N,) float32 reflectivity in [0, 1]: the relative luminance of (N, 3 or 4)
    linear RGB (Blender's material colors). Visible albedo stands in for the
    near-infrared reflectance a LiDAR sees; the learned intensity estimator corrects it."""
    linear = np.clip(np.asarray(rgb, np.float64)[:, :3], 0.0, 1.0)
    return (linear @ np.array([0.2126, 0.7152, 0.0722])).astype(np.float32)


def srgb_from_linear(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) sRGB in [0, 1] of linear RGB (Blender's material colors)."""
    linear = np.clip(np.asarray(rgb, np.float64), 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055).astype(np.float32)


def reflectivity_from_srgb(colors: np.ndarray) -> np.ndarray:
    """As reflectivity_from_linear, for (N, 3 or 4) sRGB colors in [0, 1] (files, color attributes)."""
    srgb = np.clip(np.asarray(colors, np.float64)[:, :3], 0.0, 1.0)
    return reflectivity_from_linear(np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4))


def _planes(normals: np.ndarray, points: np.ndarray, lengths: np.ndarray | None = None) -> np.ndarray:
    """(N, 4) unit normal and offset (n . x = offset) of planes through ``points`` (N, 3)
    along ``normals`` (N, 3), whose ``lengths`` (N,) are taken when the caller has them."""
    lengths = np.linalg.norm(normals, axis=1) if lengths is None else lengths
    normals = normals / lengths[:, None]
    return np.column_stack([normals, np.einsum("ij,ij->i", normals, points)])


def _vertex_bounds(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(2, 3) min and max corner of the ``vertices`` (V, 3) that ``faces`` (F, 3) use."""
    used = np.zeros(len(vertices), bool)
    used[faces.ravel()] = True
    corners = vertices[used]
    return np.stack([corners.min(0), corners.max(0)])


def relative_reflectivity(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(N,) float32: ``values`` (N,) scaled so that their ``weights``-weighted (areas)
    mean is DEFAULT_REFLECTIVITY, then clipped to [0, 1]; DEFAULT_REFLECTIVITY everywhere
    for an all-black object. Colors set the contrast within an object and the sensor's
    intensity law (fitted at DEFAULT_REFLECTIVITY) the level: a photo's exposure and
    white balance, or a material file's color convention, say little about a surface's
    near-infrared reflectivity."""
    values = np.clip(np.asarray(values, np.float64), 0, 1)
    mean = np.average(values, weights=weights) if np.sum(weights) > 0 else values.mean()
    if not mean > 0:
        return np.full(len(values), DEFAULT_REFLECTIVITY, np.float32)
    return np.clip(values * (DEFAULT_REFLECTIVITY / mean), 0, 1).astype(np.float32)


def _require_coordinates(points: np.ndarray, name: str, what: str) -> None:
    """InputError naming ``name`` when a row of ``points`` (N, 3) m is NaN, infinite or
    farther than MAX_COORDINATE from the origin on an axis."""
    bad = ~(np.abs(points) <= MAX_COORDINATE).all(axis=1)  # NaN compares False
    if bad.any():
        raise InputError(name, f"{int(bad.sum())} {what} are NaN or infinite or lie over {MAX_COORDINATE:.0e} m "
                               "from the origin (a unit or import mistake)")


def _triangles(vertices: np.ndarray, faces: np.ndarray, name: str) -> tuple:
    """(corners (F, 3, 3), normals (F, 3) of length twice the area, twice the areas (F,),
    keep (F,) bool: not of zero area, bounds (2, 3) of the faces' vertices) of the (F, 3)
    ``faces`` of float64 ``vertices``; InputError naming ``name`` for no faces, indices
    out of range, bad coordinates or every face of zero area."""
    if len(faces) == 0 or len(vertices) == 0:
        raise InputError(name, "mesh has no faces to scan")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InputError(name, f"face indices out of range for {len(vertices)} vertices")
    _require_coordinates(vertices, name, "vertices")
    corners = vertices[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    doubled_area = np.linalg.norm(normals, axis=1)
    bounds = _vertex_bounds(vertices, faces)
    keep = doubled_area > 1e-12 * np.max(bounds[1] - bounds[0])**2
    if not keep.any():
        raise InputError(name, "every face has zero area")
    return corners, normals, doubled_area, keep, bounds


def require_scannable(positions, faces, name: str, attributes: dict | None = None) -> None:
    """InputError naming ``name`` for geometry no ray target can be made of, as
    mesh_target (``faces`` (F, 3) given), gaussian_target (``attributes`` holding the
    splat fields: has_gaussians) or surfel_target refuse it: what a bank checks before
    its output folder is made."""
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    if len(faces):
        _triangles(positions, np.asarray(faces, np.int64).reshape(-1, 3), name)
        return
    if not len(positions):
        raise InputError(name, "point cloud is empty")
    _require_coordinates(positions, name, "points")
    if attributes is None or not has_gaussians(attributes):
        return
    for what in ("scale", "rotation", "opacity"):
        values = np.asarray(attributes[what], np.float64)
        if len(values) != len(positions) or not np.isfinite(values).all():
            raise InputError(name, f"splat {what} must be {len(positions)} finite rows")
    if (np.linalg.norm(np.asarray(attributes["rotation"], np.float64), axis=1) == 0).any():
        raise InputError(name, "a splat has a zero-length rotation quaternion")


def mesh_target(vertices: np.ndarray, faces: np.ndarray, name: str = "object",
                face_reflectivity: np.ndarray | None = None, engine: str = "auto",
                face_see_through: np.ndarray | None = None) -> ScanTarget:
    """Triangles, built for ``engine`` (ready_for; the other engine's structure is built
    when first cast with). vertices (V, 3) object frame m; faces (F, 3) int;
    ``face_see_through`` (F,) bool marks glass (see_through_materials).
    Faces of zero area (or with a repeated vertex) are dropped with a warning; an empty
    mesh or non-finite vertices are an InputError naming ``name``."""
    _checked_engine(engine)
    vertices = np.asarray(vertices, np.float64).reshape(-1, 3)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    corners, normals, doubled_area, keep, bounds = _triangles(vertices, faces, name)
    kept = np.flatnonzero(keep)
    used, origins = faces, corners[:, 0]
    if len(kept) < len(faces):
        warnings.warn(f"{name}: dropped {int((~keep).sum())} zero-area faces of {len(faces)}", stacklevel=2)
        used, origins, normals, doubled_area = faces[kept], origins[kept], normals[kept], doubled_area[kept]
        bounds = _vertex_bounds(vertices, used)
    reflectivity = np.full(len(kept), DEFAULT_REFLECTIVITY, np.float32)
    if face_reflectivity is not None:
        given = np.asarray(face_reflectivity, np.float32).reshape(-1)
        if len(given) != len(faces):
            raise InputError(name, f"{len(given)} face reflectivities for {len(faces)} faces")
        reflectivity = relative_reflectivity(given[kept], doubled_area)
    see_through = None
    if face_see_through is not None:
        see_through = np.asarray(face_see_through, bool).reshape(-1)
        if len(see_through) != len(faces):
            raise InputError(name, f"{len(see_through)} see-through flags for {len(faces)} faces")
        see_through = see_through[kept] if see_through[kept].any() else None
    return ready_for(ScanTarget(None, bounds, bounds, _planes(normals, origins, doubled_area), reflectivity,
                                kept.astype(np.int32), "mesh", name, vertices.astype(np.float32),
                                used.astype(np.int32), np.arange(len(kept), dtype=np.int32),
                                see_through=see_through), engine)


def see_through_materials(names, alphas=None) -> np.ndarray:
    """(M,) bool: materials a LiDAR sees through, by name (``glass``, ``window``,
    ``windshield``, any case) or by an alpha below 1 (a transparent material)."""
    by_name = np.array([bool(SEE_THROUGH_NAMES.search(name or "")) for name in names], bool)
    return by_name if alphas is None else by_name | (np.asarray(alphas, np.float64) < 1.0)


def local_frames(positions: np.ndarray, neighbours: int = 8):
    """Per point: (N, 3) normal (local PCA's smallest axis), (N, 3, 2) the two tangent
    axes, and (N,) spacing = mean distance to the ``neighbours`` nearest distinct points
    (m): a repeated point's copies count once, or its nearest would be its copies at 0 m
    and its surfel shrink to nothing."""
    from scipy.spatial import cKDTree

    k = min(neighbours, len(positions) - 1)
    if k < 3:
        raise ValueError(f"{len(positions)} distinct points are too few for local surface frames")
    distances, index = cKDTree(positions).query(positions, k=k + 1)
    if (distances[:, 1] == 0).any():  # sorted only where a point repeats: other clouds cost nothing more
        distinct, inverse = np.unique(positions, axis=0, return_inverse=True)
        normals, tangents, spacing = local_frames(distinct, neighbours)
        inverse = inverse.ravel()
        return normals[inverse], tangents[inverse], spacing[inverse]
    around = positions[index[:, 1:]] - positions[:, None, :]
    around -= around.mean(axis=1, keepdims=True)
    _, axes = np.linalg.eigh(np.einsum("nki,nkj->nij", around, around))
    return axes[:, :, 0], axes[:, :, 1:], distances[:, 1:].mean(axis=1)


def surfel_target(positions: np.ndarray, name: str = "object", colors: np.ndarray | None = None,
                  radius_scale: float = 1.0, neighbours: int = 8,
                  scales: np.ndarray | None = None, rotations: np.ndarray | None = None,
                  engine: str = "auto", opacities: np.ndarray | None = None) -> ScanTarget:
    """Oriented surfels for a point cloud, object frame (m), built for ``engine`` (as
    mesh_target).

    Point clouds: normal from local PCA over ``neighbours`` points, radius =
    ``radius_scale`` x the mean distance to them. Floaters (isolated points: the
    alignment's density test, authoring.alignment.density_inliers) are left out: a
    floater's disk is as wide as its distance to the surface, and a few percent of them
    hid the object from most rays (80-99 % of a built-in sample's returns came from its
    3 % of floaters). Gaussian splats (``scales`` (N, 3) m,
    ``rotations`` (N, 4) w x y z): an ellipse along the two larger axes with semi-axes
    ``SPLAT_SIGMAS`` x scale (x ``radius_scale``), normal along the smallest; a splat
    with ``opacities`` below SEE_THROUGH_OPACITY lets rays pass (see_through).
    """
    _checked_engine(engine)
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    require_scannable(positions, (), name)
    if not radius_scale > 0:
        raise InputError(name, f"surfel radius scale must be positive, got {radius_scale}")
    splats = scales is not None and rotations is not None
    kept = np.arange(len(positions)) if splats else np.flatnonzero(density_inliers(positions))
    positions = positions[kept]
    if splats:
        axes = rotation_matrices(rotations)
        scales = np.asarray(scales, np.float64)
        order = np.argsort(scales, axis=1)[:, ::-1]  # largest first
        tangents = np.take_along_axis(axes, order[:, None, :2], axis=2)
        semi_axes = SPLAT_SIGMAS * radius_scale * np.take_along_axis(scales, order[:, :2], axis=1)
    else:
        try:
            _, tangents, spacing = local_frames(positions, neighbours)
        except ValueError as error:
            raise InputError(name, str(error)) from None
        semi_axes = np.repeat((radius_scale * spacing)[:, None], 2, axis=1)
    angles = 2 * np.pi * np.arange(SURFEL_SIDES) / SURFEL_SIDES
    unit = np.stack([np.cos(angles), np.sin(angles)], axis=1) * _HEXAGON_FOR_DISK  # (S, 2)
    # corner (n, s) = centre + sum_k unit[s, k] * semi_axes[n, k] * tangents[n, :, k]
    corners = positions[:, None, :] + np.einsum("sk,nk,nik->nsi", unit, semi_axes, tangents)
    polygons = np.arange(len(positions) * SURFEL_SIDES).reshape(-1, SURFEL_SIDES)
    reflectivity = (np.full(len(positions), DEFAULT_REFLECTIVITY, np.float32) if colors is None
                    else relative_reflectivity(reflectivity_from_srgb(colors[kept]), semi_axes.prod(axis=1)))
    flat = corners.reshape(-1, 3)
    normals = np.cross(tangents[:, :, 0], tangents[:, :, 1])
    fan = np.array([[0, side, side + 1] for side in range(1, SURFEL_SIDES - 1)])  # a hexagon as 4 triangles
    faint = None if opacities is None else np.asarray(opacities, np.float64).reshape(-1)[kept] < SEE_THROUGH_OPACITY
    return ready_for(ScanTarget(None, np.stack([positions.min(0), positions.max(0)]),
                                np.stack([flat.min(0), flat.max(0)]), _planes(normals, positions), reflectivity,
                                kept.astype(np.int32), "surfels", name,
                                flat.astype(np.float32), polygons[:, fan].reshape(-1, 3).astype(np.int32),
                                np.repeat(np.arange(len(positions), dtype=np.int32), len(fan)),
                                see_through=faint if faint is not None and faint.any() else None), engine)


def element_colors(reconstruction) -> np.ndarray:
    """(E, 3) float32 sRGB of what a scan's ``face`` column indexes: per face (the mean of
    its vertices' colors) for a mesh, per point otherwise; grey (0.5) without colors."""
    if reconstruction.colors is None:
        return np.full((len(reconstruction.faces) or len(reconstruction.positions), 3), 0.5, np.float32)
    colors = reconstruction.colors[:, :3]
    return colors[reconstruction.faces].mean(axis=1) if len(reconstruction.faces) else colors


def gaussian_target(positions: np.ndarray, scales: np.ndarray, rotations: np.ndarray, opacities: np.ndarray,
                    name: str = "object", colors: np.ndarray | None = None) -> ScanTarget:
    """Gaussian splats scanned as Gaussians (gaussians.py), object frame (m):
    ``positions`` (N, 3) means, ``scales`` (N, 3) standard deviations, ``rotations``
    (N, 4) w x y z, ``opacities`` (N,) in [0, 1]. ``cast_bounds`` hold every splat's
    CUTOFF_SIGMAS ellipsoid; reflectivity per splat from ``colors`` (sRGB), weighted by
    opacity x its two larger scales (what a ray sees of it)."""
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    require_scannable(positions, (), name, {"scale": scales, "rotation": rotations, "opacity": opacities})
    splats = Gaussians.from_splats(positions, scales, rotations, opacities)
    extents = splats.extents
    weights = splats.opacities * np.sort(splats.scales, axis=1)[:, 1:].prod(axis=1)
    reflectivity = (np.full(len(positions), DEFAULT_REFLECTIVITY, np.float32) if colors is None
                    else relative_reflectivity(reflectivity_from_srgb(colors), weights))
    return ScanTarget(None, np.stack([positions.min(0), positions.max(0)]),
                      np.stack([(positions - extents).min(0), (positions + extents).max(0)]),
                      _planes(splats.normals, positions), reflectivity, np.arange(len(positions), dtype=np.int32),
                      "gaussians", name, gaussians=splats)


def has_gaussians(attributes: dict) -> bool:
    """Whether a reconstruction's attributes make Gaussian splats: ``scale``,
    ``rotation`` and ``opacity``."""
    return all(attributes.get(key) is not None for key in ("scale", "rotation", "opacity"))


def target_from_reconstruction(reconstruction, radius_scale: float = 1.0, engine: str = "auto",
                               gaussians: bool = True) -> ScanTarget:
    """A mesh target when the reconstruction has faces; else Gaussians when it carries
    ``scale``, ``rotation`` and ``opacity`` (and ``gaussians``); else surfels
    (splat-shaped when it carries ``scale`` and ``rotation``). Positions must already be
    in the object frame. ``engine``: what mesh and surfel targets are built for (ready_for)."""
    name = str(reconstruction.source)
    colors = reconstruction.colors
    if len(reconstruction.faces):
        face_reflectivity = None
        if colors is not None:
            face_reflectivity = reflectivity_from_srgb(colors)[reconstruction.faces].mean(axis=1)
        return mesh_target(reconstruction.positions, reconstruction.faces, name, face_reflectivity, engine)
    attributes = reconstruction.attributes
    if gaussians and has_gaussians(attributes):
        return gaussian_target(reconstruction.positions, attributes["scale"], attributes["rotation"],
                               attributes["opacity"], name, colors)
    return surfel_target(reconstruction.positions, name, colors, radius_scale,
                         scales=attributes.get("scale"), rotations=attributes.get("rotation"), engine=engine,
                         opacities=attributes.get("opacity"))
