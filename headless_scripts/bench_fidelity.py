"""How much simulated objects look like what the real sensor recorded: every labelled
object of real scans is replaced by a mesh of its class scaled to its box, the whole
scene is scanned once (objects occlude each other), and each object's simulated returns
are compared with its real ones.

    .venv/bin/python headless_scripts/bench_fidelity.py [KITTI_FOLDER] [--meshes samples|FOLDER]
        [--sensor kitti] [--min-points 1] [--no-glass] [--no-drop] [--out bench/fidelity]

KITTI_FOLDER (default ../shared/data/kitti_scans) holds velodyne/*.bin, label_2/*.txt and
calib/*.txt. Meshes by class: ``chrono`` (default) takes ../shared/data/chrono_vehicles
(sedan for Car, VW van for Van, truck for Truck), ``samples`` the built-in parametric
vehicles (truck for Truck, bicycle for Cyclist), a FOLDER ``<class>.obj|.ply`` by KITTI
class name in lower case; a class without a mesh is scanned as its box (column "mesh":
box). The scan: the sensor preset, one revolution from the origin, range noise and
the sensor's ray drop on (``--no-drop``: off), seeded; intensity the sensor's law
(physical_intensity.py).

Per object (real = the scan's points inside the labelled box, simulated = the returns
off its mesh): points and their ratio sim / real; rings hit (real rings from scan order,
sensor_fit.py) and their Jaccard index; columns per ring hit; the share of points in the
top 40 % of the box height (windows and roofs); intensity mean and Wasserstein-1 to the
real intensities, beside W1 of a constant equal to the mean of every real object point
(the constant-mean baseline). Totals: median ratio, share within +-35 %, mean Jaccard,
mean W1 of the simulated and of the constant intensities.

Prints the per-object table and the totals and writes them to <out>.md (with the
machine and the inputs), the rows and totals to <out>.json and two plots (points per
object, intensity W1) to <out>.png.
"""

import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "addon"))

import numpy as np  # noqa: E402
from scipy.stats import wasserstein_distance  # noqa: E402

from pgt_blender import cli, dev  # noqa: E402
from pgt_blender.core.boxes import box_frame  # noqa: E402
from pgt_blender.core.errors import InputError  # noqa: E402
from pgt_blender.core.intensity.objects import kitti_frames  # noqa: E402
from pgt_blender.core.scan import replay  # noqa: E402
from pgt_blender.core.scan.raycast import ScanOptions, cast_rays  # noqa: E402
from pgt_blender.core.scan.sensors import sensor_from_name  # noqa: E402

RATIO_BAND = 0.35  # the "within +-35 %"
TOP_SHARE = 0.4  # top 40 % of the box height


def frame_objects(rows, labels, sensor, meshes, options: ScanOptions, glass: bool = True) -> list:
    """One frame: the scene of meshes scanned once, then per labelled object its real and
    simulated points (box frame), rings, columns and intensities."""
    scene, owner_of_face, chosen = replay.labelled_scene(labels, meshes, glass)
    scan = cast_rays(scene, sensor, np.eye(4), options)
    owner = owner_of_face[scan.returns["face"]]
    rings = replay.real_rings(rows)
    columns = replay.azimuth_columns(rows, sensor)
    found = []
    for index, ((kind, centre, dims, heading), mesh) in enumerate(zip(labels, chosen)):
        local = box_frame(rows[:, :3], centre, heading)
        inside = np.all(np.abs(local) <= dims / 2, axis=1)
        mine = scan.returns[owner == index]
        sim_local = box_frame(np.column_stack([mine[axis] for axis in "xyz"]), centre, heading)
        found.append({"class": kind, "mesh": mesh[2], "distance": float(np.hypot(*centre[:2])), "dims": dims,
                      "real": local[inside], "sim": sim_local, "real_intensity": rows[inside, 3],
                      "sim_intensity": mine["intensity"].astype(np.float64),
                      "real_cells": (rings[inside], columns[inside]),
                      "sim_cells": (mine["ring"].astype(np.int64), mine["column"].astype(np.int64))})
    return found


def columns_per_ring(rings, columns) -> float:
    if not len(rings):
        return 0.0
    return len(set(zip(rings.tolist(), columns.tolist()))) / len(np.unique(rings))


