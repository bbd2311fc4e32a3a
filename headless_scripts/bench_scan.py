"""Speed against error of one LiDAR object scan (core.scan): mesh BVH windowed and full
revolution, surfels at several densities and radii, the range view at several densities,
and Embree (embreex) -- or Open3D when installed -- on the identical windowed rays.

    .venv/bin/python headless_scripts/bench_scan.py [--quick] [--poses 4] [--repeats 5]
        [--chrono TRUCK.obj] [--out bench/scan]

Objects (object frame, box centre at the origin): the Chrono truck chassis (11k faces),
the same mesh midpoint-subdivided twice (176k faces, the very same surface), the built-in
sample truck and an icosphere of radius 1.5 m. Each stands on the ground
(raycast.placement) at 10, 30 and 50 m from a nuScenes (HDL-32E) or KITTI (HDL-64E)
sensor, at ``--poses`` azimuths and headings per distance drawn from
default_rng([SEED, distance]) -- the same poses for every object and method; the two
Chrono trucks are also scanned at 15 and 20 m (nuScenes, BVH windowed and Embree) for
the target. Every scan is timed ``--repeats`` times (time.perf_counter around the call);
a row's time is the median over poses of each pose's median.

Error is per ray against a float64 reference of the same cells: exact Moller-Trumbore
intersection of every sensor cell's float64 direction with the placed float64 triangles
(for the subdivided truck: the original 11k faces, same surface; for the sphere also the
ideal sphere, analytically), nearest hit, gated to the sensor's [min_range, max_range]
like a scan. A scan's row is paired with its reference ray by ring * columns + column.
Columns: |range error| (median, p99, max, m) over rays both hit; false hits (scan hit,
reference miss) and missed hits (reference hit, scan miss) as % of the reference's hits.
Surfels and range-view points are drawn on the reference mesh with
trimesh.sample.sample_surface(mesh, n, seed=n); surfel BVH build time is reported apart
and excluded from the scan time. Embree times only its intersection call (output=1, the
range is needed) on float32 copies of the windowed rays the BVH path casts, in the object
frame (raycast.rays_to_cast), against the same triangles; its tfar is the range.

Prints Markdown tables and writes <out>.json, <out>.md and <out>.png.
"""

import argparse
import os
import re
import sys
import time
from itertools import repeat as same
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "addon"))

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from pgt_blender import cli, dev  # noqa: E402
from pgt_blender.core.samples import sample_vehicle  # noqa: E402
from pgt_blender.core.scan import raycast, targets  # noqa: E402
from pgt_blender.core.scan.range_view import range_view_scan  # noqa: E402
from pgt_blender.core.scan.sensors import PRESETS  # noqa: E402

CHRONO_TRUCK = dev.CHRONO_VEHICLES / "truck" / "truck_chassis.obj"
SEED = 2024
SPHERE_RADIUS = 1.5
SPHERE_SUBDIVISIONS = 4
DISTANCES = (10.0, 30.0, 50.0)
TARGET_DISTANCES = (10.0, 15.0, 20.0)
TARGET_MS = 2.0
TARGET_OBJECT = "chrono truck 176k"
SURFEL_POINTS = (20_000, 100_000, 400_000)
SURFEL_RADII = (0.5, 1.0, 2.0)
RANGE_VIEW_POINTS = (20_000, 100_000, 400_000, 1_600_000)
FAMILIES = ("bvh windowed", "bvh full revolution", "embree", "open3d", "surfels", "range view")
ERROR_FLOOR = 1e-16  # log-plot floor for exact (0 m) errors


# ----------------------------------------------------------------- float64 reference

