"""Placement into real scenes against OpenPCDet's stock sampler (its unmodified
DataBaseSampler from ../shared/consumers, which pastes each entry at its stored pose):
how fast, and where the objects end up.

    .venv/bin/python headless_scripts/bench_placement.py [--repeats 30] [--out bench/placement]

Banks, made here (seeded): the built-in truck and bicycle, prepared for nuScenes sizes,
exported as a KITTI bank (x 5..45 m, y -25..25 m every 5 m, headings every 60 deg; KITTI
Truck and Cyclist) and a nuScenes bank (+-40 m every 10 m, headings every 60 deg).

**Speed** (one core: the process is pinned to CPU 0 and numpy's threads to one): each
shared KITTI frame thinned to every 4th return (about 30k points, the size of a nuScenes
sweep), 10 objects (5 Truck, 5 Cyclist) placed with occlusion, ``--repeats`` seeds; the
median of the whole call and of each stage. The stock sampler on the same scene with
SAMPLE_GROUPS Truck:5, Cyclist:5 and the KITTI config's other settings (road plane from
the scan, as KittiDataset gives it).

**Where objects land**, on the shared scans as the datasets hand them to the samplers
(KITTI frames: camera-2 field of view; the nuScenes sample: 100 returns, with a 14 m
wide road along its sensor's x axis given as a world-frame polygon, since the sample
ships no map), ``--repeats`` samplings per scene and method. Each inserted box is judged
by its bottom's gap to the ground, against the whole scan (KITTI: all 360 degrees,
more than the samplers are given): the scan's own ground returns 0.3-4 m around its
footprint (bank.ground.fit_ground) where there are at least 50 of them, else the
ground core.placement estimates from the whole scan; and by collisions and
feasibility in the scene the samplers (and the detector) are given. On the ground: |gap| <= 0.3 m (and <= 0.1 m); floating: gap >
0.3 m; sunk: gap < -0.3 m; colliding: its footprint overlaps a scene box or another
inserted one, or a scene return stands inside it more than 0.25 m above the ground;
infeasible: its centre or a corner lies where core.placement's fusion does not let its
class stand (ground-only on KITTI; the road map on nuScenes). Prints the tables; writes
<out>.json, <out>.md, <out>.png.
"""

import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy loads: one core, as a data-loader worker
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "addon"))
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from pgt_blender import cli, dev  # noqa: E402

SPEED_COUNTS = {"Truck": 5, "Cyclist": 5}
TARGET_MS = 20.0
KITTI_FRAMES = ("000000", "000001", "000002")
NUSCENES_SCAN = "n015-2018-08-02-17-16-37+0800__LIDAR_TOP__1533201470948018.pcd.bin"
ROAD_HALF_WIDTH = 7.0  # m: the nuScenes sample's stand-in road


def make_banks(work: Path) -> dict:
    from pgt_blender.core.authoring.prepare import prepare, write_prepared
    from pgt_blender.core.bank.config import config_from_table
    from pgt_blender.core.bank.export import export_bank
    from pgt_blender.core.bank.inputs import checked_objects, prepared_objects
    from pgt_blender.core.importing import load_reconstruction
    from pgt_blender.core.samples import write_sample

    folder = work / "prepared"
    for class_name, seed in (("truck", 1), ("bicycle", 2)):
        source = write_sample(work / "samples", class_name, seed=seed, points=3000)["reconstruction.ply"]
        write_prepared(prepare(load_reconstruction(source), class_name, up="pca", heading_method="baseline",
                               seed=seed), class_name, "nuscenes", folder)
    objects = checked_objects(*prepared_objects(folder), False, folder)
    grids = {"kitti": {"headings_deg": [-180, 180, 60], "x": [5, 45, 5], "y": [-25, 25, 5]},
             "nuscenes": {"headings_deg": [-180, 180, 60], "x": [-40, 40, 10], "y": [-40, 40, 10]}}
    for dataset, grid in grids.items():
        export_bank(objects, config_from_table({"bank": {"dataset": dataset, "chunk_size": 64}, "grid": grid}),
                    work / dataset, workers=2)
    return {dataset: work / dataset for dataset in grids}


