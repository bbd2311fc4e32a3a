"""Held-out front/back accuracy of the geometric baseline (heading.baseline_score >= 0: the
end profile, a trailer's running gear), the learned classifier (front_probability >= 0.5)
and what Detect Front ships, the classifier with the baseline deciding where it is unsure
and a trailer's running gear always (heading.front_decision), leave-one-mesh-out over the built-in
sample vehicles and the Chrono vehicle meshes, at several point densities and noise levels,
on dense surface samplings and on what a LiDAR sees of the held-out mesh.

    .venv/bin/python headless_scripts/bench_heading.py [--quick] [--steps N] [--samplings N] [--seeds N]
        [--threads 2] [--chrono DIR] [--out bench/heading]

For each held-out mesh --seeds classifiers (training seeds 0, 1, ...; default 3, --quick
1: one held-out mesh can swing from right to wrong with the seed) are trained on all
the other meshes (same settings as train_heading.py but --steps, default 500 as there; --quick:
150), each judged alone and the accuracies averaged; the methods judge
--samplings seeded samplings of the held-out mesh per (points, noise) cell, half of
them turned 180 degrees (the truth turns with them). Samplings are random subsets of
the mesh's area-weighted surface sample plus Gaussian noise (sigma = noise x box
diagonal). Scans: the held-out mesh scanned by the project's ray caster
(heading_classifier.scanned_point_sets: --sensor, 10, 20 and 35 m straight ahead, 8
headings, one sweep), each view judged as it is and turned 180 degrees, with Gaussian
noise (sigma = noise x box diagonal). The classifier is trained on the other meshes'
dense samples and their scans alike (--no-scans: dense only, the former training).
Each mesh is judged as the class a user authors it as (a sample's own, a Chrono
chassis' from MESH_CLASSES; any other mesh is its own name, so the class-less rules):
that decides whether the running gear heads it. Prints Markdown tables (per cell, mean
over held-out meshes; per class and noise; per mesh and noise) and writes <out>.json
and <out>.png.
"""

import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "addon"))

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from pgt_blender import cli, dev  # noqa: E402
from pgt_blender.core.authoring import heading_classifier as hc  # noqa: E402
from pgt_blender.core.authoring.heading import CLASSIFIER_DOUBT, baseline_score, front_decision  # noqa: E402

CHRONO = dev.SHARED_DATA / "chrono_vehicles"
DENSITIES = (64, 256, 1024, 4096)
NOISE_LEVELS = (0.0, 0.01, 0.03)
METHODS = ("baseline", "classifier", "shipped")
SHIPPED = (f"the classifier, the baseline deciding where the classifier's front probability is within "
           f"{CLASSIFIER_DOUBT} of 0.5 and a trailer's running gear always (heading.front_decision: what Detect "
           f"Front does)")
# the class a user authors each Chrono mesh as (the samples are named by theirs)
MESH_CLASSES = {"MAN_10t_chassis": "truck", "truck_chassis": "truck", "CityBus_Vis": "bus", "suv_chassis": "car",
                "van_chassis": "car", "sedan_chassis_vis": "car"}


def decisions(cloud, dims, classifier, front_at_x: bool, class_name: str) -> np.ndarray:
    """(3,) int: whether each of METHODS is right about ``cloud``, an object of ``class_name``,
    each deciding ties as Detect Front does (front at +x from a score of 0 or a probability
    of 0.5)."""
    score, rule = baseline_score(cloud, dims, class_name)
    probability = hc.front_probability(cloud, dims, classifier)
    return np.array([front_decision(None, score, rule)[0] == front_at_x, (probability >= 0.5) == front_at_x,
                     front_decision(probability, score, rule)[0] == front_at_x], int)


def class_of(held_out) -> str:
    """The class ``held_out`` (a PointSet of a sample or a Chrono mesh) is authored as;
    another mesh's own name."""
    return MESH_CLASSES.get(held_out.name, held_out.name)


