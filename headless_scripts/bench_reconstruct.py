"""Frames to a COLMAP model on the CPU (core/importing/structure_from_motion.py) against
the shipped statue model: all 40 photos of ../shared/data/colmap_statue/images.

    .venv/bin/python headless_scripts/bench_reconstruct.py [--quick] [--threads 0] [--out bench/reconstruct]

Each configuration (SIFT features per image; one camera for all photos or one per
photo) reconstructs the photos in name order through ``reconstruct`` (auto matching:
all 780 pairs), then its camera centres are compared with the shipped model's
(sparse/0, made by COLMAP from the same photos) after the similarity transform that
best maps them onto the shipped ones (Umeyama): registered images, centre error
(median, p95, max) as a share of the orbit's size (RMS distance of the shipped centres
from their mean), the focal length against the shipped camera's, and the time of each
step (wall clock, perf_counter inside ``reconstruct``). --quick: the first
configuration only. Prints a Markdown table and writes <out>.json, <out>.md, <out>.png.
"""

import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "addon"))

import numpy as np  # noqa: E402
import pycolmap  # noqa: E402

from pgt_blender import cli, dev  # noqa: E402
from pgt_blender.core.importing.frames import folder_images  # noqa: E402
from pgt_blender.core.importing.structure_from_motion import (SfmOptions, camera_centre_errors,  # noqa: E402
                                                              camera_centres, reconstruct, similarity_transform)

STATUE = dev.SHARED_DATA / "colmap_statue"
CONFIGURATIONS = (("8192 features, one camera", SfmOptions()),
                  ("4096 features, one camera", SfmOptions(max_features=4096)),
                  ("8192 features, a camera per photo", SfmOptions(single_camera=False)))


def measure(label: str, options: SfmOptions, reference: dict, shipped_focal: float) -> dict:
    names = folder_images(STATUE / "images")
    with tempfile.TemporaryDirectory() as scratch:
        result = reconstruct(STATUE / "images", names, scratch, options)
        found = camera_centres(result.model)
    errors = camera_centre_errors(found, reference)
    relative = errors["relative"]
    focals = [camera["params"][0] for camera in result.cameras]
    print(f"{label}: {result.registered}/{result.images} registered, median centre error "
          f"{np.median(relative):.2%} of the orbit, {sum(result.seconds.values()):.0f} s", flush=True)
    return {"configuration": label, "max_features": options.max_features, "single_camera": options.single_camera,
            "images": result.images, "registered": result.registered, "points": result.points,
            "models": result.models, "reprojection_error_px": result.reprojection_error,
            "centre_error_median": float(np.median(relative)), "centre_error_p95": float(np.percentile(relative, 95)),
            "centre_error_max": float(relative.max()), "orbit_size": errors["orbit_size"],
            "focal_median_px": float(np.median(focals)), "focal_vs_shipped": float(np.median(focals) / shipped_focal),
            "seconds": result.seconds, "total_s": sum(result.seconds.values()),
            "centres": {name: found[name].tolist() for name in errors["names"]}}


def plot(plt, rows: list, reference: dict):
    """Top view of each configuration's centres mapped onto the shipped ones, and the
    error per photo."""
    figure, axes = plt.subplots(1, 2, figsize=(14, 6))
    names = sorted(reference)
    shipped = np.array([reference[name] for name in names])
    axes[0].scatter(shipped[:, 0], shipped[:, 2], s=60, facecolors="none", edgecolors="k", label="shipped model")
    for row, marker in zip(rows, "o^sv"):
        common = [name for name in names if name in row["centres"]]
        found = np.array([row["centres"][name] for name in common])
        target = np.array([reference[name] for name in common])
        scale, rotation, translation = similarity_transform(found, target)
        mapped = found @ (scale * rotation).T + translation
        axes[0].scatter(mapped[:, 0], mapped[:, 2], s=14, marker=marker, label=row["configuration"])
        errors = np.linalg.norm(mapped - target, axis=1) / row["orbit_size"]
        axes[1].plot(sorted(100 * errors), marker=marker, ms=3, label=row["configuration"])
    axes[0].set(xlabel="x (shipped model frame)", ylabel="z", title="camera centres, top view", aspect="equal")
    axes[1].set(xlabel="photos, sorted by error", ylabel="centre error, % of the orbit size",
                title="centre error after the similarity transform")
    for axis in axes:
        axis.grid(True, alpha=0.3)
        axis.legend(fontsize=8)
    return figure


def main(argv: list) -> int:
    parser = cli.parser("bench_reconstruct.py", __doc__)
    parser.add_argument("--quick", action="store_true", help="the first configuration only")
    parser.add_argument("--threads", type=int, default=0, help="CPU threads (0: all)")
    parser.add_argument("--out", type=Path, default=Path("bench/reconstruct"))
    args = parser.parse_args(argv)
    pycolmap.logging.minloglevel = pycolmap.logging.ERROR
    shipped = pycolmap.Reconstruction(str(STATUE / "sparse" / "0"))
    shipped_focal = float(next(iter(shipped.cameras.values())).params[0])
    reference = camera_centres(STATUE / "sparse" / "0")
    machine = dev.machine(numpy=np.__version__, pycolmap=pycolmap.__version__, threads=args.threads or "all")
    print(f"machine: {machine}\n", flush=True)
    load_before = dev.load_average()
    configurations = CONFIGURATIONS[:1] if args.quick else CONFIGURATIONS
    rows = [measure(label, SfmOptions(**{**options.__dict__, "threads": args.threads}), reference, shipped_focal)
            for label, options in configurations]
    load_after = dev.load_average()
    table = dev.markdown_table(
        ["configuration", "registered", "points", "reproj px", "centre err median", "p95", "max", "focal / shipped",
         "features s", "matching s", "mapping s", "total s"],
        [[r["configuration"], f"{r['registered']}/{r['images']}", r["points"], f"{r['reprojection_error_px']:.2f}",
          f"{r['centre_error_median']:.2%}", f"{r['centre_error_p95']:.2%}", f"{r['centre_error_max']:.2%}",
          f"{r['focal_vs_shipped']:.3f}",
          *(f"{r['seconds'][step]:.1f}" for step in ("features", "matching", "mapping")),
          f"{r['total_s']:.1f}"] for r in rows])
    inputs = {"photos": f"{len(reference)} photos of ../shared/data/colmap_statue/images (800 x 1200, many cameras, "
                        f"cropped), in name order; shipped model: 1 SIMPLE_RADIAL camera, f {shipped_focal:.1f} px",
              "errors": "camera centre distance after the best similarity transform onto the shipped centres, as a "
                        "share of the orbit size (RMS distance of the shipped centres from their mean)",
              "run": f"load average before {load_before}, after {load_after} (2 shared cores: other work on the "
                     "machine inflates the times)"}
    print("\n" + table)
    dev.write_report(args.out, "Frames to a COLMAP model on the CPU", "bench_reconstruct.py", machine, inputs, table,
                     {"machine": machine, "inputs": inputs, "rows": rows}, lambda plt: plot(plt, rows, reference))
    return 0


if __name__ == "__main__":
    cli.exit(cli.run_main(main, cli.script_argv()))
