"""Speed against error of one LiDAR object scan (core.scan), through the product's
public calls only: ``raycast.cast_rays`` with the BVH engine (windowed and full
revolution) and the Embree engine (``ScanOptions(engine="embree")``), surfel targets
at several densities and radii, and ``range_view_scan`` at several densities.

    .venv/bin/python headless_scripts/bench_scan.py [--quick] [--poses 4] [--repeats 5]
        [--chrono TRUCK.obj] [--out bench/scan]

Objects (object frame, box centre at the origin): the Chrono truck chassis (11k faces),
the same mesh midpoint-subdivided twice (176k faces, the very same surface), the built-in
sample truck and an icosphere of radius 1.5 m. Each stands on the ground
(raycast.placement) at 10, 30 and 50 m from a nuScenes (HDL-32E) or KITTI (HDL-64E)
sensor, at ``--poses`` azimuths and headings per distance drawn from
default_rng([SEED, distance]): the same poses for every object and method. The two
Chrono trucks are also scanned at 15 and 20 m (nuScenes) for the target. Surfels are
cast with the BVH engine, like the mesh rows they are compared with. Every scan is
timed ``--repeats`` times (time.perf_counter around the public call); a row's time is
the median over poses of each pose's median. Builds are reported apart ("build s"): the
mesh BVH, each surfel BVH, and for Embree its first call (the scene's build and one scan).

Error is per ray against a float64 reference of the same cells: exact Moller-Trumbore
intersection of every sensor cell's float64 direction with the placed float64 triangles
(for the subdivided truck: the original 11k faces, same surface; for the sphere also the
ideal sphere, analytically), nearest hit, gated to the sensor's [min_range, max_range]
like a scan. A scan's row is paired with its reference ray by ring * columns + column.
Columns: |range error| (median, p99, max, m) over rays both hit; false hits (scan hit,
reference miss) and missed hits (reference hit, scan miss) as % of the reference's hits.
Surfels and range-view points are drawn on the reference mesh with
trimesh.sample.sample_surface(mesh, n, seed=n).

Prints Markdown tables and writes <out>.json, <out>.md and <out>.png.
"""

import re
import sys
import time
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
FAMILIES = ("bvh windowed", "bvh full revolution", "embree", "surfels", "range view")
ERROR_FLOOR = 1e-16  # log-plot floor for exact (0 m) errors


# ----------------------------------------------------------------- float64 reference

def reference_ranges(triangles: np.ndarray, sensor, sensor_from_object: np.ndarray,
                     max_pairs: int = 2_000_000) -> np.ndarray:
    """(beams * columns,) float64 range of each sensor cell's nearest hit on ``triangles``
    (F, 3, 3) object frame, placed by ``sensor_from_object``, each ray from its laser's
    origin (Sensor.cell_origins); NaN where the ray misses or the hit lies outside
    [min_range, max_range]. Exact float64 Moller-Trumbore on the
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
    edges = np.linalg.norm(placed[:, [1, 2, 0], :2] - placed[..., :2], axis=2).max(axis=1)
    rho_low, rho_high = np.maximum(rho.min(axis=1) - edges, 1e-6), rho.max(axis=1)
    # lasers off the sensor origin see a triangle up to asin(offset / distance) elsewhere
    margin = np.arcsin(np.clip(sensor.max_origin_offset / rho_low, 0.0, 1.0))
    azimuth_low, azimuth_high = centre + relative.min(axis=1) - margin, centre + relative.max(axis=1) + margin
    z_low, z_high = placed[..., 2].min(axis=1), placed[..., 2].max(axis=1)
    elevation_high = np.arctan2(z_high, np.where(z_high > 0, rho_low, rho_high)) + margin
    elevation_low = np.arctan2(z_low, np.where(z_low > 0, rho_high, rho_low)) - margin
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
        corners = placed[tri[pair]]
        if sensor.cell_origins is not None:  # each ray from its own laser
            corners = corners - sensor.cell_origins[cell][:, None, :]
        hit, t = _moller_trumbore(corners, directions[cell])
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
    origin from each cell's laser, NaN on a miss or outside the range gate."""
    centre = sensor_from_object[:3, 3] - (0.0 if sensor.cell_origins is None else sensor.cell_origins)
    b = np.einsum("ij,ij->i", sensor.directions, np.broadcast_to(centre, sensor.directions.shape))
    disc = b * b - (np.einsum("ij,ij->i", *[np.broadcast_to(centre, sensor.directions.shape)] * 2) - radius * radius)
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


