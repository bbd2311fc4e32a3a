"""A ground-truth database's entries (a bank, a real database or a mix) as placement
draws them: by class, by range.

An entry holds what the sensor saw of an object at one pose, so it may only move in
ways that keep that view (the module ``place`` relies on these):

- **turned about the sensor's vertical axis** by an angle: a rotating LiDAR sees the
  same object the same way at every azimuth, its lasers turning with the head. The
  angle is a whole number of the sensor's column steps (``column_turn``), so the
  entry's rays stay on the sensor's columns; the azimuth placed is then within half a
  step of the one asked (0.17 deg for nuScenes' 1080 columns: 0.15 m sideways at 50 m);
- **lifted** by the ground height difference between its pose and the new one: the
  elevations of its rays shift by about lift / range (0.3 m at 30 m: 0.6 deg, about half
  of nuScenes' 1.33 deg ring gap), which no rotation can undo;
- **never moved in range**.

Boxes are centre boxes (mmdet3d's bottom boxes converted on reading); points are read
as the frameworks read them (float32 rows of ``columns``, translated by the stored box
centre or, for mmdet3d, its bottom centre) into the sensor frame at the stored pose.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import read_float32_rows
from ..gt_database import CONVENTIONS


@dataclass
class ClassEntries:
    """One class's entries sorted by range: ``boxes`` (K, 7 or 9) centre boxes at their
    stored pose, ``ranges`` (K,) horizontal sensor-to-centre distance (m), ``infos`` the
    database's info dicts in the same order."""

    boxes: np.ndarray
    ranges: np.ndarray
    infos: list

    def within(self, low: np.ndarray, high: np.ndarray) -> tuple:
        """(start, stop) (N,) each: the entries whose range lies in [low, high), (N,) m each."""
        return np.searchsorted(self.ranges, low, "left"), np.searchsorted(self.ranges, high, "left")


class EntryPool:
    """The entries of an info database ``{class: [info, ...]}`` by class, within
    ``max_distance`` m (the paper's distance filter: farther entries are never placed),
    with at least ``min_points`` points. ``load(info)`` -> (N, C) float32 points in the
    sensor frame at the stored pose (default: read from ``root`` / info["path"] the way
    the frameworks do, ``columns`` float32 per row, ``convention`` "openpcdet" or "mmdet3d")."""

    def __init__(self, infos: dict, root=None, convention: str = "openpcdet", columns: int = 4,
                 max_distance: float = 54.0, min_points: int = 5, load=None, source="database"):
        if convention not in CONVENTIONS:
            raise ValueError(f"unknown database convention {convention!r} ({', '.join(CONVENTIONS)})")
        self.convention, self.columns, self.root = convention, columns, None if root is None else Path(root)
        self.max_distance, self.min_points, self.source, self._load = max_distance, min_points, source, load
        self.classes = {}
        for name, entries in infos.items():
            kept = [info for info in entries if int(info["num_points_in_gt"]) >= min_points]
            boxes = np.array([centre_box(info["box3d_lidar"], convention) for info in kept], np.float64)
            boxes = boxes.reshape(len(kept), -1 if kept else 7)
            ranges = np.hypot(boxes[:, 0], boxes[:, 1]) if len(kept) else np.zeros(0)
            near = np.flatnonzero(ranges <= max_distance)
            order = near[np.argsort(ranges[near], kind="stable")]
            self.classes[name] = ClassEntries(boxes[order], ranges[order], [kept[i] for i in order])

    def require(self, class_names) -> None:
        """InputError naming the database when one of ``class_names`` has no entry to place."""
        empty = [name for name in class_names if name not in self.classes or not len(self.classes[name].ranges)]
        if empty:
            have = [name for name, entries in self.classes.items() if len(entries.ranges)]
            raise InputError(self.source, f"no {', '.join(map(repr, empty))} entry within {self.max_distance:g} m "
                                          f"with {self.min_points} or more points to place (it has "
                                          f"{', '.join(have) or 'none'})")

    def load(self, info: dict) -> np.ndarray:
        """(N, C) float32 points of ``info`` in the sensor frame at its stored pose."""
        if self._load is not None:
            return self._load(info)
        # stored relative to box3d_lidar[:3]: the centre, or mmdet3d's bottom centre
        rows = read_float32_rows(self.root / info["path"], self.columns, "point columns",
                                 int(info["num_points_in_gt"])).copy()
        rows[:, :3] += np.asarray(info["box3d_lidar"][:3], np.float32)
        return rows