def stock_sampler(pcdet, bank: Path, dataset: str, groups: dict):
    """OpenPCDet's DataBaseSampler over the bank's OpenPCDet pickle, the stock config's
    gt_sampling with only the database and the sample groups changed."""
    from tests.detectors import openpcdet

    config = openpcdet.gt_sampling(openpcdet.read_config(openpcdet.DATASET_CONFIGS[dataset]))
    config.DB_INFO_PATH = [f"{dataset}_dbinfos_pgt.pkl"]
    config.SAMPLE_GROUPS = [f"{name}:{count}" for name, count in groups.items()]
    config.PREPARE = {"filter_by_min_points": [f"{name}:5" for name in groups]}
    return openpcdet.build_sampler(pcdet, bank / "openpcdet", config, openpcdet.CLASS_NAMES[dataset])


def speed(banks: dict, pcdet, repeats: int) -> list:
    import copy

    from pgt_blender.core.placement.entries import open_database
    from pgt_blender.core.placement.place import PlacementConfig, place_objects
    from pgt_blender.core.scan.sensors import PRESETS
    from tests.detectors import openpcdet

    pool = open_database(banks["kitti"], "kitti")
    stock = stock_sampler(pcdet, banks["kitti"], "kitti", SPEED_COUNTS)
    rows = []
    for frame in KITTI_FRAMES:
        scene = openpcdet.kitti_scene(dev.SHARED_DATA / "kitti_scans", frame, openpcdet.CLASS_NAMES["kitti"])
        full = np.fromfile(dev.SHARED_DATA / "kitti_scans" / "velodyne" / f"{frame}.bin", np.float32).reshape(-1, 4)
        scene["points"] = full[::4]
        totals, stages, placed = [], [], []
        for seed in range(repeats):
            start = time.perf_counter()
            result = place_objects(scene["points"], scene["gt_boxes"], scene["gt_names"], pool, SPEED_COUNTS,
                                   PlacementConfig(PRESETS["kitti"]), np.random.default_rng(seed))
            totals.append(time.perf_counter() - start)
            stages.append(result.seconds)
            placed.append(int(result.inserted.sum()))
        np.random.seed(0)
        stock_times = []
        for _ in range(repeats):
            given = copy.deepcopy(scene)
            start = time.perf_counter()
            stock(given)
            stock_times.append(time.perf_counter() - start)
        rows.append({"frame": frame, "points": len(scene["points"]), "ms_median": 1e3 * float(np.median(totals)),
                     "ms_p90": 1e3 * float(np.percentile(totals, 90)),
                     "stages_ms": {name: 1e3 * float(np.median([s[name] for s in stages])) for name in stages[0]},
                     "placed_median": float(np.median(placed)), "stock_ms_median": 1e3 * float(np.median(stock_times))})
    return rows


def nuscenes_road(scene) -> object:
    """The stand-in road map of the nuScenes sample (module docstring)."""
    from pgt_blender.core.placement.maps import map_from_polygons

    corners = np.array([[-60.0, -ROAD_HALF_WIDTH], [60.0, -ROAD_HALF_WIDTH], [60.0, ROAD_HALF_WIDTH],
                        [-60.0, ROAD_HALF_WIDTH]])
    world = (np.column_stack([corners, np.zeros(4), np.ones(4)]) @ scene.lidar_to_world.T)[:, :2]
    return map_from_polygons([("road", [world])], scene.lidar_to_world)


def judge(boxes: np.ndarray, names, whole: np.ndarray, ground, given: np.ndarray, scene_boxes: np.ndarray,
          feasibility) -> list:
    """Per inserted box: its bottom gap to the ground of the ``whole`` scan (its ``ground``
    estimate where its returns cannot judge), colliding and infeasible in the ``given``
    scene (its ``feasibility``) (module docstring)."""
    from pgt_blender.core.bank.ground import MIN_GROUND_POINTS, fit_ground
    from pgt_blender.core.boxes import inside_box
    from pgt_blender.core.placement.collision import bev_overlaps, footprint_corners

    xyz = whole[:, :3].astype(np.float64)
    seen = given[:, :3].astype(np.float64)
    standing = seen[feasibility.ground.height_above(seen) > 0.25]
    overlaps = bev_overlaps(boxes, np.vstack([scene_boxes[:, :7], boxes[:, :7]]))
    overlaps[:, len(scene_boxes):][np.eye(len(boxes), dtype=bool)] = False
    judged = []
    for index, (box, name) in enumerate(zip(boxes, names)):
        fit = fit_ground(xyz, box[:3], box[3:6], box[6])
        by_scan = fit["points"] >= MIN_GROUND_POINTS
        bottom = box[2] - box[5] / 2
        gap = fit["bottom_gap"] if by_scan else bottom - ground.under_boxes(box[None])[0]
        spots = np.vstack([box[None, :2], footprint_corners(box[None])[0]])
        judged.append({"gap": float(gap), "by_scan": bool(by_scan),
                       "colliding": bool(overlaps[index].any() or inside_box(standing, box).any()),
                       "infeasible": bool(not feasibility.allows(str(name), spots).all())})
    return judged


