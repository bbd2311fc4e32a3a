"""Placing database entries into a real scene: the whole step.

For each object asked (class and count, in the order given), the cells of the bandit's
polar grid (bandit.ThompsonCells) are tried in the order of one Thompson draw per scene
(with fresh cells: a seeded shuffle), ``batch`` at a time, skipping the cells objects
were placed in already: the objects go to the best cells that suit them. In each cell
a candidate is made: an entry of the class whose
range lies in the cell's range band, turned to a random azimuth in the cell (a whole
number of column steps: entries.column_turn) and lifted onto the ground there (its
bottom at the mean ground height under its centre and corners). The first candidate of the batch that passes every check is placed:

1. **feasible**: its centre and four footprint corners stand where the class may
   (feasibility.Feasibility.allows);
2. **clear of the ego**: its footprint stays ``ego_clearance`` m from the sensor;
3. **no overlap**: its footprint, grown by ``box_margin`` m, overlaps no scene box and
   no object placed before it;
4. **nothing standing in it**: no scene return lies inside its volume more than
   ``standing_tolerance`` m above the ground (a kerb, 0.15 m, is not an obstacle).

After ``tries`` candidates an object that found no place is given up (counted in
``Placement.missing``). Then the scene's points inside the placed boxes are removed
(as the stock samplers do), the range-view occlusion runs (occlusion.occlude), and an
object left with fewer than ``min_points`` points is dropped and the occlusion redone
without it. Every random draw comes from the ``rng`` given.

Why objects were not placed is tallied per class in ``Placement.refused`` {class:
{check: count}} under the names of ``REFUSALS``: candidates refused by each check (1-4,
each counted at the first it fails), objects that found no free cell with an entry at
its range, and objects dropped as too thin once occluded.
"""

import time
from dataclasses import dataclass, field

import numpy as np

from ..boxes import inside_box
from ..scan.sensors import Sensor
from .bandit import ThompsonCells
from .collision import bev_overlaps, footprint_corners
from .entries import EntryPool, column_turn, turn_boxes, turn_points
from .feasibility import Feasibility, scene_feasibility
from .ground import Ground, estimate_ground
from .maps import MapRaster
from .occlusion import occlude

REFUSALS = {"feasible": "stood where the class may not", "ego": "stood within the ego clearance",
            "overlap": "overlapped a box", "standing": "met a scene return", "no cell": "found no free cell in range",
            "occluded": "kept too few points once occluded"}


@dataclass
class PlacementConfig:
    """Settings of ``place_objects`` (the module docstring); distances in metres."""

    sensor: Sensor
    max_distance: float = 54.0
    occlusion: bool = True
    min_points: int = 5
    box_margin: float = 0.1
    ego_clearance: float = 2.0
    standing_tolerance: float = 0.25
    tries: int = 128
    batch: int = 32
    map_bounds_ground: bool = True
    class_layers: dict | None = None


@dataclass
class Placement:
    """The augmented scene. ``points`` (K, C) float32: the inserted objects' kept points
    first, object by object (``rows`` (I, 2) start, stop of each), then the scene's kept
    points. ``boxes`` (B, 7 or 9) centre boxes, the scene's first, ``names`` (B,),
    ``inserted`` (B,) bool, ``ground_height`` (B,) the ground z each box stands on (m,
    Ground.under_boxes), ``entries`` the info dict each inserted box came from, ``turns``
    (I,) rad each was turned by. ``scene_in_boxes`` and ``scene_shadowed`` (N,) bool: scene points removed
    inside placed boxes and in their shadows. ``missing`` {class: objects not placed},
    ``refused`` {class: {check: count}} why (module docstring, REFUSALS).
    ``seconds`` {stage: s}: ground, feasibility, candidates, entries (reading and turning
    the chosen ones), compose (removal, occlusion, the output arrays)."""

    points: np.ndarray
    boxes: np.ndarray
    names: np.ndarray
    inserted: np.ndarray
    ground_height: np.ndarray
    entries: list
    turns: np.ndarray
    rows: np.ndarray
    scene_in_boxes: np.ndarray
    scene_shadowed: np.ndarray
    missing: dict = field(default_factory=dict)
    refused: dict = field(default_factory=dict)
    ground: Ground | None = None
    feasibility: Feasibility | None = None
    seconds: dict = field(default_factory=dict)


