"""Step 4's data: LiDAR objects of the two domains the intensity estimator learns between.

- Real LiDAR objects (intensity domain): an OpenPCDet / mmdetection3d ground-truth
  database, or raw KITTI scans with their label_2 boxes (the points inside each box).
- RGB objects: this project's scans of colored objects (each return takes the color
  of the face it hit), so both domains share the LiDAR's sampling pattern.

Every object is in its *box frame*: origin at the box centre, +x along its heading,
+z up, metres. Class names are lower case ("Truck" and "truck" are one class).
Training takes fixed-size sets (ObjectSet): farthest point sampling to ``points``
points, coordinates divided by half the box dims (the box is [-1, 1]^3).
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..boxes import box_frame, kitti_camera_to_lidar
from ..errors import InputError
from ..files import TEXT_LIMIT, listed, no_dead_link, read_float32_rows, regular_file
from ..scan.sensors import INTENSITY_MAX
from ..scan.targets import MAX_COORDINATE

DEFAULT_POINTS = 256  # the paper's point count per object, and its minimum
# KITTI label types that are not objects; every other type is kept under its own name.
KITTI_SKIPPED = ("DontCare",)


@dataclass
class LidarObject:
    """One object: points (N, 3) float64 in its box frame (m), dims (3,) l w h (m),
    values (N, K) float32 in [0, 1] (K = 1 intensity over the dataset's maximum, or
    K = 3 sRGB), its lower-case class and where it came from. Scanned RGB objects also
    keep ``physical`` (N,) float32 in [0, 1], the scanner's physical intensity."""

    name: str
    class_name: str
    points: np.ndarray
    dims: np.ndarray
    values: np.ndarray
    physical: np.ndarray | None = None


@dataclass
class ObjectSet:
    """Fixed-size point sets, one row per object.

    xyz:         (B, P, 3) float32 box frame divided by dims / 2 (the box is [-1, 1]^3).
    values:      (B, P, K) float32 in [0, 1]: K = 1 intensity, K = 3 sRGB.
    class_index: (B,) int64 into ``classes``.
    classes:     class names shared by both domains, sorted.
    names:       per object, for messages.
    dataset:     whose intensity scale the real values were divided by.
    """

    xyz: np.ndarray
    values: np.ndarray
    class_index: np.ndarray
    classes: tuple
    names: list
    dataset: str


def _intensities(path, values: np.ndarray, dataset: str) -> np.ndarray:
    """(N, 1) float32 in [0, 1] from a dataset's raw intensity column (finite, as
    files.read_float32_rows reads it); InputError for values beyond the dataset's range."""
    maximum = INTENSITY_MAX[dataset]
    if len(values) and (values.min() < 0 or values.max() > maximum * (1 + 1e-6)):
        raise InputError(path, f"intensities span {values.min():g}..{values.max():g}, outside {dataset}'s 0..{maximum:g}")
    return (values / maximum).astype(np.float32)[:, None]


def gt_database_objects(path, convention: str | None, dataset: str, min_points: int = 1) -> list:
    """Real objects of an OpenPCDet (``convention="openpcdet"``, points about the box
    centre) or mmdetection3d (``"mmdet3d"``, about its bottom centre; None: read from the
    infos) ``*_dbinfos_*.pkl`` whose .bin files carry x, y, z, intensity[, ...] columns
    (gt_database.py)."""
    from ..gt_database import read_objects

    objects = []
    for obj in read_objects(path, convention, min_points):
        if obj.features.shape[1] < 1:
            raise InputError(path, f"{obj.name} has no intensity column (3 columns per point)")
        values = _intensities(f"{path}: {obj.name}", obj.features[:, 0], dataset)
        objects.append(LidarObject(obj.name, obj.class_name.lower(), obj.points, obj.dims, values))
    return objects