def where_objects_land(banks: dict, pcdet, repeats: int) -> dict:
    import copy

    from pgt_blender.core.placement.entries import open_database
    from pgt_blender.core.placement.feasibility import scene_feasibility
    from pgt_blender.core.placement.ground import estimate_ground
    from pgt_blender.core.placement.place import PlacementConfig, place_objects
    from pgt_blender.core.placement.scenes import read_scene
    from pgt_blender.core.scan.sensors import PRESETS
    from tests.detectors import openpcdet

    shared = dev.SHARED_DATA
    scenes = [(f"KITTI {frame}", "kitti", read_scene(shared / "kitti_scans" / "velodyne" / f"{frame}.bin",
                                                     shared / "kitti_scans" / "label_2" / f"{frame}.txt"),
               openpcdet.kitti_scene(shared / "kitti_scans", frame, openpcdet.CLASS_NAMES["kitti"]), None)
              for frame in KITTI_FRAMES]
    sample = read_scene(shared / "nuscenes_format_sample" / "samples" / "LIDAR_TOP" / NUSCENES_SCAN,
                        shared / "nuscenes_format_sample" / "nus_info.pkl")
    scenes.append(("nuScenes sample (road map)", "nuscenes", sample,
                   openpcdet.nuscenes_scene(shared / "nuscenes_format_sample"), nuscenes_road(sample)))
    groups = {"kitti": {"Truck": 3, "Cyclist": 3}, "nuscenes": {"truck": 3, "bicycle": 3}}
    results = {}
    for label, dataset, scene, given, scene_map in scenes:
        pool = open_database(banks[dataset], dataset)
        config = PlacementConfig(PRESETS[dataset])
        points = given["points"]  # what the dataset hands to the sampler (KITTI: camera-2 view)
        boxes, names = given["gt_boxes"], given["gt_names"]
        whole = scene.points  # the judge's ground
        ground = estimate_ground(whole, radius=config.max_distance + 6.0)
        feasibility = scene_feasibility(points, estimate_ground(points, radius=config.max_distance + 6.0), scene_map,
                                        radius=config.max_distance)
        stock = stock_sampler(pcdet, banks[dataset], dataset, groups[dataset])
        np.random.seed(0)
        verdicts = {"stock (OpenPCDet, stored pose)": [], "placement": []}
        for seed in range(repeats):
            after = stock(copy.deepcopy(given))
            count = int(given["gt_boxes_mask"].sum())
            pasted = after["gt_boxes"][count:].astype(np.float64)
            verdicts["stock (OpenPCDet, stored pose)"] += judge(pasted, after["gt_names"][count:], whole, ground,
                                                                points, boxes, feasibility)
            placed = place_objects(points, boxes, names, pool, groups[dataset], config,
                                   np.random.default_rng(seed), scene_map)
            verdicts["placement"] += judge(placed.boxes[placed.inserted], placed.names[placed.inserted], whole,
                                           ground, points, boxes, feasibility)
        results[label] = {method: summary(found) for method, found in verdicts.items()}
    return results


def summary(verdicts: list) -> dict:
    gaps = np.array([v["gap"] for v in verdicts])
    share = (lambda mask: float(np.mean(mask)) if len(verdicts) else 0.0)  # noqa: E731
    return {"objects": len(verdicts), "on_ground": share(np.abs(gaps) <= 0.3), "within_10cm": share(np.abs(gaps) <= 0.1),
            "floating": share(gaps > 0.3), "sunk": share(gaps < -0.3),
            "colliding": share([v["colliding"] for v in verdicts]),
            "infeasible": share([v["infeasible"] for v in verdicts]),
            "judged_by_scan": share([v["by_scan"] for v in verdicts]),
            "gap_median_abs": float(np.median(np.abs(gaps))) if len(gaps) else None}


