"""Scan one object with a simulated rotating LiDAR and write its returns.

    pgt-scan-object --object PATH --sensor nuscenes
    .venv/bin/python headless_scripts/scan_object.py --object PATH --sensor nuscenes
        --x 15 --y 0 --heading 90 [--sweeps N] --out FILE.bin|.ply|.npy
    blender -b -P headless_scripts/scan_object.py -- (the same arguments)

--object: a mesh (.obj .ply .glb .gltf .stl), a point PLY or a Gaussian-splat PLY, in
the object frame (+x forward, +y left, +z up, metres), e.g. prepare_objects.py's
output. Meshes are ray cast as they are; Gaussian splats are scanned as Gaussians (each
ray composites the splats it meets and returns where their opacity reaches 0.5,
pgt_blender/core/scan/gaussians.py); points become surfels (splats too with --surface
surfels; or, with --surface range-view, the paper's range-view projection). The object
stands on the ground with its object-frame origin at (--x, --y) m in the sensor frame,
turned by --heading deg counter-clockwise from +x. Its box (what stands on the ground
and the printed box) is the authored one, the sidecar <object>.json's dims centred on
the origin, as in the bank; without a sidecar, the geometry's bounds. --sensor: nuscenes, kitti, lyft, vlp16 or a .toml file.

Output by suffix: .bin float32 in the dataset's columns (KITTI x y z intensity;
nuScenes/Lyft x y z intensity time_lag; a KITTI .bin takes one sweep), .ply every
column, .npy the structured rows (columns: pgt_blender/core/scan/returns.py). With --sweeps N the object moves as its
class's motion model draws (seeded; class from --class or the sidecar <object>.json),
or at --speed/--acceleration. Intensity: the sensor's physical law, or with
--intensity-checkpoint the learned estimator (train_intensity.py) on each return's
color (the file's vertex or point colors) for the object's class. Bad input: a
one-line error and exit code 1.
"""

import warnings
from pathlib import Path

import numpy as np

from .. import cli
from ..core.authoring.prepare import read_sidecar
from ..core.bank.config import MAX_SWEEPS
from ..core.boxes import centred_bounds
from ..core.errors import InputError
from ..core.files import apart_from_inputs
from ..core.importing import load_reconstruction
from ..core.intensity.estimator import scan_intensity
from ..core.scan.range_view import range_view_scan
from ..core.scan.raycast import ScanOptions, placement
from ..core.scan.returns import OUTPUT_SUFFIXES, write_scan
from ..core.scan.sensors import BIN_COLUMNS, PRESETS, sensor_from_name
from ..core.scan.sweeps import CLASS_MOTION, Motion, motion_class, sample_motion, scan_sweeps
from ..core.scan.targets import element_colors, has_gaussians, reflectivity_from_srgb, target_from_reconstruction


def sidecar(path: Path) -> dict:
    """What prepare_objects.py recorded beside the object (read_sidecar), or {}."""
    record = path.with_suffix(".json")
    return read_sidecar(record) if record.is_file() else {}


def authored_box(record: dict):
    """(2, 3) the authored box of a prepared object (its sidecar's dims, centred on the
    object-frame origin, as the bank takes it), or None without a sidecar."""
    dims = record.get("dims")
    return None if dims is None else centred_bounds(dims)


def scan(args):
    sensor = sensor_from_name(args.sensor)
    if args.sweeps > 1 and args.out.suffix == ".bin" and "time_lag" not in BIN_COLUMNS[sensor.dataset]:
        raise InputError(args.out, f"{sensor.dataset} .bin files have no time column to keep {args.sweeps} merged "
                                   f"sweeps apart; write .ply or .npy (they keep time_lag) or drop --sweeps")
    recon = load_reconstruction(args.object, with_cameras=False)
    options = ScanOptions(range_noise=args.noise, drop_rate=args.drop_rate, ray_drop=args.ray_drop, seed=args.seed)
    heading = np.radians(args.heading)
    record = sidecar(args.object)
    class_name = args.class_name or record.get("class")
    box = authored_box(record)
    if args.surface == "range-view":
        if args.sweeps != 1:
            raise InputError(args.object, "range view scans one sweep; drop --sweeps")
        positions = recon.positions.astype(np.float64)
        bounds = np.stack([positions.min(0), positions.max(0)]) if box is None else box
        reflectivity = None if recon.colors is None else reflectivity_from_srgb(recon.colors)
        pose = placement(bounds, sensor, args.x, args.y, heading)
        result = range_view_scan(positions, sensor, pose, bounds, reflectivity, options=options)
    else:
        result, bounds = ray_cast(args, recon, sensor, heading, class_name, options, box)
    if args.intensity_checkpoint and not class_name:
        raise InputError(recon.source, "the learned intensity needs the object's class: give --class")
    result.returns["intensity"], note = scan_intensity(result, bounds, element_colors(recon), class_name,
                                                       args.intensity_checkpoint, name=recon.name)
    return result, sensor, note