# ----------------------------------------------------------------- objects and timing

class Object:
    """A mesh to scan (vertices, faces, box centre at the origin), its float64 triangles and
    the object whose triangles are its reference (itself, or the surface it subdivides)."""

    def __init__(self, name, vertices, faces, source, reference=None, sphere_radius=None):
        self.name, self.source, self.sphere_radius = name, source, sphere_radius
        self.vertices, self.faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
        self.mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
        self.reference = self if reference is None else reference
        self.triangles = self.vertices[self.faces]
        start = time.perf_counter()
        self.target = targets.mesh_target(self.vertices, self.faces, self.name, engine="bvh")  # its BVH timed
        self.build_s = time.perf_counter() - start

    def describe(self) -> str:
        reference = (f"ideal sphere r={self.sphere_radius} m and its {len(self.faces)} triangles" if self.sphere_radius
                     else f"{self.reference.name} ({len(self.reference.faces)} triangles), float64 Moller-Trumbore")
        return (f"{self.source}; {len(self.faces):,} faces; {' x '.join(f'{e:.3f}' for e in self.mesh.extents)} m; "
                f"reference: {reference}")


def load_objects(chrono: Path, quick: bool) -> list:
    def centred(vertices):
        return vertices - (vertices.min(axis=0) + vertices.max(axis=0)) / 2

    objects = []
    if chrono.is_file():
        mesh = trimesh.load(chrono, force="mesh", process=False)
        source = dev.shown_path(chrono)
        truck = Object("chrono truck 11k", centred(np.asarray(mesh.vertices, np.float64)), mesh.faces, source)
        vertices, faces = trimesh.remesh.subdivide(*trimesh.remesh.subdivide(truck.vertices, truck.faces))
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


def timed(call, repeats: int, budget_s: float = 1.0):
    """(last result, median seconds) of ``repeats`` calls; slow calls stop after 3 once
    they have taken ``budget_s`` together."""
    seconds = []
    while len(seconds) < repeats and (len(seconds) < 3 or sum(seconds) < budget_s):
        start = time.perf_counter()
        result = call()
        seconds.append(time.perf_counter() - start)
    return result, float(np.median(seconds))


def poses(distance: float, count: int) -> list:
    rng = np.random.default_rng([SEED, int(round(distance * 1000))])
    return [(distance * np.cos(a), distance * np.sin(a), h)
            for a, h in zip(rng.uniform(-np.pi, np.pi, count), rng.uniform(-np.pi, np.pi, count))]


def method_calls(obj: Object, methods: set, args, builds: dict) -> dict:
    """method -> scan(sensor, sensor_from_object) through the public calls, every build
    (surfel BVHs, the Embree scene) done here and timed into ``builds``."""
    bvh = raycast.ScanOptions(engine="bvh")
    calls = {"bvh windowed": lambda sensor, matrix: raycast.cast_rays(obj.target, sensor, matrix, bvh)}
    if "full" in methods:
        calls["bvh full revolution"] = lambda sensor, matrix: raycast.cast_rays(
            obj.target, sensor, matrix, raycast.ScanOptions(window=False, engine="bvh"))
    if "embree" in methods and args.embree:
        embree = raycast.ScanOptions(engine="embree")
        start = time.perf_counter()
        raycast.cast_rays(obj.target, PRESETS["nuscenes"], raycast.placement(obj.target.bounds, PRESETS["nuscenes"],
                                                                             10.0, 0.0, 0.0), embree)
        builds[("embree", obj.name)] = time.perf_counter() - start  # first call: the scene's build + one scan
        calls["embree"] = lambda sensor, matrix: raycast.cast_rays(obj.target, sensor, matrix, embree)
    if "points" not in methods:
        return calls
    for count in args.surfel_points:
        points, _ = trimesh.sample.sample_surface(obj.reference.mesh, count, seed=count)
        for scale in args.surfel_radii:
            label = f"surfels {count // 1000}k r×{scale:g}"
            start = time.perf_counter()
            surfel = targets.surfel_target(points, label, radius_scale=scale, engine="bvh")
            builds[(label, obj.name)] = time.perf_counter() - start
            calls[label] = lambda sensor, matrix, surfel=surfel: raycast.cast_rays(surfel, sensor, matrix, bvh)
    for count in args.range_view_points:
        points, faces = trimesh.sample.sample_surface(obj.reference.mesh, count, seed=count)
        normals = obj.reference.mesh.face_normals[faces]
        calls[f"range view {count // 1000}k"] = (
            lambda sensor, matrix, points=points, normals=normals: range_view_scan(
                points, sensor, matrix, obj.target.bounds, normals=normals))
    return calls


