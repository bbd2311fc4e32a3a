"""How close estimated LiDAR intensities come to real ones, per class, on real objects
held out from training: constant class mean, the scanner's physical default, histogram
matching to the real class histogram, and the learned CycleGAN estimator.

    .venv/bin/python headless_scripts/bench_intensity.py [--quick] [--steps N]
        [--checkpoint PATH] [--holdout 000001] [--out bench/intensity]

Real objects: the KITTI scans in ../shared/data/kitti_scans cut by their labels; the
scans named by --holdout are never trained on and are what every method is judged
against. RGB objects: scans (KITTI sensor, the 12 poses of objects.RGB_POSES) of the
Chrono meshes with their material colours (sedan, SUV, van as car; truck, MAN as
truck; city bus as bus) and of the built-in samples. With --merge-classes (the
default: the shared data has one or two real objects per class) every class trains as
one, "object"; predictions still go per original class.

Metric, per class: Wasserstein-1 between the pooled per-point intensities of the
predictions (on that class's RGB objects) and of the held-out real objects, and W1
between their ball-patch mean intensities (16 farthest-point centres, radius 0.5 in the
[-1, 1]^3 box frame). Intensities are KITTI's 0..1. Lower is better.
"""

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "addon"))

import numpy as np  # noqa: E402
from scipy.stats import wasserstein_distance  # noqa: E402

from pgt_blender import cli  # noqa: E402
from pgt_blender.core.intensity import losses, objects  # noqa: E402
from pgt_blender.core.scan.sensors import PRESETS  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
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
                path = SHARED / "chrono_vehicles" / "data" / "vehicle" / relative
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
    lines = ["| class | method | W1 points | W1 patch means | mean | real mean | real objects / points | rgb objects |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['class']} | {r['method']} | {r['w1_points']:.4f} | {r['w1_patch_means']:.4f} "
                     f"| {r['mean']:.3f} | {r['real_mean']:.3f} | {r['real_objects']} / {r['real_points']} "
                     f"| {r['rgb_objects']} |")
    return "\n".join(lines)


def draw(rows):
    def figure(plt):
        classes = sorted({r["class"] for r in rows})
        fig, axes = plt.subplots(1, len(classes), figsize=(5 * len(classes), 4), squeeze=False)
        for ax, class_name in zip(axes[0], classes):
            mine = [r for r in rows if r["class"] == class_name]
            ax.bar(range(len(mine)), [r["w1_points"] for r in mine], 0.4, label="W1 per point")
            ax.bar(np.arange(len(mine)) + 0.4, [r["w1_patch_means"] for r in mine], 0.4, label="W1 patch means")
            ax.set_xticks(np.arange(len(mine)) + 0.2, [r["method"].split(" (")[0] for r in mine], rotation=20)
            ax.set_title(f"{class_name}: {mine[0]['real_objects']} held-out real object(s)")
            ax.set_ylabel("Wasserstein-1 to real (KITTI 0..1), lower is better")
            ax.legend()
        return fig
    return figure


def main(argv: list) -> int:
    parser = argparse.ArgumentParser(prog="bench_intensity.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--kitti", type=Path, default=SHARED / "kitti_scans")
    parser.add_argument("--holdout", nargs="+", default=["000001"], help="KITTI scan ids never trained on")
    parser.add_argument("--min-points", type=int, default=64, help="real training objects' minimum points")
    parser.add_argument("--steps", type=int, help="training steps (default: TrainConfig's)")
    parser.add_argument("--per-class", action="store_true", help="train classes apart instead of merged")
    parser.add_argument("--checkpoint", type=Path, help="evaluate this model instead of training one")
    parser.add_argument("--quick", action="store_true", help="few objects and steps (a smoke test)")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "intensity")
    args = parser.parse_args(argv)
    from pgt_blender.core.intensity.estimator import IntensityEstimator
    from pgt_blender.core.intensity.training import TrainConfig, train

    sensor = PRESETS["kitti"]
    real = objects.kitti_scan_objects(args.kitti)
    held_out = [o for o in real if o.name.split(":")[0] in args.holdout]
    train_real = [o for o in real if o.name.split(":")[0] not in args.holdout]
    rgb = rgb_domain(sensor, args.quick)
    merged = not args.per_class
    relabel = (lambda items: [replace(o, class_name="object") for o in items]) if merged else (lambda items: items)
    config = TrainConfig(steps=args.steps or (20 if args.quick else TrainConfig.steps))
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as scratch:
        checkpoint = args.checkpoint
        if checkpoint is None:
            real_set, rgb_set = objects.paired_sets(relabel(train_real), relabel(rgb), "kitti", args.min_points,
                                                    config.points)
            checkpoint = train(real_set, rgb_set, config, Path(scratch), progress=not args.quick)
        estimator = IntensityEstimator.load(checkpoint)
        rows = evaluate(held_out, rgb, train_real, estimator, merged)
    results = {
        "machine": cli.machine(numpy=np.__version__, torch=__import__("torch").__version__),
        "inputs": {"real": str(args.kitti), "held_out_scans": args.holdout,
                   "held_out_objects": [f"{o.name} ({len(o.points)} pts)" for o in held_out],
                   "train_real_objects": [f"{o.name} ({len(o.points)} pts)" for o in train_real
                                          if len(o.points) >= args.min_points],
                   "rgb_objects": len(rgb), "merged_classes": merged, "min_points": args.min_points,
                   "train_config": vars(config) | {"checkpoint": str(args.checkpoint) if args.checkpoint else "trained"}},
        "seconds": time.perf_counter() - start,
        "rows": rows,
    }
    print(table(rows))
    cli.write_results(args.out, results, draw(rows))
    args.out.with_suffix(".md").write_text("# LiDAR intensity: estimates against held-out real objects\n\n"
                                           + table(rows) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(cli.script_argv()))
