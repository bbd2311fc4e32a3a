"""Export a bank: entries in chunks, on any executor, resumable, then one assembly.

Output folder::

    OUT/manifest.json                           config, objects, versions, counts, sha256 per file
    OUT/<format>/<dataset>_dbinfos_pgt.pkl      the info pickle (formats.py)
    OUT/<format>/pgt_gt_database/<object>_<class>_<index>.bin
    OUT/.work/identity.json                     what this bank is made of (checked on --resume)
    OUT/.work/chunks/<chunk>.json               one chunk's infos, file checksums and statistics (records.py)

A chunk is ``chunk_size`` consecutive entries (objects in name order, each in grid
order). Each chunk's .bin files are written first, its record last, each file
atomically, so a chunk is done exactly when its record exists: a killed run resumes
with the chunks that have none, and since every entry is a function of the config and
its own seed, the bank ends byte-identical whatever the workers, shards or restarts.
The pickles and the manifest are written last, from the records, in chunk order.
"""

import hashlib
import json
import os
import pickle
import shutil
import sys
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import atomic_output
from ..scan.sensors import INTENSITY_MAX, sensor_from_name
from ..scan.sweeps import motion_class
from .config import BankConfig
from .entries import TargetCache, scan_entry
from .formats import DATABASE_CLASSES, DATABASE_FOLDER, class_name_for, database_record, entry_points
from .grid import object_entries, sweeps_of
from .inputs import BankObject, safe_name
from .records import read_record, write_record

WORK = ".work"
MANIFEST = "manifest.json"
INTENSITY_BINS = 32  # the report's per-class intensity histograms, over the dataset's range

STATS_DTYPE = np.dtype([("object", "i4"), ("index", "i4"), ("x", "f4"), ("y", "f4"), ("heading", "f4"),
                        ("points", "i4"), ("kept", "?")])


@dataclass
class BankJob:
    """Everything a worker needs: the objects, the config, the output folder."""

    objects: list
    config: BankConfig
    out: Path
    class_names: list = field(default_factory=list)  # per object: the dataset's class name

    @cached_property
    def sensor(self):
        """The bank's sensor, read once (its ray table is cached on it)."""
        return sensor_from_name(self.config.sensor or self.config.dataset)

    def entries(self) -> np.ndarray:
        """Every entry of the bank, object by object (grid.ENTRY_DTYPE)."""
        return np.concatenate([object_entries(self.config, i, motion_class(obj.class_name, name), obj.dims)
                               for i, (obj, name) in enumerate(zip(self.objects, self.class_names))])

    def chunks(self, entries: np.ndarray) -> list:
        size = self.config.chunk_size
        return [entries[start:start + size] for start in range(0, len(entries), size)]


def new_job(objects: list, config: BankConfig, out) -> BankJob:
    """A job for ``objects`` (checked BankObjects); InputError for a class without a
    dataset name, an unusable sensor or intensity checkpoint."""
    names = [class_name_for(config.dataset, obj.class_name, config.classes) for obj in objects]
    unnamed = sorted({obj.class_name for obj, name in zip(objects, names) if name is None})
    if unnamed:
        raise InputError(out, f"no {config.dataset} class for {', '.join(unnamed)}: name one in the config's "
                              f"[classes] table (\"\" skips the class)")
    job = BankJob([obj for obj, name in zip(objects, names) if name], config, Path(out),
                  [name for name in names if name])
    if not job.objects:
        raise InputError(out, "every object's class is skipped by the config's [classes] table")
    still = sorted({obj.class_name for obj, name in zip(job.objects, job.class_names)
                    if not motion_class(obj.class_name, name)})
    if still and sweeps_of(config) > 1:
        raise InputError(out, f"no motion model for {', '.join(still)} (nor for the {config.dataset} name it maps to): "
                              f"map it to a class of {', '.join(DATABASE_CLASSES[config.dataset])} in [classes]")
    if job.sensor.dataset != config.dataset:
        raise InputError(config.sensor, f"is a {job.sensor.dataset} sensor, the bank is {config.dataset}")
    if config.intensity_checkpoint:
        _estimator(config)  # fails now, not in a worker
    if config.engine == "embree":
        try:
            import embreex  # noqa: F401  (only whether it imports)
        except ImportError:
            raise InputError(out, "the config asks for the embree engine: pip install embreex") from None
    return job