def run(plan: list, args) -> tuple:
    """Scan every (object, sensor, distances, methods) of ``plan`` at its poses.
    (records: (method, object, sensor, distance) -> per-pose dicts, builds, the number of
    poses where the windowed and full-revolution rows are bit-identical, and of poses)."""
    records, builds, identical, compared = {}, {}, 0, 0
    for obj, sensor, distances, methods in plan:
        calls = method_calls(obj, methods, args, builds)
        for distance in distances:
            start = time.perf_counter()
            for index, pose in enumerate(poses(distance, args.poses)):
                matrix = raycast.placement(obj.target.bounds, sensor, *pose)
                reference = reference_ranges(obj.reference.triangles, sensor, matrix)
                ideal = sphere_ranges(obj.sphere_radius, sensor, matrix) if obj.sphere_radius else None
                scans = {}
                for method, call in calls.items():
                    repeats = min(args.repeats, 3) if method == "bvh full revolution" else args.repeats
                    scan, seconds = timed(lambda: call(sensor, matrix), repeats)
                    scans[method] = scan
                    cells = scan.returns["ring"].astype(np.int64) * sensor.columns + scan.returns["column"]
                    entry = {"seconds": seconds, "rays": int(scan.rays), "hits": len(cells),
                             **compare(cells, scan.returns["range"], reference)}
                    if ideal is not None:
                        entry["ideal"] = compare(cells, scan.returns["range"], ideal)
                    records.setdefault((method, obj.name, sensor.name, distance), []).append(entry)
                if "bvh full revolution" in scans:
                    compared += 1
                    identical += bool(np.array_equal(scans["bvh windowed"].returns,
                                                     scans["bvh full revolution"].returns))
            print(f"{obj.name:>18} | {sensor.name:8} | {distance:4.0f} m | {len(calls)} methods"
                  f" | {time.perf_counter() - start:.1f} s", flush=True)
    return records, builds, identical, compared


# ----------------------------------------------------------------- summaries and output

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


def rows_of(records: dict, builds: dict) -> list:
    rows = []
    for (method, name, sensor, distance), entries in records.items():
        ms = [1e3 * e["seconds"] for e in entries]
        row = {"method": method, "object": name, "sensor": sensor, "distance_m": distance,
               "poses": len(entries), "ms_median": float(np.median(ms)), "ms_per_pose": [round(m, 4) for m in ms],
               "rays_median": float(np.median([e["rays"] for e in entries])),
               "hits_median": float(np.median([e["hits"] for e in entries])), **summarise(entries)}
        if "ideal" in entries[0]:
            row |= summarise([e["ideal"] for e in entries], "ideal_sphere_")
        if (method, name) in builds:
            row["build_s"] = builds[(method, name)]
        rows.append(row)
    return rows


def target_summary(records: dict) -> dict | None:
    """The BVH windowed scan of the 176k truck at nuScenes 10-20 m against TARGET_MS, and
    the Embree engine on the same poses (ratio per pose)."""
    def per_scan(method):
        return np.array([1e3 * e["seconds"] for d in TARGET_DISTANCES
                         for e in records.get((method, TARGET_OBJECT, "nuscenes", d), [])])

    bvh, embree = per_scan("bvh windowed"), per_scan("embree")
    if not len(bvh):
        return None
    result = {"object": TARGET_OBJECT, "sensor": "nuscenes", "distances_m": list(TARGET_DISTANCES),
              "scans": len(bvh), "bvh_windowed_ms_median": float(np.median(bvh)), "target_ms": TARGET_MS,
              "meets_target": bool(np.median(bvh) <= TARGET_MS)}
    if len(embree):
        result |= {"embree_ms_median": float(np.median(embree)),
                   "ratio_bvh_to_embree": float(np.median(bvh / embree))}
    return result


