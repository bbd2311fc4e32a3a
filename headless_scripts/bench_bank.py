"""Throughput and memory of the bank export (core.bank.export) at nuScenes settings:
entries per second on 1 and all cores, peak memory against the bank size, bytes on disk
per entry, and what the paper's full nuScenes bank would take on this machine.

    .venv/bin/python headless_scripts/bench_bank.py [--quick] [--repeats 3]
        [--chrono TRUCK.obj] [--out bench/bank]

Objects, each a prepared object (prepare_objects.py output, in a temporary folder): the
Chrono truck chassis (11k faces; --up +z --heading none --size keep), the same mesh
midpoint-subdivided twice with trimesh.remesh.subdivide (176k faces, the very same
surface and box: its PLY beside a copy of the 11k sidecar) and the built-in sample truck
point cloud (core.samples.write_sample, prepare_objects.py --class truck --up +z, the
demo's case: scanned as surfels). --quick leaves the 176k truck out (a smoke test:
the target is judged by the full run only).

Config: BankConfig() (nuScenes: HDL-32E, 13 headings x 21 x 21 positions, 8 size
variants, 10 sweeps with motion, range noise, openpcdet + mmdet3d) except for the
grid. Throughput is timed on a thinned grid (headings every 90 deg, x and y every 10 m:
600 poses per truck; --quick: every 180 deg and 20 m, 108; chunk_size 32) with --workers 1
and all cores, the median of --repeats runs (--quick: 1); the full run also exports the
full default grid (5,677 poses per truck, chunk_size 64) once per object on all cores:
the rate at nuScenes settings, and the check of the steady-state model below.

Every export runs in a fresh Python process (so its memory is its own), which loads the
objects, plans the entries, exports them (export.run_plan: the timed part, poses/s =
poses scanned and written per second, kept/s = entries that reach the bank, >= 16
points; CPU ms/pose = user + system time of the process and its workers), assembles
the info pickles and the manifest, and then reports: its own peak RSS (getrusage
RUSAGE_SELF), its workers' peak (the largest VmHWM of its pool workers, polled from
/proc every 50 ms; RUSAGE_CHILDREN is recorded too, but bpy's and numpy's import-time
helper processes make it report at least the parent's RSS of that moment), the
assembly's peak above the RSS before it (VmHWM reset through /proc/self/clear_refs),
the bank's bytes (apparent and allocated, by part) and, once per object, the BVH build
time of all its size variants in one process: each worker builds them once per object,
a fixed cost the thinned grid amortises over fewer poses than the full one. Steady
rate = poses / (seconds - build seconds); full-grid rate projected = full poses /
(build seconds + full poses / steady rate).

Memory against the bank size, on all cores: 1, 2, 4, 8 copies (--quick: 1, 2) of one
object (the 176k truck; --quick: the 11k one) under different names (other seeds: 1x,
2x, ... entries) on the thinned grid, and one copy on the full grid (--quick: the
thinned one): more entries for the same objects. Each peak is modelled as a + b objects
+ c entries (c from the two one-object runs, 0 when they differ by under 2 %; a and b
by least squares over the copies), the assembly's growth as a + c entries (least
squares); the paper's bank is then taken as that many full-grid copies. The full run
also profiles one single-process export of the 176k truck on the thinned grid
(cProfile) by stage. --render JSON rewrites the tables and figure of an earlier run
without measuring.

Projection: the paper's nuScenes bank, 151,579 entries of 6 classes, at each object's
kept entries/s on all cores (the full-grid rate when measured, else the projected one),
its bytes per entry, and the memory fits above. Prints Markdown tables and writes <out>.json, <out>.md and <out>.png.
"""

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "addon"))

import numpy as np  # noqa: E402

from pgt_blender import cli, dev  # noqa: E402
from pgt_blender.core import boxes  # noqa: E402
from pgt_blender.core.authoring.prepare import read_sidecar  # noqa: E402
from pgt_blender.core.bank import export, folder, formats  # noqa: E402
from pgt_blender.core.scan import raycast, sweeps, targets  # noqa: E402

CHRONO_TRUCK = dev.CHRONO_VEHICLES / "truck" / "truck_chassis.obj"
TARGET_ENTRIES_PER_S = 300.0
TARGET_OBJECT = "chrono truck 176k"
SUBSET = {"chunk_size": 32, "headings_deg": [-180.0, 180.0, 90.0], "x": [-50.0, 50.0, 10.0],
          "y": [-50.0, 50.0, 10.0]}
QUICK_SUBSET = SUBSET | {"headings_deg": [-180.0, 180.0, 180.0], "x": [-50.0, 50.0, 20.0], "y": [-50.0, 50.0, 20.0]}
FULL = {}  # BankConfig() as it is: the paper's nuScenes grid
PAPER_BANK = {"truck": 36_960, "construction_vehicle": 52_800, "bus": 12_960, "trailer": 19_280,
              "motorcycle": 25_279, "bicycle": 4_300}  # the paper's nuScenes bank, kept entries per class
MIB = 2**20
NOISE = 0.02  # a peak RSS difference under 2 % between two runs is taken as run-to-run noise
PROFILE_STAGES = {  # stage -> the function whose cumulative seconds it is (a rename fails here, loudly)
    "all chunks (export.write_chunk)": export.write_chunk,
    "  BVH builds, 8 size variants (targets.target_from_reconstruction)": targets.target_from_reconstruction,
    "  10 sweeps per pose (sweeps.scan_sweeps)": sweeps.scan_sweeps,
    "    ray casting (raycast.trace_rays)": raycast.trace_rays,
    "    returns, noise (raycast.build_returns)": raycast.build_returns,
    "  box filter (boxes.inside_box)": boxes.inside_box,
    "  format records (formats.database_record)": formats.database_record,
    "  file writes (folder.write_file)": folder.write_file,
}