def main(argv: list) -> int:
    parser = cli.parser("bench_placement.py", __doc__)
    parser.add_argument("--repeats", type=int, default=30, help="seeds per scene (speed) and samplings (landing)")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "placement")
    args = parser.parse_args(argv)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {0})
    from tests.detectors import openpcdet

    load_before = dev.load_average()
    with tempfile.TemporaryDirectory() as work:
        banks = make_banks(Path(work))
        pcdet = openpcdet.load_pcdet(Path(work))
        speed_rows = speed(banks, pcdet, args.repeats)
        landing = where_objects_land(banks, pcdet, args.repeats)
    machine = dev.machine(numpy=np.__version__, threads="1 (pinned to CPU 0)")
    stage_names = list(speed_rows[0]["stages_ms"])
    speed_table = dev.markdown_table(
        ["frame", "points", "placement ms (median)", "p90", *[f"{name} ms" for name in stage_names],
         "objects placed", "stock ms", "placement / stock", "target"],
        [[r["frame"], f"{r['points']:,}", f"{r['ms_median']:.1f}", f"{r['ms_p90']:.1f}",
          *[f"{r['stages_ms'][name]:.1f}" for name in stage_names], f"{r['placed_median']:g}",
          f"{r['stock_ms_median']:.1f}", f"{r['ms_median'] / r['stock_ms_median']:.1f}x",
          f"{'meets' if r['ms_median'] <= TARGET_MS else 'MISSES'} <= {TARGET_MS:g} ms"] for r in speed_rows])
    percent = (lambda value: f"{100 * value:.0f} %")  # noqa: E731
    landing_table = dev.markdown_table(
        ["scene", "method", "objects", "on the ground (<= 0.3 m)", "<= 0.1 m", "floating", "sunk", "colliding",
         "infeasible", "judged by the scan's ground"],
        [[scene, method, s["objects"], *map(percent, [s["on_ground"], s["within_10cm"], s["floating"], s["sunk"],
                                                        s["colliding"], s["infeasible"], s["judged_by_scan"]])]
         for scene, methods in landing.items() for method, s in methods.items()])
    print(speed_table, "\n\n", landing_table, sep="")
    inputs = {"banks": "built-in truck and bicycle (nuScenes sizes): KITTI x 5..45, y -25..25 every 5 m; nuScenes "
                       "+-40 every 10 m; headings every 60 deg",
              "speed": f"KITTI frames thinned to every 4th return, 10 objects (5 Truck, 5 Cyclist), occlusion on, "
                       f"{args.repeats} seeds, medians; stock: OpenPCDet's DataBaseSampler, same scene and groups",
              "landing": f"{args.repeats} samplings per scene and method (3 Truck + 3 Cyclist / truck + bicycle each)",
              "load average": f"before {load_before}, after {dev.load_average()} (times are upper bounds)"}
    body = "## Speed (one core)\n\n" + speed_table + "\n\n## Where objects land\n\n" + landing_table

    def plot(plt):
        figure, (left, right) = plt.subplots(1, 2, figsize=(14, 4.5))
        frames = [r["frame"] for r in speed_rows]
        bottom = np.zeros(len(frames))
        for name in stage_names:
            values = np.array([r["stages_ms"][name] for r in speed_rows])
            left.bar(frames, values, bottom=bottom, label=name)
            bottom += values
        left.scatter(frames, [r["stock_ms_median"] for r in speed_rows], color="k", marker="x", label="stock sampler")
        left.axhline(TARGET_MS, color="k", ls="--", lw=1)
        left.set(ylabel="ms (median, one core)", title="Placing 10 objects into ~30k points")
        left.legend(fontsize="small")
        measures = ["on_ground", "floating", "sunk", "colliding", "infeasible"]
        width = 0.4
        for offset, method in ((-width / 2, "stock (OpenPCDet, stored pose)"), (width / 2, "placement")):
            totals = [np.mean([landing[scene][method][m] for scene in landing]) for m in measures]
            right.bar(np.arange(len(measures)) + offset, totals, width, label=method)
        right.set_xticks(np.arange(len(measures)), measures)
        right.set(ylabel="share of inserted objects (mean over scenes)", title="Where objects land")
        right.legend(fontsize="small")
        return figure

    dev.write_report(args.out, "Placement into real scenes", "bench_placement.py", machine, inputs, body,
                     {"machine": machine, "inputs": inputs, "speed": speed_rows, "landing": landing}, plot)
    return 0


if __name__ == "__main__":
    cli.exit(cli.run_main(main, cli.script_argv()))