def centre_box(box, convention: str) -> np.ndarray:
    """A stored box3d_lidar as a float64 centre box (mmdet3d's z is the bottom)."""
    box = np.asarray(box, np.float64).copy()
    if convention == "mmdet3d":
        box[2] += box[5] / 2
    return box


def column_turn(from_azimuth: np.ndarray, to_azimuth: np.ndarray, columns: int) -> np.ndarray:
    """(N,) rad: the whole number of column steps (2 pi / ``columns``) nearest to turning
    ``from_azimuth`` onto ``to_azimuth`` (N,) rad."""
    step = 2 * np.pi / columns
    difference = np.angle(np.exp(1j * (np.asarray(to_azimuth) - np.asarray(from_azimuth))))
    return np.round(difference / step) * step


def turn_boxes(boxes: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(N, 7 or 9) centre boxes turned by ``angles`` (N,) rad about the sensor's z axis:
    centre, heading (wrapped to [-pi, pi)) and velocity turned, z kept."""
    turned = np.array(boxes, np.float64, copy=True).reshape(-1, np.shape(boxes)[-1])
    cos, sin = np.cos(angles), np.sin(angles)
    for first in (0, 7)[:1 + (turned.shape[1] >= 9)]:
        x, y = turned[:, first].copy(), turned[:, first + 1].copy()
        turned[:, first], turned[:, first + 1] = cos * x - sin * y, sin * x + cos * y
    turned[:, 6] = (turned[:, 6] + angles + np.pi) % (2 * np.pi) - np.pi
    return turned


def turn_points(points: np.ndarray, angle: float, lift: float) -> np.ndarray:
    """(N, C) points turned by ``angle`` rad about the sensor's z axis and raised by
    ``lift`` m (x, y, z moved, other columns kept, dtype kept)."""
    cos, sin = np.cos(angle), np.sin(angle)
    moved = np.array(points, copy=True)
    moved[:, :2] = (moved[:, :2].astype(np.float64) @ np.array([[cos, sin], [-sin, cos]])).astype(moved.dtype)
    moved[:, 2] += lift
    return moved


def open_database(path, dataset: str, convention: str | None = None, max_distance: float = 54.0,
                  min_points: int = 5) -> EntryPool:
    """The EntryPool of a bank folder (its manifest names the info pickle; the
    openpcdet format when it has both) or of an info pickle (``convention``, checked
    and by default read from its infos: gt_database.database_convention; object files
    relative to the pickle's folder), for scans of ``dataset`` (its column count).
    InputError naming what is wrong."""
    from ..bank.folder import read_manifest
    from ..gt_database import database_convention, load_infos
    from ..scan.sensors import BIN_COLUMNS

    path = Path(path)
    if path.is_dir():
        manifest = read_manifest(path)
        formats = manifest["config"]["formats"]
        fmt = convention or ("openpcdet" if "openpcdet" in formats else formats[0])
        if fmt not in formats:
            raise InputError(path, f"the bank has no {fmt} format (it has {', '.join(formats)})")
        if manifest["config"]["dataset"] != dataset:
            raise InputError(path, f"the bank is for {manifest['config']['dataset']}, the scene is {dataset}")
        pickle_path = path / manifest["info_pickles"][fmt]
        root = path / manifest["data_root"] if manifest.get("data_root") else path / fmt
    else:
        fmt, pickle_path, root = convention, path, path.parent
    infos = load_infos(pickle_path, ("path", "box3d_lidar", "num_points_in_gt"))
    pool = EntryPool(infos, root, database_convention(pickle_path, infos, fmt), len(BIN_COLUMNS[dataset]),
                     max_distance, min_points, source=pickle_path)
    if not any(len(entries.ranges) for entries in pool.classes.values()):
        raise InputError(pickle_path, f"no entry within {max_distance:g} m with {min_points} or more points")
    return pool
