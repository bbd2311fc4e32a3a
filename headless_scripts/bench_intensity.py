"""How close estimated LiDAR intensities come to real ones, per class, on real objects
held out from every fit (leave one scan out): constant class mean, the sensor's fitted
physical law (the default without a checkpoint), histogram matching to the real class
histogram, and the learned CycleGAN estimator.

    .venv/bin/python headless_scripts/bench_intensity.py [--quick] [--steps N]
        [--checkpoint PATH] [--holdout 000001 ...] [--out bench/intensity]

Real objects: the KITTI scans in ../shared/data/kitti_scans cut by their labels. Each
scan in turn (or those named by --holdout) is held out: the physical law
(physical_intensity.py) is fitted on the other scans' labelled objects (replay.py, as
fit_returns.py does), the CycleGAN is trained on them (unless --checkpoint), and every
method is judged on the held-out scan's objects. RGB objects: scans (KITTI sensor with
the fold's law and its noise, the 12 poses of objects.RGB_POSES) of the Chrono meshes
with their material colors (sedan, SUV, van as car; truck, MAN as truck; city bus as
bus) and of the built-in samples. With --merge-classes (the default: the shared data
has one or two real objects per class) every class trains as one, "object";
predictions still go per original class. nuScenes is not measured: the shared nuScenes
sample's 100-point subsets hold no point of a labelled object.

Metric, per class and fold: Wasserstein-1 between the pooled per-point intensities of
the predictions (on that class's RGB objects) and of the held-out real objects, and W1
between their ball-patch mean intensities (16 farthest-point centres, radius 0.5 in the
[-1, 1]^3 box frame). Intensities are KITTI's 0..1. Lower is better. The summary
averages each method's W1 per point over the folds that scored the class.

Prints the per-fold and summary tables and writes them to <out>.md (with the machine
and the inputs), the rows to <out>.json and a bar chart to <out>.png.
"""

import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "addon"))

import numpy as np  # noqa: E402
from scipy.stats import wasserstein_distance  # noqa: E402

from pgt_blender import cli, dev  # noqa: E402
from pgt_blender.core.intensity import losses, objects  # noqa: E402
from pgt_blender.core.scan import replay  # noqa: E402
from pgt_blender.core.scan.sensors import PRESETS  # noqa: E402

CHRONO = {"car": ("sedan/sedan_chassis_vis.obj", "Nissan_Patrol/suv_chassis.obj", "VW_microbus/van_chassis.obj"),
          "truck": ("truck/truck_chassis.obj", "MAN_Kat1/meshes/MAN_10t_chassis.obj"),
          "bus": ("citybus/CityBus_Vis.obj",)}
METHODS = ("constant class mean", "physical default", "histogram matching", "learned (CycleGAN)")


def rgb_domain(sensor, quick: bool) -> list:
    """Scanned RGB objects: Chrono meshes by class, then the built-in samples."""
    import warnings

    found = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the Chrono meshes' zero-area faces
        for class_name, paths in CHRONO.items():
            for relative in paths[:1] if quick else paths:
                path = dev.CHRONO_VEHICLES / relative
                found += objects.material_mesh_rgb_objects(path, class_name, sensor)
    return found + ([] if quick else objects.builtin_rgb_objects(sensor))


def patch_means(obj) -> np.ndarray:
    """Mean intensity of each ball patch of one object (normalised box frame)."""
    xyz = obj.points / (obj.dims / 2)
    centres = losses.farthest_point_centres(xyz, min(losses.PATCHES, len(xyz)))
    return losses.patch_means(losses.ball_patches(xyz, centres, losses.PATCH_RADIUS), obj.values[:, 0])