def judge(held_out, classifier, points: int, noise: float, samplings: int, seed: int) -> np.ndarray:
    """(3,) right counts of METHODS over ``samplings`` samplings of ``held_out`` (a
    PointSet), the odd ones turned 180 degrees about z."""
    rng = np.random.default_rng(seed)
    sigma = noise * np.linalg.norm(held_out.dims)
    right = np.zeros(len(METHODS), int)
    for index in range(samplings):
        cloud = held_out.points[rng.choice(len(held_out.points), points, replace=False)]
        cloud = cloud + rng.normal(scale=sigma, size=cloud.shape)
        front_at_x = index % 2 == 0
        if not front_at_x:
            cloud = cloud * (-1, -1, 1)
        right += decisions(cloud, held_out.dims, classifier, front_at_x, class_of(held_out))
    return right


def judge_scans(views: list, classifier, noise: float, seed: int, class_name: str) -> tuple:
    """((3,) right counts of METHODS, judged) over the scanned ``views`` (PointSets) of a
    held-out mesh of ``class_name``, each judged as it is and turned 180 degrees, noise added."""
    rng = np.random.default_rng(seed)
    right, judged = np.zeros(len(METHODS), int), 0
    for view in views:
        noisy = view.points + rng.normal(scale=noise * np.linalg.norm(view.dims), size=view.points.shape)
        for front_at_x, cloud in ((True, noisy), (False, noisy * (-1, -1, 1))):
            right += decisions(cloud, view.dims, classifier, front_at_x, class_name)
            judged += 1
    return right, judged


def mean(rows: list, key: str, **match) -> float:
    """Mean of ``key`` over the rows whose fields equal ``match``."""
    return float(np.mean([r[key] for r in rows if all(r[k] == v for k, v in match.items())]))


