"""Export a bank: a job (objects, config, output folder), its entries in chunks run on
an executor (executors.py), each chunk scanned and written (``write_chunk``), then one
assembly of the info pickles and the manifest (folder layout and life cycle: folder.py).

A chunk is ``chunk_size`` consecutive entries (objects in name order, each in grid
order). Since every entry is a function of the config and its own seed, the bank ends
byte-identical whatever the workers, shards or restarts. The pickles and the manifest
are written last, from the chunk records, in chunk order.
"""

import json
import os
import pickle
import shutil
import time
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import atomic_output
from ..scan.targets import resolve_engine
from ..scan.sensors import INTENSITY_MAX, sensor_files, sensor_from_name
from ..scan.sweeps import motion_class
from . import executors
from .config import BankConfig
from .entries import TargetCache, scan_entries
from .formats import DATABASE_CLASSES, DATABASE_FOLDER, class_name_for, database_record, entry_points
from .grid import object_entries, sweeps_of
from .inputs import BankObject, safe_name
from .folder import (INTENSITY_BINS, MANIFEST, STATS_DTYPE, chunk_record_path, done_chunk, drop_cached,
                     exporting, pending_chunks, prepare_folder, read_identity, write_entry_file, write_file)
from .records import write_record

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
    config = replace(config, engine=resolve_engine(config.engine))  # the bank records the engine it used
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
    if config.intensity_checkpoint:  # fails now, not in a worker's first chunk
        _estimator(config).require_classes(obj.class_name for obj in job.objects)
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
              shard=None, inputs=()) -> Plan:
    """Check the inputs, ready the output folder (see ``prepare_folder``; ``inputs``: the
    files the caller read, which an overwrite must not delete, beside the config's own
    sensor and checkpoint) and list the chunks to do; ``shard`` (i, n) keeps chunk ids =
    i mod n. A caller that exports for a user holds ``out`` first (folder.exporting,
    shared for a shard), as ``export_bank`` does, so that no other export mixes in."""
    job = new_job(objects, config, out)
    entries = job.entries()
    if not len(entries):
        raise InputError(out, "the grid leaves no pose: every position is beyond max_distance or within "
                              "ego_clearance of the sensor; widen [grid] or relax those")
    chunks = job.chunks(entries)
    config_files = [*sensor_files(config.sensor), config.intensity_checkpoint]
    prepare_folder(job.out, identity(job, len(chunks)), resume, overwrite, shared=shard is not None,
                   inputs=[*inputs, *config_files])
    return Plan(job, chunks, pending_chunks(job.out, len(chunks), shard or (0, 1)))


def run_plan(plan: Plan, workers: int = 1, executor: str = "local", address: str | None = None):
    """Export the pending chunks; yields each one's ChunkDone as it finishes."""
    if executor == "ray":
        return executors.run_ray(plan.job, plan.chunks, plan.pending, address, write_chunk)
    return executors.run_local(plan.job, plan.chunks, plan.pending, workers, write_chunk)


def export_bank(objects: list, config: BankConfig, out, workers: int = 1, overwrite: bool = False,
                data_root=None) -> dict:
    """The whole export in one call (no progress bar): returns the manifest. ``data_root``
    and a bank that keeps no entry: see ``assemble``."""
    existed = Path(out).exists()
    with exporting(Path(out)):
        plan = plan_bank(objects, config, out, overwrite=overwrite)
        for _ in run_plan(plan, workers):
            pass
        return assemble(plan.job.out, data_root, existed)


CHUNK_STAGES = ("targets", "scans", "casts", "intensity", "records", "writes")


@dataclass
class ChunkDone:
    """One written chunk: its entry count and the wall seconds of its stages, as the
    executors report them (benchmarks sum them; nothing in the bank depends on them).

    targets:   building the object variants' ray targets (BVH / Embree), first use only;
    scans:     the entries' sweeps (scan_entries: rays, casts, returns, noise, drop, box crop);
    casts:     the part of ``scans`` spent in the ray engine's own calls (Scan.cast_seconds);
    intensity: the learned intensity estimator, when the config names one;
    records:   points in the dataset's columns and each format's record;
    writes:    the .bin files and the chunk record.
    """

    entries: int
    seconds: dict