# ----------------------------------------------------------------- one export (a child process)

def _status(pid="self") -> dict:
    """VmRSS and VmHWM of a process, bytes (empty when it is gone)."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return {}
    return {key: int(value) * 1024 for key, value in re.findall(r"^(VmRSS|VmHWM):\s+(\d+) kB", text, re.M)}


def _maxrss(who) -> int:
    return resource.getrusage(who).ru_maxrss * 1024  # Linux: kB


def _cpu_s() -> float:
    """User + system CPU seconds of this process and its reaped children."""
    return sum(u.ru_utime + u.ru_stime for u in map(resource.getrusage, (resource.RUSAGE_SELF,
                                                                          resource.RUSAGE_CHILDREN)))


class WorkerPoll(threading.Thread):
    """The largest VmHWM of this process's children, polled from /proc."""

    def __init__(self, interval: float = 0.05):
        super().__init__(daemon=True)
        self.interval, self.peak, self.stop = interval, 0, threading.Event()

    def children(self) -> list:
        me, found = os.getpid(), []
        for entry in os.scandir("/proc"):
            if entry.name.isdigit():
                try:
                    stat = Path(entry.path, "stat").read_text()
                except OSError:
                    continue
                if int(stat.rsplit(")", 1)[1].split()[1]) == me:
                    found.append(entry.name)
        return found

    def run(self):
        while not self.stop.wait(self.interval):
            for pid in self.children():
                self.peak = max(self.peak, _status(pid).get("VmHWM", 0))


def disk_usage(out: Path) -> dict:
    """Apparent and allocated bytes and file counts of the bank, by part."""
    parts = {}
    for path in out.rglob("*"):
        if not path.is_file():
            continue
        relative = path.relative_to(out).as_posix()
        part = ("work records" if relative.startswith(".work/") else "manifest" if relative == "manifest.json"
                else "info pickles" if relative.endswith(".pkl") else "database .bin")
        stat = path.stat()
        bucket = parts.setdefault(part, {"files": 0, "bytes": 0, "allocated": 0})
        bucket["files"] += 1
        bucket["bytes"] += stat.st_size
        bucket["allocated"] += stat.st_blocks * 512
    return parts


def child(spec: dict) -> dict:
    """One export as ``spec`` says, measured; runs in its own process."""
    targets.bvhtree_class()  # bpy first: its import-time helper process is the RUSAGE_CHILDREN baseline
    from pgt_blender.core.bank.config import BankConfig
    from pgt_blender.core.bank.entries import TargetCache
    from pgt_blender.core.bank.inputs import checked_objects, prepared_objects

    values = {key: tuple(value) if isinstance(value, list) else value for key, value in spec["config"].items()}
    config = BankConfig(**values)
    result = {}
    with tempfile.TemporaryDirectory(prefix="bench_bank_") as scratch:
        start = time.perf_counter()
        objects = []
        for source in spec["folders"]:
            objects += checked_objects(*prepared_objects(source), False, source)
        result["load_s"] = time.perf_counter() - start
        out = Path(scratch) / "bank"
        start = time.perf_counter()
        plan = export.plan_bank(objects, config, out)
        result["plan_s"] = time.perf_counter() - start
        baseline_children = _maxrss(resource.RUSAGE_CHILDREN)  # bpy's and numpy's import-time helpers
        result["load_average_1min"] = os.getloadavg()[0]
        poll = WorkerPoll()
        poll.start()
        profiler = None
        if spec.get("profile"):
            import cProfile

            profiler = cProfile.Profile()
            profiler.enable()
        start, cpu = time.perf_counter(), _cpu_s()
        poses = sum(export.run_plan(plan, spec["workers"]))
        result["export_s"] = time.perf_counter() - start
        result["export_cpu_s"] = _cpu_s() - cpu  # the pool is shut down (its workers reaped) by now
        if profiler:
            profiler.disable()
            result["profile"] = profile_summary(profiler, result["export_s"])
        poll.stop.set()
        poll.join()
        result["parent_max_rss_before_assembly"] = _maxrss(resource.RUSAGE_SELF)
        Path("/proc/self/clear_refs").write_text("5")  # VmHWM := VmRSS
        before = _status()
        start = time.perf_counter()
        manifest = export.assemble(out)
        result["assemble_s"] = time.perf_counter() - start
        after = _status()
        result |= {
            "objects": len(objects), "poses": int(poses), "chunks": len(plan.chunks), "kept": manifest["entries"],
            "parent_max_rss": _maxrss(resource.RUSAGE_SELF), "workers_max_rss": _maxrss(resource.RUSAGE_CHILDREN),
            "children_baseline_rss": baseline_children, "workers_vmhwm_polled": poll.peak,
            "rss_before_assembly": before.get("VmRSS"), "assembly_peak_rss": after.get("VmHWM"),
            "assembly_growth": after.get("VmHWM", 0) - before.get("VmRSS", 0), "disk": disk_usage(out),
            "points_per_entry": float(np.mean(_points(out, manifest))),
        }
    if spec.get("builds"):  # one process's builds of every size variant of the first object
        cache = TargetCache(objects[:1], config)
        start = time.perf_counter()
        for variant in range(config.size_variants):
            cache.get(0, variant)
        result["build_s"] = time.perf_counter() - start
    return result


