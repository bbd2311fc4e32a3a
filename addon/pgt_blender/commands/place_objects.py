"""Place bank entries into a real scene on its ground and map, with collision and
occlusion, and write the augmented scene, its boxes and a bird's-eye picture.

    pgt-place-objects --scan FILE --info INFO --bank DIR|PKL --out DIR [options]
    .venv/bin/python headless_scripts/place_objects.py --scan FILE --info INFO --bank DIR --out DIR
    blender -b -P headless_scripts/place_objects.py -- --scan FILE --info INFO --bank DIR --out DIR

--info is the scene's description: a KITTI label file (label_2/<frame>.txt, calib
beside) or an OpenPCDet / mmdetection3d info pickle holding the scan's sample. --bank
is a bank folder or any ground-truth info pickle (its objects relative to its folder).
Maps: --map-polygons (GeoJSON or a JSON list of layer polygons, world frame) or a
semantic image --map with --map-pose X0 Y0 RESOLUTION [YAW_DEG] and --map-legend
(JSON {layer: label or [r, g, b]}); the scene's pose comes from --info.

Writes OUT/scan.bin (the augmented points, inserted first, in the scan's columns),
OUT/boxes.json (every box, with the entry it came from and the ground under it) and
OUT/birdseye.png (docs/formats.md, "Placement folder"). Exit status 1 and one line on
bad input; nothing is written then.
"""

import argparse
import json
import warnings
from pathlib import Path

import numpy as np

from .. import cli
from ..core.errors import InputError
from ..core.files import TEXT_LIMIT, apart_from_inputs, regular_file
from ..core.placement.bandit import ThompsonCells
from ..core.placement.birdseye import birdseye_png
from ..core.placement.entries import open_database
from ..core.placement.folder import check_placement_folder, write_placement
from ..core.placement.maps import ImagePose, checked_class_layers, map_from_image, map_from_polygons, read_polygons
from ..core.placement.place import REFUSALS, PlacementConfig, place_objects
from ..core.placement.scenes import frame_warning, read_scene
from ..core.scan.sensors import BIN_COLUMNS, sensor_from_name

DEFAULT_COUNT = 3  # objects per bank class when --objects is not given
MAX_OBJECTS = 1000  # per class: more than a scene holds


def objects_argument(text: str) -> tuple:
    """"CLASS=N" -> (class, n), as an argparse type."""
    name, _, count = text.partition("=")
    if not name or not count.isdigit() or int(count) > MAX_OBJECTS:
        raise argparse.ArgumentTypeError(f"expected CLASS=N (a class and a count up to {MAX_OBJECTS}), got {text!r}")
    return name, int(count)