def top_share(points, height) -> float:
    return float((points[:, 2] > height / 2 - TOP_SHARE * height).mean()) if len(points) else 0.0


def measure(objects: list) -> tuple:
    """(per-object rows, totals) of the metrics in the module docstring."""
    constant = float(np.mean(np.concatenate([obj["real_intensity"] for obj in objects])))
    rows = []
    for obj in objects:
        real, sim = len(obj["real"]), len(obj["sim"])
        real_rings, sim_rings = set(obj["real_cells"][0].tolist()), set(obj["sim_cells"][0].tolist())
        union = real_rings | sim_rings
        rows.append({
            "class": obj["class"], "mesh": obj["mesh"], "distance_m": obj["distance"], "real_points": real,
            "sim_points": sim, "ratio": sim / real if real else None,
            "ring_jaccard": len(real_rings & sim_rings) / len(union) if union else None,
            "real_columns_per_ring": columns_per_ring(*obj["real_cells"]),
            "sim_columns_per_ring": columns_per_ring(*obj["sim_cells"]),
            "real_top_share": top_share(obj["real"], obj["dims"][2]),
            "sim_top_share": top_share(obj["sim"], obj["dims"][2]),
            "real_intensity_mean": float(obj["real_intensity"].mean()) if real else None,
            "sim_intensity_mean": float(obj["sim_intensity"].mean()) if sim else None,
            "w1_sim": wasserstein_distance(obj["sim_intensity"], obj["real_intensity"]) if real and sim else None,
            "w1_constant": wasserstein_distance([constant], obj["real_intensity"]) if real else None,
        })
    ratios = np.array([row["ratio"] for row in rows if row["ratio"] is not None])
    jaccards = [row["ring_jaccard"] for row in rows if row["ring_jaccard"] is not None]
    scored = [row for row in rows if row["w1_sim"] is not None]
    totals = {"objects": len(rows), "median_ratio": float(np.median(ratios)) if len(ratios) else None,
              "within_35_percent": float(np.mean(np.abs(ratios - 1) <= RATIO_BAND)) if len(ratios) else None,
              "mean_ring_jaccard": float(np.mean(jaccards)) if jaccards else None, "constant_intensity": constant,
              "mean_w1_sim": float(np.mean([row["w1_sim"] for row in scored])) if scored else None,
              "mean_w1_constant": float(np.mean([row["w1_constant"] for row in scored])) if scored else None}
    return rows, totals