def main(argv: list) -> int:
    parser = cli.parser("bench_heading.py", __doc__)
    parser.add_argument("--quick", action="store_true",
                        help="150 training steps, 8 samplings per cell (about a minute)")
    parser.add_argument("--steps", type=int, help=f"training steps per held-out mesh (default {hc.STEPS}, --quick 150)")
    parser.add_argument("--samplings", type=int,
                        help="samplings per (mesh, points, noise) cell (default 10, --quick 8)")
    parser.add_argument("--seeds", type=int, help="training seeds per held-out mesh (default 3, --quick 1)")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--chrono", type=Path, default=CHRONO, help="folder of .obj meshes, front at +x")
    parser.add_argument("--sensor", default="nuscenes", help="sensor preset of the scans")
    parser.add_argument("--no-scans", dest="scans", action="store_false",
                        help="train on dense samples only (the scans are still judged)")
    parser.add_argument("--out", type=Path, default=Path("bench/heading"))
    args = parser.parse_args(argv)
    steps = args.steps or (150 if args.quick else hc.STEPS)
    samplings = args.samplings or (8 if args.quick else 10)
    seeds = args.seeds or (1 if args.quick else 3)
    import torch  # after the arguments: --help works without it

    torch.set_num_threads(args.threads)
    labelled = hc.sample_meshes()
    if args.chrono.is_dir():
        labelled += hc.mesh_folder_meshes(args.chrono)
    else:
        print(f"note: no Chrono meshes at {args.chrono}; leave-one-out over the built-in samples only")
    meshes = [hc.point_set_from_mesh(mesh, name, source) for name, mesh, source in labelled]
    with warnings.catch_warnings():  # zero-area faces dropped: said once per mesh is enough here
        warnings.simplefilter("ignore")
        scans = [hc.scanned_point_sets(mesh, name, source, args.sensor) for name, mesh, source in labelled]
    start = time.perf_counter()
    rows, scan_rows = [], []  # one per (held-out mesh, points, noise); per (held-out mesh, noise)
    for held, held_out in enumerate(meshes):
        others = meshes[:held] + meshes[held + 1:]
        if args.scans:
            others += [view for index, views in enumerate(scans) if index != held for view in views]
        for seed in range(seeds):  # rows per seed: the means below average over them
            classifier = hc.train(others, seed=seed, steps=steps, threads=args.threads)
            for noise in NOISE_LEVELS:
                right, judged = judge_scans(scans[held], classifier, noise, held * 1000 + int(noise * 1000),
                                             class_of(held_out))
                scan_rows.append({"mesh": held_out.name, "seed": seed, "noise": noise, "views": judged,
                                  **dict(zip(METHODS, (right / judged).tolist()))})
            for points in DENSITIES:
                for noise in NOISE_LEVELS:
                    sampling_seed = held * 1_000_000 + points * 100 + int(noise * 1000)
                    right = judge(held_out, classifier, points, noise, samplings, sampling_seed)
                    rows.append({"mesh": held_out.name, "seed": seed, "points": points, "noise": noise,
                                 **dict(zip(METHODS, (right / samplings).tolist()))})
        accuracies = "; ".join(f"{kind}: " + ", ".join(f"{k} {mean(found, k, mesh=held_out.name):.3f}" for k in METHODS)
                               for kind, found in (("dense", rows), ("scans", scan_rows)))
        print(f"held out {held_out.name}: {accuracies} ({time.perf_counter() - start:.0f} s so far)", flush=True)
    seconds = time.perf_counter() - start
    cells = [{"points": p, "noise": n, **{k: mean(rows, k, points=p, noise=n) for k in METHODS}}
             for p in DENSITIES for n in NOISE_LEVELS]
    per_mesh = [{"mesh": m.name, "class": class_of(m), "source": m.source.split(" sha256:")[0],
                 **{k: mean(rows, k, mesh=m.name) for k in METHODS},
                 **{f"scan_{k}_{n:g}": mean(scan_rows, k, mesh=m.name, noise=n) for k in METHODS for n in NOISE_LEVELS}}
                for m in meshes]
    scan_cells = [{"noise": n, **{k: mean(scan_rows, k, noise=n) for k in METHODS}} for n in NOISE_LEVELS]
    machine = dev.machine(torch_threads=args.threads, torch=str(torch.__version__), numpy=np.__version__,
                          trimesh=trimesh.__version__, load_average=dev.load_average())
    settings = {"held_out_meshes": len(meshes), "training_steps": steps, "training_seeds": seeds,
                "training": "train_heading.py defaults but steps, threads and seed",
                "trained_on": "dense samples and scans" if args.scans else "dense samples",
                "scans": {"sensor": args.sensor, "ranges_m": hc.SCAN_RANGES_M, "headings": hc.SCAN_HEADINGS,
                          "views_per_mesh": [len(v) for v in scans], "judged": "each view as is and turned 180"},
                "samplings_per_cell": samplings, "flipped_share": 0.5, "densities": DENSITIES,
                "noise_levels_of_diagonal": NOISE_LEVELS, "classifier_resamplings": 4,
                "shipped": SHIPPED,
                "seconds": round(seconds, 1)}
    inputs = [m.source for m in meshes]
    print(f"\nmachine: {machine}\nsettings: {settings}\ninputs: {', '.join(s.split(' sha256:')[0] for s in inputs)}\n")
    body = tables(cells, scan_cells, per_mesh, samplings, seeds, args.sensor)
    print(body)
    markdown_inputs = {"settings": {key: str(value) for key, value in settings.items()},
                       "inputs": [source.split(" sha256:")[0] for source in inputs]}
    dev.write_report(args.out, "Heading: geometric baseline, classifier and the two shipped together, leave one mesh out",
                     "bench_heading.py", machine, markdown_inputs, body,
                     {"machine": machine, "settings": settings, "inputs": inputs, "cells": cells,
                      "scan_cells": scan_cells, "per_mesh": per_mesh, "rows": rows, "scan_rows": scan_rows},
                     lambda plt: plot(plt, cells, len(meshes)))
    print(f"in {seconds:.0f} s")
    return 0