def identity(job: BankJob, chunk_count: int) -> dict:
    """What the bank is made of: equal identities give equal banks."""
    return {"config": job.config.to_dict(), "objects": [obj.summary() for obj in job.objects],
            "class_names": job.class_names, "chunks": chunk_count}


def prepare_folder(out: Path, ident: dict, resume: bool, overwrite: bool, shared: bool = False) -> None:
    """Make ``out`` ready: new or empty; with ``overwrite`` an earlier bank there is
    removed; with ``resume`` (or ``shared``, for shards) an unfinished bank of the same
    identity is continued. Anything else is refused with InputError."""
    marker = out / WORK / "identity.json"
    if out.exists() and not out.is_dir():
        raise InputError(out, "is a file, not an output folder")
    if _cut_short(out):
        shutil.rmtree(out / WORK)
    if out.is_dir() and any(out.iterdir()):
        is_bank = marker.is_file() or (out / MANIFEST).is_file()
        if overwrite:
            if not is_bank:
                raise InputError(out, "is not empty and holds no bank: refusing to delete it; choose another --out")
            for child in out.iterdir():
                shutil.rmtree(child) if child.is_dir() else child.unlink()
        elif resume or shared:
            if not marker.is_file():
                raise InputError(out, "holds no unfinished bank to resume (no .work/identity.json)")
            if read_identity(out) != ident:
                raise InputError(out, "holds a bank of other objects or settings; use --overwrite or another --out")
            return
        else:
            raise InputError(out, "is not empty: pass --resume to continue the bank there or --overwrite to replace it")
    (out / WORK / "chunks").mkdir(parents=True, exist_ok=True)
    with atomic_output(marker) as stream:
        stream.write(json.dumps(ident, indent=1).encode())


def _cut_short(out: Path) -> bool:
    """True for a folder holding only the empty .work/chunks an export makes before its
    identity: a start cut short (a full disk), with nothing in it to keep."""
    def names(folder: Path) -> list:
        return sorted(child.name for child in folder.iterdir()) if folder.is_dir() else []

    return names(out) == [WORK] and names(out / WORK) == ["chunks"] and not names(out / WORK / "chunks")


def read_identity(out: Path) -> dict:
    """OUT/.work/identity.json; InputError naming the file when it is missing or damaged."""
    path = out / WORK / "identity.json"
    if not path.is_file():
        raise InputError(out, f"is not a bank folder: no {WORK}/identity.json")
    try:
        ident = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InputError(path, f"damaged ({type(error).__name__}: {error}); --overwrite starts the bank "
                               f"anew") from None
    if not (isinstance(ident, dict) and {"config", "objects", "class_names", "chunks"} <= ident.keys()):
        raise InputError(path, "not a bank identity (config, objects, class_names, chunks); --overwrite starts "
                               "the bank anew")
    return ident


def chunk_record_path(out: Path, chunk_id: int) -> Path:
    return out / WORK / "chunks" / f"{chunk_id:06d}.json"