def ray_cast(args, recon, sensor, heading: float, class_name: str, options, box=None):
    """A mesh, Gaussian or surfel scan over --sweeps sweeps: (Scan, the object's box
    bounds (2, 3): ``box``, else the geometry's)."""
    if args.surface == "mesh" and not len(recon.faces):
        raise InputError(args.object, "has no faces to scan as a mesh; use --surface surfels")
    if args.surface == "gaussians" and (len(recon.faces) or not has_gaussians(recon.attributes)):
        raise InputError(args.object, "is not a Gaussian splat (no scale, rotation and opacity); use --surface auto")
    if args.surface == "surfels":
        recon.faces = recon.faces[:0]
    target = target_from_reconstruction(recon, args.radius_scale, gaussians=args.surface != "surfels")
    motion = Motion()
    if args.speed is not None:
        motion = Motion(args.speed, args.acceleration)
    elif class_name and args.sweeps > 1:
        motion = sample_motion(moving_class(args, class_name), np.random.default_rng(args.seed))
    bounds = target.bounds if box is None else box
    return scan_sweeps(target, sensor, args.x, args.y, heading, motion, args.sweeps, options, bounds), bounds


def moving_class(args, class_name: str) -> str:
    """``class_name``'s motion model (sweeps.CLASS_MOTION); InputError naming where the
    class came from when it has none."""
    known = motion_class(class_name)
    if known is None:
        source = "--class" if args.class_name else args.object.with_suffix(".json")
        raise InputError(source, f"class '{class_name}' has no motion model (known: {', '.join(CLASS_MOTION)}); "
                                 f"give --speed to set the motion")
    return known


def main(argv: list) -> int:
    parser = cli.parser("scan_object.py", __doc__)
    parser.add_argument("--object", type=Path, required=True, help="mesh, point or splat file, object frame")
    parser.add_argument("--sensor", default="nuscenes", help=f"{', '.join(PRESETS)} or a .toml file")
    parser.add_argument("--x", type=cli.within(-1e4, 1e4), required=True, help="object position, sensor frame (m)")
    parser.add_argument("--y", type=cli.within(-1e4, 1e4), required=True, help="object position, sensor frame (m)")
    parser.add_argument("--heading", type=cli.finite, default=0.0, help="deg, counter-clockwise from +x")
    parser.add_argument("--sweeps", type=cli.whole(1, MAX_SWEEPS), default=1,
                        help="merged sweeps of a moving object (nuScenes: 10)")
    parser.add_argument("--class", dest="class_name", help="class for the motion model (default: sidecar JSON)")
    parser.add_argument("--speed", type=cli.within(-100, 100),
                        help="m/s along the heading, instead of the class's draw")
    parser.add_argument("--acceleration", type=cli.within(-50, 50), default=0.0, help="m/s^2, with --speed")
    parser.add_argument("--surface", choices=("auto", "mesh", "gaussians", "surfels", "range-view"), default="auto",
                        help="auto: mesh when the file has faces, Gaussians for a splat, else surfels")
    parser.add_argument("--radius-scale", type=cli.within(0.01, 100), default=1.0,
                        help="surfel radius / local point spacing")
    parser.add_argument("--intensity-checkpoint", type=Path,
                        help="intensity.pt of train_intensity.py: learned intensities instead of the physical law")
    parser.add_argument("--noise", action="store_true", help="add the sensor's range noise")
    parser.add_argument("--drop-rate", type=cli.finite, default=0.0, help="random ray drop probability")
    parser.add_argument("--ray-drop", action="store_true", help="drop returns with the sensor's fitted ray-drop "
                                                                 "model (kitti has one)")
    parser.add_argument("--seed", type=cli.SEED, default=0, help="seed of the noise and drop draws")
    parser.add_argument("--out", type=cli.output_file(*OUTPUT_SUFFIXES), required=True,
                        help=f"output file ({', '.join(OUTPUT_SUFFIXES)})")
    args = parser.parse_args(argv)
    apart_from_inputs(args.out, [args.object, args.intensity_checkpoint])
    if not 0 <= args.drop_rate < 1:
        parser.error("--drop-rate must lie in [0, 1)")
    result, sensor, intensity_note = scan(args)
    if not result.hits:
        raise InputError(args.object, f"no returns at x = {args.x:g} m, y = {args.y:g} m: the object is out of "
                                     f"the {sensor.name} sensor's range or view there; nothing written")
    write_scan(result, args.out)
    inside = result.inside_warning(args.object.name)
    if inside:
        warnings.warn(inside, stacklevel=1)
    stats = result.stats()
    box = ", ".join(f"{v:.3f}" for v in result.box)
    print(f"{sensor.name}: {stats['points']} points from {stats['rays']} rays "
          f"({stats['efficiency']:.0%} hit) in {stats['ms']:.2f} ms; intensity: {intensity_note}\n"
          f"box [x, y, z, dx, dy, dz, heading, vx, vy] = [{box}]\nwrote {args.out}")
    return 0
