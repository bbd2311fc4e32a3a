"""Export the pseudo-LiDAR object bank: every authored object scanned over the grid of
poses and written as OpenPCDet and mmdetection3d ground-truth databases.

    blender -b objects.blend -P headless_scripts/export_bank.py -- --config bank.toml --out DIR
    pgt-export-bank --blend objects.blend --config bank.toml --out DIR
    .venv/bin/python headless_scripts/export_bank.py --blend objects.blend --config bank.toml --out DIR
    .venv/bin/python headless_scripts/export_bank.py --objects PREPARED_DIR --config bank.toml --out DIR

Inputs: the .blend's authored objects (class and size set) and/or folders of prepared
objects (prepare_objects.py: <name>.ply + <name>.json). Incomplete objects are listed
and refused, or left out with --skip-incomplete. The config (TOML, every key optional:
pgt_blender/core/bank/config.py) sets the dataset, grid, jitter, sweeps and formats.

Work: chunks of entries on --workers processes (default: all cores) or on a Ray cluster
(--executor ray [--address HOST:PORT]; none: a local one). The bank is the same bytes
for a seed whatever the workers. A killed run continues with --resume. Cluster array
jobs run --shard i/n each (into the same folder, or separate ones copied together
with --assemble --from DIR ...), then one --assemble writes the info pickles and the
manifest. The bank report (report.md + report.png in the folder) compares the bank with
a real database given by --real, with its quality score per class (score_bank.py; --real-convention
says how --real stores points, by default read from its infos). --data-root makes the info paths relative to the
dataset root the detector joins them to, so the bank loads beside the real database
(also with --assemble, to move a finished bank). An output folder that is not empty is refused without
--resume/--overwrite.
Bad input: a one-line error and exit code 1; nothing half-written is left.
"""

import argparse
import os
import sys
import time
from pathlib import Path


from .. import cli
from ..core.bank import export, folder
from ..core.bank.config import BankConfig, load_config
from ..core.bank.executors import check_ray_address
from ..core.bank.inputs import checked_objects, prepared_objects
from ..core.errors import InputError
from ..core.files import apart_from_inputs


def shard_argument(text: str) -> tuple:
    """"i/n" with 0 <= i < n."""
    try:
        index, count = (int(part) for part in text.split("/"))
    except ValueError:
        index, count = -1, 0
    if not 0 <= index < count:
        raise argparse.ArgumentTypeError(f"expected i/n with 0 <= i < n, got '{text}'")
    return index, count


def gather(args) -> tuple[list, Path]:
    """The complete objects of the .blend (given, or open in Blender) and the folders."""
    objects, incomplete, sources = [], [], []
    blend = args.blend or _open_blend_file()
    if blend:
        found, missing = _blend_objects(blend, args.blend is not None)
        objects, incomplete, sources = objects + found, incomplete + missing, sources + [blend]
    for source in args.objects:
        found, missing = prepared_objects(source)
        objects, incomplete, sources = objects + found, incomplete + missing, sources + [source]
    return checked_objects(objects, incomplete, args.skip_incomplete, sources[0]), sources[0]


def _inputs(args) -> list:
    """The files and folders the command reads (None where not given): the output must
    not be or hold them, nor an overwrite delete them."""
    return [*args.objects, args.blend, args.config, args.real]


def _open_blend_file():
    """The .blend Blender was started with (blender -b FILE -P ...), if any."""
    if "bpy" not in sys.modules:
        return None
    import bpy

    return Path(bpy.data.filepath) if bpy.data.filepath else None


def _blend_objects(path: Path, open_it: bool) -> tuple:
    import bpy

    from ..blender import headless
    from ..blender.bank import scene_bank_objects

    headless.ensure_registered()
    if open_it:
        if not path.is_file():
            raise InputError(path, "no such .blend file")
        try:
            bpy.ops.wm.open_mainfile(filepath=str(path))
        except RuntimeError as error:
            raise InputError(path, f"not a readable .blend file: {str(error).splitlines()[0]}") from None
    return scene_bank_objects(bpy.context.scene)


def export_bank(args) -> int:
    if args.data_root is not None:
        export.check_data_root(args.data_root)
    if args.executor == "ray":
        check_ray_address(args.address)
    if args.assemble:
        with folder.exporting(args.out):
            reference = real_reference(args, folder.read_identity(args.out)["config"])
            for shard in args.shard_dirs:
                folder.copy_shard(shard, args.out)
            return finish(args, export.assemble(args.out, args.data_root), reference, 0.0)
    config = load_config(args.config) if args.config else BankConfig()
    existed = args.out.exists()
    # held before the slow reads (the real database, the objects): a busy folder is said at once
    with folder.exporting(args.out, shared=args.shard is not None):
        reference = real_reference(args, config.to_dict())
        objects, source = gather(args)
        plan = export.plan_bank(objects, config, args.out, args.resume, args.overwrite, args.shard,
                                inputs=_inputs(args))
        print(f"{len(plan.job.objects)} object(s) from {source}: {sum(map(len, plan.chunks)):,} poses in "
              f"{len(plan.chunks)} chunks, {len(plan.pending)} to do ({config.dataset}, {', '.join(config.formats)})")
        started = time.perf_counter()
        _progress(export.run_plan(plan, args.workers, args.executor, args.address), plan.pending_entries)
        seconds = time.perf_counter() - started
        if args.shard is not None:
            print(f"shard {args.shard[0]}/{args.shard[1]} done in {seconds:.1f} s; "
                  f"when every shard is done: export_bank.py --assemble --out {args.out}")
            return 0
        return finish(args, export.assemble(args.out, args.data_root, existed), reference, seconds,
                      plan.pending_entries)


