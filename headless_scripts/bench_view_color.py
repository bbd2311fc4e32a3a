"""View-agnostic color (Algorithm 1) at scale: time, memory and the share of elements hit
for a synthetic splat capture of 10^5 .. 10^6 splats seen by 100 training views.

    .venv/bin/python headless_scripts/bench_view_color.py [--sizes 1e5 1e6] [--views 100] [--out bench/view_color]

The capture is ``samples.table_scene`` scaled to the size (a ball of radius 0.5 on a 4 x 4
table with clutter; half the splats on the ball, SH degree 3, opacity 0.9) seen by an orbit
of views at 1600 x 1200 pixels (fx 1400, 3DGS's default training width), 4 m away at 30
degrees elevation. Timed: ``core.capture.apply_capture`` with view color alone (spacing
estimate, one z-buffer and one SH evaluation per view), wall clock. Memory: the peak of
numpy's allocations during that call (tracemalloc, which numpy reports to) above what was
allocated before it, and the process's peak resident size. Hit share: elements some view
hits; the ball's facing share: of the ball's splats that face at least one camera
(analytic), the share hit. Prints a Markdown table; writes <out>.md, <out>.json, <out>.png.
"""

import resource
import sys
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "addon"))

import numpy as np  # noqa: E402
import scipy  # noqa: E402

from pgt_blender import cli, dev  # noqa: E402
from pgt_blender.core.capture import CaptureOptions, apply_capture, samples  # noqa: E402
from pgt_blender.core.importing.sh import coefficient_attributes  # noqa: E402
from pgt_blender.core.reconstruction import Reconstruction  # noqa: E402

CAMERA = {"width": 1600, "height": 1200, "fx": 1400.0}


def capture(size: int, views: int, seed: int) -> tuple:
    """The synthetic capture of ``size`` splats and ``views`` cameras, and the ball's mask."""
    rng = np.random.default_rng(seed)
    scene = samples.table_scene(rng, size // 2, size - size // 2 - size // 20, size // 20)
    positions = scene["positions"]
    coefficients = rng.uniform(-0.03, 0.03, (len(positions), 3, 16)).astype(np.float32)
    coefficients[:, :, 0] = rng.uniform(-0.3, 0.3, (len(positions), 3))
    cameras = samples.orbit_cameras(views, 4.0, 30.0, target=scene["ball_centre"], **CAMERA)
    attributes = {"opacity": np.full(len(positions), 0.9, np.float32), **coefficient_attributes(coefficients)}
    recon = Reconstruction(positions=positions, kind="gaussian_splat", source=Path("synthetic"), sha256="",
                           colors=np.ones((len(positions), 4), np.float32), attributes=attributes, cameras=cameras)
    return recon, scene


def run(size: int, views: int, seed: int) -> dict:
    recon, scene = capture(size, views, seed)
    tracemalloc.start()
    before, _ = tracemalloc.get_traced_memory()
    started = time.perf_counter()
    result = apply_capture(recon, CaptureOptions(view_color=True, seed=seed))
    seconds = time.perf_counter() - started
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    hit = result.attributes["view_hit"]
    ball = scene["foreground"]
    normals = (recon.positions[ball] - scene["ball_centre"]) * 2.0
    facing = np.zeros(int(ball.sum()), bool)
    for view in recon.cameras:
        facing |= np.einsum("ij,ij->i", normals, view.centre - recon.positions[ball]) > 0
    report = result.capture["view_color"]
    return {"splats": len(recon.positions), "views": views, "seconds": round(seconds, 2),
            "seconds_per_view": round(seconds / views, 3), "splats_views_per_s": round(len(recon.positions) * views / seconds),
            "peak_numpy_mb": round((peak - before) / 1e6, 1),
            "max_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3, 1),
            "hit_share": report["hit_share"], "ball_facing_hit_share": round(float(hit[ball][facing].mean()), 4),
            "mean_views_per_hit": report["mean_views_per_hit_element"], "spacing": result.capture["spacing"]}


def main(argv: list) -> int:
    parser = cli.parser("bench_view_color.py", __doc__)
    parser.add_argument("--sizes", type=float, nargs="+", default=[1e5, 1e6])
    parser.add_argument("--views", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("bench/view_color"))
    args = parser.parse_args(argv)
    load_before = dev.load_average()
    rows = [run(int(size), args.views, args.seed) for size in args.sizes]
    machine = dev.machine(numpy=np.__version__, scipy=scipy.__version__,
                          load_average=f"{load_before} before, {dev.load_average()} after (a shared machine: "
                                       f"other work inflates the times)")
    header = ["splats", "views", "seconds", "s / view", "splat-views / s", "numpy peak MB", "max RSS MB",
              "hit share", "ball facing hit", "views per hit"]
    body = cli.markdown_table(header, [[f"{r['splats']:,}", r["views"], r["seconds"], r["seconds_per_view"],
                                        f"{r['splats_views_per_s']:,}", r["peak_numpy_mb"], r["max_rss_mb"],
                                        r["hit_share"], r["ball_facing_hit_share"], r["mean_views_per_hit"]]
                                       for r in rows])
    inputs = {"scene": "samples.table_scene: ball r 0.5 on a 4 x 4 table, clutter; half the splats on the ball",
              "views": f"{args.views} orbit views, 4 m, 30 deg elevation, {CAMERA}",
              "splats": "SH degree 3, opacity 0.9", "seed": args.seed}
    print(f"machine: {machine}\n\n{body}")
    dev.write_report(args.out, "View-agnostic color (Algorithm 1) at scale", "bench_view_color.py", machine, inputs,
                     body, {"machine": machine, "inputs": inputs, "rows": rows}, lambda plt: plot(plt, rows))
    return 0


def plot(plt, rows: list):
    figure, (left, right) = plt.subplots(1, 2, figsize=(9, 3.5))
    splats = [r["splats"] for r in rows]
    left.loglog(splats, [r["seconds"] for r in rows], "o-", label="total")
    left.set_xlabel("splats")
    left.set_ylabel(f"seconds for {rows[0]['views']} views")
    left.grid(True, which="both", alpha=0.3)
    right.semilogx(splats, [r["peak_numpy_mb"] for r in rows], "o-", label="numpy peak")
    right.semilogx(splats, [r["max_rss_mb"] for r in rows], "x--", label="process max RSS")
    right.set_xlabel("splats")
    right.set_ylabel("MB")
    right.legend()
    right.grid(True, which="both", alpha=0.3)
    figure.suptitle("View-agnostic color: time and memory")
    return figure


if __name__ == "__main__":
    cli.exit(cli.run_main(main, cli.script_argv()))