def number(value, digits=2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def rounded(values: tuple) -> str:
    return ", ".join(f"{value:.4g}" for value in values)


def table(rows: list) -> str:
    return dev.markdown_table(
        ["class", "mesh", "distance m", "points real / sim", "ratio", "ring Jaccard", "columns/ring real / sim",
         "top 40 % real / sim", "intensity real / sim", "W1 sim", "W1 constant"],
        [[r["class"], r["mesh"], f"{r['distance_m']:.1f}", f"{r['real_points']} / {r['sim_points']}",
          number(r["ratio"]), number(r["ring_jaccard"]),
          f"{r['real_columns_per_ring']:.1f} / {r['sim_columns_per_ring']:.1f}",
          f"{r['real_top_share']:.2f} / {r['sim_top_share']:.2f}",
          f"{number(r['real_intensity_mean'], 3)} / {number(r['sim_intensity_mean'], 3)}", number(r["w1_sim"], 3),
          number(r["w1_constant"], 3)] for r in rows], "ll" + "r" * 9)


def draw(rows: list):
    def figure(plt):
        fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
        real = [row["real_points"] for row in rows]
        left.loglog(real, [max(row["sim_points"], 0.5) for row in rows], "o")
        span = [max(min(real), 1), max(real)]
        left.plot(span, span, "k--", label="sim = real")
        left.fill_between(span, [v * (1 - RATIO_BAND) for v in span], [v * (1 + RATIO_BAND) for v in span],
                          alpha=0.2, label="+-35 %")
        left.set(xlabel="real points in the box", ylabel="simulated points", title="points per object")
        left.legend()
        scored = [row for row in rows if row["w1_sim"] is not None]
        x = np.arange(len(scored))
        right.bar(x - 0.2, [row["w1_sim"] for row in scored], 0.4, label="simulated (physical default)")
        right.bar(x + 0.2, [row["w1_constant"] for row in scored], 0.4, label="constant mean")
        right.set_xticks(x, [f"{row['class']}\n{row['distance_m']:.0f} m" for row in scored])
        right.set(ylabel="W1 to real intensities", title="intensity")
        right.legend()
        return fig
    return figure


def main(argv: list) -> int:
    parser = cli.parser("bench_fidelity.py", __doc__)
    parser.add_argument("folder", type=Path, nargs="?", default=dev.SHARED_DATA / "kitti_scans", help="KITTI frames")
    parser.add_argument("--meshes", default=str(dev.CHRONO_VEHICLES),
                        help="class meshes: samples, the Chrono vehicle folder (default) or a folder of <class>.obj/.ply")
    parser.add_argument("--sensor", default="kitti", help="sensor preset or TOML")
    parser.add_argument("--min-points", type=int, default=1, help="real points an object needs to be scored")
    parser.add_argument("--no-glass", action="store_true", help="scan glass materials as solid surfaces")
    parser.add_argument("--no-drop", action="store_true", help="scan without the sensor's ray-drop model")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "fidelity")
    args = parser.parse_args(argv)
    sensor = sensor_from_name(args.sensor)
    if sensor.dataset != "kitti":
        raise InputError(args.sensor, f"is a {sensor.dataset} sensor; the scans are KITTI's")
    meshes = replay.class_meshes(args.meshes)
    options = ScanOptions(window=False, range_noise=True, ray_drop=not args.no_drop, seed=args.seed)
    start = time.perf_counter()
    objects = [obj for _, rows, labels in kitti_frames(args.folder) if labels
               for obj in frame_objects(rows, labels, sensor, meshes, options, not args.no_glass)
               if len(obj["real"]) >= args.min_points]
    if not objects:
        raise InputError(args.folder, f"no labelled object has {args.min_points} real points")
    rows, totals = measure(objects)
    seconds = time.perf_counter() - start
    import scipy

    machine = dev.machine(numpy=np.__version__, scipy=scipy.__version__, load_average=dev.load_average())
    body = ("Per object: real = the scan's points inside its labelled box, sim = the simulated returns off its mesh "
            "(box frame).\n\n" + table(rows) + f"\n\n{totals['objects']} objects: median points ratio sim / real "
            f"{number(totals['median_ratio'])}, {number(100 * totals['within_35_percent'], 0)} % within +-35 %, "
            f"mean ring Jaccard {number(totals['mean_ring_jaccard'])}; intensity W1, mean over objects, "
            f"{number(totals['mean_w1_sim'], 3)} simulated vs {number(totals['mean_w1_constant'], 3)} constant mean "
            f"({totals['constant_intensity']:.3f})")
    shown_meshes = args.meshes if args.meshes == "samples" else dev.shown_path(args.meshes)
    inputs = {"folder": dev.shown_path(args.folder), "meshes": shown_meshes, "glass": not args.no_glass,
              "sensor": sensor.name, "seed": args.seed, "min_points": args.min_points,
              "ray_drop": None if args.no_drop or not sensor.ray_drop else list(sensor.ray_drop),
              "intensity_law": list(sensor.intensity_law) if sensor.intensity_law else None}
    markdown_inputs = {"real frames": f"{dev.shown_path(args.folder)}: {len(rows)} labelled objects with >= "
                                      f"{args.min_points} real points",
                       "meshes": f"{shown_meshes} (glass {'solid' if args.no_glass else 'seen through'})",
                       "scan": f"sensor {sensor.name}, one revolution from the origin, range noise, seed {args.seed}",
                       "ray drop (a, k)": "off" if args.no_drop else rounded(sensor.ray_drop) or "none (no model)",
                       "intensity law (scale, range exponent, spread)": rounded(sensor.intensity_law)
                       or "the unfitted default",
                       "run": f"{seconds:.1f} s on a shared machine (the load average above is taken at the end)"}
    print(f"machine: {machine}", *(f"{key}: {value}" for key, value in markdown_inputs.items()), "", body, sep="\n")
    dev.write_report(args.out, "Fidelity: simulated objects against real KITTI scans", "bench_fidelity.py", machine,
                     markdown_inputs, body, {"machine": machine, "inputs": inputs, "objects": rows, "totals": totals},
                     draw(rows))
    return 0


if __name__ == "__main__":
    sys.exit(cli.run_main(main, cli.script_argv()))