def tables(cells: list, scan_cells: list, per_mesh: list, samplings: int, seeds: int, sensor: str) -> str:
    """The Markdown tables of a run (what it prints and writes to <out>.md)."""
    lines = []
    add = lines.append
    heads, rule = " | ".join(METHODS), "---:|" * len(METHODS)
    add(f"Accuracy, mean over {len(per_mesh)} held-out meshes ({samplings} samplings each, half turned 180 degrees) "
        f"and {seeds} training seeds; baseline: the end profile, a trailer's running gear; shipped: {SHIPPED}:\n")
    add(f"| points | noise (of box diagonal) | {heads} |")
    add(f"|---:|---:|{rule}")
    for c in cells:
        add(f"| {c['points']} | {c['noise']:.0%} | " + " | ".join(f"{c[k]:.3f}" for k in METHODS) + " |")
    add("| all | all | " + " | ".join(f"{mean(cells, k):.3f}" for k in METHODS) + " |")
    add(f"\nScans ({sensor}, {', '.join(f'{r:g}' for r in hc.SCAN_RANGES_M)} m, {hc.SCAN_HEADINGS} headings), "
        f"mean over held-out meshes and {seeds} training seeds:\n")
    add(f"| noise (of box diagonal) | {heads} |")
    add(f"|---:|{rule}")
    for c in scan_cells:
        add(f"| {c['noise']:.0%} | " + " | ".join(f"{c[k]:.3f}" for k in METHODS) + " |")
    noise_heads = " | ".join(f"scans {n:.0%}: {heads}" for n in NOISE_LEVELS)
    keys = list(METHODS) + [f"scan_{k}_{n:g}" for n in NOISE_LEVELS for k in METHODS]
    add("\nPer class (the mean over its held-out meshes): dense (mean over all cells) and scans per noise level:\n")
    add(f"| class | meshes | dense: {heads} | {noise_heads} |")
    add("|---|---:|" + "---:|" * len(keys))
    for name in dict.fromkeys(m["class"] for m in per_mesh):
        add(f"| {name} | {sum(m['class'] == name for m in per_mesh)} | "
            + " | ".join(f"{mean(per_mesh, k, **{'class': name}):.3f}" for k in keys) + " |")
    add("\nPer held-out mesh: dense (mean over all cells) and scans per noise level:\n")
    add(f"| held-out mesh | class | source | dense: {heads} | {noise_heads} |")
    add("|---|---|---|" + "---:|" * len(keys))
    for m in per_mesh:
        add(f"| {m['mesh']} | {m['class']} | {m['source']} | " + " | ".join(f"{m[k]:.3f}" for k in keys) + " |")
    pairs = [("shipped", "baseline")] + [(f"scan_shipped_{n:g}", f"scan_baseline_{n:g}") for n in NOISE_LEVELS]
    worst = min(m[shipped] - m[baseline] for m in per_mesh for shipped, baseline in pairs)
    add(f"\nShipped against the baseline, per held-out mesh and column: worst {worst:+.3f}.")
    return "\n".join(lines)


def plot(plt, cells: list, meshes: int):
    figure, axis = plt.subplots(figsize=(6, 4))
    for index, noise in enumerate(NOISE_LEVELS):
        mine = [c for c in cells if c["noise"] == noise]
        color = f"C{index}"
        axis.semilogx([c["points"] for c in mine], [c["classifier"] for c in mine], "o-", color=color,
                      label=f"classifier, noise {noise:.0%}")
        axis.semilogx([c["points"] for c in mine], [c["baseline"] for c in mine], "x--", color=color,
                      label=f"baseline, noise {noise:.0%}")
        axis.semilogx([c["points"] for c in mine], [c["shipped"] for c in mine], "s:", color=color,
                      label=f"shipped, noise {noise:.0%}")
    axis.axhline(0.5, color="grey", lw=0.8)
    axis.set_xlabel("points per object")
    axis.set_ylabel("front/back accuracy")
    axis.set_ylim(0, 1.02)
    axis.set_title(f"heading, leave-one-mesh-out over {meshes} meshes")
    axis.grid(True, which="both", alpha=0.3)
    axis.legend(fontsize=7)
    return figure


if __name__ == "__main__":
    sys.exit(cli.run_main(main, cli.script_argv()))