def _points(out: Path, manifest: dict) -> list:
    """Points per kept entry (num_points_in_gt of the first format's info pickle)."""
    import pickle

    fmt = manifest["config"]["formats"][0]
    infos = pickle.loads((out / manifest["info_pickles"][fmt]).read_bytes())
    return [info["num_points_in_gt"] for entries in infos.values() for info in entries] or [0]


def profile_summary(profiler, seconds: float) -> dict:
    """Cumulative seconds per stage and the top functions by own time."""
    import pstats

    stats = pstats.Stats(profiler).stats  # (file, line, name) -> (cc, nc, tt, ct, callers)
    stages = {}
    for stage, function in PROFILE_STAGES.items():
        code = function.__code__
        stages[stage] = stats.get((code.co_filename, code.co_firstlineno, code.co_name), (0, 0, 0, 0.0))[3]
    top = sorted(stats.items(), key=lambda item: -item[1][2])[:12]
    return {"seconds_profiled": seconds, "stages_cumulative_s": stages,
            "top_own_time": [{"function": f"{Path(file).name}:{line}({func})", "calls": nc, "own_s": tt,
                              "cumulative_s": ct} for (file, line, func), (_, nc, tt, ct, _) in top]}


# ----------------------------------------------------------------- the objects

def prepare(script_args: list) -> None:
    command = [sys.executable, str(ROOT / "headless_scripts" / "prepare_objects.py"), *map(str, script_args)]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    if done.returncode:
        raise RuntimeError(f"prepare_objects.py failed:\n{done.stdout}\n{done.stderr}")


def make_objects(scratch: Path, chrono: Path, subdivided: bool = True) -> dict:
    """Prepared-object folders by name, each with its description (the 176k truck only
    when ``subdivided``)."""
    import trimesh

    from pgt_blender.core.samples import write_sample

    objects = {}
    if chrono.is_file():
        source = scratch / "chrono_source"
        source.mkdir()
        for path in (chrono, chrono.with_suffix(".mtl")):
            if path.is_file():
                shutil.copy(path, source / path.name)
        folder = scratch / "chrono_11k"
        prepare(["--in", source, "--class", "truck", "--out", folder, "--up", "+z", "--heading", "none",
                 "--size", "keep"])
        ply = next(folder.glob("*.ply"))
        mesh = trimesh.load(ply, process=False)
        shown = f"../{chrono.relative_to(ROOT.parent)}" if chrono.is_relative_to(ROOT.parent) else str(chrono)
        objects["chrono truck 11k"] = {"folder": folder, "source": f"{shown}, prepare_objects.py --class truck "
                                       "--up +z --heading none --size keep", "faces": len(mesh.faces),
                                       "points": len(mesh.vertices)}
    if chrono.is_file() and subdivided:
        vertices, faces = trimesh.remesh.subdivide(mesh.vertices, mesh.faces)
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
        fine = scratch / "chrono_176k"
        fine.mkdir()
        name = f"{ply.stem}_176k"
        (fine / f"{name}.ply").write_bytes(trimesh.Trimesh(vertices, faces, process=False).export(file_type="ply"))
        shutil.copy(ply.with_suffix(".json"), fine / f"{name}.json")  # same box: the same surface
        objects[TARGET_OBJECT] = {"folder": fine, "source": "chrono truck 11k, trimesh.remesh.subdivide x2 "
                                  "(midpoint: the same surface), its sidecar", "faces": len(faces),
                                  "points": len(vertices)}
    if not chrono.is_file():
        print(f"note: no Chrono truck at {chrono}; only the sample truck is measured\n")
    sample = scratch / "sample_source"
    paths = write_sample(scratch / "sample_files", "truck")
    sample.mkdir()
    shutil.copy(paths["reconstruction.ply"], sample / paths["reconstruction.ply"].name)
    folder = scratch / "sample_truck"
    prepare(["--in", sample, "--class", "truck", "--out", folder, "--up", "+z"])
    points = read_sidecar(next(folder.glob("*.json")))["points"]
    objects["sample truck (surfels)"] = {"folder": folder, "source": "core.samples.write_sample(dir, 'truck') "
                                         "reconstruction.ply, prepare_objects.py --class truck --up +z",
                                         "faces": 0, "points": points}
    for entry in objects.values():
        entry["dims_m"] = [round(v, 3) for v in read_sidecar(next(entry["folder"].glob("*.json")))["dims"]]
    return objects


def copies(folder: Path, count: int, scratch: Path) -> Path:
    """A folder with ``count`` copies of the prepared object in ``folder``, other names."""
    target = scratch / f"{folder.name}_x{count}"
    target.mkdir()
    ply = next(folder.glob("*.ply"))
    for index in range(count):
        for suffix in (".ply", ".json"):
            os.link(ply.with_suffix(suffix), target / f"{ply.stem}_copy{index}{suffix}")
    return target


# ----------------------------------------------------------------- the run

def export_once(folders: list, config: dict, workers: int, **options) -> dict:
    """One measured export in a fresh Python process."""
    with tempfile.NamedTemporaryFile("r", suffix=".json") as result:
        spec = {"folders": [str(f) for f in folders], "config": config, "workers": workers,
                "result": result.name, **options}
        start = time.perf_counter()
        done = subprocess.run([sys.executable, __file__, "--child", json.dumps(spec)], cwd=ROOT,
                              capture_output=True, text=True)
        if done.returncode:
            raise RuntimeError(f"export child failed:\n{done.stdout}\n{done.stderr}")
        measured = json.loads(Path(result.name).read_text())
    return measured | {"process_s": time.perf_counter() - start}