def reference_ranges(triangles: np.ndarray, sensor, sensor_from_object: np.ndarray,
                     max_pairs: int = 2_000_000) -> np.ndarray:
    """(beams * columns,) float64 range of each sensor cell's nearest hit on ``triangles``
    (F, 3, 3) object frame, placed by ``sensor_from_object``; NaN where the ray misses or
    the hit lies outside [min_range, max_range]. Exact float64 Moller-Trumbore on the
    (triangle, cell) pairs whose angular windows overlap: a triangle's azimuth span is
    that of its corners (its xy shadow does not contain the sensor, so the azimuth is
    monotone along every edge); its elevation span is bounded conservatively."""
    placed = triangles @ sensor_from_object[:3, :3].T + sensor_from_object[:3, 3]
    rho = np.linalg.norm(placed[..., :2], axis=2)
    if (rho.min(axis=1) < 1e-3).any():
        raise ValueError("reference: the sensor sits under a triangle; place the object farther away")
    centre = np.arctan2(*placed[..., :2].reshape(-1, 2).mean(axis=0)[::-1])
    relative = np.angle(np.exp(1j * (np.arctan2(placed[..., 1], placed[..., 0]) - centre)))
    if np.ptp(relative, axis=1).max() > np.pi / 2:
        raise ValueError("reference: a triangle spans more than 90 degrees of azimuth")
    azimuth_low, azimuth_high = centre + relative.min(axis=1), centre + relative.max(axis=1)
    edges = np.linalg.norm(placed[:, [1, 2, 0], :2] - placed[..., :2], axis=2).max(axis=1)
    rho_low, rho_high = np.maximum(rho.min(axis=1) - edges, 1e-6), rho.max(axis=1)
    z_low, z_high = placed[..., 2].min(axis=1), placed[..., 2].max(axis=1)
    elevation_high = np.arctan2(z_high, np.where(z_high > 0, rho_low, rho_high))
    elevation_low = np.arctan2(z_low, np.where(z_low > 0, rho_high, rho_low))
    elevations = np.radians(np.asarray(sensor.elevations_deg))
    ring_first = np.searchsorted(elevations, elevation_low - 1e-7, side="left")
    ring_last = np.searchsorted(elevations, elevation_high + 1e-7, side="right") - 1
    ring_count = np.maximum(ring_last - ring_first + 1, 0)
    # level 1: (triangle, ring) pairs
    tri = np.repeat(np.arange(len(placed)), ring_count)
    ring = ring_first[tri] + np.arange(len(tri)) - np.repeat(np.cumsum(ring_count) - ring_count, ring_count)
    # the columns whose centre azimuth lies in the span: azimuth = start + direction * step * (c + 0.5) + offset
    offsets = np.asarray(sensor.azimuth_offsets_deg)[ring]
    ends = np.stack([np.degrees(azimuth_low[tri]), np.degrees(azimuth_high[tri])], axis=1)
    steps = sensor.direction * (ends - offsets[:, None] - sensor.start_azimuth_deg) / sensor.azimuth_step_deg - 0.5
    column_first = np.ceil(steps.min(axis=1) - 1e-6).astype(np.int64) - 1  # one column of slack each side
    column_last = np.floor(steps.max(axis=1) + 1e-6).astype(np.int64) + 1
    column_count = np.maximum(column_last - column_first + 1, 0)
    best = np.full(sensor.beams * sensor.columns, np.inf)
    directions = sensor.directions
    bounds = np.concatenate([[0], np.cumsum(column_count)])
    start = 0
    while start < len(tri):  # level 2 in chunks of at most ~max_pairs (triangle, cell) pairs
        stop = max(int(np.searchsorted(bounds, bounds[start] + max_pairs, side="right")) - 1, start + 1)
        counts = column_count[start:stop]
        pair = np.repeat(np.arange(start, stop), counts)
        column = column_first[pair] + np.arange(len(pair)) - np.repeat(bounds[start:stop] - bounds[start], counts)
        cell = ring[pair] * sensor.columns + np.mod(column, sensor.columns)
        hit, t = _moller_trumbore(placed[tri[pair]], directions[cell])
        np.minimum.at(best, cell[hit], t[hit])
        start = stop
    best[(best < sensor.min_range) | (best > sensor.max_range)] = np.nan
    return best


