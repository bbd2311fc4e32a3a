"""Per-class object sets of a ground-truth database, streamed one object at a time
(gt_database.iter_objects): a bank's or a real one's, so memory holds only SET_POINTS
points per object, never a database's files.

Every object is *box-normalised*: its points in its box frame (origin at the box
centre, +x its heading, +z up) divided by half its box dims, so the box is [-1, 1]^3;
then SET_POINTS of them are drawn (without replacement when it has that many, else
with), from a Generator seeded by (seed, object's rank in its class). Two statistics
use all of an object's points or only its box: how much of the box its points fill
(``fill``) and where the box stands against the dataset's flat ground (``grade``).
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..bank.folder import INTENSITY_BINS, MANIFEST, info_path_root, read_manifest
from ..errors import InputError
from ..gt_database import iter_objects
from ..scan.sensors import INTENSITY_MAX, sensor_from_name

SET_POINTS = 64  # points per object, as the paper's FID
REFERENCE_GROUPS = 32  # the paper's real-reference sampling: point-count groups
PAPER_REFERENCE_SIZE = 593  # objects per class the paper's sampling kept
REFERENCES = ("all", "dense")


@dataclass
class ClassSet:
    """One class's objects.

    xyz:        (n, SET_POINTS, 3) float32 box-normalised points.
    intensity:  (n, SET_POINTS) float32 intensity over the dataset's maximum, in [0, 1].
    points:     (n,) int64 points per object (all of its points, not the drawn ones).
    distance:   (n,) float64 m, box-centre distance from the sensor, hypot(x, y).
    histogram:  (INTENSITY_BINS,) int64 counts of every point's intensity over [0, 1].
    fill:       (n, 3) float64 box units, per box axis (x along the heading, y, z) half
                the range of all of the object's box-normalised points: 1 when they span
                the box side, less when the box is larger than what was hit.
    grade:      (n,) float64 degrees, the box bottom's elevation angle from the foot
                of the sensor: atan2(bottom z + mounting_height, distance), the
                dataset's preset mounting height (0 on flat ground at -mounting_height;
                road grade spreads it, see bank/ground.py).
    """

    xyz: np.ndarray
    intensity: np.ndarray
    points: np.ndarray
    distance: np.ndarray
    histogram: np.ndarray
    fill: np.ndarray
    grade: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


def dense_reference(counts: np.ndarray, size: int = PAPER_REFERENCE_SIZE, groups: int = REFERENCE_GROUPS) -> np.ndarray:
    """The paper's real-reference sampling (supplement, Quality of Pseudo Labels), as we
    read it: objects sorted by point count, descending, cut into ``groups`` contiguous
    groups of (near) equal size; each group gives its densest ceil(size / groups)
    objects, groups in order, until ``size`` are chosen. Returns indices into
    ``counts``: every density range is represented, dense objects first within each."""
    order = np.argsort(-counts, kind="stable")
    if len(order) <= size:
        return order
    per_group = -(-size // groups)
    chosen = np.concatenate([group[:per_group] for group in np.array_split(order, groups)])
    return chosen[:size]


def database_sets(info_pickle, convention: str | None, dataset: str, root=None, reference: str = "all",
                  seed: int = 0, limit: int | None = None, min_points: int = 1, progress=None) -> dict:
    """{class name: ClassSet} of the database ``info_pickle`` (``convention`` openpcdet or
    mmdet3d, None: read from its infos, gt_database.database_convention; its .bin
    intensities on ``dataset``'s scale). ``reference`` "dense" applies
    dense_reference (size ``limit`` or the paper's 593); "all" keeps every object, or
    ``limit`` of them drawn without replacement (seeded) when given. ``progress(n)`` is
    called after each object read."""
    if reference not in REFERENCES:
        raise ValueError(f"unknown reference sampling {reference!r} ({', '.join(REFERENCES)})")
    rng = np.random.default_rng(seed)

    def choose(class_name, counts):
        if reference == "dense":
            return dense_reference(counts, limit or PAPER_REFERENCE_SIZE)
        if limit is not None and len(counts) > limit:
            return np.sort(rng.choice(len(counts), limit, replace=False))
        return range(len(counts))

    maximum = INTENSITY_MAX[dataset]
    mounting_height = sensor_from_name(dataset).mounting_height
    columns = {}  # class -> lists of per-object arrays
    for obj in iter_objects(info_pickle, convention, min_points, root, choose):
        if obj.features.shape[1] < 1:
            raise InputError(info_pickle, f"{obj.name} has no intensity column (3 columns per point)")
        found = columns.setdefault(obj.class_name, {"xyz": [], "intensity": [], "points": [], "distance": [],
                                                    "histogram": np.zeros(INTENSITY_BINS, np.int64), "fill": [],
                                                    "grade": []})
        intensity = np.clip(obj.features[:, 0] / maximum, 0.0, 1.0).astype(np.float32)
        normalised = obj.points / (obj.dims / 2)
        draw = np.random.default_rng([seed, len(found["points"])])
        pick = draw.choice(len(obj.points), SET_POINTS, replace=len(obj.points) < SET_POINTS)
        distance = float(np.hypot(*obj.centre[:2]))
        found["xyz"].append(normalised[pick].astype(np.float32))
        found["intensity"].append(intensity[pick])
        found["points"].append(len(obj.points))
        found["distance"].append(distance)
        found["histogram"] += np.histogram(intensity, INTENSITY_BINS, (0.0, 1.0))[0]
        found["fill"].append(np.ptp(normalised, axis=0) / 2)
        bottom = obj.centre[2] - obj.dims[2] / 2 + mounting_height
        found["grade"].append(float(np.degrees(np.arctan2(bottom, distance))))
        if progress is not None:
            progress(1)
    return {name: ClassSet(np.stack(found["xyz"]), np.stack(found["intensity"]),
                           np.array(found["points"], np.int64), np.array(found["distance"]), found["histogram"],
                           np.array(found["fill"]), np.array(found["grade"]))
            for name, found in sorted(columns.items())}


def bank_database(out) -> tuple:
    """(info pickle, convention, dataset, root) of the bank in folder ``out``, from its
    manifest (folder.read_manifest): the OpenPCDet pickle when the bank has one, else
    the mmdet3d one."""
    out = Path(out)
    manifest = read_manifest(out)
    pickles = manifest["info_pickles"]
    convention = next((fmt for fmt in ("openpcdet", "mmdet3d") if fmt in pickles), None)
    if convention is None:
        raise InputError(out / MANIFEST, "lists no openpcdet or mmdet3d info pickle")
    info_pickle = out / pickles[convention]
    return info_pickle, convention, manifest["config"]["dataset"], info_path_root(info_pickle)
