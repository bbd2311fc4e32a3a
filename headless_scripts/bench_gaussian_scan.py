"""Gaussian splats scanned as Gaussians against the same splats as surfels, both
against the mesh they were fitted to (core/scan/gaussians.py, targets.surfel_target).

    .venv/bin/python headless_scripts/bench_gaussian_scan.py [--quick] [--poses 2] [--repeats 3]
        [--mesh SEDAN.obj] [--out bench/gaussian_scan]

Splats fitted to a known mesh (the Chrono sedan body, 39k faces, box centre at the
origin): N points drawn on its surface (trimesh.sample.sample_surface(mesh, N,
seed=N)), each a flat Gaussian in its face's plane: tangent scales sigma = the mean
point spacing sqrt(area / N) (x SIGMA_SCALE), normal scale 0, rotation from the face's
frame, opacity drawn uniform in OPACITY (default_rng(N)). The same splats are scanned
two ways: as Gaussians (``gaussian_target``: compositing, return where the opacity
reaches 0.5) and as surfels (``surfel_target`` with their scales, rotations and
opacities: a 2-sigma ellipse each, the faint ones seen through; the Embree engine,
the product's default). The truth is the mesh itself: bench_scan.reference_ranges, the
float64 nearest hit of every cell's ray on the placed triangles.

Poses: --poses per distance (10, 20, 40 m) on nuScenes (HDL-32E) and KITTI (HDL-64E,
lasers off the origin), azimuth and heading from default_rng([SEED, distance]); every
method scans the same poses. Per method: |range error| median and p95 over rays both it
and the mesh hit; false hits (it hits, the mesh does not) and missed hits (the mesh
hits, it does not) as % of the mesh's hits; time per scan (median over poses of the
median of --repeats calls of ``cast_rays``); build time apart. Prints Markdown tables
and writes <out>.json, <out>.md and <out>.png.
"""

import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "addon"))
sys.path.insert(0, str(ROOT / "headless_scripts"))

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from bench_scan import compare, reference_ranges, summarise, timed  # noqa: E402
from pgt_blender import cli, dev  # noqa: E402
from pgt_blender.core.scan import raycast  # noqa: E402
from pgt_blender.core.scan.gaussians import CUTOFF_SIGMAS, HIT_OPACITY, quaternions  # noqa: E402
from pgt_blender.core.scan.sensors import PRESETS  # noqa: E402
from pgt_blender.core.scan.targets import gaussian_target, surfel_target  # noqa: E402

SEDAN = dev.CHRONO_VEHICLES / "sedan" / "sedan_chassis_vis.obj"
SEED = 2024
DISTANCES = (10.0, 20.0, 40.0)
SPLAT_COUNTS = (20_000, 100_000)
SIGMA_SCALE = 1.0  # tangent sigma / mean point spacing
OPACITY = (0.5, 1.0)