def _moller_trumbore(corners: np.ndarray, directions: np.ndarray):
    """(M,) bool hit and (M,) float64 t of rays from the origin along ``directions`` (M, 3)
    against triangles ``corners`` (M, 3, 3); edges count as hits, t > 0."""
    v0 = corners[:, 0]
    e1, e2 = corners[:, 1] - v0, corners[:, 2] - v0
    p = np.cross(directions, e2)
    det = np.einsum("ij,ij->i", e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = 1.0 / det
        s = -v0
        u = np.einsum("ij,ij->i", s, p) * inverse
        q = np.cross(s, e1)
        v = np.einsum("ij,ij->i", directions, q) * inverse
        t = np.einsum("ij,ij->i", e2, q) * inverse
        hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return hit, t


def sphere_ranges(radius: float, sensor, sensor_from_object: np.ndarray) -> np.ndarray:
    """(beams * columns,) float64 range to the ideal sphere of ``radius`` about the object
    origin, NaN on a miss or outside the range gate."""
    centre = sensor_from_object[:3, 3]
    b = sensor.directions @ centre
    disc = b * b - (centre @ centre - radius * radius)
    with np.errstate(invalid="ignore"):
        t = b - np.sqrt(disc)
    t[(disc < 0) | (t <= 0) | (t < sensor.min_range) | (t > sensor.max_range)] = np.nan
    return t


def compare(cells: np.ndarray, ranges: np.ndarray, reference: np.ndarray) -> dict:
    """Pair a scan's returns (flat cells, ranges) with the reference: per-ray errors on
    rays both hit, false and missed hit counts, reference hit count."""
    scanned = np.full(len(reference), np.nan)
    scanned[cells] = ranges
    both = np.isfinite(scanned) & np.isfinite(reference)
    return {"errors": np.abs(scanned[both] - reference[both]),
            "false": int((np.isfinite(scanned) & np.isnan(reference)).sum()),
            "missed": int((np.isnan(scanned) & np.isfinite(reference)).sum()),
            "reference_hits": int(np.isfinite(reference).sum())}


# ----------------------------------------------------------------- objects and methods

class Object:
    """A mesh to scan (vertices, faces, box centre at the origin) with its reference."""

    def __init__(self, name, vertices, faces, source, reference=None, sphere_radius=None):
        self.name, self.source = name, source
        self.vertices, self.faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
        self.mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        self.reference = self if reference is None else reference
        self.sphere_radius = sphere_radius
        self.triangles = self.vertices[self.faces]
        self._target = None

    @property
    def target(self):
        if self._target is None:
            start = time.perf_counter()
            self._target = targets.mesh_target(self.vertices, self.faces, self.name)
            self.build_s = time.perf_counter() - start
        return self._target

    @property
    def bounds(self):
        return self.target.bounds

    def describe(self) -> dict:
        return {"source": self.source, "faces": len(self.faces),
                "extents_m": [round(float(e), 3) for e in self.mesh.extents],
                "reference": (f"ideal sphere r={self.sphere_radius} m and its {len(self.faces)} triangles"
                              if self.sphere_radius else f"{self.reference.name} ({len(self.reference.faces)} "
                              "triangles), float64 Moller-Trumbore")}


def centred(vertices):
    vertices = np.asarray(vertices, np.float64)
    return vertices - (vertices.min(axis=0) + vertices.max(axis=0)) / 2


def load_objects(chrono: Path, quick: bool) -> list:
    objects = []
    if chrono.is_file():
        mesh = trimesh.load(chrono, force="mesh", process=False)
        source = f"../{chrono.relative_to(ROOT.parent)}" if chrono.is_relative_to(ROOT.parent) else str(chrono)
        truck = Object("chrono truck 11k", centred(mesh.vertices), mesh.faces, source)
        vertices, faces = trimesh.remesh.subdivide(truck.vertices, truck.faces)
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
        objects += [truck, Object(TARGET_OBJECT, vertices, faces, "chrono truck 11k, trimesh.remesh.subdivide x2 "
                                  "(midpoint: the same surface)", reference=truck)]
    else:
        print(f"note: no Chrono truck at {chrono}; the target row cannot be measured\n")
    if not quick:
        sample = sample_vehicle("truck")
        objects.append(Object("sample truck", sample.vertices, sample.faces, "core.samples.sample_vehicle('truck')"))
    sphere = trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS, radius=SPHERE_RADIUS)
    objects.append(Object(f"sphere r{SPHERE_RADIUS:g}", sphere.vertices, sphere.faces,
                          f"trimesh.creation.icosphere(subdivisions={SPHERE_SUBDIVISIONS}, radius={SPHERE_RADIUS})",
                          sphere_radius=SPHERE_RADIUS))
    return objects


def surface_points(obj: Object, count: int):
    """``count`` points on the reference surface (seed=count) and their true normals."""
    points, faces = trimesh.sample.sample_surface(obj.reference.mesh, count, seed=count)
    return points, obj.reference.mesh.face_normals[faces]


def embree_engine():
    """(name, version, make(triangles) -> intersect(origin, directions, max_range) -> ranges)
    of the first outside ray engine that imports, else None."""
    try:
        from embreex import rtcore, rtcore_scene
        from embreex.mesh_construction import TriangleMesh
    except ImportError:
        pass
    else:
        import embreex

        version = f"embreex {embreex.__version__}, {str(rtcore.EmbreeDevice()).strip()}"

        def make(vertices, faces):
            scene = rtcore_scene.EmbreeScene()
            TriangleMesh(scene, vertices.astype(np.float32), faces.astype(np.int32))

            def intersect(origins, directions, far):
                result = scene.run(origins, directions, dists=far, output=1)
                return np.where(result["primID"] >= 0, result["tfar"].astype(np.float64), np.nan)
            return intersect
        return "embree", version, make
    try:
        import open3d
    except ImportError:
        return None

    def make(vertices, faces):
        scene = open3d.t.geometry.RaycastingScene()
        scene.add_triangles(open3d.core.Tensor(vertices.astype(np.float32)),
                            open3d.core.Tensor(faces.astype(np.uint32)))

        def intersect(origins, directions, far):
            rays = open3d.core.Tensor(np.hstack([origins, directions]))
            t = scene.cast_rays(rays)["t_hit"].numpy().astype(np.float64)
            return np.where(t <= far, t, np.nan)
        return intersect
    return "open3d", f"open3d {open3d.__version__}", make


def timed(call, repeats: int, budget_s: float = 1.0):
    """(last result, median seconds) of ``repeats`` calls; slow calls stop after 3 once
    they have taken ``budget_s`` together."""
    seconds = []
    while len(seconds) < repeats and (len(seconds) < 3 or sum(seconds) < budget_s):
        start = time.perf_counter()
        result = call()
        seconds.append(time.perf_counter() - start)
    return result, float(np.median(seconds))