def place_objects(points: np.ndarray, boxes: np.ndarray, names, pool: EntryPool, counts: dict,
                  config: PlacementConfig, rng: np.random.Generator, scene_map: MapRaster | None = None,
                  bandit: ThompsonCells | None = None, source="scan") -> Placement:
    """Place ``counts`` {class: n} objects of ``pool`` into a scene of (N, C) sensor-frame
    ``points`` and (M, 7 or 9) centre ``boxes`` named ``names`` (M,). InputError naming
    ``source`` when the scan has no ground, or the pool's source when it has no entry
    of a class asked for."""
    pool.require([name for name, count in counts.items() if count > 0])
    clock = _Clock()
    points = np.asarray(points, np.float32)
    width = boxes.shape[1] if np.ndim(boxes) == 2 and len(boxes) else _box_width(pool)
    scene_boxes = np.asarray(boxes, np.float64).reshape(-1, width)
    xyz = points[:, :3].astype(np.float64)
    ground = estimate_ground(xyz, radius=config.max_distance + 6.0, source=source)
    height = ground.height_above(xyz)
    clock.lap("ground")
    feasibility = scene_feasibility(points, ground, scene_map, radius=config.max_distance,
                                    map_bounds_ground=config.map_bounds_ground,
                                    layers_by_class=config.class_layers, height_above=height)
    clock.lap("feasibility")
    obstacles = xyz[height > config.standing_tolerance]
    bandit = bandit or ThompsonCells(max_range=config.max_distance)
    order = np.argsort(-bandit.draw(rng), kind="stable")
    taken = np.zeros(len(order), bool)  # by position in ``order``: an object stands there

    placed, entries, turns, missing = [], [], [], {}
    refused = {class_name: dict.fromkeys(REFUSALS, 0) for class_name, count in counts.items() if count > 0}
    for class_name, count in counts.items():
        mask = feasibility.map_mask(class_name)
        for _ in range(count):
            found = _place_one(pool.classes[class_name], class_name, mask, order, taken, bandit, feasibility,
                               ground, np.vstack([scene_boxes[:, :7]] + [box[None, :7] for box in placed]),
                               obstacles, config, rng, refused[class_name])
            if found is None:
                missing[class_name] = missing.get(class_name, 0) + 1
                continue
            box, pick, turn = found
            placed.append(box)
            entries.append((class_name, pick))
            turns.append(turn)

    clock.lap("candidates")
    clouds = []
    for (class_name, pick), box, turn in zip(entries, placed, turns):
        stored = pool.classes[class_name]
        clouds.append(turn_points(pool.load(stored.infos[pick]), turn, box[2] - stored.boxes[pick, 2]))
    entries = [(class_name, pool.classes[class_name].infos[pick]) for class_name, pick in entries]
    clock.lap("entries")
    placement = _compose(points, xyz, scene_boxes, np.asarray(names), placed, entries, turns, clouds, ground,
                         feasibility, config, missing, refused)
    clock.lap("compose")
    placement.seconds = clock.laps
    return placement


class _Clock:
    """Seconds per stage: ``lap(name)`` books the time since the previous lap."""

    def __init__(self):
        self.laps, self._last = {}, time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = now - self._last
        self._last = now


def _box_width(pool: EntryPool) -> int:
    for entries in pool.classes.values():
        if len(entries.boxes):
            return entries.boxes.shape[1]
    return 7