def fitted_splats(mesh: trimesh.Trimesh, count: int) -> dict:
    """Flat Gaussians on ``mesh``'s surface (see the module docstring): positions, scales,
    rotations (w x y z), opacities."""
    points, faces = trimesh.sample.sample_surface(mesh, count, seed=count)
    normals = mesh.face_normals[faces]
    helper = np.where(np.abs(normals[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = np.cross(normals, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(normals, u)
    sigma = SIGMA_SCALE * np.sqrt(mesh.area / count)
    rng = np.random.default_rng(count)
    return {"positions": points, "scales": np.tile([sigma, sigma, 0.0], (count, 1)),
            "rotations": quaternions(np.stack([u, v, normals], axis=2)),
            "opacities": rng.uniform(*OPACITY, count), "sigma": sigma}


def poses(distance: float, count: int) -> list:
    rng = np.random.default_rng([SEED, int(round(distance * 1000))])
    return [(distance * np.cos(a), distance * np.sin(a), h)
            for a, h in zip(rng.uniform(-np.pi, np.pi, count), rng.uniform(-np.pi, np.pi, count))]


def main(argv: list) -> int:
    parser = cli.parser("bench_gaussian_scan.py", __doc__)
    parser.add_argument("--quick", action="store_true", help="20k splats, nuScenes, 10 and 20 m, 1 pose")
    parser.add_argument("--poses", type=int, default=2, help="azimuth/heading poses per distance")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls per scan")
    parser.add_argument("--mesh", type=Path, default=SEDAN, help="the mesh the splats are fitted to")
    parser.add_argument("--out", type=Path, default=Path("bench/gaussian_scan"))
    args = parser.parse_args(argv)
    counts = SPLAT_COUNTS[:1] if args.quick else SPLAT_COUNTS
    sensors = [PRESETS["nuscenes"]] + ([] if args.quick else [PRESETS["kitti"]])
    distances = DISTANCES[:2] if args.quick else DISTANCES
    args.poses = 1 if args.quick else args.poses
    loaded = trimesh.load(args.mesh, force="mesh", process=False)
    vertices = np.asarray(loaded.vertices, np.float64)
    vertices -= (vertices.min(axis=0) + vertices.max(axis=0)) / 2
    mesh = trimesh.Trimesh(vertices, loaded.faces, process=False)
    triangles = vertices[mesh.faces]
    bounds = np.stack([vertices.min(axis=0), vertices.max(axis=0)])
    machine = dev.machine(numpy=np.__version__, trimesh=trimesh.__version__)
    print(f"machine: {machine}\n", flush=True)
    load_before, start = dev.load_average(), time.perf_counter()

    methods, builds, sigmas = {}, {}, {}
    for count in counts:
        splats = fitted_splats(mesh, count)
        sigmas[count] = splats["sigma"]
        arrays = [splats[key] for key in ("positions", "scales", "rotations", "opacities")]
        for label, build in ((f"gaussians {count // 1000}k", lambda: gaussian_target(*arrays, name="splats")),
                             (f"surfels {count // 1000}k", lambda: surfel_target(
                                 splats["positions"], "splats", scales=splats["scales"],
                                 rotations=splats["rotations"], opacities=splats["opacities"], engine="embree"))):
            began = time.perf_counter()
            methods[label] = build()
            builds[label] = time.perf_counter() - began
    options = raycast.ScanOptions(engine="embree")
    records = {}
    for sensor in sensors:
        for distance in distances:
            began = time.perf_counter()
            for pose in poses(distance, args.poses):
                # Placed by the mesh's box, so every method sees the object at the very same pose.
                matrix = raycast.placement(bounds, sensor, *pose)
                truth = reference_ranges(triangles, sensor, matrix)
                for label, target in methods.items():
                    scan, seconds = timed(lambda: raycast.cast_rays(target, sensor, matrix, options), args.repeats)
                    cells = scan.returns["ring"].astype(np.int64) * sensor.columns + scan.returns["column"]
                    records.setdefault((label, sensor.name, distance), []).append(
                        {"seconds": seconds, "hits": len(cells), **compare(cells, scan.returns["range"], truth)})
            print(f"{sensor.name:8} | {distance:4.0f} m | {time.perf_counter() - began:.1f} s", flush=True)
    elapsed, load_after = time.perf_counter() - start, dev.load_average()

    rows = []
    for (label, sensor, distance), entries in records.items():
        summary = summarise(entries)
        errors = np.concatenate([e["errors"] for e in entries])
        rows.append({"method": label, "sensor": sensor, "distance_m": distance, "poses": len(entries),
                     "ms_median": float(np.median([1e3 * e["seconds"] for e in entries])),
                     "error_p95_m": float(np.percentile(errors, 95)) if len(errors) else None,
                     "build_s": builds[label], **summary})
    overall = []
    for label in methods:
        mine = [r for r in rows if r["method"] == label]
        entries = [e for (name, _, _), found in records.items() if name == label for e in found]
        summary = summarise(entries)
        errors = np.concatenate([e["errors"] for e in entries])
        overall.append({"method": label, "ms_median": float(np.median([r["ms_median"] for r in mine])),
                        "error_median_m": summary["error_median_m"],
                        "error_p95_m": float(np.percentile(errors, 95)) if len(errors) else None,
                        "false_pct": summary["false_pct"], "missed_pct": summary["missed_pct"],
                        "build_s": builds[label]})
    body = "## per method (all sensors, distances and poses)\n\n" + dev.markdown_table(
        ["method", "ms / scan (median of rows)", "build s", "|range err| median m", "p95 m", "false %", "missed %"],
        [[o["method"], f"{o['ms_median']:.1f}", f"{o['build_s']:.2f}", f"{o['error_median_m']:.4f}",
          f"{o['error_p95_m']:.4f}", f"{o['false_pct']:.2f}", f"{o['missed_pct']:.2f}"] for o in overall])
    body += "\n\n## per sensor and distance (medians over poses)\n\n" + dev.markdown_table(
        ["method", "sensor", "m", "ms / scan", "|range err| median m", "p95 m", "false %", "missed %"],
        [[r["method"], r["sensor"], f"{r['distance_m']:g}", f"{r['ms_median']:.1f}", f"{r['error_median_m']:.4f}",
          f"{r['error_p95_m']:.4f}", f"{r['false_pct']:.2f}", f"{r['missed_pct']:.2f}"]
         for r in sorted(rows, key=lambda r: (r["sensor"], r["distance_m"], r["method"]))], "ll" + "r" * 6)
    inputs = {"mesh": f"{args.mesh.name}: {len(mesh.faces):,} faces, {' x '.join(f'{e:.2f}' for e in mesh.extents)} "
                      f"m, box centre at the origin; the truth is its float64 ray cast (bench_scan.reference_ranges)",
              "splats": {f"{count // 1000}k": f"flat, sigma {sigmas[count] * 100:.1f} cm in the face plane, 0 along "
                                              f"the normal, opacity uniform {OPACITY}" for count in counts},
              "gaussians": f"cutoff {CUTOFF_SIGMAS:g} sigma, return where the accumulated opacity reaches "
                           f"{HIT_OPACITY:g}",
              "surfels": "2-sigma ellipses of the same splats, opacity < 0.5 seen through, Embree engine",
              "poses": f"{args.poses} per distance at {', '.join(f'{d:g}' for d in distances)} m on "
                       f"{', '.join(s.name for s in sensors)}: default_rng([{SEED}, round(distance * 1000)])",
              "run": f"{elapsed:.0f} s; load average before {load_before}, after {load_after} (2 shared cores: "
                     "other work on the machine inflates the times)"}
    print("\n" + body)
    dev.write_report(args.out, "Gaussian splats scanned as Gaussians against surfels", "bench_gaussian_scan.py",
                     machine, inputs, body, {"machine": machine, "inputs": inputs, "overall": overall, "rows": rows},
                     lambda plt: plot(plt, rows))
    return 0


def plot(plt, rows: list):
    """Time against p95 range error and against false + missed hits, per method."""
    figure, axes = plt.subplots(1, 2, figsize=(14, 5.5), sharex=True)
    methods = sorted({r["method"] for r in rows})
    for method, color in zip(methods, plt.get_cmap("tab10")(np.arange(len(methods)))):
        for sensor, fill in (("nuscenes", True), ("kitti", False)):
            part = [r for r in rows if r["method"] == method and r["sensor"] == sensor]
            style = {"s": 50, "edgecolors": color, "facecolors": color if fill else "none",
                     "marker": "o" if method.startswith("gaussians") else "s", "label": method if fill else None}
            x = [r["ms_median"] for r in part]
            axes[0].scatter(x, [r["error_p95_m"] for r in part], **style)
            axes[1].scatter(x, [r["false_pct"] + r["missed_pct"] for r in part], **style | {"label": None})
    for axis in axes:
        axis.set(xscale="log", xlabel="median ms per object scan (builds excluded)")
        axis.grid(True, which="both", alpha=0.3)
    axes[0].set(ylabel="p95 |range error| vs the mesh, m", yscale="log")
    axes[1].set(ylabel="false + missed hits, % of the mesh's hits")
    axes[0].legend(fontsize=8)
    figure.suptitle("Splats fitted to a mesh: Gaussians against surfels (filled nuScenes, hollow KITTI)", fontsize=10)
    return figure


if __name__ == "__main__":
    cli.exit(cli.run_main(main, cli.script_argv()))