# ----------------------------------------------------------------- the run

def poses(distance: float, count: int) -> list:
    rng = np.random.default_rng([SEED, int(round(distance * 1000))])
    return [(distance * np.cos(a), distance * np.sin(a), h)
            for a, h in zip(rng.uniform(-np.pi, np.pi, count), rng.uniform(-np.pi, np.pi, count))]


class Bench:
    def __init__(self, args, objects, engine):
        self.args, self.objects, self.engine = args, objects, engine
        self.references = {}
        self.records = {}  # (method, object, sensor, distance) -> list of per-pose dicts
        self.builds = {}  # (method, object) -> seconds
        self.identical = []  # windowed rows == full revolution rows, per pose
        self.engines = {}  # (engine, object) -> intersect
        self.point_sets = {}  # (reference object, count) -> (points, normals), the current object's
        self.surfel_targets = {}  # (label, object) -> ScanTarget, the current object's

    def reference(self, obj, sensor, distance, index, matrix):
        key = (obj.reference.name, sensor.name, distance, index)
        if key not in self.references:
            start = time.perf_counter()
            mesh = reference_ranges(obj.reference.triangles, sensor, matrix)
            ideal = sphere_ranges(obj.sphere_radius, sensor, matrix) if obj.sphere_radius else None
            self.references[key] = (mesh, ideal, time.perf_counter() - start)
        return self.references[key]

    def record(self, method, obj, sensor, distance, seconds, rays, cells, ranges, reference, ideal):
        entry = {"seconds": seconds, "rays": int(rays), "hits": len(cells), **compare(cells, ranges, reference)}
        if ideal is not None:
            entry["ideal"] = compare(cells, ranges, ideal)
        self.records.setdefault((method, obj.name, sensor.name, distance), []).append(entry)
        return entry

    def run_pose(self, obj, sensor, distance, index, pose, methods):
        repeats = self.args.repeats
        target = obj.target
        matrix = raycast.placement(obj.bounds, sensor, *pose)  # one placement for every method
        reference, ideal, _ = self.reference(obj, sensor, distance, index, matrix)

        def scanned(method, call, reps=repeats):
            scan, seconds = timed(call, reps)
            cells = scan.returns["ring"].astype(np.int64) * sensor.columns + scan.returns["column"]
            self.record(method, obj, sensor, distance, seconds, scan.rays, cells, scan.returns["range"],
                        reference, ideal)
            return scan

        window = scanned("bvh windowed", lambda: raycast.cast_rays(target, sensor, matrix, raycast.ScanOptions()))
        if "full" in methods:
            full = scanned("bvh full revolution", lambda: raycast.cast_rays(
                target, sensor, matrix, raycast.ScanOptions(window=False)), reps=max(1, min(3, repeats)))
            self.identical.append(bool(np.array_equal(window.returns, full.returns)))
        if self.engine is not None and "engine" in methods:
            name, _, make = self.engine
            key = (name, obj.name)
            if key not in self.builds:
                start = time.perf_counter()
                intersect = make(obj.vertices, obj.faces)
                intersect(np.zeros((1, 3), np.float32), np.array([[1, 0, 0]], np.float32),
                          np.ones(1, np.float32))  # commits the scene: its build
                self.builds[key] = time.perf_counter() - start
                self.engines[key] = intersect
            intersect = self.engines[key]
            cells, origin, directions = raycast.rays_to_cast(sensor, target.cast_bounds, matrix)
            origins = np.broadcast_to(origin.astype(np.float32), directions.shape).copy()
            directions32 = directions.astype(np.float32)
            far = np.full(len(cells), sensor.max_range, np.float32)
            ranges, seconds = timed(lambda: intersect(origins, directions32, far), repeats)
            keep = (ranges >= sensor.min_range) & (ranges <= sensor.max_range)
            entry = self.record(name, obj, sensor, distance, seconds, len(cells), cells[keep], ranges[keep],
                                reference, ideal)
            # diagnostic: the BVH's own per-ray loop on the same rays, without the rest of cast_rays
            from mathutils import Vector  # importable once bpy is loaded
            listed = directions.tolist()
            _, entry["bvh_cast_seconds"] = timed(lambda: list(map(
                target.bvh.ray_cast, same(Vector(origin), len(listed)), listed,
                same(sensor.max_range, len(listed)))), repeats)
            entry["bvh_seconds"] = self.records[("bvh windowed", obj.name, sensor.name, distance)][-1]["seconds"]
        for count in self.args.surfel_points if "surfels" in methods else ():
            for scale in self.args.surfel_radii:
                label = f"surfels {count // 1000}k r×{scale:g}"
                surfel = self.surfels(obj, count, scale, label)
                scanned(label, lambda: raycast.cast_rays(surfel, sensor, matrix, raycast.ScanOptions()))
        for count in self.args.range_view_points if "range view" in methods else ():
            points, normals = self.points(obj, count)
            scanned(f"range view {count // 1000}k", lambda: range_view_scan(points, sensor, matrix, obj.bounds,
                                                                            normals=normals))

    def points(self, obj, count):
        key = (obj.reference.name, count)
        if key not in self.point_sets:
            self.point_sets[key] = surface_points(obj, count)
        return self.point_sets[key]

    def surfels(self, obj, count, scale, label):
        key = (label, obj.name)
        if key not in self.surfel_targets:
            points, _ = self.points(obj, count)
            start = time.perf_counter()
            self.surfel_targets[key] = targets.surfel_target(points, label, radius_scale=scale)
            self.builds[key] = time.perf_counter() - start
            print(f"  built {label} on {obj.name}: {self.builds[key]:.1f} s", flush=True)
        return self.surfel_targets[key]

    def run(self, plan):
        """plan: (object, sensor, distances, methods) entries."""
        previous = None
        for obj, sensor, distances, methods in plan:
            if obj is not previous:  # surfel BVHs and points of the last object are done with
                self.surfel_targets.clear()
                self.point_sets.clear()
                previous = obj
            for distance in distances:
                start = time.perf_counter()
                for index, pose in enumerate(poses(distance, self.args.poses)):
                    self.run_pose(obj, sensor, distance, index, pose, methods)
                print(f"{obj.name:>18} | {sensor.name:8} | {distance:4.0f} m | {', '.join(sorted(methods)) or 'bvh'}"
                      f" | {time.perf_counter() - start:.1f} s", flush=True)
        self.surfel_targets.clear()


