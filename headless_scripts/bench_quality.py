"""Does the bank quality score (core.quality) rank what the paper ranks? Banks of the
same objects, one matched to the dataset and one per deliberate defect
(core.quality.defects), scored against two references:

- real: the KITTI scans' labelled objects (../shared/data/kitti_scans, cut into an
  OpenPCDet database by core.quality.reference; 1-2 objects per class);
- stand-in: a bank of the matched settings with another seed (seed 1), standing in
  for a real database large enough to separate the defects (it shares the objects and
  the simulator with the banks scored, so it checks the metrics' sensitivity, not the
  simulator's realism).

    .venv/bin/python headless_scripts/bench_quality.py [--quick] [--out bench/quality]

Objects: dev.RANKING_OBJECTS (Chrono sedan as Car, Chrono truck as Truck, the built-in
sample bicycle as Cyclist), prepared to KITTI's class sizes. Banks: KITTI, OpenPCDet
format, min_points 5, one size variant, grid headings every 45 deg, x 10..60 m and
y -20..20 m every 10 m (--quick: every 90 deg, x 30..60 every 15, y -10..10 every 10).
The encoder is trained once per reference (scoring the matched bank) and reused
for the defects: the same one score_bank would train for each. Each metric is
averaged over the classes both sides have; a defect "ranks worse" on a
metric when its average is worse than the matched bank's (lower is better except
coverage; 1-NN accuracy by its distance from 0.5), "clearly worse" when at least 1.3x
it (COV at most 1/1.3x; 1-NNA at least 0.6). Writes <out>.md (tables), <out>.json (every
class's scores) and <out>.png. Timings are wall-clock on a shared machine (upper bounds).
"""

import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "addon"))

import numpy as np  # noqa: E402

from pgt_blender import cli, dev  # noqa: E402
from pgt_blender.core.bank.config import config_from_table  # noqa: E402
from pgt_blender.core.bank.export import export_bank  # noqa: E402
from pgt_blender.core.quality.defects import DEFECTS, MATCHED, build_banks  # noqa: E402
from pgt_blender.core.quality.reference import kitti_scan_database  # noqa: E402
from pgt_blender.core.quality.score import score_bank  # noqa: E402
from pgt_blender.core.quality.sets import bank_database  # noqa: E402

METRICS = ("frechet", "mmd", "coverage", "one_nn_accuracy", "w1_points", "w1_intensity", "w1_fill", "w1_grade")
HEADINGS = {"frechet": "Fréchet", "mmd": "MMD-CD", "coverage": "COV", "one_nn_accuracy": "1-NNA",
            "w1_points": "W1 points", "w1_intensity": "W1 intensity", "w1_fill": "W1 fill", "w1_grade": "W1 grade"}
CLEAR = 1.3  # "clearly worse": at least this many times the matched bank's value


def base_table(quick: bool) -> dict:
    grid = ({"headings_deg": [-135, 135, 90], "x": [30, 60, 15], "y": [-10, 10, 10]} if quick else
            {"headings_deg": [-180, 135, 45], "x": [10, 60, 10], "y": [-20, 20, 10]})
    return {"bank": {"dataset": "kitti", "formats": ["openpcdet"], "min_points": 5, "chunk_size": 64},
            "grid": grid, "jitter": {"size_variants": 1}}


def badness(metric: str, value: float) -> float:
    """Larger is worse, for every metric."""
    if metric == "coverage":
        return -value
    if metric == "one_nn_accuracy":
        return abs(value - 0.5)
    return value


def clearly_worse(metric: str, value: float, matched: float) -> bool:
    """At least CLEAR times the matched value (COV: at most 1 / CLEAR times; 1-NNA: at least 0.6)."""
    if metric == "coverage":
        return value <= matched / CLEAR
    if metric == "one_nn_accuracy":
        return value >= 0.6
    return value >= CLEAR * matched


def ranking_table(found: dict) -> str:
    """One reference's table: a row per bank, a column per metric (class averages)."""
    matched = found[MATCHED]["average"]
    rows = []
    for name in (MATCHED, *DEFECTS):
        cells = []
        for metric in METRICS:
            value = found[name]["average"][metric]
            cell = f"{value:.3g}"
            if name != MATCHED and badness(metric, value) > badness(metric, matched[metric]):
                cell = f"**{cell} ✓**" if clearly_worse(metric, value, matched[metric]) else f"{cell} ✓"
            cells.append(cell)
        rows.append([name, *cells])
    return cli.markdown_table(["bank"] + [HEADINGS[m] for m in METRICS], rows)


