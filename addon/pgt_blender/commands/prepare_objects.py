"""Prepare a folder of reconstructions for scanning: align (PCA, refined to the
object's surface planes unless --no-refine), head (front at +x)
and size each one, and write it in the object frame with a sidecar JSON.

    pgt-prepare-objects --in DIR --class truck --out DIR
    .venv/bin/python headless_scripts/prepare_objects.py --in DIR --class truck --out DIR
        [--dataset nuscenes] [--up auto] [--heading auto] [--size class|keep|L,W,H]
        [--uniform] [--seed 0] [--checkpoint PATH] [--no-refine]
    blender -b -P headless_scripts/prepare_objects.py -- --in DIR --class truck --out DIR

Inputs: every .ply/.obj/.glb/.gltf/.stl file and COLMAP model folder (or folder with
sparse/0) directly in --in. Outputs per input: <name>.ply (object frame: +x forward,
+y left, +z up, metres, origin at the box centre) and <name>.json (class, dataset,
dims [l, w, h] m, transform = row-major 4x4 object_from_source, source_sha256, the
steps). The i-th input (sorted by name) draws its size with seed --seed + i.
A bad input is reported on stderr and skipped; the exit code is then 1.
"""

import argparse
import sys
from pathlib import Path


from .. import cli
from ..core.authoring.heading import best_available_method
from ..core.authoring.prepare import UP_CHOICES, heading_label, prepare, write_prepared
from ..core.classes import CLASS_SIZES
from ..core.errors import InputError
from ..core.files import apart_from_inputs
from ..core.importing import SUPPORTED, find_reconstructions, load_reconstruction

def size_argument(text: str):
    """"class", "keep" or "L,W,H" in metres."""
    if text in ("class", "keep"):
        return text
    try:
        dims = [float(v) for v in text.split(",")]
    except ValueError:
        dims = []
    if len(dims) != 3 or not all(0.001 <= dim <= 1000 for dim in dims):  # NaN fails too
        raise argparse.ArgumentTypeError(f"expected class, keep or three sizes L,W,H of 0.001 .. 1000 m; "
                                         f"got '{text[:60]}'")
    return dims


def main(argv: list) -> int:
    parser = cli.parser("prepare_objects.py", __doc__)
    parser.add_argument("--in", dest="inputs", type=Path, required=True, help="folder of reconstructions")
    parser.add_argument("--class", dest="class_name", required=True,
                        help="class name in --dataset (a nuScenes trailer is headed by its running gear)")
    parser.add_argument("--out", type=cli.OUTPUT_FOLDER, required=True, help="output folder")
    parser.add_argument("--dataset", choices=sorted(CLASS_SIZES), default="nuscenes",
                        help="whose class sizes --size class draws from")
    parser.add_argument("--up", choices=UP_CHOICES, default="auto",
                        help="up direction: cameras' mean up (auto, when there are cameras), PCA minor axis, or a source axis")
    parser.add_argument("--heading", choices=("auto", "classifier", "baseline", "none"), default="auto",
                        help="front/back: auto is the classifier where torch imports, else the geometric baseline")
    parser.add_argument("--size", type=size_argument, default="class",
                        help="class (class mean with clipped 10%% noise), keep (already metric) or L,W,H metres")
    parser.add_argument("--uniform", action="store_true", help="scale all axes by one factor (keeps proportions)")
    parser.add_argument("--seed", type=cli.SEED, default=0, help="seed of the first object's size draw")
    parser.add_argument("--checkpoint", type=Path, help="heading classifier checkpoint (default: the shipped one)")
    parser.add_argument("--no-refine", dest="refine", action="store_false",
                        help="keep the up choice and PCA yaw as they are (no refinement to the surface planes)")
    args = parser.parse_args(argv)
    apart_from_inputs(args.out, [args.inputs, args.checkpoint])
    if args.class_name not in CLASS_SIZES[args.dataset]:
        parser.error(f"{args.dataset} has no class '{args.class_name}' (have: {', '.join(CLASS_SIZES[args.dataset])})")
    inputs = find_reconstructions(args.inputs)
    if not inputs:
        raise InputError(args.inputs, f"no reconstructions found (supported: {SUPPORTED})")
    method = args.heading
    if method == "auto":
        method, why_not = best_available_method(args.checkpoint)
        if why_not:
            print(f"note: {why_not}; heading by the geometric baseline", file=sys.stderr)
    mode, exact = (args.size, None) if isinstance(args.size, str) else ("exact", args.size)
    failures = 0
    print(f"{'object':32} {'points':>8} {'up':>6} {'tilt °':>6} {'heading':>29}  dims [l, w, h] m")
    for index, path in enumerate(inputs):
        try:
            recon = load_reconstruction(path)
            authored = prepare(recon, args.class_name, args.dataset, args.up, method, mode, exact,
                               args.uniform, args.seed + index, args.checkpoint, args.refine)
            write_prepared(authored, args.class_name, args.dataset, args.out)
        except InputError as error:
            print(f"error: {error}", file=sys.stderr)
            failures += 1
            continue
        align, *rest = authored.steps
        heading = next((s.details for s in rest if s.name == "heading"), {"by": "none"})
        score = f" {heading['score']:.3g}" if "score" in heading else ""  # as Detect Front reports it
        dims = ", ".join(f"{d:.2f}" for d in authored.dims)
        print(f"{recon.name:32} {len(recon.positions):8d} {align.details['up_from']:>6} "
              f"{align.details['tilt_deg']:6.2f} "
              f"{heading_label(heading) + score:>29}  [{dims}]")
    print(f"\n{len(inputs) - failures} of {len(inputs)} prepared into {args.out}")
    return 1 if failures else 0
