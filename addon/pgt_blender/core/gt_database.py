"""Ground-truth databases as OpenPCDet and mmdetection3d write them, read (the bank's
writer is bank/formats.py): an info pickle ``*_dbinfos_*.pkl`` = {class name: [info,
...]}, each info naming a float32 ``.bin`` of the object's points (``path``, relative to
the dataset root: the pickle's folder unless a bank manifest says otherwise) with its
``box3d_lidar`` [x, y, z, dx, dy, dz, heading, (vx, vy)] and ``num_points_in_gt``.

Both tools store the points translated by the box (never rotated): OpenPCDet by the
box centre, mmdetection3d by its bottom centre. Pickles are read without running code
(safe_pickle); every problem is an InputError naming the file.
"""

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError
from .files import read_float32_rows, regular_file
from .safe_pickle import load_pickle
from .scan.targets import MAX_COORDINATE

REQUIRED_KEYS = ("name", "path", "image_idx", "gt_idx", "box3d_lidar", "num_points_in_gt")
OBJECT_KEYS = ("path", "box3d_lidar", "num_points_in_gt")  # what reading the objects needs
CONVENTIONS = ("mmdet3d", "openpcdet")
CONVENTION_NOTES = {"openpcdet": "OpenPCDet infos (points about the box centre, no group_id)",
                    "mmdet3d": "mmdetection3d infos (points about the box bottom, a group_id each)"}
MAX_POINT_VALUES = 64  # floats per point in an object file: x, y, z and features (the datasets store 4 or 5)


@dataclass
class DatabaseObject:
    """One object of a database in its box frame: ``points`` (N, 3) float64 metres,
    origin at the box centre, +x its heading; ``dims`` (3,) length, width, height;
    ``features`` (N, C) float32 the file's columns after x, y, z (intensity, ...);
    ``name`` "<class>:<path>"; ``source`` the pickle with its checksum; ``centre``
    (3,) float64 the box centre in the sensor frame (m)."""

    name: str
    class_name: str
    points: np.ndarray
    dims: np.ndarray
    features: np.ndarray
    source: str
    centre: np.ndarray


def load_infos(path, required: tuple = REQUIRED_KEYS) -> dict:
    """The info pickle at ``path``: a dict of class name -> list of info dicts, each with
    the ``required`` keys, a finite box3d_lidar of 7 or more values (centre and dimensions
    within MAX_COORDINATE m) and a count >= 0."""
    path = Path(path)
    infos = load_pickle(path)  # names a missing file, a folder or a pipe (files.regular_file)
    if not (isinstance(infos, dict) and all(isinstance(name, str) and isinstance(entries, list)
                                            for name, entries in infos.items())):
        raise InputError(path, "not an info database: expected a dict of class name -> list of infos")
    for name, entries in infos.items():
        for index, info in enumerate(entries):
            if not isinstance(info, dict):
                raise InputError(path, f"info {index} of '{name}' is a {type(info).__name__}, not a dict")
            missing = [key for key in required if key not in info]
            if missing:
                raise InputError(path, f"info {index} of '{name}' lacks {', '.join(missing)}")
            box = np.asarray(info["box3d_lidar"])
            if box.dtype.kind not in "fiu" or box.ndim != 1 or box.size < 7 or not np.isfinite(box).all() \
                    or not (box[3:6] > 0).all() or np.abs(box[:6]).max() > MAX_COORDINATE:
                raise InputError(path, f"info {index} of '{name}': box3d_lidar must be 7 or more finite numbers, "
                                       f"its dimensions positive, within {MAX_COORDINATE:g} m, "
                                       f"got {info['box3d_lidar']!r}")
            count = info["num_points_in_gt"]
            if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or not 0 <= count < 2**31:
                raise InputError(path, f"info {index} of '{name}': num_points_in_gt must be a count >= 0, "
                                       f"got {count!r}")
            if "path" in info and not (isinstance(info["path"], str) and "\0" not in info["path"]):
                raise InputError(path, f"info {index} of '{name}': path must be a file path string, "
                                       f"got {info['path']!r}")
    return infos