def _place_one(entries, class_name, mask, order, taken, bandit, feasibility, ground, boxes, obstacles, config, rng,
               refused):
    """(box, entry index, turn) of the first candidate that passes the checks, or None;
    the cell it stands in is marked ``taken``, the refusals counted in ``refused``."""
    low, high, _, _ = bandit.bounds(order)
    first_entry, past_entry = entries.within(low, high)
    free = np.flatnonzero(~taken & (past_entry > first_entry))  # cells with an entry at their range
    if not len(free):
        refused["no cell"] += 1
    for first in range(0, min(config.tries, len(free)), config.batch):
        positions = free[first:min(first + config.batch, config.tries)]
        _, _, start, stop = bandit.bounds(order[positions])
        spans = past_entry[positions] - first_entry[positions]
        picks = first_entry[positions] + (rng.random(len(positions)) * spans).astype(np.int64)
        stored = entries.boxes[picks]
        target = rng.uniform(start, stop)
        turn = column_turn(np.arctan2(stored[:, 1], stored[:, 0]), target, config.sensor.columns)
        candidates = turn_boxes(stored, turn)  # the checks, cheapest first, each on what passed the last
        spots = np.concatenate([candidates[:, None, :2], footprint_corners(candidates)], axis=1).reshape(-1, 2)
        feasible = feasibility.allows(class_name, spots, mask).reshape(len(candidates), 5).all(axis=1)
        ok = feasible & (_ego_gap(candidates) >= config.ego_clearance)
        clear = ok.copy()
        ok[ok] = ~bev_overlaps(candidates[ok, :7], boxes, config.box_margin).any(axis=1)
        refused["feasible"] += int((~feasible).sum())
        refused["ego"] += int((feasible & ~clear).sum())
        refused["overlap"] += int((clear & ~ok).sum())
        survivors = np.flatnonzero(ok)
        candidates[survivors, 2] = ground.under_boxes(candidates[survivors]) + candidates[survivors, 5] / 2
        for index in survivors:
            if not inside_box(obstacles, candidates[index]).any():
                taken[positions[index]] = True
                return candidates[index], int(picks[index]), float(turn[index])
            refused["standing"] += 1
    return None


def _ego_gap(boxes: np.ndarray) -> np.ndarray:
    """(N,) m from the sensor (the origin) to each box footprint."""
    cos, sin = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    along, across = boxes[:, 0] * cos + boxes[:, 1] * sin, -boxes[:, 0] * sin + boxes[:, 1] * cos
    return np.hypot(np.maximum(np.abs(along) - boxes[:, 3] / 2, 0.0), np.maximum(np.abs(across) - boxes[:, 4] / 2, 0.0))


def _compose(points, xyz, scene_boxes, names, placed, entries, turns, clouds, ground, feasibility, config, missing,
             refused):
    """The Placement: scene points (and their float64 ``xyz``) inside placed boxes removed,
    occlusion, thin objects dropped."""
    placed = np.array(placed, np.float64).reshape(-1, scene_boxes.shape[1])
    in_boxes = np.zeros(len(points), bool)
    for box in placed:
        in_boxes |= inside_box(xyz, box)
    keep = np.ones(len(placed), bool)
    while True:
        chosen = np.flatnonzero(keep)
        inserted = np.concatenate([clouds[i] for i in chosen]) if len(chosen) else np.zeros((0, points.shape[1]),
                                                                                           np.float32)
        owner = np.repeat(np.arange(len(chosen)), [len(clouds[i]) for i in chosen])
        if config.occlusion and len(inserted):
            scene_kept, inserted_kept = occlude(config.sensor, xyz[~in_boxes], inserted, owner)
        else:
            scene_kept, inserted_kept = np.ones((~in_boxes).sum(), bool), np.ones(len(inserted), bool)
        counts = np.bincount(owner[inserted_kept], minlength=len(chosen))
        thin = chosen[counts < config.min_points]
        if not len(thin):
            break
        keep[thin] = False
        for i in thin:
            missing[entries[i][0]] = missing.get(entries[i][0], 0) + 1
            refused[entries[i][0]]["occluded"] += 1
    shadowed = np.zeros(len(points), bool)
    shadowed[np.flatnonzero(~in_boxes)[~scene_kept]] = True
    stops = np.cumsum(counts)
    rows = np.column_stack([stops - counts, stops]).astype(np.int64)
    out_points = np.concatenate([inserted[inserted_kept], points[~in_boxes][scene_kept]])
    out_boxes = np.vstack([scene_boxes, placed[keep]]) if len(chosen) else scene_boxes
    out_names = np.array([*names.tolist(), *(entries[i][0] for i in chosen)], str)
    inserted_mask = np.concatenate([np.zeros(len(scene_boxes), bool), np.ones(len(chosen), bool)])
    bottoms = ground.under_boxes(out_boxes) if len(out_boxes) else np.zeros(0)
    return Placement(out_points, out_boxes, out_names, inserted_mask, bottoms, [entries[i][1] for i in chosen],
                     np.array([turns[i] for i in chosen]), rows, in_boxes, shadowed, missing, refused, ground,
                     feasibility)