def target_line(target: dict | None) -> str:
    if target is None:
        return "target: not measured (no Chrono truck)"
    line = (f"target: bvh windowed, {target['object']}, nuScenes, {target['distances_m'][0]:g}-"
            f"{target['distances_m'][-1]:g} m: median {target['bvh_windowed_ms_median']:.3f} ms per object scan over "
            f"{target['scans']} scans -> {'meets' if target['meets_target'] else 'MISSES'} <= {TARGET_MS:g} ms")
    if "embree_ms_median" in target:
        line += (f"; the Embree engine (cast_rays, engine='embree') {target['embree_ms_median']:.3f} ms, "
                 f"{target['ratio_bvh_to_embree']:.1f}x faster")
    return line


def fmt(value, digits=2):
    if value is None:
        return "-"
    if value == 0:
        return "0"
    return f"{value:.{digits}e}" if abs(value) < 1e-2 or abs(value) >= 1e4 else f"{value:.{digits + 1}g}"


def tables(rows: list) -> str:
    """Per method and sensor (medians over objects x distances), then every row, then
    the sphere against the ideal sphere."""
    keys = sorted({(r["method"], r["sensor"]) for r in rows}, key=lambda k: (method_order(k[0]), k[1] != "nuscenes"))
    summary = []
    for method, sensor in keys:
        mine = [r for r in rows if (r["method"], r["sensor"]) == (method, sensor)]
        p99 = [r["error_p99_m"] for r in mine if r["error_p99_m"] is not None]
        builds = [r["build_s"] for r in mine if "build_s" in r]
        median = {key: float(np.median([r[key] for r in mine])) for key in ("ms_median", "false_pct", "missed_pct")}
        summary.append([method, sensor, len(mine), f"{median['ms_median']:.3f}",
                        fmt(float(np.median(builds))) if builds else "-", fmt(float(np.median(p99)) if p99 else None),
                        f"{median['false_pct']:.2f}", f"{median['missed_pct']:.2f}"])
    text = "## per method (medians over objects x distances)\n\n" + dev.markdown_table(
        ["method", "sensor", "rows", "ms / scan (median of rows)", "build s", "abs err p99 m (median of rows)",
         "false % (median)", "missed % (median)"], summary, "ll" + "r" * 6)
    text += "\n\n## all rows (object x sensor x distance, medians over poses)\n\n" + dev.markdown_table(
        ["method", "object", "sensor", "m", "ms / scan (median)", "rays", "hits", "abs err median m", "abs err p99 m",
         "abs err max m", "false %", "missed %"],
        [[r["method"], r["object"], r["sensor"], f"{r['distance_m']:g}", f"{r['ms_median']:.3f}",
          f"{r['rays_median']:,.0f}", f"{r['hits_median']:,.0f}", fmt(r["error_median_m"]), fmt(r["error_p99_m"]),
          fmt(r["error_max_m"]), f"{r['false_pct']:.2f}", f"{r['missed_pct']:.2f}"] for r in rows], "lll" + "r" * 9)
    sphere = [r for r in rows if "ideal_sphere_paired" in r]
    if sphere:
        text += "\n\n## sphere against the ideal sphere (the tessellation's own error)\n\n" + dev.markdown_table(
            ["method", "sensor", "m", "abs err median m vs ideal", "p99 vs ideal", "false % vs ideal",
             "missed % vs ideal"],
            [[r["method"], r["sensor"], f"{r['distance_m']:g}", fmt(r["ideal_sphere_error_median_m"]),
              fmt(r["ideal_sphere_error_p99_m"]), f"{r['ideal_sphere_false_pct']:.2f}",
              f"{r['ideal_sphere_missed_pct']:.2f}"] for r in sphere], "ll" + "r" * 5)
    return text + "\n"