def family(method: str) -> str:
    return next(f for f in FAMILIES if method.startswith(f))


def method_order(method: str) -> tuple:
    """Family, then point count (20k before 100k), then the name."""
    count = re.search(r"(\d+)k", method)
    return FAMILIES.index(family(method)), int(count.group(1)) if count else 0, method


def summarise(entries: list, prefix: str = "") -> dict:
    errors = np.concatenate([e["errors"] for e in entries])
    reference_hits = sum(e["reference_hits"] for e in entries)
    false, missed = sum(e["false"] for e in entries), sum(e["missed"] for e in entries)
    share = 100.0 / max(reference_hits, 1)
    stat = (lambda q: float(np.percentile(errors, q))) if len(errors) else (lambda q: None)
    return {f"{prefix}paired": int(len(errors)), f"{prefix}error_median_m": stat(50), f"{prefix}error_p99_m": stat(99),
            f"{prefix}error_max_m": stat(100), f"{prefix}reference_hits": reference_hits, f"{prefix}false": false,
            f"{prefix}missed": missed, f"{prefix}false_pct": false * share, f"{prefix}missed_pct": missed * share}


def rows_of(bench: Bench) -> list:
    rows = []
    for (method, name, sensor, distance), entries in bench.records.items():
        ms = [1e3 * e["seconds"] for e in entries]
        row = {"method": method, "family": family(method), "object": name, "sensor": sensor, "distance_m": distance,
               "poses": len(entries), "ms_median": float(np.median(ms)), "ms_per_pose": [round(m, 4) for m in ms],
               "rays_median": float(np.median([e["rays"] for e in entries])),
               "hits_median": float(np.median([e["hits"] for e in entries])), **summarise(entries)}
        if "ideal" in entries[0]:
            row |= summarise([e["ideal"] for e in entries], "ideal_sphere_")
        if "bvh_seconds" in entries[0]:
            bvh = [1e3 * e["bvh_seconds"] for e in entries]
            cast = [1e3 * e["bvh_cast_seconds"] for e in entries]
            row |= {"bvh_windowed_ms_median": float(np.median(bvh)),
                    "bvh_ray_cast_loop_ms_median": float(np.median(cast)),
                    "ratio_bvh_windowed_to_engine": float(np.median(np.array(bvh) / np.array(ms)))}
        build = bench.builds.get((method, name))
        if build is not None:
            row["build_s"] = build
        rows.append(row)
    return rows