def write_chunk(job: BankJob, cache: TargetCache, chunk_id: int, entries: np.ndarray) -> ChunkDone:
    """Scan ``entries``, write their .bin files in every format, then the chunk record;
    the written files' pages leave the page cache (folder.drop_cached)."""
    config, sensor = job.config, job.sensor
    infos = {fmt: [] for fmt in config.formats}
    files, stats = {}, np.zeros(len(entries), STATS_DTYPE)
    seconds = dict.fromkeys(CHUNK_STAGES, 0.0)
    clock = [time.perf_counter()]

    def lap(stage: str) -> None:
        now = time.perf_counter()
        seconds[stage] += now - clock[0]
        clock[0] = now

    built = cache.build_seconds
    scans = scan_entries(cache, sensor, entries, config)
    seconds["targets"] = cache.build_seconds - built
    seconds["casts"] = sum(scan.cast_seconds for scan in scans)
    lap("scans")
    seconds["scans"] -= seconds["targets"]
    for fmt in config.formats:
        (job.out / fmt / DATABASE_FOLDER).mkdir(parents=True, exist_ok=True)
    intensities = {}
    for row, entry, scan in zip(stats, entries, scans):
        obj: BankObject = job.objects[entry["object"]]
        rows = scan.returns
        row["object"], row["index"], row["heading"] = entry["object"], entry["index"], entry["heading"]
        row["x"], row["y"], row["points"] = scan.box[0], scan.box[1], len(rows)
        row["kept"] = len(rows) >= config.min_points
        if not row["kept"]:
            continue
        if config.constant_intensity is not None:
            rows["intensity"] = config.constant_intensity
        elif config.intensity_checkpoint:
            rows["intensity"] = _learned_intensity(config, cache, entry, obj, scan)
            lap("intensity")
        class_name = job.class_names[entry["object"]]
        name = f"{safe_name(obj.name)}_{safe_name(class_name)}_{int(entry['index']):05d}.bin"
        shared = {"name": class_name, "path": f"{DATABASE_FOLDER}/{name}", "image_idx": _group_id(entry),
                  "pgt_object": obj.name, "gt_idx": int(entry["index"])}
        points = entry_points(rows, config.dataset)
        for fmt in config.formats:
            data, info = database_record(fmt, config.dataset, points, scan.box, shared)
            lap("records")
            relative = f"{fmt}/{info['path']}"
            files[relative] = write_entry_file(job.out / relative, data)
            lap("writes")
            infos[fmt].append(info)
        intensities.setdefault(class_name, []).append(rows["intensity"])
    histograms = {name: np.histogram(np.concatenate(values), INTENSITY_BINS,
                                     (0.0, INTENSITY_MAX[config.dataset]))[0].astype(np.int64)
                  for name, values in intensities.items()}
    lap("records")
    record = {"chunk": chunk_id, "infos": infos, "files": files, "stats": stats, "intensity": histograms}
    write_file(chunk_record_path(job.out, chunk_id), write_record(record))
    drop_cached(job.out / relative for relative in files)
    lap("writes")
    return ChunkDone(len(entries), seconds)


def _group_id(entry) -> int:
    """Unique over the bank (objects' grids never exceed 2**24 entries) and never a real
    frame's index (from 2**24 up): a sampler that reads an entry's camera frame by it
    fails at once instead of pasting another frame's image."""
    return (int(entry["object"]) + 1) * 2**24 + int(entry["index"])


_estimators: dict = {}


def _estimator(config: BankConfig):
    from ..intensity.estimator import IntensityEstimator

    if config.intensity_checkpoint not in _estimators:
        _estimators[config.intensity_checkpoint] = IntensityEstimator.load(config.intensity_checkpoint,
                                                                           config.dataset)
    return _estimators[config.intensity_checkpoint]


