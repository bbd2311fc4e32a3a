"""Throughput, stages and memory of the bank export at nuScenes settings, through the
public bank API (export.plan_bank, run_plan, assemble): kept entries per second on 1
and all cores, where a worker's time goes (the export's own stage clock,
export.ChunkDone), peak memory against the bank size, bytes per entry, and what the
paper's nuScenes bank would take on this machine.

    .venv/bin/python headless_scripts/bench_bank.py [--quick] [--repeats 3] [--engine auto|bvh|embree]
        [--chrono TRUCK.obj] [--out bench/bank]

Objects, prepared with core.authoring.prepare (as prepare_objects does): the Chrono truck
chassis (11k faces; up +z, heading none, size keep), the same mesh midpoint-subdivided
twice with trimesh.remesh.subdivide (176k faces, the very same surface and box), and the
built-in sample truck's reconstruction (core.samples.write_sample; up +z, heading by the
geometric baseline, nuScenes truck size: scanned as surfels). --quick leaves the 176k
truck out and runs once (a smoke test; the target is judged by the full run only).

Config: BankConfig() (nuScenes: HDL-32E, 13 headings x 21 x 21 positions, 8 size
variants, 10 sweeps with ego and object motion, range noise, ray drop, openpcdet +
mmdet3d) with ``--engine``, except for the grid: throughput is timed on a thinned grid
(headings every 90 deg, x and y every 10 m: 600 poses per object; --quick every 180 deg
and 20 m, 108; chunk_size 32) with 1 worker and all cores, the median of --repeats
runs; the full run also exports the full default grid (5,677 poses per truck, chunk_size
64) on all cores, also the median of --repeats runs: the kernel's part of the CPU (new
files' pages) varies by up to 3x from one run to the next on a virtual machine.

Every export runs in a fresh Python process (its memory is its own): it loads the
objects, plans, exports (export.run_plan: the timed part; kept/s = entries that reach
the bank), assembles, and reports its CPU seconds (user + system, with its workers; the
system part apart; the memory poll's own left out), its own peak RSS (VmHWM:
getrusage's starts at the benchmark's own peak, which a child started by subprocess
inherits), its workers' peaks (the largest VmHWM of its pool workers, and their largest
private resident memory, smaps_rollup, polled from /proc every 0.2 s) and the bank's
bytes by part. Stages
are the sum over chunks of export.ChunkDone.seconds (per worker wall time; with all
cores they add up across workers); the engine ratio is the export's CPU per entry over
the time its ray engine's own calls took per entry (Scan.cast_seconds: the Embree or BVH
call), how far the pipeline runs from its ray engine; the user-CPU ratio leaves out the
kernel's part (making files, first touches of memory). Last, the machine's own cost of
writing the bank's files (file_write_cost: new files of an entry's size by one process,
by all cores at once, and by one right after deleting), the floor under the writes
stage, and of a new page of memory the first time and again (page_touch_cost, measured
first): on a virtual machine the first touch can cost many times more (the host backs
the page then); the export frees each chunk's page-cache pages once written back
(folder.drop_cached), so the next chunk's files reuse them. Every bank stays on
disk until the benchmark ends: on ext4 without a journal, files made within minutes of
deleting many cost several times more (measured there), which would charge one export
for the cleanup of the one before.

Memory against the bank size: 1, 2, 4, 8 copies (--quick: 1, 2) of one object (the 176k
truck; --quick: the 11k one) under other names (more entries, more objects) on the
thinned grid, all cores. Prints Markdown tables; writes <out>.json, <out>.md, <out>.png.
"""

import argparse
import hashlib
import json
import os
import re
import resource
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
from pgt_blender.core.bank import export  # noqa: E402
from pgt_blender.core.scan.raycast import ENGINES  # noqa: E402
from pgt_blender.core.scan.targets import resolve_engine  # noqa: E402

CHRONO_TRUCK = dev.CHRONO_VEHICLES / "truck" / "truck_chassis.obj"
TARGET_ENTRIES_PER_S = 1000.0
TARGET_ENGINE_RATIO = 3.0
TARGET_OBJECT = "chrono truck 176k"
SUBSET = {"chunk_size": 32, "headings_deg": [-180.0, 180.0, 90.0], "x": [-50.0, 50.0, 10.0],
          "y": [-50.0, 50.0, 10.0]}
