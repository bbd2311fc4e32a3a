"""Reconstruct photos or a video's frames into a COLMAP sparse model, on the CPU.

    pgt-reconstruct-frames FRAMES_DIR|VIDEO --out DIR
    .venv/bin/python headless_scripts/reconstruct_frames.py FRAMES_DIR|VIDEO --out DIR
        [--every K] [--pick every|sharpest] [--matching auto|orbit|exhaustive] [--overlap 10]
        [--camera single|per-image] [--max-features 8192] [--max-image-size 1600] [--threads 0] [--seed 0]

FRAMES_DIR: a folder of .jpg/.jpeg/.png images, matched in name order; VIDEO: a video
file (.mp4 .mov .m4v .avi .mkv .webm, decoded with PyAV: pip install
'pgt_blender[video]'), whose kept frames are written to DIR/images. --every K keeps one
frame in K (default: 10 for a video, 1 for a folder): the first of each run of K
(--pick every) or the sharpest (--pick sharpest, the default: the highest variance of
the Laplacian). Then pycolmap: SIFT features, matching ("orbit": each frame with its
next --overlap frames and those 2^j ahead, cyclically, which closes an orbit video's
loop; "exhaustive": all pairs; "auto": exhaustive up to 60 images), incremental
mapping (pgt_blender/core/importing/structure_from_motion.py). Writes DIR/database.db
and DIR/sparse/0, the model pgt-import-reconstruction and the Import panel read.
Progress bars on stderr; bad input: a one-line error and exit code 1.
"""

import os
import shutil
from pathlib import Path

from .. import cli
from ..core.errors import InputError
from ..core.files import apart_from_inputs, folders_made
from ..core.importing.frames import PICKS, VIDEO_SUFFIXES, choose_images, decode_video
from ..core.importing.source import MAX_IMAGE_SIDE
from ..core.importing.structure_from_motion import MATCHINGS, SfmOptions, reconstruct

VIDEO_EVERY = 10  # a video's default: 1 frame kept in 10 (3 per second at 30 fps)


def main(argv: list) -> int:
    parser = cli.parser("reconstruct_frames.py", __doc__)
    parser.add_argument("input", type=Path, help="folder of images, or a video file")
    parser.add_argument("--out", type=cli.OUTPUT_FOLDER, required=True,
                        help="output folder (database.db, sparse/0, images/)")
    parser.add_argument("--every", type=cli.whole(1, 10**4),
                        help=f"keep 1 frame in K (default {VIDEO_EVERY} for a video, 1 for a folder)")
    parser.add_argument("--pick", choices=PICKS, default="sharpest", help="which frame of each run of K")
    parser.add_argument("--matching", choices=MATCHINGS, default="auto", help="image pairs to match")
    parser.add_argument("--overlap", type=cli.whole(1, 1000), default=10,
                        help="orbit matching: neighbours each frame meets")
    parser.add_argument("--camera", choices=("single", "per-image"), default="single",
                        help="one camera for all frames (a video), or one per image (photos from many cameras)")
    parser.add_argument("--max-features", type=cli.whole(1, 10**6), default=8192, help="SIFT features per image")
    parser.add_argument("--max-image-size", type=cli.whole(1, MAX_IMAGE_SIDE), default=1600,
                        help="px: larger images are scaled down for SIFT")
    parser.add_argument("--threads", type=cli.whole(0, 64), default=0,
                        help="CPU threads (0: all; only 1 gives the same bytes every run)")
    parser.add_argument("--seed", type=cli.SEED, default=0, help="RANSAC's and the mapper's random seed")
    parser.add_argument("--quiet", action="store_true", help="no progress bars and no COLMAP log")
    args = parser.parse_args(argv)
    apart_from_inputs(args.out, [args.input])  # its database and sparse/ would land among the photos
    options = SfmOptions(args.matching, args.overlap, args.camera == "single", args.max_features,
                         args.max_image_size, args.threads, args.seed)
    _quiet_colmap(args.quiet)
    progress = not args.quiet
    if args.input.is_dir():
        names = choose_images(args.input, args.every or 1, args.pick, progress)
        result = reconstruct(args.input, names, args.out, options, progress)
    elif args.input.is_file() and args.input.suffix.lower() in VIDEO_SUFFIXES:
        result = _reconstruct_video(args, options, progress)
    elif args.input.exists():
        raise InputError(args.input, f"not a folder of images nor a video ({', '.join(VIDEO_SUFFIXES)})")
    else:
        raise InputError(args.input, "no such file or folder")
    total = sum(result.seconds.values())
    print(cli.markdown_table(
        ["images", "registered", "points", "reprojection px", "models", "features s", "matching s", "mapping s"],
        [[result.images, result.registered, result.points, f"{result.reprojection_error:.2f}", result.models,
          *(f"{result.seconds[step]:.1f}" for step in ("features", "matching", "mapping"))]]))
    print("\ncamera(s): " + "; ".join(f"{c['model']} {', '.join(f'{p:.4g}' for p in c['params'])}"
                                       for c in result.cameras[:3]) + (" ..." if len(result.cameras) > 3 else ""))
    print(f"wrote {result.model} in {total:.1f} s (import it: pgt-import-reconstruction {result.model})")
    return 0


def _reconstruct_video(args, options: SfmOptions, progress: bool):
    """Decode the video's frames into a folder beside OUT/images, reconstruct them, then
    move them into OUT/images. A failure names the video and leaves OUT as it was."""
    partial = args.out / ".images.partial"
    with folders_made(args.out):
        shutil.rmtree(partial, ignore_errors=True)
        try:
            names = decode_video(args.input, partial, args.every or VIDEO_EVERY, args.pick, progress)
            result = reconstruct(partial, names, args.out, options, progress)
        except BaseException as error:
            shutil.rmtree(partial, ignore_errors=True)
            if isinstance(error, InputError) and error.path == partial:
                raise InputError(args.input, error.problem) from None
            raise
    folder = args.out / "images"
    folder.mkdir(exist_ok=True)
    for name in names:  # the model names its images; their folder is found beside it
        os.replace(partial / name, folder / name)
    partial.rmdir()
    return result


def _quiet_colmap(quiet: bool) -> None:
    """COLMAP logs every step at INFO to stderr: keep warnings only, or nothing when
    quiet (a failure is the one error line this command prints)."""
    import pycolmap

    pycolmap.logging.minloglevel = pycolmap.logging.FATAL if quiet else pycolmap.logging.WARNING