def detected_convention(infos: dict) -> str | None:
    """Whose ground-truth database ``infos`` is: "mmdet3d" when every info carries a
    group_id (mmdet3d's create_groundtruth_database always writes one; its points are
    about the box bottom), "openpcdet" when none does (points about the box centre),
    None when empty or mixed."""
    tagged = {"group_id" in info for entries in infos.values() for info in entries}
    if len(tagged) != 1:
        return None
    return "mmdet3d" if tagged.pop() else "openpcdet"


def database_convention(path, infos: dict, given: str | None = None) -> str:
    """The convention of the database ``infos`` read from ``path``: ``given`` (a
    command's convention option) when the infos agree, else what they show
    (detected_convention), else (empty or mixed) "openpcdet". InputError naming
    ``path`` when ``given`` contradicts them: every object would be off by half its
    height."""
    if given is not None and given not in CONVENTIONS:
        raise ValueError(f"unknown ground-truth database convention '{given}' ({', '.join(CONVENTIONS)})")
    found = detected_convention(infos)
    if given is not None and found is not None and given != found:
        raise InputError(path, f"holds {CONVENTION_NOTES[found]}, not {given}'s: leave the convention out (it is "
                               f"read from the file) or give {found}")
    return given or found or "openpcdet"


def read_objects(path, convention: str | None = None, min_points: int = 5) -> list:
    """Every object of ``iter_objects`` in a list."""
    return list(iter_objects(path, convention, min_points))


def iter_objects(path, convention: str | None = None, min_points: int = 5, root=None, choose=None):
    """Yield a DatabaseObject per info of the pickle at ``path`` with at least
    ``min_points`` points (by class name, then as listed), one .bin file read at a
    time, so a database of any size streams. Each is turned into its box frame: moved
    by the box centre ("openpcdet") or bottom centre ("mmdet3d": ``convention``, checked
    and by default read from the infos: database_convention), rotated by -heading about
    z. Object files are relative to ``root`` (default: the pickle's folder).
    ``choose(class_name, counts)`` -> indices into ``counts`` (the (n,)
    num_points_in_gt of the class's infos with enough points) picks which to read, in
    that order (default: all)."""
    path = Path(path)
    root = path.parent if root is None else Path(root)
    infos = load_infos(path, OBJECT_KEYS)
    convention = database_convention(path, infos, convention)
    source = f"gt_database:{path.name} ({convention}) sha256:{hashlib.sha256(path.read_bytes()).hexdigest()}"
    for class_name, class_infos in sorted(infos.items()):
        usable = [info for info in class_infos if int(info["num_points_in_gt"]) >= max(min_points, 1)]
        counts = np.array([int(info["num_points_in_gt"]) for info in usable], np.int64)
        for index in (range(len(usable)) if choose is None else choose(class_name, counts)):
            info = usable[index]
            yield _object(root / info["path"], np.asarray(info["box3d_lidar"], np.float64)[:7],
                          int(counts[index]), convention, class_name, info["path"], source)


def _object(path: Path, box: np.ndarray, count: int, convention: str, class_name: str, relative: str,
            source: str) -> DatabaseObject:
    if not (box[3:6] > 0).all():
        raise InputError(path, f"its box has non-positive dims {box[3:6].tolist()}")
    floats = regular_file(path).stat().st_size // 4  # checked before the read: a file of gigabytes stays unread
    if not 3 * count <= floats <= MAX_POINT_VALUES * count or floats % count:
        raise InputError(path, f"{floats} floats do not split into the {count} points its info declares "
                               f"(3 to {MAX_POINT_VALUES} values each)")
    columns = read_float32_rows(path, floats // count, rows=count)
    points = columns[:, :3].astype(np.float64)
    if convention == "mmdet3d":
        points[:, 2] -= box[5] / 2  # bottom centre -> centre
    cos, sin = np.cos(box[6]), np.sin(box[6])
    points[:, :2] = points[:, :2] @ np.array([[cos, -sin], [sin, cos]])  # rows rotated by -heading
    centre = box[:3].copy()
    if convention == "mmdet3d":
        centre[2] += box[5] / 2  # mmdet3d's box3d_lidar z is the bottom
    return DatabaseObject(f"{class_name}:{relative}", class_name, points, box[3:6].copy(), columns[:, 3:].copy(),
                          source, centre)
