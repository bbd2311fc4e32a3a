"""Train the CycleGAN LiDAR intensity estimator (rgb -> intensity, group intensity loss)
and write its checkpoints, loss log and config.

    pgt-train-intensity --out DIR [--real SRC ...] [--rgb SRC ...]
    .venv/bin/python headless_scripts/train_intensity.py --out DIR [--real SRC ...] [--rgb SRC ...]
        [--gt-convention openpcdet|mmdet3d] [--dataset kitti] [--min-points 64] [--points 256] [--steps 1000]
        [--checkpoint-every 100] [--seed 0] [--threads 2] [--resume]
    blender -b -P headless_scripts/train_intensity.py -- (the same arguments)

--real (repeatable): a ground-truth database .pkl (points about the box centre for
--gt-convention openpcdet, the bottom centre for mmdet3d; by default read from its infos) or a KITTI folder (velodyne,
label_2, calib); default ../shared/data/kitti_scans when present. --rgb (repeatable): a
folder of prepared colored objects (prepare_objects.py's output) or CLASS=MESH for a
mesh with material colors (e.g. car=sedan.obj); default the built-in sample vehicles.
Objects under --min-points points are dropped; only classes both domains have are
trained. The paper drops objects under 256 points; the default here is 64, because the
three shared KITTI scans hold one object of a class the samples have, a 71-point truck.
Use --min-points 256 on a real database.

Writes DIR/config.json, DIR/losses.csv (one row per step), DIR/checkpoint.pt (every
--checkpoint-every steps) and DIR/intensity.pt (the estimator). After an interruption,
the same command with --resume goes on from the last checkpoint and ends with the same
bytes as an uninterrupted run (so does raising --steps with --resume). Same inputs,
seed and --threads give the same bytes. Bad input: a one-line error, exit status 1.
"""

import csv
import time
from pathlib import Path


from .. import cli
from ..core.files import apart_from_inputs
from ..core.intensity import model
from ..core.intensity.estimator import IntensityEstimator
from ..core.intensity.objects import rgb_source
from ..core.intensity.training import TrainConfig, train



def load_sets(args) -> tuple:
    """(real ObjectSet, rgb ObjectSet) the arguments name; InputError for bad input."""
    from ..core.intensity.objects import training_sets

    return training_sets(args.real, args.rgb, args.dataset, args.min_points, args.points, args.seed,
                         convention=args.gt_convention)


def inference_rate(path: Path, rgb) -> float:
    """Points per second of the trained estimator over the rgb training objects (their
    normalised coordinates are box-frame metres in a box of dims 2, 2, 2)."""
    estimator = IntensityEstimator.load(path)
    objects = [(xyz, (2.0, 2.0, 2.0), values, rgb.classes[index])
               for xyz, values, index in zip(rgb.xyz, rgb.values, rgb.class_index)]
    for _ in range(2):  # the first pass pays torch's warm-up
        estimator.predict_many(objects, list(rgb.names))
    return estimator.last_rate


def parse(argv: list):
    parser = cli.parser("train_intensity.py", __doc__)
    defaults = TrainConfig()
    parser.add_argument("--out", type=cli.OUTPUT_FOLDER, required=True,
                        help="folder for the checkpoints, log and config")
    parser.add_argument("--real", type=Path, action="append", required=True,
                        help="GT database .pkl or KITTI folder (e.g. ../shared/data/kitti_scans), repeatable")
    parser.add_argument("--rgb", action="append", default=[],
                        help="folder of prepared colored objects or CLASS=MESH, repeatable (default: the built-in samples)")
    cli.convention_option(parser, "--gt-convention", "a --real .pkl")
    parser.add_argument("--dataset", default="kitti", choices=("kitti", "nuscenes", "lyft"),
                        help="whose LiDAR and intensity scale the real objects have")
    parser.add_argument("--min-points", type=cli.whole(0, 10**7), default=64,
                        help="drop objects with fewer points (paper: 256)")
    parser.add_argument("--points", type=cli.CLOUD_POINTS, default=defaults.points,
                        help="points per object the networks see")
    parser.add_argument("--steps", type=cli.STEPS, default=defaults.steps, help="optimiser steps")
    parser.add_argument("--checkpoint-every", type=cli.STEPS, default=defaults.checkpoint_every,
                        help="steps between checkpoints (what --resume goes on from)")
    parser.add_argument("--seed", type=cli.SEED, default=defaults.seed, help="seed of every draw")
    parser.add_argument("--threads", type=cli.THREADS, default=defaults.threads,
                        help="torch CPU threads (part of what makes the bytes repeat)")
    parser.add_argument("--resume", action="store_true", help="go on from DIR/checkpoint.pt")
    args = parser.parse_args(argv)
    apart_from_inputs(args.out, [*args.real, *(path for _, path in map(rgb_source, args.rgb))])
    config = TrainConfig(points=args.points, steps=args.steps, checkpoint_every=args.checkpoint_every,
                         seed=args.seed, threads=args.threads)
    try:
        config.check()
    except ValueError as error:
        parser.error(str(error))
    return args, config


def main(argv: list) -> int:
    args, config = parse(argv)
    start = time.perf_counter()
    model.require_torch(args.out)
    real, rgb = load_sets(args)
    print(f"{len(real.names)} real and {len(rgb.names)} rgb objects of {', '.join(real.classes)} "
          f"({real.dataset}), loaded in {time.perf_counter() - start:.0f} s")
    if args.resume and not (args.out / "checkpoint.pt").is_file():
        print(f"note: no checkpoint in {args.out}; starting at step 0")
    start = time.perf_counter()
    final = train(real, rgb, config, args.out, resume=args.resume)
    seconds = time.perf_counter() - start
    with open(args.out / "losses.csv", newline="") as stream:
        last = list(csv.DictReader(stream))[-1]
    print(f"trained to step {config.steps} in {seconds:.0f} s ({config.threads} threads); last step: "
          + ", ".join(f"{key} {value}" for key, value in last.items() if key != "step"))
    print(f"inference: {inference_rate(final, rgb):.3g} points/s over the rgb objects")
    print(f"wrote {final} ({final.stat().st_size / 1024:.0f} KiB), checkpoint.pt, losses.csv, config.json")
    return 0