def averages(scores: dict) -> dict:
    return {metric: float(np.nanmean([found[metric] for found in scores["classes"].values()]))
            for metric in METRICS}


def main(argv: list) -> int:
    parser = cli.parser("bench_quality.py", __doc__)
    parser.add_argument("--quick", action="store_true", help="a small grid (a smoke test)")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "bench" / "quality")
    args = parser.parse_args(argv)
    import scipy
    import torch

    with tempfile.TemporaryDirectory() as work:
        work = Path(work)
        objects = dev.ranking_objects(work / "objects")
        table = base_table(args.quick)
        load_before, started = dev.load_average(), time.perf_counter()
        banks = build_banks(objects, table, work / "banks")
        standin = work / "standin"
        export_bank(objects, config_from_table({**table, "bank": {**table["bank"], "seed": 1}}), standin)
        build_seconds = time.perf_counter() - started
        references = {"real": kitti_scan_database(dev.SHARED_DATA / "kitti_scans", work / "real"),
                      "stand-in": bank_database(standin)[0]}
        results, score_seconds, training = {}, [], {}
        for label, reference in references.items():
            results[label], encoder = {}, None
            for name, bank in banks.items():  # matched first: it trains the encoder the others reuse
                started = time.perf_counter()
                scores = score_bank(bank, reference, encoder=encoder, seed=0)
                score_seconds.append(time.perf_counter() - started)
                training.setdefault(label, score_seconds[-1])
                encoder = scores["encoder"]
                results[label][name] = {"classes": scores["classes"], "average": averages(scores)}
    tables = []
    for label, found in results.items():
        sizes = ", ".join(f"{name} {values['real_objects']}" for name, values in found[MATCHED]["classes"].items())
        tables.append(f"### Reference: {label} (objects per class: {sizes})\n\n" + ranking_table(found))
    body = (f"✓: worse than the matched bank (by any margin); **bold**: clearly worse (at least {CLEAR:g}x the "
            f"matched value; COV at most {1 / CLEAR:.2f}x; 1-NNA at least 0.6). Class averages.\n\n" + "\n\n".join(tables))
    print("\n" + body)
    summary = {label: {name: [m for m in METRICS if badness(m, found[name]["average"][m])
                              > badness(m, found[MATCHED]["average"][m])] for name in DEFECTS}
               for label, found in results.items()}
    machine = dev.machine(numpy=np.__version__, scipy=scipy.__version__, torch=torch.__version__)
    inputs = {"objects": "Chrono sedan (Car), Chrono truck (Truck), built-in sample bicycle (Cyclist), KITTI sizes",
              "config": base_table(args.quick),
              "bank entries": {name: sum(v["bank_objects"] for v in results["real"][name]["classes"].values())
                               for name in banks},
              "run": f"banks built in {build_seconds:.0f} s, scored in {np.median(score_seconds):.1f} s median per "
                     f"bank (the matched bank, encoder training included: "
                     f"{', '.join(f'{label} {seconds:.0f} s' for label, seconds in training.items())}; the defects "
                     f"reuse its encoder); load average before {load_before}, after "
                     f"{dev.load_average()} (other work on the machine inflates the times: upper bounds)"}
    record = {"machine": machine, "inputs": inputs, "loadavg": dev.load_average(), "quick": args.quick,
              "build_seconds": build_seconds, "score_seconds_median": float(np.median(score_seconds)),
              "worse_than_matched": summary, "results": results}

    def draw(plt):
        figure, axes = plt.subplots(len(results), len(METRICS), figsize=(3 * len(METRICS), 3.2 * len(results)))
        for row, (label, found) in enumerate(results.items()):
            for column, metric in enumerate(METRICS):
                values = [found[name]["average"][metric] for name in (MATCHED, *DEFECTS)]
                axis = axes[row, column]
                axis.bar(range(len(values)), values, color=["C2"] + ["C3"] * len(DEFECTS))
                axis.set_xticks(range(len(values)), [MATCHED, *DEFECTS], rotation=60, ha="right", fontsize=7)
                axis.set_title(f"{HEADINGS[metric]} ({label})", fontsize=9)
        return figure

    dev.write_report(args.out, "Bank quality score: ranking deliberate defects", "bench_quality.py", machine, inputs,
                     body, record, draw)
    return 0


if __name__ == "__main__":
    sys.exit(cli.run_main(main, cli.script_argv()))
