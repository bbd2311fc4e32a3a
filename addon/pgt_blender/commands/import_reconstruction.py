"""Import a reconstruction (COLMAP folder, 3D Gaussian Splatting output folder, Gaussian-splat
/ point / mesh PLY, Plenoxels .npz, OBJ, GLB, GLTF, STL) into a Blender scene, headless.

    pgt-import-reconstruction INPUT [--out scene.blend] [--json]
    pgt-import-reconstruction 3DGS_RUN --view-color --foreground masks --masks MASKS [--mask-share 0.5]
    pgt-import-reconstruction grid.npz --cameras cameras.json --view-color --foreground plane
    .venv/bin/python headless_scripts/import_reconstruction.py INPUT [...]
    blender -b [file.blend] -P headless_scripts/import_reconstruction.py -- INPUT [...]

--view-color replaces each splat's or voxel's color by its mean spherical-harmonic color over
the training views whose rays hit it (the paper's Algorithm 1; attributes view_hit,
view_count); --foreground keeps the object: "masks" (per-image masks in --masks) or "plane"
(removes the support plane, keeps the connected object at the centre of the camera orbit).
--json prints one JSON object (points, faces, cameras, attributes, kind, sha256, capture ...).
Exit status 1 and a one-line message on bad input; nothing is written then.
"""

import json
from pathlib import Path


import bpy

from ..blender import headless, objects
from .. import cli
from ..core.capture import FOREGROUND_MODES, CaptureOptions
from ..core.files import apart_from_inputs
from ..core.importing import load_reconstruction


def main(argv: list) -> int:
    parser = cli.parser("import_reconstruction.py", __doc__)
    parser.add_argument("input", type=Path, help="COLMAP model folder or reconstruction file")
    parser.add_argument("--out", type=cli.output_file(".blend"), help="save the scene to this .blend")
    parser.add_argument("--json", action="store_true", help="print what arrived as one JSON object")
    parser.add_argument("--no-cameras", action="store_true", help="leave the cameras out of the scene")
    parser.add_argument("--cameras", type=Path,
                        help="training cameras (a 3DGS cameras.json or a COLMAP model folder) in the input's frame; "
                             "default: a 3DGS run's own, or a cameras.json beside a splat or .npz file")
    parser.add_argument("--view-color", action="store_true",
                        help="view-agnostic color: mean SH color over the views whose rays hit each element")
    parser.add_argument("--foreground", choices=FOREGROUND_MODES, default="none",
                        help="keep the object: per-image masks (--masks) or remove the support plane")
    parser.add_argument("--masks", type=Path, help="folder of per-image masks, named after the images")
    parser.add_argument("--mask-share", type=float, default=0.5,
                        help="share of the views seeing an element that must put it inside the mask (default 0.5)")
    parser.add_argument("--seed", type=cli.SEED, default=0, help="seed of the capture steps' random draws")
    args = parser.parse_args(argv)
    apart_from_inputs(args.out, [args.input, args.cameras, args.masks])
    if args.foreground == "masks" and not args.masks:
        parser.error("--foreground masks needs --masks FOLDER")
    if args.masks and args.foreground != "masks":
        parser.error("--masks is read with --foreground masks; give it")
    if not 0 <= args.mask_share <= 1:
        parser.error("--mask-share must be within [0, 1]")
    capture = CaptureOptions(view_color=args.view_color, foreground=args.foreground, masks=args.masks,
                             mask_share=args.mask_share, seed=args.seed)
    headless.ensure_registered()
    headless.start_scene()
    recon = load_reconstruction(args.input, with_cameras=not args.no_cameras, cameras=args.cameras,
                                capture=capture if capture.needs_cameras else None)
    obj = objects.add_reconstruction(bpy.context.scene, recon, not args.no_cameras)
    if args.out:
        headless.save_blend(args.out)
    summary = headless.object_summary(obj)
    if recon.capture:
        summary["capture"] = recon.capture
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"imported {summary['object']} ({summary['kind']}): {summary['points']} points, "
              f"{summary['faces']} faces, {summary['cameras']} cameras"
              + (f" -> {args.out}" if args.out else ""))
    return 0