def _learned_intensity(config: BankConfig, cache: TargetCache, entry, obj: BankObject, scan) -> np.ndarray:
    """The estimator's intensities (dataset scale) for the scan's returns
    (intensity/estimator.scan_intensity). One object per call: the same numbers whatever
    the chunking."""
    import torch

    from ..intensity.estimator import scan_intensity

    torch.set_num_threads(1)  # float sums in a fixed order: the same bytes on any machine load
    bounds = cache.get(int(entry["object"]), int(entry["variant"])).bounds
    values, _ = scan_intensity(scan, bounds, cache.element_rgb(int(entry["object"])), obj.class_name,
                               _estimator(config), name=obj.name)
    return values


def assemble(out: Path, data_root=None, existed: bool | None = None) -> dict:
    """Write every format's info pickle and then the manifest from the chunk records
    (all must exist: InputError names the missing ones). Returns the manifest.
    ``existed``: right after an export into ``out``, whether the folder was there before
    it; a bank that kept no entry is then removed (``out`` too when the export made
    it), since there is nothing to resume. None (assembling shards) leaves ``out`` as is.

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
    # A list for every class of the dataset: the samplers index the pickle by each class they sample.
    infos = {fmt: {name: [] for name in DATABASE_CLASSES[config["dataset"]]} for fmt in config["formats"]}
    prefixes = {fmt: _path_prefix(out / fmt, data_root) for fmt in config["formats"]}
    files, counts, dropped, damaged = {}, {}, {}, []
    for chunk_id in range(ident["chunks"]):  # each record read, and its files checked, once
        record = done_chunk(out, chunk_id)
        if record is None:
            damaged.append(chunk_id)
            continue
        for fmt, entries in record["infos"].items():
            for info in entries:
                infos[fmt].setdefault(info["name"], []).append(dict(info, path=prefixes[fmt] + info["path"]))
        files.update(record["files"])
        for row in record["stats"]:
            name = ident["class_names"][row["object"]]
            bucket = counts if row["kept"] else dropped
            bucket[name] = bucket.get(name, 0) + 1
    if damaged:
        raise InputError(chunk_record_path(out, damaged[0]), f"damaged or an entry file it lists is missing "
                                                             f"({len(damaged)} chunk(s)); --resume redoes them")
    if not counts:
        if existed is not None:
            _discard_bank(out, keep_folder=existed)
        raise InputError(out, f"no entry kept: all {sum(dropped.values()):,} poses had fewer than "
                              f"{config['min_points']} points in their box; lower bank.min_points (a config file's) "
                              f"or bring the grid closer")
    pickle_name = f"{config['dataset']}_dbinfos_pgt.pkl"
    for fmt, by_class in infos.items():
        relative = f"{fmt}/{pickle_name}"
        files[relative] = write_file(out / relative, pickle.dumps(by_class, protocol=4))
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


def kept_summary(manifest: dict) -> str:
    """What a finished bank holds, in the one wording of the command line, the demo and
    the Bank panel: '1,234 entries [bus 600, truck 634], 12 poses dropped below 5 points'."""
    counts = ", ".join(f"{name} {count:,}" for name, count in manifest["counts"].items())
    dropped = sum(manifest["dropped_below_min_points"].values())
    return (f"{manifest['entries']:,} entries [{counts}], {dropped:,} poses dropped below "
            f"{manifest['config']['min_points']} points")


def _discard_bank(out: Path, keep_folder: bool) -> None:
    """Remove what an export that kept no entry wrote into ``out`` (its work folder and
    empty format folders; the folder held nothing else, prepare_folder saw to it), and
    ``out`` itself unless ``keep_folder``."""
    for child in out.iterdir():
        shutil.rmtree(child) if child.is_dir() else child.unlink()
    if not keep_folder:
        out.rmdir()


def check_data_root(data_root) -> None:
    """InputError unless ``data_root`` (see ``assemble``) is a folder: checked before an
    export starts too, so that a typo does not surface after the last chunk."""
    if not Path(data_root).is_dir():
        raise InputError(data_root, "the dataset root is not a folder")


def _path_prefix(format_folder: Path, data_root) -> str:
    """What goes before an info path relative to its format folder: "" without a
    data root, else the format folder relative to the data root plus "/"."""
    if data_root is None:
        return ""
    check_data_root(data_root)
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