def _text_lines(path: Path) -> list:
    """The lines of a text file a user names; InputError when it is not readable text."""
    try:
        return regular_file(path, TEXT_LIMIT).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(path, f"not a readable text file ({type(error).__name__}: {error})") from None


def _read_calibration(path: Path) -> np.ndarray:
    """(4, 4) rect_from_velodyne of a KITTI calib file (R0_rect @ Tr_velo_to_cam)."""
    rows = {key.strip(): numbers for key, numbers in (line.split(":", 1) for line in _text_lines(path) if ":" in line)}
    try:
        rect, velo_to_cam = np.eye(4), np.eye(4)
        rect[:3, :3] = np.array(rows["R0_rect"].split(), np.float64).reshape(3, 3)
        velo_to_cam[:3, :4] = np.array(rows["Tr_velo_to_cam"].split(), np.float64).reshape(3, 4)
    except (KeyError, ValueError):
        raise InputError(path, "not a KITTI calib file (needs R0_rect and Tr_velo_to_cam)") from None
    matrix = rect @ velo_to_cam
    if not (np.isfinite(matrix).all() and abs(np.linalg.det(matrix)) > 1e-6):
        raise InputError(path, "R0_rect @ Tr_velo_to_cam is not a finite, invertible transform")
    return matrix


def kitti_label_boxes(label_path: Path, calib_path: Path) -> list:
    """[(type, centre (3,) velodyne frame, dims (l, w, h), heading)] of a KITTI label_2
    file. Labels give the bottom centre in the rectified camera frame and ry about its
    -y axis: heading = -ry - pi/2 in the velodyne frame."""
    velodyne_from_rect = np.linalg.inv(_read_calibration(calib_path))
    kinds, camera_boxes = [], []
    for number, line in enumerate(_text_lines(label_path), 1):
        fields = line.split()
        if not fields or fields[0] in KITTI_SKIPPED:
            continue
        try:
            height, width, length, x, y, z, ry = map(float, fields[8:15])
        except ValueError:
            raise InputError(label_path, f"line {number} is not a KITTI label (15 fields)") from None
        values = np.array([height, width, length, x, y, z, ry])
        if not (np.isfinite(values).all() and min(height, width, length) > 0
                and np.abs(values[:6]).max() <= MAX_COORDINATE):
            raise InputError(label_path, f"line {number}: the box must be finite numbers with positive dimensions, "
                                         f"within {MAX_COORDINATE:g} m")
        kinds.append(fields[0])
        camera_boxes.append([x, y, z, length, height, width, ry])
    boxes = kitti_camera_to_lidar(np.array(camera_boxes).reshape(-1, 7), velodyne_from_rect)
    return [(kind, box[:3], box[3:6], float(box[6])) for kind, box in zip(kinds, boxes)]


def kitti_frames(folder):
    """Yield (scan path, (N, 4) float64 rows x y z intensity, kitti_label_boxes) of every
    ``velodyne/*.bin`` in a KITTI ``folder`` with ``label_2`` and ``calib`` files of the
    same name; InputError naming what is missing or damaged."""
    folder = Path(folder)
    scans = listed(folder / "velodyne", "*.bin") if (folder / "velodyne").is_dir() else []
    if not scans:
        raise InputError(folder, "no velodyne/*.bin scans (expected a KITTI folder with velodyne, label_2, calib)")
    for scan in scans:
        label, calib = folder / "label_2" / f"{scan.stem}.txt", folder / "calib" / f"{scan.stem}.txt"
        for needed in (label, calib):
            if not no_dead_link(needed).is_file():
                raise InputError(scan, f"has no {needed.name} in {needed.parent.name}")
        rows = read_float32_rows(scan, 4, "values (x, y, z, intensity)")
        yield scan, rows.astype(np.float64), kitti_label_boxes(label, calib)