QUICK_SUBSET = SUBSET | {"headings_deg": [-180.0, 180.0, 180.0], "x": [-50.0, 50.0, 20.0], "y": [-50.0, 50.0, 20.0]}
PAPER_BANK = {"truck": 36_960, "construction_vehicle": 52_800, "bus": 12_960, "trailer": 19_280,
              "motorcycle": 25_279, "bicycle": 4_300}  # the paper's nuScenes bank, kept entries per class
MIB = 2**20
PAGE = resource.getpagesize()  # bytes; 4 kB on x86-64 Linux


# ----------------------------------------------------------------- one export (a child process)

def _vmhwm(pid) -> int:
    """Peak resident bytes of a process (0 when it is gone)."""
    try:
        found = re.search(r"^VmHWM:\s+(\d+) kB", Path(f"/proc/{pid}/status").read_text(), re.M)
    except OSError:
        return 0
    return int(found.group(1)) * 1024 if found else 0


def _private(pid) -> int:
    """Resident bytes of a process that no other process shares (0 when it is gone): a
    forked worker's RSS also counts the parent's pages it shares, the objects among them."""
    try:
        rollup = Path(f"/proc/{pid}/smaps_rollup").read_text()
    except OSError:
        return 0
    return 1024 * sum(int(kb) for kb in re.findall(r"^Private_(?:Clean|Dirty):\s+(\d+) kB", rollup, re.M))


def _cpu_s() -> tuple:
    """(user, system) CPU seconds of this process and its reaped children."""
    usages = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
    return sum(u.ru_utime for u in usages), sum(u.ru_stime for u in usages)


class WorkerPoll(threading.Thread):
    """The largest VmHWM and the largest private resident memory of this process's
    children (listed by /proc's per-thread ``children`` files: cheap), polled every
    ``interval`` seconds; ``cpu_s`` its own (user, system) CPU seconds once stopped
    (reading smaps_rollup walks a worker's page tables: about 0.03 ms per entry of a
    full-grid export, the benchmark's cost, not the exporter's)."""

    def __init__(self, interval: float = 0.2):
        super().__init__(daemon=True)
        self.interval, self.peak, self.private, self.stop = interval, 0, 0, threading.Event()
        self.cpu_s = (0.0, 0.0)

    def run(self):
        tasks = Path(f"/proc/{os.getpid()}/task")
        while not self.stop.wait(self.interval):
            for task in tasks.iterdir():
                try:
                    children = (task / "children").read_text().split()
                except OSError:
                    continue
                for pid in children:
                    self.peak, self.private = max(self.peak, _vmhwm(pid)), max(self.private, _private(pid))
        usage = resource.getrusage(resource.RUSAGE_THREAD)
        self.cpu_s = (usage.ru_utime, usage.ru_stime)


def file_write_cost(size: int, folder: Path, processes: int, count: int = 2000) -> dict:
    """This machine's cost of writing ``count`` new files of ``size`` bytes into a new
    folder in ``folder`` (as the bank writes its entries), µs per file: wall, user and
    system CPU; by one process, then by ``processes`` at once into one folder (as the
    exporter's workers do: ``concurrent``), then by one right after deleting the first
    files (``after_deleting``): ext4 without a journal skips the inodes freed in the
    last minutes one by one when it makes a file, so writing soon after deleting many
    files costs more, whatever writes."""
    from concurrent.futures import ProcessPoolExecutor

    files = folder / "file_write_cost"
    files.mkdir()
    alone = _write_files(files, "a", size, count)
    with ProcessPoolExecutor(processes) as pool:
        runs = list(pool.map(_write_files, [files] * processes, [f"c{i}_" for i in range(processes)],
                             [size] * processes, [count] * processes))
    together = {key: float(np.mean([run[key] for run in runs])) for key in alone}
    for path in files.glob("a*"):
        path.unlink()
    return {"bytes": size, "files": count, **alone, "concurrent": together | {"processes": processes},
            "after_deleting": _write_files(files, "b", size, count)}


