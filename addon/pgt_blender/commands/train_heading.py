"""Train the front/back heading classifier (PointNet, BCE, 180-degree flips with p = 0.5,
no rotation augmentation) and save a checkpoint with its training config.

    pgt-train-heading --out PATH [--seed 0] [--steps 500] [--points 512]
    .venv/bin/python headless_scripts/train_heading.py --out PATH [--seed 0] [--steps 500] [--points 512]
        [--chrono DIR] [--gt-database PKL [--gt-convention mmdet3d|openpcdet]] [--no-samples] [--threads 1]
        [--scans nuscenes|kitti|...|SENSOR.toml]
    blender -b -P headless_scripts/train_heading.py -- --out PATH [...]

Training sets: the built-in sample vehicles (unless --no-samples), the meshes under
--chrono (the shipped checkpoint used ../shared/data/chrono_vehicles) and, with --gt-database,
the objects of an mmdetection3d / OpenPCDet ground-truth database; with --scans, also
what that sensor sees of every mesh (heading_classifier.scanned_point_sets: partial
one-sided views at 10, 20 and 35 m and 8 headings). Same inputs, seed
and --threads give the same checkpoint bytes. Exit status 1 and a one-line message on
bad input; nothing is written then. The shipped checkpoint is this script's run with
--chrono ../shared/data/chrono_vehicles --scans nuscenes --out
addon/pgt_blender/models/heading_pointnet.pt (dense samples and scans of the six
built-in vehicles and the six Chrono chassis, 270 point sets).
"""

import time
from pathlib import Path


import numpy as np
from tqdm import tqdm

from .. import cli
from ..core.authoring import heading_classifier as hc
from ..core.errors import InputError
from ..core.files import apart_from_inputs



def training_sets(args) -> list:
    """The point sets the arguments name; InputError for a missing or bad input."""
    meshes = [] if args.no_samples else hc.sample_meshes()
    if args.chrono is not None:
        meshes += hc.mesh_folder_meshes(args.chrono)
    sets = [hc.point_set_from_mesh(mesh, name, source) for name, mesh, source in meshes]
    if args.scans:
        sets += [view for name, mesh, source in meshes for view in hc.scanned_point_sets(mesh, name, source, args.scans)]
    if args.gt_database is not None:
        database = hc.read_gt_database(args.gt_database, args.gt_convention)
        if not database:
            raise InputError(args.gt_database, "the ground-truth database has no object with enough points")
        sets += database
    if not sets:
        raise InputError(args.out, "nothing to train on (--no-samples and no meshes or ground-truth database)")
    return sets


def accuracy_both_ways(classifier, sets: list, points: int = 512) -> float:
    """Share of (set, way round) pairs classified right, each set drawn once at ``points``."""
    rng = np.random.default_rng(0)
    right = 0
    for item in sets:
        cloud = hc.resample(item.points, points, rng)
        right += hc.front_probability(cloud, item.dims, classifier) > 0.5
        right += hc.front_probability(cloud * (-1, -1, 1), item.dims, classifier) < 0.5
    return right / (2 * len(sets))


def main(argv: list) -> int:
    parser = cli.parser("train_heading.py", __doc__)
    parser.add_argument("--out", type=cli.output_file(".pt"), required=True, help="checkpoint to write (.pt)")
    parser.add_argument("--seed", type=cli.SEED, default=0, help="seed of every draw")
    parser.add_argument("--steps", type=cli.STEPS, default=hc.STEPS, help="optimiser steps (batches of 32)")
    parser.add_argument("--points", type=cli.CLOUD_POINTS, default=512, help="points per cloud the network sees")
    parser.add_argument("--chrono", type=Path,
                        help="folder of .obj meshes, front at +x (the shipped checkpoint: ../shared/data/chrono_vehicles)")
    parser.add_argument("--gt-database", type=Path, help="mmdet3d / OpenPCDet *_dbinfos_*.pkl")
    cli.convention_option(parser, "--gt-convention", "--gt-database")
    parser.add_argument("--no-samples", action="store_true", help="leave out the built-in sample vehicles")
    parser.add_argument("--scans", metavar="SENSOR",
                        help="also train on this sensor's scans of every mesh (a preset name or a .toml)")
    parser.add_argument("--threads", type=cli.THREADS, default=1,
                        help="torch CPU threads (part of what makes bytes repeat)")
    args = parser.parse_args(argv)
    apart_from_inputs(args.out, [args.chrono, args.gt_database])
    hc.require_torch(args.out)
    sets = training_sets(args)
    print(f"training on {len(sets)} point sets: " + ", ".join(item.name for item in sets[:12])
          + (", ..." if len(sets) > 12 else ""))
    start = time.perf_counter()
    with tqdm(total=args.steps, unit="step", mininterval=1.0) as bar:
        def progress(step, loss):  # step counts from 0; the last one's loss is the one reported
            bar.update()
            if step % 50 == 0 or step == args.steps - 1:
                bar.set_postfix(loss=f"{loss:.3f}")

        classifier = hc.train(sets, seed=args.seed, steps=args.steps, points=args.points,
                              threads=args.threads, progress=progress)
    seconds = time.perf_counter() - start
    args.out.parent.mkdir(parents=True, exist_ok=True)
    hc.save_checkpoint(args.out, classifier)
    config = classifier.config
    print(f"trained {config['steps']} steps (seed {config['seed']}, {config['points']} points, batch "
          f"{config['batch']}) in {seconds:.0f} s; final batch loss {config['final_loss']:.3f}; "
          f"training-set accuracy both ways round {accuracy_both_ways(classifier, sets, args.points):.3f}")
    for source in config["sources"]:
        print(f"  {source['point_sets']:5d} x {source['source']}")
    print(f"wrote {args.out} ({args.out.stat().st_size / 1024:.0f} KiB)")
    return 0