def chunk_record(out: Path, chunk_id: int, path: Path | None = None) -> dict | None:
    """The record of chunk ``chunk_id`` (read from ``path``, default its place in OUT),
    or None when it is missing or damaged: such a chunk is not done and is redone.
    Checked field by field."""
    path = chunk_record_path(out, chunk_id) if path is None else path
    if not path.is_file():
        return None
    try:
        record = read_record(path)
    except (OSError, ValueError, TypeError, KeyError):  # what damaged JSON or array fields raise
        return None
    fields = {"chunk": int, "infos": dict, "files": dict, "stats": np.ndarray, "intensity": dict}
    whole = isinstance(record, dict) and all(isinstance(record.get(key), kind) for key, kind in fields.items()) \
        and record["chunk"] == chunk_id and record["stats"].dtype == STATS_DTYPE \
        and all(isinstance(infos, list) and all(isinstance(info, dict) for info in infos)
                for infos in record["infos"].values()) \
        and all(isinstance(name, str) and isinstance(digest, str) for name, digest in record["files"].items())
    return record if whole else None


def pending_chunks(out: Path, chunk_count: int, shard=(0, 1)) -> list:
    """The chunk ids of this shard (id % count == index) without a whole record."""
    index, count = shard
    return [i for i in range(index, chunk_count, count) if chunk_record(out, i) is None]


@dataclass
class Plan:
    """A bank ready to run: its job, every chunk of entries, the chunk ids left to do."""

    job: BankJob
    chunks: list
    pending: list

    @property
    def pending_entries(self) -> int:
        return sum(len(self.chunks[i]) for i in self.pending)


def plan_bank(objects: list, config: BankConfig, out, resume: bool = False, overwrite: bool = False,
              shard=None) -> Plan:
    """Check the inputs, ready the output folder (see ``prepare_folder``) and list the
    chunks to do; ``shard`` (i, n) keeps chunk ids = i mod n."""
    job = new_job(objects, config, out)
    entries = job.entries()
    if not len(entries):
        raise InputError(out, "the grid leaves no pose: every position is beyond max_distance or within "
                              "ego_clearance of the sensor; widen [grid] or relax those")
    chunks = job.chunks(entries)
    prepare_folder(job.out, identity(job, len(chunks)), resume, overwrite, shared=shard is not None)
    return Plan(job, chunks, pending_chunks(job.out, len(chunks), shard or (0, 1)))


def run_plan(plan: Plan, workers: int = 1, executor: str = "local", address: str | None = None):
    """Export the pending chunks; yields each one's entry count as it finishes."""
    if executor == "ray":
        return run_ray(plan.job, plan.chunks, plan.pending, address)
    return run_local(plan.job, plan.chunks, plan.pending, workers)


def export_bank(objects: list, config: BankConfig, out, workers: int = 1, overwrite: bool = False,
                data_root=None) -> dict:
    """The whole export in one call (no progress bar): returns the manifest. ``data_root``:
    see ``assemble``."""
    plan = plan_bank(objects, config, out, overwrite=overwrite)
    for _ in run_plan(plan, workers):
        pass
    return assemble(plan.job.out, data_root)


# One job per worker process, set by the pool's initializer (or before a fork).
_job: BankJob | None = None
_cache: TargetCache | None = None


def start_worker(job: BankJob) -> None:
    global _job, _cache
    if "bpy" not in sys.modules:
        # A spawned worker inherits the parent's sys.path, to which the bpy module added
        # its scripts folders; their "bpy" package would shadow the module itself.
        sys.path[:] = [path for path in sys.path if Path(path).parent.name != "scripts"]
    _job, _cache = job, TargetCache(job.objects, job.config)


def run_chunk(chunk_id: int, entries: np.ndarray) -> int:
    """Export one chunk in this worker (``start_worker`` first); returns its entry count."""
    write_chunk(_job, _cache, chunk_id, entries)
    return len(entries)