def throughput_row(name: str, grid: str, workers: int, runs: list, build_s: float | None,
                   full_poses: int | None) -> dict:
    seconds = [r["export_s"] for r in runs]
    median = float(np.median(seconds))
    first = runs[0]
    disk = first["disk"]
    kept = first["kept"]
    total = sum(p["allocated"] for p in disk.values())
    row = {"object": name, "grid": grid, "workers": workers, "poses": first["poses"], "kept": kept,
           "runs": len(runs), "export_s": seconds, "export_s_median": median,
           "poses_per_s": first["poses"] / median, "kept_per_s": kept / median,
           "cpu_ms_per_pose": 1e3 * float(np.median([r["export_cpu_s"] for r in runs])) / first["poses"],
           "load_average_1min": [round(r["load_average_1min"], 2) for r in runs],
           "plan_s": float(np.median([r["plan_s"] for r in runs])),
           "assemble_s": float(np.median([r["assemble_s"] for r in runs])),
           "parent_max_rss": max(r["parent_max_rss"] for r in runs),
           "workers_max_rss": max(r["workers_max_rss"] for r in runs) if workers > 1 else None,
           "workers_vmhwm_polled": max(r["workers_vmhwm_polled"] for r in runs) if workers > 1 else None,
           "children_baseline_rss": first["children_baseline_rss"],
           "points_per_entry": first["points_per_entry"],
           "disk_allocated_per_entry": total / kept if kept else None,
           "disk_bytes_per_entry": sum(p["bytes"] for p in disk.values()) / kept if kept else None,
           "disk_allocated_per_entry_without_work": (total - disk.get("work records", {}).get("allocated", 0)) / kept
           if kept else None, "disk": disk}
    if build_s is not None:
        build = row["build_s"] = build_s
        if median > build * 1.05:
            steady = first["poses"] / (median - build)
            row["steady_poses_per_s"] = steady
            if full_poses:
                row["projected_full_grid_poses"] = full_poses
                row["projected_full_grid_poses_per_s"] = full_poses / (build + full_poses / steady)
    return row


