"""Import a reconstruction (COLMAP folder, Gaussian-splat / point / mesh PLY, OBJ, GLB,
GLTF, STL) into a Blender scene, headless.

    pgt-import-reconstruction INPUT [--out scene.blend] [--json]
    .venv/bin/python headless_scripts/import_reconstruction.py INPUT [--out scene.blend] [--json]
    blender -b [file.blend] -P headless_scripts/import_reconstruction.py -- INPUT [...]

--json prints one JSON object (points, faces, cameras, attributes, kind, sha256, ...).
Exit status 1 and a one-line message on bad input; nothing is written then.
"""

import argparse
import json
from pathlib import Path


import bpy

from ..blender import headless, objects
from .. import cli
from ..core.errors import InputError
from ..core.importing import load_reconstruction


def main(argv: list) -> int:
    parser = argparse.ArgumentParser(prog="import_reconstruction.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("input", type=Path, help="COLMAP model folder or reconstruction file")
    parser.add_argument("--out", type=Path, help="save the scene to this .blend")
    parser.add_argument("--json", action="store_true", help="print what arrived as one JSON object")
    parser.add_argument("--no-cameras", action="store_true", help="skip COLMAP cameras")
    args = parser.parse_args(argv)
    headless.ensure_registered()
    headless.start_scene()
    recon = load_reconstruction(args.input, with_cameras=not args.no_cameras)
    if args.out and args.out.is_dir():
        raise InputError(args.out, "is a folder; --out is the .blend file to write")
    obj = objects.add_reconstruction(bpy.context.scene, recon, not args.no_cameras)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        try:
            bpy.ops.wm.save_as_mainfile(filepath=str(args.out.resolve()))
        except RuntimeError as error:  # Blender reports a failed write as a RuntimeError
            raise InputError(args.out, f"cannot write the .blend: {str(error).strip().splitlines()[-1]}") from None
    summary = headless.object_summary(obj)
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"imported {summary['object']} ({summary['kind']}): {summary['points']} points, "
              f"{summary['faces']} faces, {summary['cameras']} cameras"
              + (f" -> {args.out}" if args.out else ""))
    return 0


run = cli.command(main)