def write_chunk(job: BankJob, cache: TargetCache, chunk_id: int, entries: np.ndarray) -> None:
    """Scan ``entries``, write their .bin files in every format, then the chunk record."""
    config, sensor = job.config, job.sensor
    infos = {fmt: [] for fmt in config.formats}
    files, stats = {}, np.zeros(len(entries), STATS_DTYPE)
    histograms = {}
    for row, entry in zip(stats, entries):
        obj: BankObject = job.objects[entry["object"]]
        scan, keep = scan_entry(cache, sensor, entry, config)
        rows = scan.returns[keep]
        row["object"], row["index"], row["heading"] = entry["object"], entry["index"], entry["heading"]
        row["x"], row["y"], row["points"] = scan.box[0], scan.box[1], len(rows)
        row["kept"] = len(rows) >= config.min_points
        if not row["kept"]:
            continue
        if config.constant_intensity is not None:
            rows["intensity"] = config.constant_intensity
        elif config.intensity_checkpoint:
            rows["intensity"] = _learned_intensity(config, cache, entry, obj, scan, keep)
        class_name = job.class_names[entry["object"]]
        name = f"{safe_name(obj.name)}_{safe_name(class_name)}_{int(entry['index']):05d}.bin"
        shared = {"name": class_name, "path": f"{DATABASE_FOLDER}/{name}", "image_idx": _group_id(entry),
                  "pgt_object": obj.name, "gt_idx": int(entry["index"])}
        points = entry_points(rows, config.dataset)
        for fmt in config.formats:
            data, info = database_record(fmt, config.dataset, points, scan.box, shared)
            relative = f"{fmt}/{info['path']}"
            files[relative] = _write_bytes(job.out / relative, data.tobytes())
            infos[fmt].append(info)
        histogram = histograms.setdefault(class_name, np.zeros(INTENSITY_BINS, np.int64))
        histogram += np.histogram(rows["intensity"], INTENSITY_BINS, (0.0, INTENSITY_MAX[config.dataset]))[0]
    record = {"chunk": chunk_id, "infos": infos, "files": files, "stats": stats, "intensity": histograms}
    _write_bytes(chunk_record_path(job.out, chunk_id), write_record(record))


def _group_id(entry) -> int:
    """Unique over the bank: objects' grids never exceed 2**24 entries."""
    return int(entry["object"]) * 2**24 + int(entry["index"])


