"""Import throughput: points/s for 10^4 .. 10^7 points, file read (core) and Blender
object build (foreach_set) timed apart, for point PLY (xyz + uchar RGB) and
Gaussian-splat PLY (62 floats per splat, SH degree 3).

    .venv/bin/python headless_scripts/bench_import.py [--sizes 1e4 1e5 1e6 1e7] [--repeats 5] [--out bench/import]

Inputs: seeded random clouds (seed = the point count) written as binary PLY; each size
is imported ``--repeats`` times, each on a fresh empty scene. Prints a Markdown table of
the medians and writes it to <out>.md (with the machine and the inputs), the rows to
<out>.json and median seconds against points to <out>.png.
"""

import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "addon"))

import bpy  # noqa: E402
import numpy as np  # noqa: E402

from pgt_blender import cli, dev  # noqa: E402
from pgt_blender.blender import headless, objects  # noqa: E402
from pgt_blender.core.importing import load_reconstruction  # noqa: E402
from pgt_blender.core.importing.ply import write_ply  # noqa: E402
from pgt_blender.core.importing.points import SPLAT_FIELDS  # noqa: E402


def make_input(kind: str, count: int, directory: Path) -> Path:
    """A seeded random cloud of ``count`` points as a binary PLY of ``kind``."""
    rng = np.random.default_rng(count)
    columns = {axis: rng.normal(size=count).astype(np.float32) for axis in "xyz"}
    if kind == "point_ply":
        columns.update({c: rng.integers(0, 256, count, dtype=np.uint8) for c in ("red", "green", "blue")})
    else:
        names = SPLAT_FIELDS + tuple(f"f_rest_{i}" for i in range(45))  # SH degree 3
        columns.update({name: rng.normal(size=count).astype(np.float32) for name in names})
    path = directory / f"{kind}_{count}.ply"
    write_ply(path, columns)
    return path


def time_import(path: Path, repeats: int) -> tuple:
    """Median seconds of (core read, Blender build), each on a fresh scene."""
    reads, builds = [], []
    for _ in range(repeats):
        bpy.ops.wm.read_factory_settings(use_empty=True)
        start = time.perf_counter()
        recon = load_reconstruction(path)
        middle = time.perf_counter()
        objects.add_reconstruction(bpy.context.scene, recon)
        end = time.perf_counter()
        reads.append(middle - start)
        builds.append(end - middle)
    return statistics.median(reads), statistics.median(builds)


def main(argv: list) -> int:
    parser = cli.parser("bench_import.py", __doc__)
    parser.add_argument("--sizes", type=float, nargs="+", default=[1e4, 1e5, 1e6, 1e7])
    parser.add_argument("--splat-max", type=float, default=1e6, help="largest Gaussian-splat size (62 floats each)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("bench/import"))
    args = parser.parse_args(argv)
    headless.ensure_registered()
    start = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory() as temporary:
        for kind in ("point_ply", "gaussian_splat"):
            for count in (int(s) for s in args.sizes):
                if kind == "gaussian_splat" and count > args.splat_max:
                    continue
                path = make_input(kind, count, Path(temporary))
                read, build = time_import(path, args.repeats)
                rows.append({"kind": kind, "points": count, "file_mb": path.stat().st_size / 1e6,
                             "read_s": read, "build_s": build, "total_s": read + build,
                             "points_per_s": count / (read + build)})
                path.unlink()
    machine = dev.machine(blender=bpy.app.version_string, numpy=np.__version__, repeats=args.repeats,
                          statistic="median", load_average=dev.load_average())
    table = dev.markdown_table(
        ["input", "points", "file MB", "read s", "Blender build s", "total s", "points/s"],
        [[r["kind"], f"{r['points']:,}", f"{r['file_mb']:.1f}", f"{r['read_s']:.4f}", f"{r['build_s']:.4f}",
          f"{r['total_s']:.4f}", f"{r['points_per_s']:,.0f}"] for r in rows])
    body = (f"read s, Blender build s: medians of {args.repeats} imports each; total s: their sum; points/s: points / "
            "total s.\n\n" + table)
    inputs = {"clouds": "seeded random (numpy default_rng(points)) binary PLY: point_ply xyz float + uchar RGB; "
                        "gaussian_splat 62 floats per splat (SH degree 3)",
              "sizes": ", ".join(f"{int(size):,}" for size in args.sizes) + f" (splats up to {int(args.splat_max):,})",
              "timed": "read = load_reconstruction (core parse, checks, sha256); build = objects.add_reconstruction "
                       "(foreach_set); each repeat on a fresh empty scene (read_factory_settings)",
              "run": f"{time.perf_counter() - start:.0f} s on a shared machine (the load average above is taken at "
                     "the end)"}
    print(f"machine: {machine}\n\n{body}")
    dev.write_report(args.out, "Import throughput: point and Gaussian-splat PLY", "bench_import.py", machine, inputs,
                     body, {"machine": machine, "rows": rows}, lambda plt: plot(plt, rows))
    return 0


def plot(plt, rows: list):
    figure, axis = plt.subplots(figsize=(6, 4))
    for kind in dict.fromkeys(r["kind"] for r in rows):
        mine = [r for r in rows if r["kind"] == kind]
        axis.loglog([r["points"] for r in mine], [r["total_s"] for r in mine], "o-", label=f"{kind} total")
        axis.loglog([r["points"] for r in mine], [r["build_s"] for r in mine], "x--", label=f"{kind} Blender build")
    axis.set_xlabel("points")
    axis.set_ylabel("median seconds")
    axis.set_title("pgt_blender import time")
    axis.grid(True, which="both", alpha=0.3)
    axis.legend()
    return figure


if __name__ == "__main__":
    cli.exit(cli.run_main(main, cli.script_argv()))