def target_summary(bench: Bench, engine_name: str | None) -> dict | None:
    keys = [("bvh windowed", TARGET_OBJECT, "nuscenes", d) for d in TARGET_DISTANCES]
    entries = [e for k in keys for e in bench.records.get(k, [])]
    if not entries:
        return None
    bvh = np.array([1e3 * e["seconds"] for e in entries])
    result = {"object": TARGET_OBJECT, "sensor": "nuscenes", "distances_m": [k[3] for k in keys if k in bench.records],
              "scans": len(entries), "bvh_windowed_ms_median": float(np.median(bvh)),
              "bvh_windowed_ms_per_distance": {
                  f"{k[3]:g}": float(np.median([1e3 * e["seconds"] for e in bench.records[k]]))
                  for k in keys if k in bench.records},
              "target_ms": TARGET_MS, "meets_target": bool(np.median(bvh) <= TARGET_MS),
              "rays_median": float(np.median([e["rays"] for e in entries]))}
    engine = [e for k in keys for e in bench.records.get((engine_name, *k[1:]), [])]
    if engine:  # each entry carries the BVH windowed time of its own pose
        times = np.array([1e3 * e["seconds"] for e in engine])
        paired = np.array([1e3 * e["bvh_seconds"] for e in engine])
        cast = np.array([1e3 * e["bvh_cast_seconds"] for e in engine])
        result |= {"engine": engine_name, "engine_ms_median": float(np.median(times)),
                   "ratio_bvh_windowed_to_engine": float(np.median(paired / times)),
                   "bvh_ray_cast_loop_ms_median": float(np.median(cast)),
                   "ratio_ray_cast_loop_to_engine": float(np.median(cast / times)),
                   "within_2x": bool(np.median(paired / times) <= 2.0)}
    return result


# ----------------------------------------------------------------- output

def fmt(value, digits=2):
    if value is None:
        return "-"
    if value == 0:
        return "0"
    return f"{value:.{digits}e}" if abs(value) < 1e-2 or abs(value) >= 1e4 else f"{value:.{digits + 1}g}"


def table(rows: list) -> str:
    return dev.markdown_table(
        ["method", "object", "sensor", "m", "ms / scan (median)", "rays", "hits", "abs err median m", "abs err p99 m",
         "abs err max m", "false %", "missed %"],
        [[r["method"], r["object"], r["sensor"], f"{r['distance_m']:g}", f"{r['ms_median']:.3f}",
          f"{r['rays_median']:,.0f}", f"{r['hits_median']:,.0f}", fmt(r["error_median_m"]), fmt(r["error_p99_m"]),
          fmt(r["error_max_m"]), f"{r['false_pct']:.2f}", f"{r['missed_pct']:.2f}"] for r in rows], "lll" + "r" * 9)


def method_table(rows: list) -> str:
    """Per method and sensor: medians over its rows (objects x distances)."""
    keys = sorted({(r["method"], r["sensor"]) for r in rows},
                  key=lambda k: (method_order(k[0]), k[1] != "nuscenes"))
    cells = []
    for method, sensor in keys:
        mine = [r for r in rows if (r["method"], r["sensor"]) == (method, sensor)]
        p99 = [r["error_p99_m"] for r in mine if r["error_p99_m"] is not None]
        builds = [r["build_s"] for r in mine if "build_s" in r]
        median = {key: float(np.median([r[key] for r in mine])) for key in ("ms_median", "false_pct", "missed_pct")}
        cells.append([method, sensor, len(mine), f"{median['ms_median']:.3f}",
                      fmt(float(np.median(builds))) if builds else "-", fmt(float(np.median(p99)) if p99 else None),
                      f"{median['false_pct']:.2f}", f"{median['missed_pct']:.2f}"])
    return dev.markdown_table(["method", "sensor", "rows", "ms / scan (median of rows)", "build s",
                               "abs err p99 m (median of rows)", "false % (median)", "missed % (median)"],
                              cells, "ll" + "r" * 6)


def sphere_table(rows: list) -> str:
    return dev.markdown_table(
        ["method", "sensor", "m", "abs err median m vs ideal", "p99 vs ideal", "false % vs ideal", "missed % vs ideal"],
        [[r["method"], r["sensor"], f"{r['distance_m']:g}", fmt(r["ideal_sphere_error_median_m"]),
          fmt(r["ideal_sphere_error_p99_m"]), f"{r['ideal_sphere_false_pct']:.2f}",
          f"{r['ideal_sphere_missed_pct']:.2f}"] for r in rows if "ideal_sphere_paired" in r], "ll" + "r" * 5)


def markdown_header(machine: dict, inputs: dict, settings: dict) -> str:
    """The .md's preamble: machine, versions, inputs and how the medians were taken."""
    lines = ["# LiDAR object scan: time against error", "",
             "Written by `headless_scripts/bench_scan.py` (its docstring describes the method).", "",
             "**machine and versions**: " + ", ".join(f"{key} {value}" for key, value in machine.items()), "",
             "**objects** (object frame, box centre at the origin):", ""]
    lines += [f"- {name}: {o['source']}; {o['faces']:,} faces; {' x '.join(f'{e:g}' for e in o['extents_m'])} m; "
              f"reference: {o['reference']}" for name, o in inputs["objects"].items()]
    lines += ["", "**sensors**:", ""] + [f"- {name}: {note}" for name, note in inputs["sensors"].items()]
    rest = {key: value for key, value in inputs.items() if key not in ("objects", "sensors")}
    lines += ["", "**inputs**: " + "; ".join(f"{key} {value}" for key, value in rest.items()), "",
              "**settings**:", ""] + [f"- {key}: {value}" for key, value in settings.items()]
    return "\n".join(lines) + "\n"


