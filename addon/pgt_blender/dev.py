"""Helpers of the repository's scripts and tests, not shipped in the extension
(build_extension.py leaves this file out): where the third-party test data lies, and
how benchmarks state their machine and write <out>.json and <out>.png.

The shared data (real scans, meshes, COLMAP, splats, calibration tables, the detector
consumers) is ``$PGT_SHARED_DATA`` when set, else ``../shared/data`` beside the
repository: the one setting every script default and test reads.
"""

import json
import os
import platform
from pathlib import Path

from .cli import markdown_table  # noqa: F401  (the benchmarks' tables: one home, in cli)

SHARED_DATA = Path(os.environ.get("PGT_SHARED_DATA") or Path(__file__).resolve().parents[3] / "shared" / "data")
CHRONO_VEHICLES = SHARED_DATA / "chrono_vehicles" / "data" / "vehicle"


def machine(**details) -> dict:
    """The benchmark machine: CPU model, core count, Python version, then ``details``
    (library versions, settings)."""
    return {"cpu": _cpu_name(), "cores": os.cpu_count(), "python": platform.python_version(), **details}


def _cpu_name() -> str:
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def write_results(out: Path, results: dict, draw) -> None:
    """Write ``results`` to <out>.json and the figure ``draw(pyplot)`` returns to
    <out>.png (Agg backend: no screen needed), then say where they are."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(results, indent=2))
    figure = draw(plt)
    figure.tight_layout()
    figure.savefig(out.with_suffix(".png"), dpi=100)
    print(f"\nwrote {out.with_suffix('.json')} and {out.with_suffix('.png')}")


def load_average() -> list:
    """The 1, 5 and 15 minute load averages: other work on the machine inflates timings."""
    return [round(value, 2) for value in os.getloadavg()]


def markdown_report(title: str, script: str, machine: dict, inputs: dict, body: str) -> str:
    """A benchmark's <out>.md: ``title``, the script that wrote it, the machine and its
    versions, ``inputs`` (key -> value; a dict or list value becomes a bullet list), then
    ``body`` (its tables)."""
    lines = [f"# {title}", "", f"Written by `headless_scripts/{script}` (its docstring describes the method).", "",
             "**machine and versions**: " + ", ".join(f"{key} {value}" for key, value in machine.items()), ""]
    for key, value in inputs.items():
        if isinstance(value, dict):
            lines += [f"**{key}**:", "", *(f"- {name}: {item}" for name, item in value.items()), ""]
        elif isinstance(value, list) and value and isinstance(value[0], str):
            lines += [f"**{key}**:", "", *(f"- {item}" for item in value), ""]
        else:
            lines += [f"**{key}**: {value}", ""]
    return "\n".join(lines) + "\n" + body.rstrip() + "\n"


# The quality score's ranking check (test_quality.py, bench_quality.py): KITTI classes
# the shared scans label, each from a real mesh (Chrono) or the built-in sample.
RANKING_OBJECTS = (("car", CHRONO_VEHICLES / "sedan" / "sedan_chassis_vis.obj"),
                   ("truck", CHRONO_VEHICLES / "truck" / "truck_chassis.obj"),
                   ("cyclist", None))


def ranking_objects(folder, dataset: str = "kitti") -> list:
    """BankObjects of RANKING_OBJECTS, prepared into ``folder`` (z up, the mesh's own
    heading, sized to the dataset's class mean)."""
    from .core.authoring.prepare import prepare, write_prepared
    from .core.bank.inputs import checked_objects, prepared_objects
    from .core.importing import load_reconstruction
    from .core.samples import write_sample

    folder = Path(folder)
    for class_name, mesh in RANKING_OBJECTS:
        if mesh is None:
            mesh = write_sample(folder / "sample_bicycle", "bicycle", seed=0, points=3000)["reconstruction.ply"]
            authored = prepare(load_reconstruction(mesh), class_name, dataset, up="pca", heading_method="baseline")
        else:
            authored = prepare(load_reconstruction(mesh), class_name, dataset, up="+z", heading_method="none")
        write_prepared(authored, class_name, dataset, folder / "prepared")
    found, incomplete = prepared_objects(folder / "prepared")
    return checked_objects(found, incomplete, False, folder / "prepared")


# How the tests and bench_placement judge whether a box stands on a scan's ground.
FOOTPRINT_RETURNS = 20  # returns under a footprint that make a judgement


def scan_ground_gap(points, box):
    """(gap, how): box bottom minus the scan's own ground at the box, m, for (N, >= 3)
    scan points (before anything was placed) and a (>= 7,) centre box. The ground is the
    median height of the lowest returns under the footprint (within 0.2 m of their 5th
    percentile; "footprint", with FOOTPRINT_RETURNS or more), else a plane fitted to the
    returns 0.3-4 m around it (bank.ground.fit_ground, "ring", with MIN_GROUND_POINTS or
    more), else (None, "none")."""
    import numpy as np

    from .core.bank.ground import MIN_GROUND_POINTS, fit_ground
    from .core.boxes import box_frame

    xyz = np.asarray(points, np.float64)[:, :3]
    box = np.asarray(box, np.float64)
    local = box_frame(xyz, box[:3], box[6])
    under = xyz[(np.abs(local[:, :2]) <= box[3:5] / 2).all(axis=1), 2]
    bottom = box[2] - box[5] / 2
    if len(under) >= FOOTPRINT_RETURNS:
        lowest = under[under <= np.percentile(under, 5) + 0.2]
        return float(bottom - np.median(lowest)), "footprint"
    fit = fit_ground(xyz, box[:3], box[3:6], box[6])
    if fit["points"] >= MIN_GROUND_POINTS:
        return fit["bottom_gap"], "ring"
    return None, "none"