def _write_bytes(path: Path, data: bytes) -> str:
    """Write ``data`` atomically (parents made) and return its sha256."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as stream:
        stream.write(data)
    return hashlib.sha256(data).hexdigest()


_estimators: dict = {}


def _estimator(config: BankConfig):
    from ..intensity.estimator import IntensityEstimator

    if config.intensity_checkpoint not in _estimators:
        _estimators[config.intensity_checkpoint] = IntensityEstimator.load(config.intensity_checkpoint,
                                                                           config.dataset)
    return _estimators[config.intensity_checkpoint]


def _learned_intensity(config: BankConfig, cache: TargetCache, entry, obj: BankObject, scan, keep) -> np.ndarray:
    """The estimator's intensities (dataset scale) for the kept returns
    (intensity/estimator.scan_intensity). One object per call: the same numbers whatever
    the chunking."""
    import torch

    from ..intensity.estimator import scan_intensity

    torch.set_num_threads(1)  # float sums in a fixed order: the same bytes on any machine load
    _, bounds = cache.get(int(entry["object"]), int(entry["variant"]))
    values, _ = scan_intensity(scan, bounds, cache.element_rgb(int(entry["object"])), obj.class_name,
                               _estimator(config), keep, obj.name)
    return values


def assemble(out: Path, data_root=None) -> dict:
    """Write every format's info pickle and then the manifest from the chunk records
    (all must exist: InputError names the missing ones). Returns the manifest.

    Info paths: both frameworks join ``path`` to their dataset root (OpenPCDet
    ``root_path / path``, where root_path is DATA_PATH for KITTI and DATA_PATH/VERSION
    for nuScenes and Lyft; mmdet3d ``os.path.join(data_root, path)``). Without
    ``data_root`` paths are relative to the format folder (``OUT/<format>``: give that
    folder as the root); with it they are relative to ``data_root`` (``..`` where the
    bank lies outside it), so the bank sits beside the real database. The manifest's
    ``data_root`` records it relative to OUT (None: the format folders)."""
    ident = read_identity(out)
    config = ident["config"]
    missing = [i for i in range(ident["chunks"]) if not chunk_record_path(out, i).is_file()]
    if missing:
        raise InputError(out, f"{len(missing)} of {ident['chunks']} chunks not exported yet "
                              f"(first: {missing[0]}); run the missing shards or --resume")
    damaged = [i for i in range(ident["chunks"]) if chunk_record(out, i) is None]
    if damaged:
        raise InputError(chunk_record_path(out, damaged[0]), f"damaged ({len(damaged)} chunk record(s)); "
                                                             f"--resume redoes them")
    # A list for every class of the dataset: the samplers index the pickle by each class they sample.
    infos = {fmt: {name: [] for name in DATABASE_CLASSES[config["dataset"]]} for fmt in config["formats"]}
    prefixes = {fmt: _path_prefix(out / fmt, data_root) for fmt in config["formats"]}
    files, counts, dropped = {}, {}, {}
    for chunk_id in range(ident["chunks"]):
        record = chunk_record(out, chunk_id)
        for fmt, entries in record["infos"].items():
            for info in entries:
                infos[fmt].setdefault(info["name"], []).append(dict(info, path=prefixes[fmt] + info["path"]))
        files.update(record["files"])
        for row in record["stats"]:
            name = ident["class_names"][row["object"]]
            bucket = counts if row["kept"] else dropped
            bucket[name] = bucket.get(name, 0) + 1
    if not counts:
        raise InputError(out, f"no entry kept: all {sum(dropped.values()):,} poses had fewer than "
                              f"{config['min_points']} points in their box; lower bank.min_points or bring the "
                              f"grid closer")
    pickle_name = f"{config['dataset']}_dbinfos_pgt.pkl"
    for fmt, by_class in infos.items():
        relative = f"{fmt}/{pickle_name}"
        files[relative] = _write_bytes(out / relative, pickle.dumps(by_class, protocol=4))
    manifest = {
        "pgt_blender": _version(), "config": config, "seed": config["seed"], "objects": ident["objects"],
        "versions": _library_versions(), "frames": FRAMES,
        "info_pickles": {fmt: f"{fmt}/{pickle_name}" for fmt in config["formats"]},
        "data_root": None if data_root is None else Path(os.path.relpath(Path(data_root).absolute(),
                                                                        out.absolute())).as_posix(),
        "entries": sum(counts.values()), "counts": dict(sorted(counts.items())),
        "dropped_below_min_points": dict(sorted(dropped.items())),
        "files": dict(sorted(files.items())),
    }
    with atomic_output(out / MANIFEST) as stream:
        stream.write(json.dumps(manifest, indent=1).encode())
    return manifest


def info_path_root(info_pickle: Path) -> Path:
    """The folder a bank pickle's info paths are relative to: the data root its
    manifest records (OUT/manifest.json beside OUT/<format>/), else the pickle's folder."""
    manifest = Path(info_pickle).parent.parent / MANIFEST
    try:
        data_root = json.loads(manifest.read_text()).get("data_root")
    except (OSError, ValueError, AttributeError):
        data_root = None
    return Path(info_pickle).parent if data_root is None else manifest.parent / data_root


def _path_prefix(format_folder: Path, data_root) -> str:
    """What goes before an info path relative to its format folder: "" without a
    data root, else the format folder relative to the data root plus "/"."""
    if data_root is None:
        return ""
    if not Path(data_root).is_dir():
        raise InputError(data_root, "the dataset root is not a folder")
    return Path(os.path.relpath(format_folder.absolute(), Path(data_root).absolute())).as_posix() + "/"