def target_line(target: dict | None) -> str:
    if target is None:
        return "target: not measured (no Chrono truck)"
    per = ", ".join(f"{d} m {ms:.2f}" for d, ms in target["bvh_windowed_ms_per_distance"].items())
    span = "-".join(f"{d:g}" for d in target["distances_m"])
    line = (f"target: bvh windowed, {target['object']}, nuScenes, {span} m: "
            f"median {target['bvh_windowed_ms_median']:.3f} ms per object scan over {target['scans']} scans "
            f"({per}; {target['rays_median']:,.0f} rays median) -> "
            f"{'meets' if target['meets_target'] else 'MISSES'} <= {TARGET_MS:g} ms")
    if "engine" in target:
        line += (f"; {target['engine']} on the identical rays {target['engine_ms_median']:.3f} ms, ratio "
                 f"BVH / {target['engine']} {target['ratio_bvh_windowed_to_engine']:.2f}x "
                 f"({'within' if target['within_2x'] else 'NOT within'} 2x; the BVH ray_cast loop alone "
                 f"{target['bvh_ray_cast_loop_ms_median']:.3f} ms = {target['ratio_ray_cast_loop_to_engine']:.2f}x)")
    return line


def style_of(plt, method: str, methods: list) -> dict:
    """Marker and color: one per method; surfels shade by density and mark by radius."""
    kind = family(method)
    fixed = {"bvh windowed": ("o", "tab:blue"), "bvh full revolution": ("s", "tab:gray"),
             "embree": ("*", "tab:red"), "open3d": ("*", "tab:red")}
    if kind in fixed:
        marker, color = fixed[kind]
        return {"marker": marker, "color": color, "s": 110 if marker == "*" else 40}
    variants = [m for m in methods if family(m) == kind]
    if kind == "surfels":
        counts = sorted({m.split()[1] for m in variants}, key=lambda c: int(c[:-1]))
        scales = sorted({m.split()[2] for m in variants})
        shade = 0.35 + 0.6 * counts.index(method.split()[1]) / max(len(counts) - 1, 1)
        marker = ("^", "v", ">", "<")[scales.index(method.split()[2]) % 4]
        return {"marker": marker, "color": plt.get_cmap("YlGn")(shade), "s": 40}
    shade = 0.4 + 0.55 * variants.index(method) / max(len(variants) - 1, 1)
    return {"marker": "D", "color": plt.get_cmap("Purples")(shade), "s": 34}


def plot(plt, rows: list):
    figure, axes = plt.subplots(1, 2, figsize=(16, 6.5), sharex=True)
    methods = sorted({r["method"] for r in rows}, key=method_order)
    for method in methods:
        base = style_of(plt, method, methods)
        mine = [r for r in rows if r["method"] == method and r["error_p99_m"] is not None]
        labelled = False
        for sensor, fill in (("nuscenes", True), ("kitti", False)):
            part = [r for r in mine if r["sensor"] == sensor]
            if not part:
                continue
            style = {"marker": base["marker"], "s": base["s"], "facecolors": base["color"] if fill else "none",
                     "edgecolors": base["color"], "alpha": 0.85, "linewidths": 1.2,
                     "label": None if labelled else method}
            labelled = True
            x = [r["ms_median"] for r in part]
            axes[0].scatter(x, [max(r["error_p99_m"], ERROR_FLOOR) for r in part], **style)
            axes[1].scatter(x, [max(r["false_pct"] + r["missed_pct"], 1e-3) for r in part], **style | {"label": None})
    for axis in axes:
        axis.set_xscale("log")
        axis.set_yscale("log")
        axis.axvline(TARGET_MS, color="k", ls="--", lw=1)
        axis.text(TARGET_MS, axis.get_ylim()[1], f" {TARGET_MS:g} ms target", va="top", fontsize=8)
        axis.set_xlabel("median ms per object scan (builds excluded)")
        axis.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel(f"p99 |range error| vs float64 reference, m (floored at {ERROR_FLOOR:g})")
    axes[1].set_ylabel("false + missed hits, % of reference hits (floored at 1e-3 = none)")
    axes[1].legend(*axes[0].get_legend_handles_labels(), loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8,
                   frameon=False)
    figure.suptitle("pgt_blender LiDAR object scans: time against error; one marker per object x sensor x distance "
                    "(median over poses); filled = nuScenes HDL-32E, hollow = KITTI HDL-64E", fontsize=10)
    return figure