def plot(plt, rows: list):
    """Time against p99 error and against false + missed hits: one color per method,
    filled nuScenes, hollow KITTI."""
    figure, axes = plt.subplots(1, 2, figsize=(16, 6.5), sharex=True)
    methods = sorted({r["method"] for r in rows}, key=method_order)
    colors = plt.get_cmap("tab20")(np.linspace(0, 1, max(len(methods), 2)))
    for method, color in zip(methods, colors):
        for sensor, fill in (("nuscenes", True), ("kitti", False)):
            part = [r for r in rows if r["method"] == method and r["sensor"] == sensor and r["error_p99_m"] is not None]
            style = {"marker": "*" if method == "embree" else "o", "s": 60, "edgecolors": color, "linewidths": 1.2,
                     "facecolors": color if fill else "none", "label": method if fill else None}
            x = [r["ms_median"] for r in part]
            axes[0].scatter(x, [max(r["error_p99_m"], ERROR_FLOOR) for r in part], **style)
            axes[1].scatter(x, [max(r["false_pct"] + r["missed_pct"], 1e-3) for r in part], **style | {"label": None})
    for axis in axes:
        axis.set(xscale="log", yscale="log", xlabel="median ms per object scan (builds excluded)")
        axis.axvline(TARGET_MS, color="k", ls="--", lw=1)
        axis.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel(f"p99 |range error| vs float64 reference, m (floored at {ERROR_FLOOR:g})")
    axes[1].set_ylabel("false + missed hits, % of reference hits (floored at 1e-3 = none)")
    axes[1].legend(*axes[0].get_legend_handles_labels(), loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8,
                   frameon=False)
    figure.suptitle("LiDAR object scans: time against error (filled nuScenes HDL-32E, hollow KITTI HDL-64E; "
                    f"dashed: the {TARGET_MS:g} ms target)", fontsize=10)
    return figure


def main(argv: list) -> int:
    parser = cli.parser("bench_scan.py", __doc__)
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
    try:
        import embreex
        args.embree = f"embreex {embreex.__version__}"
    except ImportError:
        args.embree = None

    objects = load_objects(args.chrono, args.quick)
    import bpy  # loaded by the mesh targets (BVHTree); its version is the BVH engine's

    machine = dev.machine(numpy=np.__version__, trimesh=trimesh.__version__, bpy=bpy.app.version_string,
                          embree=args.embree or "not installed")
    plan = []
    for obj in objects:
        subdivided = obj.reference is not obj  # the same surface as its reference: mesh engines only
        plan += [(obj, sensor, distances, {"full", "embree"} | (set() if subdivided else {"points"}))
                 for sensor in sensors]
        if obj.name.startswith("chrono truck") and not args.quick:
            plan.append((obj, PRESETS["nuscenes"], tuple(d for d in TARGET_DISTANCES if d not in distances),
                         {"embree"}))
    print(f"machine: {machine}\n", flush=True)
    load_before, start = dev.load_average(), time.perf_counter()
    records, builds, identical, compared = run(plan, args)
    elapsed, load_after = time.perf_counter() - start, dev.load_average()
    for obj in objects:
        builds[("bvh windowed", obj.name)] = builds[("bvh full revolution", obj.name)] = obj.build_s

    names = [o.name for o in objects]
    rows = sorted(rows_of(records, builds), key=lambda r: (names.index(r["object"]), r["sensor"] != "nuscenes",
                                                           r["distance_m"], method_order(r["method"])))
    target = target_summary(records)
    inputs = {"objects": {o.name: o.describe() for o in objects},
              "sensors": {s.name: s.note for s in sensors},
              "poses": f"{args.poses} per distance at {', '.join(f'{d:g}' for d in distances)} m (target also "
                       f"{', '.join(f'{d:g}' for d in TARGET_DISTANCES)} m): default_rng([{SEED}, round(distance * "
                       "1000)]), azimuth and heading uniform in [-pi, pi), the same for every object and method",
              "timing": f"time.perf_counter around the public call, {args.repeats} repeats (full revolution at most 3),"
                        " median per pose, then median over poses; builds apart",
              "points": f"surfels {list(args.surfel_points)} x radius scales {list(args.surfel_radii)}, range view "
                        f"{list(args.range_view_points)}: trimesh.sample.sample_surface(reference, n, seed=n)",
              "windowed equals full revolution": f"{identical}/{compared} poses bit-identical",
              "run": f"{elapsed:.0f} s; load average before {load_before}, after {load_after} (other work on the "
                     "machine inflates the times)"}
    body = tables(rows)
    line = target_line(target)
    print("\n" + body + "\n" + line)
    dev.write_report(args.out, "LiDAR object scan: time against error", "bench_scan.py", machine, inputs,
                     f"**{line}**\n\n{body}", {"machine": machine, "inputs": inputs, "target": target, "rows": rows},
                     lambda plt: plot(plt, rows))
    return 0


if __name__ == "__main__":
    cli.exit(cli.run_main(main, cli.script_argv()))