FRAMES = ("sensor frame of the dataset's LiDAR (KITTI x forward, y left; nuScenes x right, y forward; z up); "
          "openpcdet: points and box3d_lidar z relative to / at the box centre; mmdet3d: at the box bottom "
          "centre; points keep the sensor's orientation; heading from +x counter-clockwise")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("pgt_blender")
    except PackageNotFoundError:
        return "unknown"


def _library_versions() -> dict:
    import numpy
    import scipy

    versions = {"numpy": numpy.__version__, "scipy": scipy.__version__}
    try:
        import bpy

        versions["blender"] = bpy.app.version_string
    except ImportError:
        pass
    return versions


def copy_shard(source: Path, out: Path) -> int:
    """Copy a shard folder's whole chunk records and their database files into ``out``
    (same identity required); returns the records copied. Damaged records are left:
    their chunks stay to do."""
    if read_identity(source) != read_identity(out):
        raise InputError(source, "is not a shard of this bank (its .work/identity.json differs)")
    copied = 0
    for record_path in sorted((source / WORK / "chunks").glob("*.json")):
        record = chunk_record(source, int(record_path.stem), record_path) if record_path.stem.isdigit() else None
        if record is None:
            continue  # damaged: the chunk stays to do
        for relative in record["files"]:
            target = out / relative
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source / relative, target)
        shutil.copyfile(record_path, out / WORK / "chunks" / record_path.name)  # last: the chunk counts once here
        copied += 1
    return copied


def run_local(job: BankJob, chunks: list, pending: list, workers: int):
    """Yield each pending chunk's entry count as it finishes, on ``workers`` processes
    (1: in this process). Linux forks (the BVH library is already loaded), except for a
    learned intensity: PyTorch's thread pool does not survive a fork, so those workers,
    like every worker elsewhere, are spawned with the job."""
    if workers <= 1 or len(pending) <= 1:
        cache = TargetCache(job.objects, job.config)
        for chunk_id in pending:
            write_chunk(job, cache, chunk_id, chunks[chunk_id])
            yield len(chunks[chunk_id])
        return
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    forks = sys.platform == "linux" and not job.config.intensity_checkpoint
    context = multiprocessing.get_context("fork" if forks else "spawn")
    with ProcessPoolExecutor(workers, context, initializer=start_worker, initargs=(job,)) as pool:
        queue = list(pending)
        running = set()
        while queue or running:
            # A bounded queue: at most two chunks per worker wait, so memory stays flat.
            while queue and len(running) < 2 * workers:
                chunk_id = queue.pop(0)
                running.add(pool.submit(run_chunk, chunk_id, chunks[chunk_id]))
            done, running = wait(running, return_when=FIRST_COMPLETED)
            for future in done:
                yield future.result()


def run_ray(job: BankJob, chunks: list, pending: list, address: str | None):
    """The same chunks as tasks on a Ray cluster (``address`` None: a local one). Every
    node must see ``job.out`` (a shared file system) and have pgt_blender's Python."""
    import ray

    ray.init(address=address, ignore_reinit_error=True, log_to_driver=False,
             runtime_env={"env_vars": {"PYTHONPATH": os.pathsep.join(p for p in _python_path() if p)}})
    try:
        job_ref = ray.put(job)
        remote = ray.remote(_ray_chunk)
        running = [remote.remote(job_ref, chunk_id, chunks[chunk_id]) for chunk_id in pending]
        while running:
            done, running = ray.wait(running, num_returns=1)
            yield ray.get(done[0])
    finally:
        ray.shutdown()


def _python_path() -> list:
    """This process's import path for pgt_blender, so Ray workers find the same code."""
    package_parent = str(Path(__file__).resolve().parents[3])
    return [package_parent, os.environ.get("PYTHONPATH", "")]


def _ray_chunk(job: BankJob, chunk_id: int, entries: np.ndarray) -> int:
    """One chunk as a Ray task: a worker process starts the job on its first task."""
    if _job is None or _job.out != job.out:
        start_worker(job)
    return run_chunk(chunk_id, entries)