def page_touch_cost(size: int = 2**30) -> dict:
    """System CPU µs per page (PAGE bytes) of writing ``size`` bytes of newly allocated
    memory, the first time and again right after freeing it. The kernel's own cost is the
    second; on a virtual machine whose host backs guest memory only when it is first
    touched, and takes free memory back (free page reporting), the first includes the
    host's fault, which a new page-cache page pays too."""
    def touch() -> float:
        before = resource.getrusage(resource.RUSAGE_SELF).ru_stime
        block = np.ones(size // 8)
        spent = resource.getrusage(resource.RUSAGE_SELF).ru_stime - before
        del block
        return 1e6 * spent / (size / PAGE)

    return {"bytes": size, "page_bytes": PAGE, "first_us": touch(), "again_us": touch()}


def _write_files(files: Path, prefix: str, size: int, count: int) -> dict:
    """Write ``count`` files of ``size`` random bytes named ``prefix``<i>.bin into
    ``files``: µs per file of wall, user and system CPU of this process."""
    data = os.urandom(size)
    start, before = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
    for index in range(count):
        with open(files / f"{prefix}{index}.bin", "wb") as stream:
            stream.write(data)
    wall, after = time.perf_counter() - start, resource.getrusage(resource.RUSAGE_SELF)
    return {"wall_us": 1e6 * wall / count, "user_us": 1e6 * (after.ru_utime - before.ru_utime) / count,
            "system_us": 1e6 * (after.ru_stime - before.ru_stime) / count}


def disk_usage(out: Path) -> dict:
    """Allocated bytes and file counts of the bank, by part."""
    parts = {}
    for path in (p for p in out.rglob("*") if p.is_file()):
        relative = path.relative_to(out).as_posix()
        part = ("work records" if relative.startswith(".work/") else "manifest" if relative == "manifest.json"
                else "info pickles" if relative.endswith(".pkl") else "database .bin")
        bucket = parts.setdefault(part, {"files": 0, "allocated": 0})
        bucket["files"] += 1
        bucket["allocated"] += path.stat().st_blocks * 512
    return parts


def child(spec: dict) -> dict:
    """One export as ``spec`` says, measured; runs in its own process."""
    from pgt_blender.core.bank.config import BankConfig
    from pgt_blender.core.bank.inputs import checked_objects, prepared_objects
    from pgt_blender.core.gt_database import load_infos

    config = BankConfig(**{key: tuple(v) if isinstance(v, list) else v for key, v in spec["config"].items()})
    objects = []
    for source in spec["folders"]:
        objects += checked_objects(*prepared_objects(source), False, source)
    out = Path(spec["out"])  # kept until the benchmark ends (file_write_cost says why)
    plan = export.plan_bank(objects, config, out)
    poll = WorkerPoll()
    poll.start()
    load, start, (user, system) = os.getloadavg()[0], time.perf_counter(), _cpu_s()
    stages = dict.fromkeys(export.CHUNK_STAGES, 0.0)
    poses = 0
    address = spec.get("address")
    for chunk in export.run_plan(plan, spec["workers"], "ray" if address else "local", address):
        poses += chunk.entries
        for stage, seconds in chunk.seconds.items():
            stages[stage] += seconds
    seconds = time.perf_counter() - start
    poll.stop.set()
    poll.join()
    user_end, system_end = np.subtract(_cpu_s(), poll.cpu_s)
    result = {"export_s": seconds, "export_cpu_s": user_end - user + system_end - system,
              "export_system_s": system_end - system, "load_1min": load, "stages_s": stages}
    manifest = export.assemble(out)
    infos = load_infos(out / manifest["info_pickles"][config.formats[0]])
    points = [info["num_points_in_gt"] for entries in infos.values() for info in entries]
    return result | {"poses": poses, "kept": manifest["entries"], "disk": disk_usage(out),
                     "manifest_sha256": hashlib.sha256((out / "manifest.json").read_bytes()).hexdigest(),
                     "parent_max_rss": _vmhwm(os.getpid()),
                     "workers_max_rss": poll.peak, "workers_max_private": poll.private,
                     "points_per_entry": float(np.mean(points or [0]))}


def export_once(folders: list, config: dict, workers: int, scratch: Path, address: str | None = None,
                env: dict | None = None) -> dict:
    """One measured export in a fresh Python process into a new folder in ``scratch``:
    on ``workers`` local processes, or with ``address`` on that Ray cluster (``env``:
    the driver's environment, e.g. its token settings). The bank stays until the caller
    removes ``scratch`` (file_write_cost: deleting files slows the next export's writes)."""
    with tempfile.NamedTemporaryFile("r", suffix=".json") as result:
        spec = {"folders": [str(f) for f in folders], "config": config, "workers": workers, "result": result.name,
                "address": address, "out": tempfile.mkdtemp(prefix="bank_", dir=scratch)}
        done = subprocess.run([sys.executable, __file__, "--child", json.dumps(spec)], cwd=ROOT,
                              capture_output=True, text=True, env=env)
        if done.returncode:
            raise RuntimeError(f"export child failed:\n{done.stdout}\n{done.stderr}")
        return json.loads(Path(result.name).read_text())


# ----------------------------------------------------------------- the objects

def make_objects(scratch: Path, chrono: Path, subdivided: bool) -> dict:
    """name -> {folder of one prepared object, its description}."""
    import trimesh

    from pgt_blender.core.authoring.prepare import prepare, write_prepared
    from pgt_blender.core.importing import load_reconstruction
    from pgt_blender.core.samples import write_sample

    sources = {}
    if chrono.is_file():
        shown = dev.shown_path(chrono)
        sources["chrono truck 11k"] = (chrono, shown, dict(up="+z", heading_method="none", size="keep"))
        if subdivided:
            mesh = trimesh.load(chrono, force="mesh", process=False)
            fine = scratch / "truck_chassis_176k.ply"
            fine.write_bytes(trimesh.Trimesh(*trimesh.remesh.subdivide(*trimesh.remesh.subdivide(
                mesh.vertices, mesh.faces)), process=False).export(file_type="ply"))
            sources[TARGET_OBJECT] = (fine, f"{shown}, trimesh.remesh.subdivide x2 (the same surface)",
                                      dict(up="+z", heading_method="none", size="keep"))
    else:
        print(f"note: no Chrono truck at {chrono}; only the sample truck is measured\n")
    sample = write_sample(scratch / "sample_files", "truck")["reconstruction.ply"]
    sources["sample truck (surfels)"] = (sample, "core.samples.write_sample('truck') reconstruction",
                                         dict(up="+z", heading_method="baseline"))
    objects = {}
    for index, (name, (path, shown, steps)) in enumerate(sources.items()):
        folder = scratch / f"object{index}"
        authored = prepare(load_reconstruction(path), "truck", **steps)
        write_prepared(authored, "truck", "nuscenes", folder)
        sidecar = authored.sidecar("truck", "nuscenes")
        objects[name] = {"folder": folder, "source": f"{shown}; {steps}", "points": int(sidecar["points"]),
                         "dims_m": [round(float(d), 3) for d in sidecar["dims"]]}
    return objects


def copies(folder: Path, count: int, scratch: Path) -> Path:
    """A folder with ``count`` hard-linked copies of the prepared object in ``folder``."""
    target = scratch / f"{folder.name}_x{count}"
    target.mkdir()
    ply = next(folder.glob("*.ply"))
    for index in range(count):
        for suffix in (".ply", ".json"):
            os.link(ply.with_suffix(suffix), target / f"{ply.stem}_copy{index}{suffix}")
    return target


# ----------------------------------------------------------------- summaries

def throughput_row(name: str, grid: str, workers: int, runs: list) -> dict:
    first, seconds = runs[0], float(np.median([r["export_s"] for r in runs]))
    kept = first["kept"]
    stages = {stage: float(np.median([r["stages_s"][stage] for r in runs])) for stage in first["stages_s"]}
    cpu_ms = 1e3 * float(np.median([r["export_cpu_s"] for r in runs])) / first["poses"]
    system_ms = 1e3 * float(np.median([r["export_system_s"] for r in runs])) / first["poses"]
    cast_ms = 1e3 * stages["casts"] / first["poses"]
    return {"object": name, "grid": grid, "workers": workers, "poses": first["poses"], "kept": kept,
            "runs": len(runs), "export_s": seconds, "kept_per_s": kept / seconds, "cpu_ms_per_entry": cpu_ms,
            "system_ms_per_entry": system_ms,
            "cast_ms_per_entry": cast_ms, "engine_ratio": cpu_ms / cast_ms if cast_ms else None,
            "user_engine_ratio": (cpu_ms - system_ms) / cast_ms if cast_ms else None,
            "engine_ratio_runs": [r["export_cpu_s"] / r["stages_s"]["casts"] if r["stages_s"]["casts"] else None
                                  for r in runs],
            "stages_ms_per_entry": {stage: 1e3 * s / first["poses"] for stage, s in stages.items()},
            "load_1min": [round(r["load_1min"], 2) for r in runs], "parent_max_rss": first["parent_max_rss"],
            "workers_max_rss": first["workers_max_rss"] if workers > 1 else None,
            "workers_max_private": first["workers_max_private"] if workers > 1 else None,
            "points_per_entry": first["points_per_entry"],
            "bytes_per_entry": sum(p["allocated"] for p in first["disk"].values()) / max(kept, 1), "disk": first["disk"]}


def projection(throughput: list) -> list:
    """The paper's bank at each object's kept entries/s on all cores (full grid when run)."""
    total, cores = sum(PAPER_BANK.values()), max(r["workers"] for r in throughput)
    rows = []
    for name in dict.fromkeys(r["object"] for r in throughput):
        mine = [r for r in throughput if r["object"] == name and r["workers"] == cores]
        row = next((r for r in mine if r["grid"] == "full"), mine[0])
        rows.append({"object": name, "grid": row["grid"], "kept_per_s": row["kept_per_s"],
                     "minutes": total / row["kept_per_s"] / 60, "disk_gb": total * row["bytes_per_entry"] / 1e9})
    return rows


def target_summary(throughput: list) -> dict | None:
    cores = max(r["workers"] for r in throughput)
    mine = [r for r in throughput if r["object"] == TARGET_OBJECT and r["workers"] == cores]
    if not mine:
        return None
    row = next((r for r in mine if r["grid"] == "full"), mine[0])
    return {"object": TARGET_OBJECT, "workers": cores, "grid": row["grid"], "kept_per_s": row["kept_per_s"],
            "engine_ratio": row["engine_ratio"], "engine_ratio_runs": row["engine_ratio_runs"],
            "meets_rate": bool(row["kept_per_s"] >= TARGET_ENTRIES_PER_S),
            "meets_ratio": bool(row["engine_ratio"] is not None and row["engine_ratio"] <= TARGET_ENGINE_RATIO)}


def target_line(target: dict | None, quick: bool) -> str:
    if target is None:
        return f"target: not measured ({'--quick leaves the 176k truck out' if quick else 'no Chrono truck'})"
    return (f"target: >= {TARGET_ENTRIES_PER_S:g} kept entries/s and CPU per entry <= {TARGET_ENGINE_RATIO:g}x the "
            f"cast time, {target['object']}, {target['grid']} grid, {target['workers']} cores: "
            f"{target['kept_per_s']:.0f}/s ({'meets' if target['meets_rate'] else 'MISSES'}), ratio "
            f"{target['engine_ratio']:.1f}x ({'meets' if target['meets_ratio'] else 'MISSES'}; runs "
            f"{', '.join(f'{ratio:.1f}x' for ratio in target['engine_ratio_runs'])})")


def mb(value) -> str:
    return "-" if value is None else f"{value / MIB:,.0f}"


def tables(throughput: list, series: list, projected: list, files: dict, pages: dict) -> str:
    stages = list(export.CHUNK_STAGES)
    text = "## throughput\n\n" + dev.markdown_table(
        ["object", "grid", "workers", "poses", "kept", "s (median of n)", "kept/s", "CPU ms/entry",
         "of which system", "cast ms/entry", "CPU / cast", "user CPU / cast", "parent max RSS MB",
         "worker max RSS MB", "worker max private MB", "kB/entry"],
        [[r["object"], r["grid"], r["workers"], f"{r['poses']:,}", f"{r['kept']:,}",
          f"{r['export_s']:.2f} ({r['runs']})", f"{r['kept_per_s']:.0f}", f"{r['cpu_ms_per_entry']:.2f}",
          f"{r['system_ms_per_entry']:.2f}", f"{r['cast_ms_per_entry']:.2f}",
          *("-" if r[ratio] is None else f"{r[ratio]:.1f}x" for ratio in ("engine_ratio", "user_engine_ratio")),
          mb(r["parent_max_rss"]), mb(r["workers_max_rss"]), mb(r["workers_max_private"]),
          f"{r['bytes_per_entry'] / 1e3:,.1f}"] for r in throughput], "ll" + "r" * 14)
    together, again = files["concurrent"], files["after_deleting"]
    text += (f"\n\nThis machine's cost of writing a new file of {files['bytes'] / 1e3:.0f} kB (one format's "
             f"entry) into a new folder, {files['files']:,} files: {files['wall_us']:.0f} µs wall, "
             f"{files['user_us']:.0f} µs user and {files['system_us']:.0f} µs system CPU per file by one process; "
             f"{together['wall_us']:.0f} µs wall and {together['system_us']:.0f} µs system each by "
             f"{together['processes']} processes at once; by one right after deleting the first files, "
             f"{again['wall_us']:.0f} µs wall and {again['system_us']:.0f} µs system (file_write_cost: ext4 "
             f"without a journal steps over recently freed inodes; so the benchmark deletes its banks only at "
             f"its end). An entry writes one file per format.")
    text += (f" Each new page of memory ({pages['page_bytes'] // 1024} kB; page_touch_cost, {pages['bytes'] / MIB:,.0f} MB written) cost "
             f"{pages['first_us']:.2f} µs of system CPU the first time and {pages['again_us']:.2f} µs again right "
             f"after freeing it: where the first is many times the second, the host backs the guest's memory only "
             f"on first touch and takes free memory back; the export frees each chunk's page-cache pages once "
             f"written back (folder.drop_cached), so later chunks reuse them rather than pay that first touch.")
    text += ("\n\n## where a worker's time goes (export.ChunkDone stages, ms per entry; casts are part of scans)\n\n"
             + dev.markdown_table(["object", "grid", "workers", *stages],
                                  [[r["object"], r["grid"], r["workers"],
                                    *(f"{r['stages_ms_per_entry'][s]:.3f}" for s in stages)]
                                   for r in throughput], "ll" + "r" * (1 + len(stages))))
    text += "\n\n## memory against the bank size (all cores)\n\n" + dev.markdown_table(
        ["objects", "kept", "s", "parent max RSS MB", "worker max RSS MB", "worker max private MB",
         "bank on disk MB"],
        [[r["objects"], f"{r['kept']:,}", f"{r['export_s']:.1f}", mb(r["parent_max_rss"]), mb(r["workers_max_rss"]),
          mb(r["workers_max_private"]), f"{sum(p['allocated'] for p in r['disk'].values()) / MIB:,.1f}"]
         for r in series])
    text += ("\n\nA forked worker's RSS counts the pages it shares with the parent (the objects' geometry: "
             "they grow with the objects, not with the entries); its private memory is its own: the "
             "runtime, its object's ray target and one chunk's arrays (they grow with chunk_size).")
    text += (f"\n\n## the paper's nuScenes bank ({sum(PAPER_BANK.values()):,} entries) on this machine\n\n"
             + dev.markdown_table(["entries like", "grid", "kept/s", "minutes", "disk GB"],
                                  [[r["object"], r["grid"], f"{r['kept_per_s']:.0f}", f"{r['minutes']:.1f}",
                                    f"{r['disk_gb']:.1f}"] for r in projected]))
    return text + "\n"


def plot(throughput: list, series: list, series_object: str):
    def draw(plt):
        figure, axes = plt.subplots(1, 2, figsize=(15, 5.5))
        x = np.arange(len(throughput))
        axes[0].bar(x, [r["kept_per_s"] for r in throughput], 0.6)
        axes[0].axhline(TARGET_ENTRIES_PER_S, color="k", ls="--", lw=1, label=f"target {TARGET_ENTRIES_PER_S:g}/s")
        axes[0].set_xticks(x, [f"{r['object']}\n{r['grid']}, {r['workers']} w" for r in throughput], fontsize=7,
                           rotation=30, ha="right")
        axes[0].set(ylabel="kept entries per second (median of runs)", title="bank export, nuScenes settings")
        axes[0].legend(fontsize=8)
        kept = [r["kept"] for r in series]
        for key, label in (("parent_max_rss", "parent max RSS"), ("workers_max_rss", "worker max RSS (VmHWM)"),
                           ("workers_max_private", "worker max private")):
            axes[1].plot(kept, [r[key] / MIB for r in series], "o-", label=label)
        axes[1].set(xlabel=f"bank size, kept entries (copies of {series_object})", ylabel="MiB",
                    title="peak memory against the bank size (all cores)")
        axes[1].grid(alpha=0.3)
        axes[1].legend(fontsize=8)
        return figure
    return draw


def main(argv: list) -> int:
    parser = cli.parser("bench_bank.py", __doc__)
    parser.add_argument("--quick", action="store_true", help="a smoke test: no 176k truck, 108-pose grid, "
                        "1 run each, 1 and 2 copies, no full grid")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per object and worker count")
    parser.add_argument("--chrono", type=Path, default=CHRONO_TRUCK, help="the Chrono truck chassis .obj")
    parser.add_argument("--engine", choices=ENGINES, default="auto", help="the bank's ray engine (config scan.engine)")
    parser.add_argument("--out", type=Path, help="default: bench/bank_<engine used>")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        spec = json.loads(args.child)
        Path(spec["result"]).write_text(json.dumps(child(spec)))
        return 0
    args.engine = resolve_engine(args.engine)
    args.out = args.out or ROOT / "bench" / f"bank_{args.engine}"
    repeats = 1 if args.quick else args.repeats
    grid = "quick" if args.quick else "thinned"
    subset = (QUICK_SUBSET if args.quick else SUBSET) | {"engine": args.engine}
    workers = sorted({1, os.cpu_count() or 1})
    import bpy  # the BVH engine's library (each export process loads its own)

    machine = dev.machine(numpy=np.__version__, bpy=bpy.app.version_string, engine=args.engine)
    print(f"machine: {machine}\n", flush=True)
    load_before, started = dev.load_average(), time.perf_counter()
    pages = page_touch_cost()
    with tempfile.TemporaryDirectory(prefix="bench_bank_objects_") as scratch:
        scratch = Path(scratch)
        objects = make_objects(scratch, args.chrono, subdivided=not args.quick)
        throughput = []
        for name, entry in objects.items():
            for count in workers:
                runs = [export_once([entry["folder"]], subset, count, scratch) for _ in range(repeats)]
                throughput.append(throughput_row(name, grid, count, runs))
                print(f"{name}, {count} worker(s): {throughput[-1]['kept_per_s']:.0f} kept/s", flush=True)
            if not args.quick:
                runs = [export_once([entry["folder"]], {"engine": args.engine}, workers[-1], scratch)
                        for _ in range(repeats)]
                throughput.append(throughput_row(name, "full", workers[-1], runs))
                print(f"{name}, full grid: {throughput[-1]['kept_per_s']:.0f} kept/s", flush=True)
        series_object = TARGET_OBJECT if TARGET_OBJECT in objects else next(iter(objects))
        series = []
        for count in (1, 2) if args.quick else (1, 2, 4, 8):
            run = export_once([copies(objects[series_object]["folder"], count, scratch)], subset, workers[-1],
                              scratch)
            series.append(run | {"objects": count})
        database = next(r for r in throughput if r["object"] == series_object)["disk"]["database .bin"]
        files = file_write_cost(int(database["allocated"] / database["files"]), scratch, workers[-1])
    inputs = {"objects": {name: f"{o['source']}; {o['points']:,} points; box {o['dims_m']} m"
                          for name, o in objects.items()},
              "config": f"BankConfig() with engine {args.engine}; {grid} grid: headings {subset['headings_deg']}, "
                        f"x {subset['x']}, y {subset['y']}, chunk_size {subset['chunk_size']}"
                        + ("" if args.quick else "; full grid: BankConfig() as is, on all cores"),
              "runs": f"median of {repeats} per object and worker count, each a fresh process; workers {workers}",
              "paper bank": ", ".join(f"{k} {v:,}" for k, v in PAPER_BANK.items()),
              "run": f"{time.perf_counter() - started:.0f} s; load average before {load_before}, after "
                     f"{dev.load_average()} (other work on the machine inflates the times: upper bounds)"}
    projected, target = projection(throughput), target_summary(throughput)

    body, line = tables(throughput, series, projected, files, pages), target_line(target, args.quick)
    print("\n" + body + "\n" + line)
    dev.write_report(args.out, "Bank export: throughput, stages and memory at nuScenes settings", "bench_bank.py",
                     machine, inputs, f"**{line}**\n\n{body}",
                     {"machine": machine, "inputs": inputs, "throughput": throughput, "file_writes": files,
                      "page_touch": pages,
                      "memory_series": series, "projection": projected, "target": target},
                     plot(throughput, series, series_object))
    return 0


if __name__ == "__main__":
    cli.exit(cli.run_main(main, cli.script_argv()))