def _progress(finished, total: int) -> None:
    """Drain ``finished`` (export.ChunkDone per chunk) under a progress bar with rate and ETA."""
    try:
        from tqdm import tqdm
    except ImportError:  # Blender's own Python may lack tqdm: a plain count instead
        done = 0
        for chunk in finished:
            done += chunk.entries
            print(f"\r{done:,}/{total:,} poses", end="", file=sys.stderr, flush=True)
        print(file=sys.stderr)
        return
    with tqdm(total=total, unit=" poses", smoothing=0.1, mininterval=1.0) as bar:
        for chunk in finished:
            bar.update(chunk.entries)


def real_reference(args, config: dict):
    """The --real database's statistics, read before any bank file is written (a bad
    database leaves nothing behind); None without --real."""
    from ..core.bank import report

    return report.real_reference(args.real, config, convention=args.real_convention) if args.real else None


def quality_score(args) -> dict:
    """The bank's quality score against --real (Fréchet when torch imports: the encoder
    is trained on --real and cached in the bank's .work folder)."""
    from ..core.quality.score import quality_available, score_bank

    return score_bank(args.out, args.real, args.real_convention, learned=quality_available())


def finish(args, manifest: dict, reference, seconds: float, poses: int = 0) -> int:
    """Write the bank report (beside ``reference`` when given) and print the headline numbers."""
    from ..core.bank.report import write_report

    try:
        report = f"report: {write_report(args.out, reference, quality_score(args) if reference else None)[0]}"
    except KeyboardInterrupt:  # the bank itself is whole: say how to get its report
        raise KeyboardInterrupt(f"{args.out}: the bank is written but not its report; "
                                f"export_bank.py --assemble --out {args.out} writes it") from None
    rate = f" ({poses / seconds:,.0f} poses/s)" if seconds and poses else ""
    print(f"bank: {export.kept_summary(manifest)}{rate}\nwrote {args.out}; {report}")
    if manifest["data_root"] is None:  # the frameworks join info paths to their dataset root, not to these
        print(f"info paths are relative to {args.out}/<format>/: to train beside a real database, "
              f"export_bank.py --assemble --out {args.out} --data-root <the dataset root>")
    else:
        print(f"info paths are relative to the dataset root {(args.out / manifest['data_root']).resolve()}")
    return 0


def main(argv: list) -> int:
    parser = cli.parser("export_bank.py", __doc__)
    parser.add_argument("--config", type=Path,
                        help="bank TOML, every key optional (docs/bank.toml lists them; default: the paper's nuScenes bank)")
    parser.add_argument("--out", type=cli.OUTPUT_FOLDER, required=True, help="output folder")
    parser.add_argument("--blend", type=Path, help=".blend with authored objects (python route)")
    parser.add_argument("--objects", type=Path, action="append", default=[],
                        help="folder of prepared objects (repeatable)")
    parser.add_argument("--skip-incomplete", action="store_true", help="leave out objects without class or size")
    parser.add_argument("--workers", type=cli.whole(1, 1024), default=os.cpu_count(),
                        help="processes (default: all cores)")
    parser.add_argument("--executor", choices=("local", "ray"), default="local",
                        help="local processes or a Ray cluster (--address)")
    parser.add_argument("--address", help="Ray cluster address (default: start a local one)")
    parser.add_argument("--resume", action="store_true", help="continue the unfinished bank in --out")
    parser.add_argument("--overwrite", action="store_true", help="replace the bank in --out")
    parser.add_argument("--shard", type=shard_argument, help="i/n: export only chunk ids = i mod n")
    parser.add_argument("--assemble", action="store_true",
                        help="write the pickles and manifest of --out once all shards are done")
    parser.add_argument("--data-root", type=Path,
                        help="the dataset root the framework joins info paths to (OpenPCDet: DATA_PATH for KITTI, "
                             "DATA_PATH/VERSION for nuScenes and Lyft; mmdet3d: data_root): paths are written "
                             "relative to it (default: relative to each format folder)")
    parser.add_argument("--real", type=Path, help="a real *_dbinfos_*.pkl the bank report compares with")
    cli.convention_option(parser, "--real-convention", "--real")
    parser.add_argument("--from", dest="shard_dirs", type=Path, nargs="+", default=[],
                        help="with --assemble: shard folders to copy into --out first")
    args = parser.parse_args(argv)
    apart_from_inputs(args.out, _inputs(args))
    if args.resume and args.overwrite:
        parser.error("--resume and --overwrite exclude each other")
    if args.workers < 1:
        parser.error("--workers must be at least 1")
    if not (args.assemble or args.blend or args.objects or _open_blend_file()):
        parser.error("no input: give --blend FILE, --objects DIR, or run in Blender with a .blend")
    return export_bank(args)