def main(argv: list) -> int:
    parser = cli.parser("place_objects.py", __doc__)
    parser.add_argument("--scan", type=Path, required=True, help="the scene's point file (float32 rows)")
    parser.add_argument("--info", type=Path, required=True,
                        help="KITTI label file, or OpenPCDet / mmdetection3d info pickle with the scan's sample")
    parser.add_argument("--bank", type=Path, required=True, help="bank folder or ground-truth info pickle")
    parser.add_argument("--out", type=cli.OUTPUT_FOLDER, required=True,
                        help="folder to write scan.bin, boxes.json, birdseye.png")
    parser.add_argument("--dataset", choices=sorted(BIN_COLUMNS), help="the scene's dataset (default: from --info)")
    cli.convention_option(parser, "--convention", "--bank", " (a bank folder: the format whose pickle is read, "
                                                           "default openpcdet)")
    parser.add_argument("--objects", type=objects_argument, action="append", metavar="CLASS=N",
                        help=f"objects to place per class (repeat; default {DEFAULT_COUNT} of every bank class)")
    parser.add_argument("--sensor", help="sensor preset or .toml for occlusion and column steps "
                                         "(default: the dataset's)")
    parser.add_argument("--map-polygons", type=Path, help="map layers as polygons (GeoJSON or JSON list), world frame")
    parser.add_argument("--map", type=Path, help="semantic map image (Lyft-style raster)")
    parser.add_argument("--map-pose", type=cli.finite, nargs="+", metavar="V",
                        help="X0 Y0 RESOLUTION [YAW_DEG]: the image's top-left corner in the world, m per pixel")
    parser.add_argument("--map-legend", type=Path, help="JSON {layer: label or [r, g, b]} of the map image")
    parser.add_argument("--class-layers", type=Path, help="a JSON file {class: [layer, ...]} over the default layers")
    parser.add_argument("--thompson", type=Path, help="Thompson cells state (JSON) to draw cells from")
    parser.add_argument("--max-distance", type=cli.within(0, 1000), default=54.0,
                        help="farthest entry placed, m (default 54)")
    parser.add_argument("--no-occlusion", action="store_true", help="skip the range-view ray tracing")
    parser.add_argument("--seed", type=cli.SEED, default=0, help="seed of every draw (default 0)")
    args = parser.parse_args(argv)
    apart_from_inputs(args.out,
                      [args.scan, args.info, args.bank, args.map_polygons, args.map, args.map_legend,
                       args.class_layers, args.thompson])
    check_placement_folder(args.out)
    if args.map is not None and (args.map_pose is None or args.map_legend is None):
        parser.error("--map needs --map-pose and --map-legend")
    if args.map is None and (args.map_pose is not None or args.map_legend is not None):
        parser.error("--map-pose and --map-legend describe a --map image; give it")
    if args.class_layers is not None and args.map is None and args.map_polygons is None:
        parser.error("--class-layers names layers of a map: give --map or --map-polygons")
    if args.map_pose is not None and len(args.map_pose) not in (3, 4):
        parser.error("--map-pose takes X0 Y0 RESOLUTION [YAW_DEG]")

    scene = read_scene(args.scan, args.info, args.dataset)
    mismatch = frame_warning(args.scan, args.info)
    if mismatch:
        warnings.warn(mismatch, stacklevel=1)
    pool = open_database(args.bank, scene.dataset, args.convention, args.max_distance)
    counts = dict(args.objects or [(name, DEFAULT_COUNT) for name, entries in pool.classes.items()
                                   if len(entries.ranges)])
    scene_map = _scene_map(args, scene.lidar_to_world)
    bandit = ThompsonCells.load(args.thompson) if args.thompson else None
    config = PlacementConfig(sensor_from_name(args.sensor or scene.dataset), max_distance=args.max_distance,
                             occlusion=not args.no_occlusion, class_layers=_class_layers(args.class_layers))
    placement = place_objects(scene.points, scene.boxes, scene.names, pool, counts, config,
                              np.random.default_rng(args.seed), scene_map, bandit, source=args.scan)
    title = f"{args.scan.name}: {int(placement.inserted.sum())} objects placed (seed {args.seed})"
    try:
        picture = birdseye_png(scene.points, placement, title)
    except ImportError:  # matplotlib is not in Blender's own Python
        picture = None
    paths = write_placement(args.out, placement, scene, args.seed, picture)

    placed = placement.names[placement.inserted]
    rows = [[name, count, int((placed == name).sum()), placement.missing.get(name, 0),
             _refusals(placement.refused.get(name, {}))] for name, count in counts.items()]
    print(cli.markdown_table(["class", "asked", "placed", "not placed", "why tries were refused"], rows, "lrrrl"))
    print(f"\nscene: {len(scene.points)} points, {len(scene.boxes)} boxes; removed {int(placement.scene_in_boxes.sum())} "
          f"inside placed boxes and {int(placement.scene_shadowed.sum())} in their shadows")
    picture = paths.get("birdseye.png", "no birdseye.png (matplotlib is not installed)")
    print(f"wrote {paths['scan.bin']} ({len(placement.points)} points), {paths['boxes.json']}, {picture}")
    if not placement.inserted.any():  # a scene written unchanged should not pass unnoticed
        reasons = "; ".join(f"{name}: {_refusals(refused)}" for name, refused in placement.refused.items())
        warnings.warn(f"{args.scan}: no object placed ({reasons}); another --seed, a larger --max-distance or "
                      f"fewer objects may place some", stacklevel=1)
    return 0


def _refusals(refused: dict) -> str:
    """How often each check refused something (place.REFUSALS), most first."""
    counted = sorted(((count, check) for check, count in refused.items() if count), key=lambda item: -item[0])
    return ", ".join(f"{count} {REFUSALS[check]}" for count, check in counted) or "none"


def _json(path: Path | None):
    if path is None:
        return None
    regular_file(path, TEXT_LIMIT)
    try:
        return json.loads(path.read_text())
    except OSError as error:
        raise InputError(path, f"cannot read the file ({error.strerror or error})") from None
    except (ValueError, RecursionError) as error:
        raise InputError(path, f"not JSON ({error})") from None


def _class_layers(path: Path | None):
    return None if path is None else checked_class_layers(_json(path), path)


def _scene_map(args, lidar_to_world: np.ndarray):
    if args.map_polygons is not None:
        return map_from_polygons(read_polygons(args.map_polygons), lidar_to_world)
    if args.map is None:
        return None
    from matplotlib.image import imread
    from PIL import Image

    regular_file(args.map)
    try:
        with warnings.catch_warnings():  # a large map is fine; Pillow refuses one past twice its limit
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(args.map):  # refuses a header claiming more pixels than memory holds
                pass
            image = imread(args.map)
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as error:
        raise InputError(args.map, f"not a readable image ({type(error).__name__}: {error})") from None
    if image.dtype.kind == "f":  # matplotlib reads PNGs as floats in [0, 1]
        image = np.round(image * 255).astype(np.uint8)
    return map_from_image(image, _json(args.map_legend), ImagePose(*args.map_pose), lidar_to_world,
                          source=args.map, legend_source=args.map_legend)