def histogram_matched(values: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``values`` mapped through their ranks onto the quantiles of ``reference``."""
    ranks = (np.argsort(np.argsort(values, kind="stable"), kind="stable") + 0.5) / len(values)
    return np.quantile(reference, ranks).astype(np.float32)


def predictions(method: str, rgb: list, train_real: np.ndarray, estimator, class_label) -> list:
    """Per RGB object, (N, 1) predicted intensities in [0, 1]."""
    if method == "constant class mean":
        return [np.full((len(o.points), 1), train_real.mean(), np.float32) for o in rgb]
    if method == "physical default":
        return [o.physical[:, None].astype(np.float32) for o in rgb]
    if method == "histogram matching":
        return [histogram_matched(o.physical, train_real)[:, None] for o in rgb]
    return [v[:, None] for v in estimator.predict_many([(o.points, o.dims, o.values, class_label(o)) for o in rgb])]


def evaluate(held_out: list, rgb: list, train_real: list, estimator, merged: bool) -> list:
    rows = []
    for class_name in sorted({o.class_name for o in held_out} & {o.class_name for o in rgb}):
        real = [o for o in held_out if o.class_name == class_name]
        fake = [o for o in rgb if o.class_name == class_name]
        reference = [o for o in train_real if o.class_name == class_name] or train_real
        reference_values = np.concatenate([o.values[:, 0] for o in reference])
        real_points = np.concatenate([o.values[:, 0] for o in real])
        real_patches = np.concatenate([patch_means(o) for o in real])
        for method in METHODS:
            start = time.perf_counter()
            predicted = predictions(method, fake, reference_values, estimator,
                                    (lambda o: "object") if merged else (lambda o: o.class_name))
            seconds = time.perf_counter() - start
            as_objects = [replace(o, values=p) for o, p in zip(fake, predicted)]
            points = np.concatenate([p[:, 0] for p in predicted])
            rows.append({
                "class": class_name, "method": method, "real_objects": len(real), "real_points": int(len(real_points)),
                "rgb_objects": len(fake), "rgb_points": int(len(points)),
                "w1_points": float(wasserstein_distance(points, real_points)),
                "w1_patch_means": float(wasserstein_distance(np.concatenate([patch_means(o) for o in as_objects]),
                                                             real_patches)),
                "mean": float(points.mean()), "real_mean": float(real_points.mean()),
                "points_per_s": float(len(points) / seconds) if seconds > 0 else None,
            })
    return rows


def table(rows: list) -> str:
    return dev.markdown_table(
        ["held out", "class", "method", "W1 points", "W1 patch means", "mean", "real mean", "real objects / points",
         "rgb objects"],
        [[r["fold"], r["class"], r["method"], f"{r['w1_points']:.4f}", f"{r['w1_patch_means']:.4f}",
          f"{r['mean']:.3f}", f"{r['real_mean']:.3f}", f"{r['real_objects']} / {r['real_points']}", r["rgb_objects"]]
         for r in rows], "lll" + "r" * 6)


def summary_table(averaged: list) -> str:
    return dev.markdown_table(["class", "method", "W1 points, mean over folds", "/ constant class mean", "folds"],
                              [[r["class"], r["method"], f"{r['w1_points']:.4f}", f"{r['vs_constant']:.2f}",
                                ", ".join(r["folds"])] for r in averaged], "llrrl")


def draw(averaged: list):
    def figure(plt):
        classes = sorted({r["class"] for r in averaged})
        fig, axes = plt.subplots(1, len(classes), figsize=(5 * len(classes), 4), squeeze=False)
        for ax, class_name in zip(axes[0], classes):
            mine = [r for r in averaged if r["class"] == class_name]
            ax.bar(range(len(mine)), [r["w1_points"] for r in mine])
            ax.set_xticks(range(len(mine)), [r["method"].split(" (")[0] for r in mine], rotation=20)
            ax.set_title(f"{class_name}: held out in {', '.join(mine[0]['folds'])}")
            ax.set_ylabel("W1 per point to real (KITTI 0..1), lower is better")
        return fig
    return figure


def fold_law(frames: list, held_out: str, sensor) -> tuple:
    """The intensity law fitted on the replayed frames other than ``held_out``."""
    return replay.fit_frames_intensity_law([frame for frame in frames if frame["frame"] != held_out], sensor)


def summary(rows: list) -> list:
    """Per class: each method's W1 per point averaged over the folds that held it out,
    and its ratio to the constant class mean's."""
    found = []
    for class_name in sorted({row["class"] for row in rows}):
        constant = np.mean([row["w1_points"] for row in rows
                            if row["class"] == class_name and row["method"] == METHODS[0]])
        for method in METHODS:
            w1 = np.mean([row["w1_points"] for row in rows if row["class"] == class_name and row["method"] == method])
            found.append({"class": class_name, "method": method, "w1_points": float(w1),
                          "vs_constant": float(w1 / constant) if constant > 0 else None,
                          "folds": sorted({row["fold"] for row in rows if row["class"] == class_name})})
    return found


def main(argv: list) -> int:
    parser = cli.parser("bench_intensity.py", __doc__)
    parser.add_argument("--kitti", type=Path, default=dev.SHARED_DATA / "kitti_scans")
    parser.add_argument("--holdout", nargs="+", help="KITTI scan ids held out in turn (default: every scan)")
    parser.add_argument("--min-points", type=int, default=64, help="real training objects' minimum points")
    parser.add_argument("--steps", type=int, help="training steps (default: TrainConfig's)")
    parser.add_argument("--per-class", action="store_true", help="train classes apart instead of merged")
    parser.add_argument("--checkpoint", type=Path, help="evaluate this model instead of training one per fold")
    parser.add_argument("--quick", action="store_true", help="few objects and steps (a smoke test)")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "intensity")
    args = parser.parse_args(argv)
    from pgt_blender.core.intensity.estimator import IntensityEstimator
    from pgt_blender.core.intensity.training import TrainConfig, train

    sensor = PRESETS["kitti"]
    real = objects.kitti_scan_objects(args.kitti)
    frames = replay.replay_frames(objects.kitti_frames(args.kitti), sensor,
                                  replay.class_meshes(str(dev.CHRONO_VEHICLES)))
    scans = args.holdout or [frame["frame"] for frame in frames]
    merged = not args.per_class
    relabel = (lambda items: [replace(o, class_name="object") for o in items]) if merged else (lambda items: items)
    config = TrainConfig(steps=args.steps or (20 if args.quick else TrainConfig.steps))
    start = time.perf_counter()
    rows, folds = [], []
    for scan in scans:
        held_out = [o for o in real if o.name.split(":")[0] == scan]
        train_real = [o for o in real if o.name.split(":")[0] != scan]
        law = fold_law(frames, scan, sensor)
        rgb = rgb_domain(replace(sensor, intensity_law=law), args.quick)
        with tempfile.TemporaryDirectory() as scratch:
            checkpoint = args.checkpoint
            if checkpoint is None:
                real_set, rgb_set = objects.paired_sets(relabel(train_real), relabel(rgb), "kitti", args.min_points,
                                                        config.points)
                checkpoint = train(real_set, rgb_set, config, Path(scratch), progress=not args.quick)
            fold_rows = evaluate(held_out, rgb, train_real, IntensityEstimator.load(checkpoint), merged)
        rows += [row | {"fold": scan} for row in fold_rows]
        folds.append({"held_out": scan, "law": law, "held_out_objects": [f"{o.name} ({len(o.points)} pts)"
                                                                        for o in held_out],
                      "scored_classes": sorted({row["class"] for row in fold_rows})})
    averaged = summary(rows)
    seconds = time.perf_counter() - start
    machine = dev.machine(numpy=np.__version__, torch=__import__("torch").__version__,
                          load_average=dev.load_average())
    train_config = vars(config) | {"checkpoint": str(args.checkpoint) if args.checkpoint else "trained"}
    results = {
        "machine": machine,
        "inputs": {"real": dev.shown_path(args.kitti), "folds": folds, "rgb_objects_per_fold": len(rgb),
                   "merged_classes": merged, "min_points": args.min_points, "train_config": train_config},
        "seconds": seconds,
        "rows": rows,
        "summary": averaged,
    }
    fold_lines = [f"held out {fold['held_out']}: {', '.join(fold['held_out_objects'])}; law fitted on the others "
                  f"{tuple(round(value, 4) for value in fold['law'])}; scored classes "
                  f"{', '.join(fold['scored_classes']) or 'none (no RGB object of its classes)'}" for fold in folds]
    print("\n".join(fold_lines))
    body = ("Per fold: W1 between the predicted and the held-out real per-point intensities and between their "
            "ball-patch means (KITTI 0..1, lower is better); mean: the predictions' mean intensity.\n\n"
            + table(rows) + "\n\nPer class: W1 per point averaged over the folds that scored it, and its ratio "
            "to the constant class mean's.\n\n" + summary_table(averaged))
    print("\n" + body)
    inputs = {"real objects": f"{dev.shown_path(args.kitti)}, cut by their labels; held out in turn: "
                              f"{', '.join(scans)}",
              "folds": fold_lines,
              "RGB objects": f"{len(rgb)} per fold: the Chrono meshes "
                             f"{'(the first per class)' if args.quick else 'and the built-in samples'}, scanned at "
                             f"{len(objects.RGB_POSES)} poses with the fold's law and the KITTI sensor's noise",
              "training": {"classes": "merged into one" if merged else "apart", "min real points": args.min_points,
                           **{key: str(value) for key, value in train_config.items()}},
              "run": f"{seconds:.0f} s on a shared machine (the load average above is taken at the end)"}
    dev.write_report(args.out, "LiDAR intensity: estimates against held-out real objects", "bench_intensity.py",
                     machine, inputs, body, results, draw(averaged))
    return 0


if __name__ == "__main__":
    sys.exit(cli.run_main(main, cli.script_argv()))