def main(argv: list) -> int:
    parser = argparse.ArgumentParser(prog="bench_scan.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="Chrono trucks + sphere, nuScenes, 15 m, 2 poses, "
                        "3 repeats, 20k surfels / range-view points (~20 s)")
    parser.add_argument("--poses", type=int, default=4, help="azimuth/heading poses per distance")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats per scan (full revolution: at most 3)")
    parser.add_argument("--chrono", type=Path, default=CHRONO_TRUCK, help="the Chrono truck chassis .obj")
    parser.add_argument("--out", type=Path, default=Path("bench/scan"))
    args = parser.parse_args(argv)
    if args.quick:
        args.poses, args.repeats = min(args.poses, 2), min(args.repeats, 3)
    args.surfel_points = SURFEL_POINTS[:1] if args.quick else SURFEL_POINTS
    args.surfel_radii = (1.0,) if args.quick else SURFEL_RADII
    args.range_view_points = RANGE_VIEW_POINTS[:1] if args.quick else RANGE_VIEW_POINTS
    sensors = [PRESETS["nuscenes"]] + ([] if args.quick else [PRESETS["kitti"]])
    distances = (15.0,) if args.quick else DISTANCES

    objects = load_objects(args.chrono, args.quick)
    targets.bvhtree_class()  # loads bpy (and with it mathutils) outside Blender
    import bpy

    engine = embree_engine()
    versions = {"numpy": np.__version__, "trimesh": trimesh.__version__, "bpy": bpy.app.version_string,
                "ray_engine": engine[1] if engine else "none installed (embreex, open3d)"}
    machine = dev.machine(**versions)
    everything = {"full", "engine", "surfels", "range view"}
    plan = []
    for obj in objects:
        subdivided = obj.reference is not obj  # the same surface as its reference: BVH paths only
        for sensor in sensors:
            methods = {"full", "engine"} if subdivided else everything
            plan.append((obj, sensor, distances, methods))
        if obj.name.startswith("chrono truck") and not args.quick:
            extra = tuple(d for d in TARGET_DISTANCES if d not in distances)
            plan.append((obj, PRESETS["nuscenes"], extra, {"engine"}))
    bench = Bench(args, objects, engine)
    print(f"machine: {machine}\n", flush=True)
    load_before = [round(x, 2) for x in os.getloadavg()]
    start = time.perf_counter()
    bench.run(plan)
    elapsed = time.perf_counter() - start
    load_after = [round(x, 2) for x in os.getloadavg()]
    for obj in objects:  # the mesh BVH builds
        bench.builds.setdefault(("bvh windowed", obj.name), obj.build_s)
        bench.builds.setdefault(("bvh full revolution", obj.name), obj.build_s)

    names = [o.name for o in objects]
    rows = sorted(rows_of(bench), key=lambda r: (names.index(r["object"]), r["sensor"] != "nuscenes",
                                                 r["distance_m"], method_order(r["method"])))
    target = target_summary(bench, engine[0] if engine else None)
    inputs = {"objects": {o.name: o.describe() for o in objects},
              "sensors": {s.name: s.note for s in sensors},
              "distances_m": list(distances), "target_distances_m": list(TARGET_DISTANCES),
              "poses_per_distance": args.poses, "repeats": args.repeats,
              "surfel_points": list(args.surfel_points), "surfel_radius_scales": list(args.surfel_radii),
              "range_view_points": list(args.range_view_points)}
    settings = {"seed": SEED, "poses": "default_rng([seed, round(distance * 1000)]): azimuth, heading uniform in "
                "[-pi, pi); object box centre at (distance cos azimuth, distance sin azimuth); same for all objects",
                "timed": "time.perf_counter around cast_rays / range_view_scan / the engine's intersection call; "
                "median over repeats per pose (a call slower than ~0.33 s: 3 repeats), then median over poses; builds "
                "excluded",
                "points": "trimesh.sample.sample_surface(reference mesh, n, seed=n); range view with the true face "
                "normals", "error": "|scan range - float64 reference| on cells both hit; false = scan hit where the "
                "reference misses; missed = reference hit the scan lacks; % of reference hits, summed over poses",
                "columns": "rays = rays cast (range view: points projected), hits = returns, medians over poses",
                "windowed_equals_full_revolution": f"{sum(bench.identical)}/{len(bench.identical)} poses bit-identical",
                "run_seconds": round(elapsed, 1),
                "load_average_1_5_15_min": {"before": load_before, "after": load_after,
                                            "note": "other work on the machine inflates the times"}}
    header = markdown_header(machine, inputs, settings)
    body = (f"## per method (medians over objects x distances)\n\n{method_table(rows)}\n\n"
            f"## all rows (object x sensor x distance, medians over poses)\n\n{table(rows)}\n")
    if any("ideal_sphere_paired" in r for r in rows):
        body += f"\n## sphere against the ideal sphere (the tessellation's own error)\n\n{sphere_table(rows)}\n"
    line = target_line(target)
    print("\n" + body + "\n" + line)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".md").write_text(f"{header}\n**{line}**\n\n{body}")
    dev.write_results(args.out, {"machine": machine, "inputs": inputs, "settings": settings, "target": target,
                                 "rows": rows}, lambda plt: plot(plt, rows))
    print(f"wrote {args.out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(cli.run_main(main, cli.script_argv()))
