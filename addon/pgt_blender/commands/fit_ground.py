"""Fit the bank's ground model (height and slope under each pose) to real labelled scans.

    pgt-fit-ground KITTI_FOLDER [--mounting-height 1.73] [--json]
    .venv/bin/python headless_scripts/fit_ground.py KITTI_FOLDER [--mounting-height 1.73] [--json]

KITTI_FOLDER holds velodyne/*.bin, label_2/*.txt and calib/*.txt of the same frames.
Per labelled box: a plane fitted to the ground returns around its footprint gives the
ground height under it (offset from -mounting height), the road grade from the sensor
(atan(offset / distance)) and the local pitch and roll. The summary is the model of
pgt_blender/core/bank/ground.py: grade_deg and slope_deg, RMS over the boxes with enough
ground returns; the bank config's [ground] defaults are this script's output on the
shared KITTI frames. Bad input: a one-line error and exit code 1.
"""

import json
from pathlib import Path


from .. import cli
from ..core.bank.ground import MIN_GROUND_POINTS, fit_kitti_frames
from ..core.errors import InputError


def _number(value, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def main(argv: list) -> int:
    parser = cli.parser("fit_ground.py", __doc__)
    parser.add_argument("folder", type=Path, help="KITTI frames: velodyne/, label_2/, calib/")
    parser.add_argument("--mounting-height", type=cli.within(0.1, 10), default=1.73,
                        help="sensor height above the ground, m")
    parser.add_argument("--json", action="store_true", help="print the fit as one JSON object")
    args = parser.parse_args(argv)
    fit = fit_kitti_frames(args.folder, args.mounting_height)
    if not fit["used"]:  # degenerate: an error in the command line, as an empty scan is
        raise InputError(args.folder, f"none of its {len(fit['boxes'])} labelled boxes has >= {MIN_GROUND_POINTS} "
                                      f"ground returns around it: no ground to fit")
    if args.json:
        print(json.dumps(fit))
        return 0
    print(cli.markdown_table(
        ["frame", "type", "distance m", "ground returns", "ground offset m", "grade deg", "pitch deg", "roll deg",
         "box bottom - ground m"],
        [[box["frame"], box["type"], f"{box['distance']:.1f}", box["points"],
          *(_number(box[key]) for key in ("offset", "grade", "pitch", "roll", "bottom_gap"))] for box in fit["boxes"]],
        "ll" + "r" * 7))
    print(f"\nfrom the {fit['used']} boxes with >= {MIN_GROUND_POINTS} ground returns: "
          f"grade_deg = {_number(fit['grade_deg'])}, slope_deg = {_number(fit['slope_deg'])}")
    return 0