def kitti_scan_objects(folder, min_points: int = 1) -> list:
    """Real objects cut from raw KITTI scans (``kitti_frames``): the points inside each
    labelled box, in its box frame."""
    objects = []
    for scan, rows, labels in kitti_frames(folder):
        for index, (kind, centre, dims, heading) in enumerate(labels):
            local = box_frame(rows[:, :3], centre, heading)
            inside = (np.abs(local) <= dims / 2).all(axis=1)
            if inside.sum() >= max(min_points, 1):
                values = _intensities(scan, rows[inside, 3], "kitti")
                objects.append(LidarObject(f"{scan.stem}:{index}:{kind}", kind.lower(), local[inside], dims, values))
    return objects


def farthest_point_sample(points: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """(count,) indices of ``points`` (N, 3), N >= count, by farthest point sampling from
    a seeded random start: each next point is the one farthest from those chosen."""
    if len(points) < count:
        raise ValueError(f"{len(points)} points are fewer than the {count} to sample")
    chosen = np.empty(count, np.int64)
    chosen[0] = np.random.default_rng(seed).integers(len(points))
    distance = np.full(len(points), np.inf)
    for i in range(1, count):
        distance = np.minimum(distance, ((points - points[chosen[i - 1]]) ** 2).sum(axis=1))
        chosen[i] = int(np.argmax(distance))
    return chosen


def object_set(objects: list, classes: tuple, dataset: str, points: int = DEFAULT_POINTS, seed: int = 0) -> ObjectSet:
    """The objects of ``classes`` as an ObjectSet of ``points`` points each: farthest point
    sampling from seed + i for the i-th object, all points for one of exactly ``points``
    (fewer is the caller's to drop or top up)."""
    kept = [obj for obj in objects if obj.class_name in classes]
    picks = [farthest_point_sample(obj.points, points, seed + i) if len(obj.points) > points
             else np.arange(points) for i, obj in enumerate(kept)]
    xyz = np.stack([obj.points[pick] / (obj.dims / 2) for obj, pick in zip(kept, picks)]).astype(np.float32)
    values = np.stack([obj.values[pick] for obj, pick in zip(kept, picks)]).astype(np.float32)
    index = np.array([classes.index(obj.class_name) for obj in kept], np.int64)
    return ObjectSet(xyz, values, index, tuple(classes), [obj.name for obj in kept], dataset)


def paired_classes(real: list, rgb: list, min_points: int, min_objects: int = 1, classes=None,
                   source="training data") -> tuple:
    """The classes to train: ``classes`` if given (each must have ``min_objects`` objects
    of at least ``min_points`` points in both domains), else every class that has them.
    InputError naming ``source`` (the real data), the class, the count and the
    thresholds otherwise."""
    def counts(objects):
        found = {}
        for obj in objects:
            if len(obj.points) >= min_points:
                found[obj.class_name] = found.get(obj.class_name, 0) + 1
        return found

    real_counts, rgb_counts = counts(real), counts(rgb)
    wanted = sorted(classes) if classes else sorted(set(real_counts) | set(rgb_counts))
    usable = [c for c in wanted if min(real_counts.get(c, 0), rgb_counts.get(c, 0)) >= min_objects]
    short = [c for c in wanted if c not in usable]
    if classes and short or not usable:
        detail = "; ".join(f"{c}: {real_counts.get(c, 0)} real, {rgb_counts.get(c, 0)} rgb" for c in short) \
            or f"no class has any (real: {len(real)} objects, rgb: {len(rgb)} objects)"
        raise InputError(source, f"too few objects with at least {min_points} points "
                                 f"(need {min_objects} per class in each domain): {detail}")
    return tuple(usable)


# Where the RGB domain's objects stand for their scans: (distance m, azimuth deg, heading deg).
RGB_POSES = tuple((distance, azimuth, heading) for distance in (8.0, 15.0, 25.0)
                  for azimuth, heading in ((0.0, 90.0), (30.0, 0.0), (-60.0, 200.0), (120.0, 315.0)))


def scanned_rgb_objects(target, element_rgb: np.ndarray, class_name: str, name: str, sensor,
                        poses=RGB_POSES) -> list:
    """One RGB object per pose: ``target`` (a core.scan ScanTarget, object frame) scanned
    by ``sensor`` with its noise (range noise, intensity spread; seeded by the pose's
    index) at (distance, azimuth, heading) poses; each return takes the sRGB color
    ``element_rgb`` (E, 3) of the face or point it hit (the scan's ``face``)."""
    from ..scan.raycast import ScanOptions, scan_object

    objects = []
    for index, (distance, azimuth, heading) in enumerate(poses):
        x, y = distance * np.cos(np.radians(azimuth)), distance * np.sin(np.radians(azimuth))
        scan = scan_object(target, sensor, x, y, np.radians(heading), ScanOptions(range_noise=True, seed=index))
        rgb = np.asarray(element_rgb, np.float32)[scan.returns["face"], :3]
        objects.append(LidarObject(f"{name}@{distance:g}m/{azimuth:g}/{heading:g}", class_name.lower(),
                                   scan.box_frame_points(target.bounds), target.size, rgb,
                                   scan.returns["intensity"] / sensor.intensity_max))
    return objects


def builtin_rgb_objects(sensor, classes=None, poses=RGB_POSES) -> list:
    """Scans of the built-in sample vehicles, each face colored by its part."""
    from ..classes import MINORITY_CLASSES
    from ..samples import sample_vehicle
    from ..scan.targets import mesh_target, reflectivity_from_srgb

    objects = []
    for class_name in classes or MINORITY_CLASSES:
        vehicle = sample_vehicle(class_name)
        face_rgb = vehicle.colors_at(vehicle.vertices[vehicle.faces].mean(axis=1))
        target = mesh_target(vehicle.vertices, vehicle.faces, f"sample {class_name}",
                             reflectivity_from_srgb(face_rgb))
        objects += scanned_rgb_objects(target, face_rgb, class_name, f"sample:{class_name}", sensor, poses)
    return objects


def prepared_rgb_objects(folder, sensor, poses=RGB_POSES) -> list:
    """Scans of the colored prepared objects in ``folder``: <name>.ply in the object
    frame with a <name>.json sidecar naming its class (prepare_objects.py's output)."""
    from ..authoring.prepare import read_sidecar
    from ..importing import load_reconstruction
    from ..scan.targets import element_colors, target_from_reconstruction

    folder = Path(folder)
    objects = []
    for sidecar in listed(folder, "*.json"):
        model = sidecar.with_suffix(".ply")
        if not no_dead_link(model).is_file():
            continue
        class_name = read_sidecar(sidecar).get("class")
        if not class_name:
            raise InputError(sidecar, "sidecar has no class")
        recon = load_reconstruction(model, with_cameras=False)
        if recon.colors is None:
            raise InputError(model, "has no colors, so it cannot be an RGB-domain object")
        objects += scanned_rgb_objects(target_from_reconstruction(recon), element_colors(recon), class_name,
                                       model.stem, sensor, poses)
    if not objects:
        raise InputError(folder, "no prepared objects (<name>.ply with a <name>.json sidecar)")
    return objects


def material_mesh_rgb_objects(path, class_name: str, sensor, poses=RGB_POSES) -> list:
    """Scans of a mesh whose parts carry material colors (e.g. OBJ + MTL ``Kd``), in the
    object frame (+x forward, +z up, m); each face takes its material's main color
    (importing.mesh.read_material_mesh; grey where the file has none)."""
    from ..importing.mesh import read_material_mesh
    from ..scan.targets import mesh_target, reflectivity_from_srgb

    mesh = read_material_mesh(path)
    face_rgb = np.where(np.isnan(mesh.face_srgb), 0.5, mesh.face_srgb).astype(np.float32)
    target = mesh_target(mesh.vertices, mesh.faces, Path(path).name, reflectivity_from_srgb(face_rgb))
    return scanned_rgb_objects(target, face_rgb, class_name, Path(path).stem, sensor, poses)


def real_objects(source, dataset: str, convention: str | None = None) -> list:
    """Real objects of a ground-truth database pickle or a KITTI folder."""
    source = Path(source)
    if source.suffix == ".pkl":
        return gt_database_objects(source, convention, dataset)
    if source.is_dir():
        if dataset != "kitti":  # its 0..1 intensities would train a 0..255 model
            raise InputError(source, f"is a KITTI folder (KITTI's LiDAR and intensity scale): train a {dataset} "
                                     f"model on a {dataset} database .pkl, or this folder with the dataset kitti")
        return kitti_scan_objects(source)
    raise InputError(source, "not a ground-truth database .pkl or a KITTI folder")


def training_sets(real_sources: list, rgb_sources: list, dataset: str, min_points: int = DEFAULT_POINTS,
                  points: int = DEFAULT_POINTS, seed: int = 0, classes=None, convention: str = "openpcdet"):
    """(real ObjectSet, rgb ObjectSet) over the classes both domains have (paired_classes).
    ``rgb_sources``: folders of prepared objects, or "class=mesh path" for a mesh with
    material colors (e.g. "car=sedan.obj"); none = the built-in samples. Objects
    with fewer than ``min_points`` points are dropped; those below ``points`` (when
    ``min_points`` < ``points``) are topped up by repeating points, seeded."""
    from ..scan.sensors import PRESETS

    real = [obj for source in real_sources for obj in real_objects(source, dataset, convention)]
    sensor = PRESETS[dataset]
    rgb = [obj for source in rgb_sources for obj in rgb_objects(source, sensor)] or builtin_rgb_objects(sensor)
    return paired_sets(real, rgb, dataset, min_points, points, seed, classes, source=real_sources[0])


def paired_sets(real: list, rgb: list, dataset: str, min_points: int = DEFAULT_POINTS,
                points: int = DEFAULT_POINTS, seed: int = 0, classes=None, source="training data") -> tuple:
    """(real ObjectSet, rgb ObjectSet) of LidarObject lists, over paired_classes."""
    chosen = paired_classes(real, rgb, min_points, classes=classes, source=source)
    rng = np.random.default_rng(seed)
    sets = []
    for objects in (real, rgb):
        kept = [_topped_up(obj, points, rng) for obj in objects if len(obj.points) >= min_points]
        sets.append(object_set(kept, chosen, dataset, points, seed))
    return tuple(sets)


def rgb_source(source) -> tuple:
    """(class name, path) of one RGB source, "class=mesh path"; (None, path) for a
    folder of prepared objects. InputError for "=mesh path", a mesh without its class."""
    if isinstance(source, str) and "=" in source:
        class_name, path = source.split("=", 1)
        if not class_name.strip():
            raise InputError(path, f"'{source}' names no class: give CLASS=MESH, e.g. car={path}")
        return class_name, Path(path)
    return None, Path(source)


def rgb_objects(source, sensor) -> list:
    """RGB objects of one source (rgb_source): a mesh of a class or a folder of prepared objects."""
    class_name, path = rgb_source(source)
    if class_name is not None:
        return material_mesh_rgb_objects(path, class_name, sensor)
    return prepared_rgb_objects(path, sensor)


def _topped_up(obj: LidarObject, points: int, rng: np.random.Generator) -> LidarObject:
    if len(obj.points) >= points:
        return obj
    extra = rng.integers(len(obj.points), size=points - len(obj.points))
    physical = None if obj.physical is None else np.concatenate([obj.physical, obj.physical[extra]])
    return LidarObject(obj.name, obj.class_name, np.concatenate([obj.points, obj.points[extra]]), obj.dims,
                       np.concatenate([obj.values, obj.values[extra]]), physical)