def fit_line(x, y) -> tuple:
    """Least-squares slope and intercept (slope 0 for a single point)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) < 2 or np.ptp(x) == 0:
        return 0.0, float(y.mean())
    slope, intercept = np.polyfit(x, y, 1)
    return float(slope), float(intercept)


def full_grid_poses(objects: dict) -> dict:
    """Poses of the full default grid per object (no scanning)."""
    from pgt_blender.core.bank.config import BankConfig
    from pgt_blender.core.bank.grid import object_entries

    config = BankConfig()
    counts = {}
    for name, entry in objects.items():
        sidecar = read_sidecar(next(entry["folder"].glob("*.json")))
        counts[name] = len(object_entries(config, 0, sidecar["class"], np.asarray(sidecar["dims"], float)))
    return counts


def fit_model(series: list, key: str) -> list:
    """[a, b, c] of value = a + b objects + c kept entries: c from the two one-object runs
    (the same object, more entries; a difference under NOISE of the value counts as
    none), then a and b by least squares over the copies."""
    single = [r for r in series if r["objects"] == 1]
    low, high = min(single, key=lambda r: r["kept"]), max(single, key=lambda r: r["kept"])
    change = high[key] - low[key]
    per_entry = (change / (high["kept"] - low["kept"]) if high["kept"] > low["kept"] and abs(change) > NOISE * low[key]
                 else 0.0)
    copied = [r for r in series if r is not high]
    per_object, intercept = fit_line([r["objects"] for r in copied], [r[key] - per_entry * r["kept"] for r in copied])
    return [intercept, per_object, per_entry]


def memory_summary(series: list, name: str, workers: int, throughput: list, full_poses: int) -> dict:
    """Fits over the memory series and their values at the paper's bank size, made of
    copies of ``name`` on the full grid."""
    kept = [r["kept"] for r in series]
    models = {key: fit_model(series, key)
              for key in ("parent_max_rss", "workers_vmhwm_polled", "workers_max_rss", "rss_before_assembly")}
    assembly = fit_line(kept, [r["assembly_growth"] for r in series])
    pickles = fit_line(kept, [r["disk"].get("info pickles", {}).get("bytes", 0) for r in series])
    rows = [r for r in throughput if r["object"] == name and r["workers"] == workers]
    full = [r for r in rows if r["grid"] == "full"]
    per_object = full[0]["kept"] if full else full_poses * rows[0]["kept"] / rows[0]["poses"]
    total = sum(PAPER_BANK.values())
    count = int(np.ceil(total / per_object))

    def at(model):
        return model[0] + model[1] * count + model[2] * total

    return {"object": name, "workers": workers, "runs": [(r["objects"], r["grid"], r["kept"]) for r in series],
            "models_intercept_per_object_per_entry_bytes": models,
            "assembly_growth_fit_slope_intercept": assembly, "info_pickle_bytes_fit_slope_intercept": pickles,
            "full_scale": {"entries": total, "kept_per_object_full_grid": per_object, "objects": count,
                           "assembly_growth": assembly[1] + assembly[0] * total,
                           "parent_before_assembly": at(models["rss_before_assembly"]),
                           "parent_peak": max(at(models["parent_max_rss"]), at(models["rss_before_assembly"])
                                              + assembly[1] + assembly[0] * total),
                           "worker_peak": at(models["workers_vmhwm_polled"])},
            "measured_worker_peak_range": [min(r["workers_vmhwm_polled"] for r in series),
                                           max(r["workers_vmhwm_polled"] for r in series)],
            "measured_kept_range": [min(kept), max(kept)]}


def memory_note(summary: dict) -> str:
    models = summary["models_intercept_per_object_per_entry_bytes"]
    parts = [f"{label} {mb(models[key][0])} MB + {models[key][1] / MIB:,.1f} MB per object + "
             f"{models[key][2]:,.0f} B per kept entry" for key, label in
             (("parent_max_rss", "parent max RSS"), ("workers_vmhwm_polled", "worker max RSS (polled)"),
              ("rss_before_assembly", "parent RSS before assembly"))]
    slope, intercept = summary["assembly_growth_fit_slope_intercept"]
    return (f"{summary['object']}, {summary['workers']} workers. Fits (per entry: the two one-object runs, a "
            f"difference under {NOISE:.0%} taken as none; per object: least squares over the copies; RSS counts "
            "pages shared with the parent in every process): "
            + "; ".join(parts) + f"; assembly peak growth {intercept / MIB:,.1f} MB + {slope:,.0f} B per kept entry; "
            f"info pickles (all formats) {summary['info_pickle_bytes_fit_slope_intercept'][0]:,.0f} B per entry")


def full_scale_memory_line(summary: dict) -> str:
    full = summary["full_scale"]
    return (f"memory at the paper's size, {full['entries']:,} entries as {full['objects']} copies of "
            f"{summary['object']} ({full['kept_per_object_full_grid']:,.0f} kept entries each on the full grid), "
            f"extrapolated by the fits above: assembly growth {mb(full['assembly_growth'])} MB, parent peak "
            f"{mb(full['parent_peak'])} MB (before assembly {mb(full['parent_before_assembly'])} MB), worker peak "
            f"{mb(full['worker_peak'])} MB each (measured {mb(summary['measured_worker_peak_range'][0])}-"
            f"{mb(summary['measured_worker_peak_range'][1])} MB over {summary['measured_kept_range'][0]:,}-"
            f"{summary['measured_kept_range'][1]:,} entries; a worker holds one chunk and the current object's "
            "BVHs, plus what it shares with the parent since the fork: every object's geometry). The per-object "
            "terms are linear extrapolations of allocator-dominated growth (the geometry itself is much smaller), "
            "likely upper bounds")


def projection(throughput: list) -> list:
    """The paper's bank at each object's kept entries/s on all cores."""
    total = sum(PAPER_BANK.values())
    rows = []
    cores = max(r["workers"] for r in throughput)
    for name in dict.fromkeys(r["object"] for r in throughput):
        mine = [r for r in throughput if r["object"] == name and r["workers"] == cores]
        full = [r for r in mine if r["grid"] == "full"]
        subset = [r for r in mine if r["grid"] != "full"]
        if full:
            rate, basis = full[0]["kept_per_s"], "full grid, measured"
        elif subset and "projected_full_grid_poses_per_s" in subset[0]:
            r = subset[0]
            rate, basis = r["projected_full_grid_poses_per_s"] * r["kept"] / r["poses"], "full grid, projected"
        else:
            rate, basis = subset[0]["kept_per_s"], "thinned grid"
        disk = (full or subset)[0]
        cpu_rate = cores * 1e3 / disk["cpu_ms_per_pose"] * disk["kept"] / disk["poses"]
        rows.append({"object": name, "basis": basis, "workers": cores, "kept_per_s": rate,
                     "entries": total, "hours": total / rate / 3600, "cpu_bound_kept_per_s": cpu_rate,
                     "hours_cpu_bound": total / cpu_rate / 3600, "points_per_entry": disk["points_per_entry"],
                     "disk_gb": total * disk["disk_allocated_per_entry"] / 1e9,
                     "disk_gb_without_work": total * disk["disk_allocated_per_entry_without_work"] / 1e9})
    return rows


# ----------------------------------------------------------------- output

def mb(value) -> str:
    return "-" if value is None else f"{value / MIB:,.0f}"


def throughput_table(rows: list) -> str:
    def cells(r):
        steady = f"{r['steady_poses_per_s']:.0f}" if "steady_poses_per_s" in r else "-"
        projected = f"{r['projected_full_grid_poses_per_s']:.0f}" if "projected_full_grid_poses_per_s" in r else "-"
        return [r["object"], r["grid"], r["workers"], f"{r['poses']:,}", f"{r['kept']:,}",
                f"{r['export_s_median']:.2f} ({r['runs']})", f"{r['poses_per_s']:.0f}", f"{r['kept_per_s']:.0f}",
                f"{r['cpu_ms_per_pose']:.1f}", f"{r.get('build_s', float('nan')):.2f}", steady, projected,
                mb(r["parent_max_rss"]), mb(r["workers_vmhwm_polled"]), f"{r['disk_allocated_per_entry'] / 1e3:,.1f}"]
    return dev.markdown_table(["object", "grid", "workers", "poses", "kept", "s (median of n)", "poses/s", "kept/s",
                               "CPU ms/pose", "BVH builds s", "steady poses/s", "full-grid poses/s (projected)",
                               "parent max RSS MB", "worker max RSS MB", "disk kB/entry"],
                              [cells(r) for r in rows], "ll" + "r" * 13)


def memory_table(rows: list) -> str:
    return dev.markdown_table(
        ["objects", "grid", "poses", "kept", "s", "kept/s", "parent max RSS MB", "worker max RSS MB (polled VmHWM)",
         "worker max RSS MB (getrusage)", "RSS before assembly MB", "assembly peak growth MB", "info pickles MB",
         "bank on disk MB"],
        [[r["objects"], r["grid"], f"{r['poses']:,}", f"{r['kept']:,}", f"{r['export_s']:.1f}",
          f"{r['kept'] / r['export_s']:.0f}", mb(r["parent_max_rss"]), mb(r["workers_vmhwm_polled"]),
          mb(r["workers_max_rss"]), mb(r["rss_before_assembly"]), f"{r['assembly_growth'] / MIB:,.1f}",
          f"{r['disk'].get('info pickles', {}).get('bytes', 0) / MIB:,.1f}",
          f"{sum(p['allocated'] for p in r['disk'].values()) / MIB:,.1f}"] for r in rows],
        "rl" + "r" * 11)


def projection_table(rows: list) -> str:
    return dev.markdown_table(
        ["entries like", "basis", "workers", "kept/s", "hours for 151,579", "CPU-bound kept/s", "hours, CPU-bound",
         "points/entry", "disk GB (without .work)"],
        [[r["object"], r["basis"], r["workers"], f"{r['kept_per_s']:.0f}", f"{r['hours']:.2f}",
          f"{r['cpu_bound_kept_per_s']:.0f}", f"{r['hours_cpu_bound']:.2f}", f"{r['points_per_entry']:,.0f}",
          f"{r['disk_gb']:.1f} ({r['disk_gb_without_work']:.1f})"] for r in rows], "ll" + "r" * 7)


def profile_table(profile: dict) -> str:
    total = profile["seconds_profiled"]
    stages = dev.markdown_table(["stage (cumulative; indented = inside the one above)", "s", "% of export"],
                                [[stage.replace("  ", "&nbsp;&nbsp;"), f"{s:.2f}", f"{100 * s / total:.0f}"]
                                 for stage, s in profile["stages_cumulative_s"].items()])
    functions = dev.markdown_table(["function (top own time)", "calls", "own s", "cumulative s"],
                                   [[f["function"], f"{f['calls']:,}", f"{f['own_s']:.2f}", f"{f['cumulative_s']:.2f}"]
                                    for f in profile["top_own_time"]])
    return f"export under cProfile: {total:.1f} s (profiling inflates Python-level calls)\n\n{stages}\n\n{functions}"


def target_summary(throughput: list) -> dict | None:
    cores = max(r["workers"] for r in throughput)
    mine = [r for r in throughput if r["object"] == TARGET_OBJECT and r["workers"] == cores]
    if not mine:
        return None
    row = next((r for r in mine if r["grid"] == "full"), mine[0])
    return {"object": TARGET_OBJECT, "workers": cores, "grid": row["grid"], "poses_per_s": row["poses_per_s"],
            "kept_per_s": row["kept_per_s"], "target_entries_per_s": TARGET_ENTRIES_PER_S,
            "meets_target": bool(row["kept_per_s"] >= TARGET_ENTRIES_PER_S),
            "factor_short": TARGET_ENTRIES_PER_S / row["kept_per_s"]}


def target_line(target: dict | None, quick: bool) -> str:
    if target is None:
        return ("target: not measured (--quick leaves the 176k truck to the full run)" if quick
                else "target: not measured (no Chrono truck)")
    return (f"target: >= {TARGET_ENTRIES_PER_S:g} entries/s on {target['workers']} cores for a ~100k-triangle "
            f"object at nuScenes settings: {target['object']}, {target['grid']} grid: "
            f"{target['poses_per_s']:.0f} poses/s, {target['kept_per_s']:.0f} kept entries/s -> "
            + ("meets it" if target["meets_target"] else f"MISSES it ({target['factor_short']:.1f}x short)"))


def plot(throughput: list, series: list, series_object: str):
    def draw(plt):
        figure, axes = plt.subplots(1, 2, figsize=(15, 5.5))
        labels = [f"{r['object']}\n{r['grid']}, {r['workers']} w" for r in throughput]
        x = np.arange(len(throughput))
        axes[0].bar(x - 0.2, [r["poses_per_s"] for r in throughput], 0.4, label="poses/s (scanned, written)")
        axes[0].bar(x + 0.2, [r["kept_per_s"] for r in throughput], 0.4, label="kept entries/s")
        axes[0].axhline(TARGET_ENTRIES_PER_S, color="k", ls="--", lw=1)
        axes[0].text(-0.4, TARGET_ENTRIES_PER_S, f" target {TARGET_ENTRIES_PER_S:g}/s (2 cores, ~100k faces)",
                     va="bottom", fontsize=8)
        projected = [(i, r["projected_full_grid_poses_per_s"]) for i, r in enumerate(throughput)
                     if "projected_full_grid_poses_per_s" in r]
        if projected:
            axes[0].scatter([i - 0.2 for i, _ in projected], [v for _, v in projected], marker="_", s=300,
                            color="k", zorder=3, label="poses/s projected to the full grid (builds amortised)")
        axes[0].set_xticks(x, labels, fontsize=7, rotation=30, ha="right")
        axes[0].set_ylabel("per second (median of runs)")
        axes[0].set_title("bank export throughput, nuScenes settings (10 sweeps, noise, 2 formats)", fontsize=10)
        axes[0].legend(fontsize=8)
        copied = [r for r in series if r is not series[-1]]
        for key, label, marker, color in (("parent_max_rss", "parent max RSS", "o", "tab:blue"),
                                           ("workers_vmhwm_polled", "worker max RSS (polled VmHWM)", "s", "tab:orange"),
                                           ("workers_max_rss", "worker max RSS (getrusage)", "D", "tab:gray"),
                                           ("assembly_growth", "assembly peak growth", "^", "tab:green")):
            axes[1].plot([r["kept"] for r in copied], [r[key] / MIB for r in copied], marker + "-", color=color,
                         label=f"{label}, 1, 2, ... objects")
            axes[1].scatter([series[-1]["kept"]], [series[-1][key] / MIB], marker=marker, s=70, facecolors="none",
                            edgecolors=color, linewidths=1.5)
        axes[1].scatter([], [], marker="o", facecolors="none", edgecolors="k",
                        label=f"hollow: 1 object, {series[-1]['grid']} grid")
        axes[1].set_xlabel(f"bank size, kept entries ({series_object})")
        axes[1].set_ylabel("MiB")
        axes[1].set_title("peak memory against the bank size (all cores)", fontsize=10)
        axes[1].grid(alpha=0.3)
        axes[1].legend(fontsize=8)
        return figure
    return draw


def markdown_header(machine: dict, objects: dict, settings: dict) -> str:
    lines = ["# Bank export: throughput and memory at nuScenes settings", "",
             "Written by `headless_scripts/bench_bank.py` (its docstring describes the method).", "",
             "**machine and versions**: " + ", ".join(f"{key} {value}" for key, value in machine.items()), "",
             "**objects** (prepared objects, object frame):", ""]
    lines += [f"- {name}: {o['source']}; {o['faces']:,} faces, {o['points']:,} points; box "
              f"{' x '.join(f'{d:g}' for d in o['dims_m'])} m" for name, o in objects.items()]
    lines += ["", "**settings**:", ""] + [f"- {key}: {value}" for key, value in settings.items()]
    return "\n".join(lines) + "\n"


def main(argv: list) -> int:
    parser = argparse.ArgumentParser(prog="bench_bank.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a smoke test (~40 s): no 176k truck, 108-pose grid, "
                        "1 run each, 1 and 2 copies, no full grid, no profile")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per object and worker count")
    parser.add_argument("--chrono", type=Path, default=CHRONO_TRUCK, help="the Chrono truck chassis .obj")
    parser.add_argument("--engine", choices=("bvh", "embree"), default="bvh",
                        help="the bank's ray engine (config scan.engine)")
    parser.add_argument("--out", type=Path, help="default: bench/bank (bvh) or bench/bank_embree")
    parser.add_argument("--render", type=Path, help="only rewrite the tables and figure from this earlier .json")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    args.out = args.out or ROOT / "bench" / ("bank" if args.engine == "bvh" else f"bank_{args.engine}")
    if args.render:
        results = json.loads(args.render.read_text())
        report({key: results[key] for key in ("machine", "inputs", "settings", "quick", "series_object", "workers",
                                              "throughput", "memory_series", "profile")}, args.out)
        return 0
    if args.child:
        spec = json.loads(args.child)
        Path(spec["result"]).write_text(json.dumps(child(spec)))
        return 0
    repeats = 1 if args.quick else args.repeats
    subset, grid = (QUICK_SUBSET, "quick") if args.quick else (SUBSET, "thinned")
    subset, full = subset | {"engine": args.engine}, FULL | {"engine": args.engine}
    copy_counts = (1, 2) if args.quick else (1, 2, 4, 8)
    workers = sorted({1, os.cpu_count() or 1})
    import scipy
    import trimesh

    from pgt_blender.core.bank.config import BankConfig
    from pgt_blender.core.scan import targets

    targets.bvhtree_class()  # loads bpy outside Blender (its version; each export process loads its own)
    import bpy

    machine = dev.machine(numpy=np.__version__, scipy=scipy.__version__, trimesh=trimesh.__version__,
                          bpy=bpy.app.version_string)
    print(f"machine: {machine}\n", flush=True)
    load_before = [round(x, 2) for x in os.getloadavg()]
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_bank_objects_") as scratch:
        scratch = Path(scratch)
        objects = make_objects(scratch, args.chrono, subdivided=not args.quick)
        full_poses = full_grid_poses(objects)
        throughput, full_runs = [], {}
        for name, entry in objects.items():
            build_s = None  # measured once per object, after its first export
            for count in workers:
                runs = [export_once([entry["folder"]], subset, count, builds=build_s is None and not i)
                        for i in range(repeats)]
                build_s = runs[0].get("build_s", build_s)
                throughput.append(throughput_row(name, grid, count, runs, build_s, full_poses[name]))
                print(f"{name}, {count} worker(s): {throughput[-1]['poses_per_s']:.0f} poses/s", flush=True)
            if not args.quick:
                run = full_runs[name] = export_once([entry["folder"]], full, workers[-1])
                throughput.append(throughput_row(name, "full", workers[-1], [run], build_s, None))
                print(f"{name}, full grid, {workers[-1]} worker(s): {throughput[-1]['poses_per_s']:.0f} poses/s",
                      flush=True)
        series_object = TARGET_OBJECT if TARGET_OBJECT in objects and not args.quick else next(iter(objects))
        series = []
        for count in copy_counts:
            folder = copies(objects[series_object]["folder"], count, scratch)
            run = export_once([folder], subset, workers[-1])
            series.append(run | {"objects": count, "grid": grid})
            print(f"{count} x {series_object}: parent {mb(run['parent_max_rss'])} MB, workers "
                  f"{mb(run['workers_vmhwm_polled'])} MB", flush=True)
        # more entries per object, the objects the same: the full grid (--quick: the thinned one)
        dense = full_runs.get(series_object) or export_once([objects[series_object]["folder"]],
                                                             SUBSET | {"engine": args.engine}, workers[-1])
        series.append(dense | {"objects": 1, "grid": "full" if series_object in full_runs else "thinned"})
        profile = None
        if not args.quick and TARGET_OBJECT in objects:
            profile = export_once([objects[TARGET_OBJECT]["folder"]], subset, 1, profile=True)["profile"]
    elapsed = time.perf_counter() - started
    load_after = [round(x, 2) for x in os.getloadavg()]
    default = BankConfig()
    settings = {
        "config": f"BankConfig() (dataset nuscenes, sensor HDL-32E, {default.size_variants} size variants, sweeps "
                  f"0 = nuScenes' 10, range_noise {default.range_noise}, formats {', '.join(default.formats)}, "
                  f"min_points {default.min_points}, chunk_size {default.chunk_size}) with the grid below; "
                  f"ray engine {args.engine}",
        f"{grid} grid": f"headings {subset['headings_deg']}, x {subset['x']}, y {subset['y']}, chunk_size "
                        f"{subset['chunk_size']} (poses per object in the table)",
        "full grid": ("BankConfig() as is: headings -180..180 every 30 deg (13), x and y -50..50 every 5 m "
                      "(21 x 21), minus the ego clearance; one run per object on all cores")
                     if not args.quick else "not run (--quick)",
        "runs": f"median of {repeats} run(s) per object and worker count, each a fresh process; timed: "
                "export.run_plan (scan + .bin writes + chunk records); planning (export.plan_bank) and assembly apart",
        "workers": f"{workers}: 1 = in the parent process, {workers[-1]} = a fork pool of that many",
        "memory": "parent = RUSAGE_SELF ru_maxrss of the export process; worker = the largest VmHWM of its pool "
                  "workers, polled from /proc every 50 ms (VmHWM only grows, so the poll misses at most a worker's "
                  "last 50 ms); RUSAGE_CHILDREN ru_maxrss (JSON workers_max_rss, table 2) is never below the "
                  "parent's RSS when bpy and numpy ran their import-time helper processes (xdg-user-dir, lscpu: "
                  "vfork children that report the parent's peak; "
                  f"{mb(throughput[0]['children_baseline_rss'])} MB here), so it overstates small workers; "
                  "assembly growth = VmHWM during export.assemble (reset by /proc/self/clear_refs) - VmRSS before "
                  "it; MB = MiB",
        "cpu": "CPU ms/pose = user + system seconds of the export process and its workers during run_local, per "
               "pose: less sensitive than wall time to other work on the machine",
        "disk": "allocated bytes (st_blocks * 512) of the whole bank folder, .work chunk records included, per kept "
                "entry; 'without .work' leaves the chunk records out",
        "paper bank": f"{sum(PAPER_BANK.values()):,} entries: " + ", ".join(f"{k} {v:,}" for k, v in PAPER_BANK.items())
                      + "; each projection row assumes every entry costs what this object's do (time, points, "
                      "bytes): big trucks at 10 sweeps are the expensive end, bicycles and motorcycles give fewer "
                      "points; CPU-bound = workers / CPU seconds per pose (what idle cores would give); assembly "
                      "from the fitted growth per entry of the memory series",
        "run_seconds": round(elapsed, 1),
        "load_average_1_5_15_min": {"before": load_before, "after": load_after,
                                    "note": "other work on the machine inflates the times"},
    }
    inputs = {name: {key: value for key, value in o.items() if key != "folder"} | {"full_grid_poses": full_poses[name]}
              for name, o in objects.items()}
    report({"machine": machine, "inputs": inputs, "settings": settings, "quick": args.quick,
            "series_object": series_object, "workers": workers, "throughput": throughput,
            "memory_series": series, "profile": profile}, args.out)
    return 0


def report(results: dict, out: Path) -> None:
    """The summaries, tables and figure of the measurements in ``results``; prints the
    tables and writes <out>.md, <out>.json and <out>.png."""
    throughput, series, name = results["throughput"], results["memory_series"], results["series_object"]
    summary = memory_summary(series, name, results["workers"][-1], throughput,
                             results["inputs"][name]["full_grid_poses"])
    projected = projection(throughput)
    target = target_summary(throughput)
    line = target_line(target, results["quick"])
    body = (f"## throughput\n\n{throughput_table(throughput)}\n\n"
            f"## memory against the bank size\n\n{memory_table(series)}\n\n{memory_note(summary)}\n\n"
            f"## the paper's nuScenes bank ({sum(PAPER_BANK.values()):,} entries) on this machine\n\n"
            f"{projection_table(projected)}\n\n{full_scale_memory_line(summary)}\n")
    if results["profile"]:
        body += (f"\n## where the time goes: one worker, {TARGET_OBJECT}, thinned grid\n\n"
                 f"{profile_table(results['profile'])}\n")
    print("\n" + body + "\n" + line)
    header = markdown_header(results["machine"], results["inputs"], results["settings"])
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(f"{header}\n**{line}**\n\n{body}")
    dev.write_results(out, results | {"target": target, "memory_summary": summary, "projection": projected},
                      plot(throughput, series, name))
    print(f"wrote {out.with_suffix('.md')}")


if __name__ == "__main__":
    sys.exit(cli.run_main(main, cli.script_argv()))
