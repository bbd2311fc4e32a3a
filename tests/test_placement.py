"""Placement into real scenes (core/placement): ground, maps, fusion, collision,
occlusion, Thompson sampling and the whole step, on analytic scenes (a sensor's rays
cast exactly onto planes and boxes) and on the shared real scans (KITTI frames, the
nuScenes sample with its mmdetection3d info)."""

import json
import os
import pickle
from pathlib import Path

import numpy as np
import pytest

from pgt_blender.core.bank.config import config_from_table
from pgt_blender.core.bank.export import export_bank
from pgt_blender.core.bank.inputs import checked_objects, prepared_objects
from pgt_blender.core.authoring.prepare import prepare, write_prepared
from pgt_blender.core.boxes import inside_box
from pgt_blender.core.errors import InputError
from pgt_blender.core.importing import load_reconstruction
from pgt_blender.core.placement.bandit import ThompsonCells, ThompsonFile
from pgt_blender.core.placement.collision import bev_overlaps, footprint_corners
from pgt_blender.core.placement.entries import EntryPool, column_turn, open_database, turn_boxes, turn_points
from pgt_blender.core.placement.feasibility import scene_feasibility
from pgt_blender.core.placement.folder import read_placement
from pgt_blender.core.placement.ground import estimate_ground
from pgt_blender.core.placement.maps import (ImagePose, checked_class_layers, checked_legend, map_from_image,
                                             map_from_polygons, read_polygons)
from pgt_blender.core.placement.occlusion import occlude
from pgt_blender.core.placement.place import PlacementConfig, place_objects
from pgt_blender.core.placement.scenes import read_scene
from pgt_blender.core.samples import write_sample
from pgt_blender.core.scan.range_view import cells_of_points
from pgt_blender.core.scan.sensors import PRESETS
from pgt_blender.dev import scan_ground_gap

from .conftest import run_script

NUSCENES, KITTI = PRESETS["nuscenes"], PRESETS["kitti"]


# --- analytic scenes ------------------------------------------------------------------


def cast(sensor, ground, boxes=(), cells=None) -> tuple:
    """(points (K, 3), cells (K,)) of the sensor's rays (all cells, or ``cells``) hitting
    ``ground(x, y) -> z`` (a plane: z = c + a x + b y given as (a, b, c)) or axis-aligned
    ``boxes`` [(low (3,), high (3,))], first hit only, from the sensor origin."""
    cells = np.arange(sensor.beams * sensor.columns) if cells is None else np.asarray(cells)
    directions = sensor.directions[cells]
    a, b, c = ground
    down = directions[:, 2] - a * directions[:, 0] - b * directions[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(down < 0, c / down, np.inf)
        for low, high in boxes:
            t0, t1 = (np.asarray(low) / directions), (np.asarray(high) / directions)
            near, far = np.minimum(t0, t1).max(axis=1), np.maximum(t0, t1).min(axis=1)
            t = np.where((near <= far) & (near > 0) & (near < t), near, t)
    hit = np.isfinite(t) & (t <= 80)
    return directions[hit] * t[hit, None], cells[hit]


VAN = ((8.0, -4.0, -2.0), (13.0, -2.0, 0.4))  # axis-aligned, 5 x 2 m, standing on the road


@pytest.mark.parametrize("surface", ["3 % grade", "kerb"])
def test_ground_follows_slopes_and_kerbs_and_ignores_a_parked_van(surface):
    """nuScenes rays on a 3 % grade, or on a level road with a 0.15 m kerb (a raised
    platform past y = 6 m), with a van on the road: every measured cell within 3.5 cm of
    the true surface (1.5 m from the kerb's edge) but the van's own, which sees only its
    flank's foot (within 0.1 m: ground.py's accuracy note); its returns stand above the
    ground."""
    if surface == "kerb":
        points, _ = cast(NUSCENES, (0.0, 0.0, -1.84), boxes=[VAN, ((-80.0, 6.0, -2.0), (80.0, 80.0, -1.69))])
        truth = lambda xy: np.where(xy[:, 1] > 6.0, -1.69, -1.84)  # noqa: E731
    else:
        points, _ = cast(NUSCENES, (0.03, 0.0, -1.84), boxes=[VAN])
        truth = lambda xy: -1.84 + 0.03 * xy[:, 0]  # noqa: E731
    ground = estimate_ground(points, radius=40.0)
    centres = ground.origin + (np.argwhere(ground.measured)[:, ::-1] + 0.5) * ground.cell
    assert ground.measured.sum() > 100
    off_van = ~((centres[:, 0] > 7) & (centres[:, 0] < 14) & (centres[:, 1] > -5) & (centres[:, 1] < -1))
    judged = off_van & ((np.abs(centres[:, 1] - 6.0) > 1.5) if surface == "kerb" else True)
    error = np.abs(ground.height(centres) - truth(centres))
    np.testing.assert_array_less(error[judged], 0.035)
    np.testing.assert_array_less(error[~off_van], 0.1)
    van = inside_box(points, np.array([10.5, -3.0, -0.8, 5.0, 2.0, 2.4, 0.0]))
    high = points[van][points[van, 2] - truth(points[van]) > 0.45]  # above the flank's foot
    assert len(high) > 100 and (ground.height_above(high) > 0.3).all()


def test_ground_follows_a_steep_grade_where_cells_see_one_or_two_rings():
    """nuScenes rays on an 8 degree grade: a cell crossed by one or two rings takes its
    slope from its neighbourhood (alone, the ridge pulled it to a quarter of the grade)."""
    grade = np.tan(np.radians(8.0))
    points, _ = cast(NUSCENES, (grade, 0.0, -1.84))
    ground = estimate_ground(points)
    slopes = ground.coefficients[..., 0][ground.measured]
    assert np.median(slopes) > 0.9 * grade
    xy = np.random.default_rng(0).uniform(-40, 40, (20000, 2))
    xy = xy[ground.is_measured(xy) & (np.hypot(*xy.T) > 5)]
    assert np.median(np.abs(ground.height(xy) - (-1.84 + grade * xy[:, 0]))) < 0.01


def test_a_scan_without_ground_below_the_sensor_is_refused():
    ceiling, _ = cast(NUSCENES, (0.0, 0.0, 30.0))  # a plane above: only the upward beams see it
    with pytest.raises(InputError, match="scan.bin: no ground found"):
        estimate_ground(ceiling[ceiling[:, 2] > 0], source="scan.bin")


def test_bev_overlap_of_turned_boxes():
    square = [0.0, 0.0, 0.0, 2.0, 2.0, 1.0, 0.0]
    diamond = [2.3, 0.0, 0.0, 2.0, 2.0, 1.0, np.pi / 4]  # corner at x = 2.3 - 1.414 = 0.886 < 1: overlaps
    apart = [2.5, 0.0, 0.0, 2.0, 2.0, 1.0, np.pi / 4]  # corner at 1.086: clear
    touching = [2.0, 0.0, 0.0, 2.0, 2.0, 1.0, 0.0]  # shares an edge: not an overlap
    long_thin = [0.0, 3.0, 0.0, 10.0, 0.5, 1.0, np.pi / 2]  # crosses nothing: x in [-0.25, 0.25], y in [-2, 8]
    found = bev_overlaps(np.array([square]), np.array([diamond, apart, touching, long_thin]))
    assert found.tolist() == [[True, False, False, True]]
    assert bev_overlaps(np.array([square]), np.array([touching]), margin=0.01).tolist() == [[True]]
    corners = footprint_corners(np.array([[1.0, 2.0, 0.0, 4.0, 2.0, 1.0, np.pi / 2]]))[0]
    np.testing.assert_allclose(sorted(map(tuple, corners.round(9))), [(0, 0), (0, 4), (2, 0), (2, 4)], atol=1e-9)


def test_occlusion_is_exact_cell_by_cell():
    """Points built on the sensor's own rays, so which ones a nearer point hides is known
    by construction: a wall at 10 m in some cells, an object at 20 m in others (half of
    them behind the wall), ground at 30 m behind both, a second object behind the first."""
    rng = np.random.default_rng(0)
    cells = rng.choice(NUSCENES.beams * NUSCENES.columns, 600, replace=False)
    wall, obj, other, free = np.split(cells, [150, 300, 350])
    behind_wall = obj[:75]
    scene_cells = np.concatenate([wall, obj[75:], free, behind_wall])
    scene_ranges = np.concatenate([np.full(150, 10.0), np.full(75, 30.0), np.full(len(free), 30.0), np.full(75, 10.0)])
    inserted_cells = np.concatenate([obj, other, obj[100:120]])
    inserted_ranges = np.concatenate([np.full(150, 20.0), np.full(50, 25.0), np.full(20, 22.0)])
    owner = np.concatenate([np.zeros(150, int), np.ones(50, int), np.ones(20, int)])
    scene = NUSCENES.return_points(scene_cells, scene_ranges)
    inserted = NUSCENES.return_points(inserted_cells, inserted_ranges)
    scene_kept, inserted_kept = occlude(NUSCENES, scene, inserted, owner)
    # scene: the 75 ground points at 30 m in the object's unobstructed cells are in its shadow
    expected_scene = np.ones(len(scene_cells), bool)
    expected_scene[150:225] = False
    np.testing.assert_array_equal(scene_kept, expected_scene)
    # inserted: the object's 75 points behind the wall, and object 1's 20 points at 22 m
    # behind object 0's at 20 m; object 1's own cells are clear
    expected_inserted = np.ones(len(inserted_cells), bool)
    expected_inserted[:75] = False
    expected_inserted[200:] = False
    np.testing.assert_array_equal(inserted_kept, expected_inserted)


def test_an_entry_turned_by_whole_columns_keeps_its_rings_and_columns():
    """The turn placement uses moves every return by exactly k columns, ring unchanged,
    range unchanged, also with KITTI's lasers off the sensor origin (they turn with the
    head)."""
    for sensor in (NUSCENES, KITTI):
        cells = np.arange(sensor.beams) * sensor.columns + 37
        points = sensor.return_points(cells, np.full(len(cells), 15.0))
        angle = column_turn(np.zeros(1), np.array([0.9]), sensor.columns)[0]
        steps = round(angle / (2 * np.pi / sensor.columns))
        moved = turn_points(np.column_stack([points, np.ones(len(points))]), angle, 0.0)
        new_cells, new_ranges = cells_of_points(sensor, moved[:, :3])
        rings, columns = np.divmod(new_cells, sensor.columns)
        np.testing.assert_array_equal(rings, np.arange(sensor.beams))
        np.testing.assert_array_equal(columns, (37 + sensor.direction * steps) % sensor.columns)
        np.testing.assert_allclose(new_ranges, 15.0, atol=1e-9)
        assert abs(angle - 0.9) <= np.pi / sensor.columns + 1e-12
    box = turn_boxes(np.array([[10.0, 0.0, -1.0, 4.0, 2.0, 1.5, 3.0, 1.0, 0.0]]), np.array([np.pi / 2]))[0]
    np.testing.assert_allclose(box, [0.0, 10.0, -1.0, 4.0, 2.0, 1.5, 3.0 + np.pi / 2 - 2 * np.pi, 0.0, 1.0],
                               atol=1e-12)


# --- maps and fusion ------------------------------------------------------------------


def yaw_pose(yaw_deg: float, x: float, y: float) -> np.ndarray:
    pose = np.eye(4)
    cos, sin = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    pose[:2, :2] = [[cos, -sin], [sin, cos]]
    pose[:2, 3] = x, y
    return pose


def test_polygons_and_an_image_of_the_same_map_agree_and_holes_are_cut(tmp_path):
    """A road square with a hole and a sidewalk strip, in the world, seen from a sensor
    at (100, 200) turned by 30 degrees: the polygon raster and the image raster (its
    pose: 0.1 m per pixel from the world origin's top-left at y = 300) agree but for
    pixels on the outlines, and the sensor-frame raster is the world shapes turned."""
    road = [[[80, 180], [130, 180], [130, 230], [80, 230]], [[100, 195], [105, 195], [105, 205], [100, 205]]]
    sidewalk = [[70, 180], [78, 180], [78, 230], [70, 230]]
    path = tmp_path / "map.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"layer": "road"}, "geometry": {"type": "Polygon", "coordinates": road}},
        {"type": "Feature", "properties": {"layer": "sidewalk"},
         "geometry": {"type": "MultiPolygon", "coordinates": [[sidewalk]]}}]}))
    pose = yaw_pose(30.0, 100.0, 200.0)
    polygons = map_from_polygons(read_polygons(path), pose, radius=20.0, resolution=0.2)
    assert polygons.layers == ("road", "sidewalk")
    world = np.array([[110.0, 210.0], [102.5, 200.0], [74.0, 200.0], [90.0, 235.0]])  # road, hole, sidewalk, none
    local = (np.column_stack([world, np.zeros(4), np.ones(4)]) @ np.linalg.inv(pose).T)[:, :2]
    assert polygons.allows(["road"], local).tolist() == [True, False, False, False]
    assert polygons.allows(["sidewalk"], local).tolist() == [False, False, False, False]  # beyond 20 m
    near = map_from_polygons(read_polygons(path), yaw_pose(0.0, 85.0, 200.0), radius=20.0, resolution=0.2)
    assert near.allows(["sidewalk"], np.array([[74.0 - 85.0, 0.0]])).tolist() == [True]

    xs = (np.arange(3000) + 0.5) * 0.1
    ys = 300.0 - (np.arange(3000) + 0.5) * 0.1
    grid_x, grid_y = np.meshgrid(xs, ys)
    image = np.zeros(grid_x.shape, np.uint8)
    image[(grid_x > 80) & (grid_x < 130) & (grid_y > 180) & (grid_y < 230)] = 1
    image[(grid_x > 100) & (grid_x < 105) & (grid_y > 195) & (grid_y < 205)] = 0
    image[(grid_x > 70) & (grid_x < 78) & (grid_y > 180) & (grid_y < 230)] = 2
    raster = map_from_image(image, {"road": 1, "sidewalk": 2}, ImagePose(0.0, 300.0, 0.1), pose, 20.0, 0.2)
    differs = raster.masks != polygons.masks
    assert differs.sum() < 0.02 * polygons.masks.sum()
    with pytest.raises(InputError, match="map.png: the map image does not cover the scene"):
        map_from_image(image, {"road": 1}, ImagePose(0.0, 300.0, 0.1), yaw_pose(0, 5.0, 200.0), 20.0, 0.2,
                       source="map.png")
    with pytest.raises(InputError, match="map.png: the map image does not cover the scene"):
        map_from_image(image, {"road": 1}, ImagePose(1e308, 300.0, 1e-300), pose, 20.0, 0.2, source="map.png")


@pytest.mark.parametrize("legend, channels, problem", [
    ({}, 1, "expected a JSON object"),
    ([1], 1, "expected a JSON object"),
    ({"road": [300, 300, 300]}, 3, "legend entry 'road' is [300, 300, 300]: expected [r, g, b] of 0-255"),
    ({"road": float("nan")}, 1, "legend entry 'road' is nan: expected a label 0-255"),
    ({"road": True}, 1, "legend entry 'road' is True"),
    ({"road": [1, 2, 3]}, 1, "expected a label 0-255 for a one-channel image"),
    ({"road": 4}, 3, "expected [r, g, b] of 0-255 for a colour image"),
])
def test_map_legends_hold_8_bit_keys_for_the_image(legend, channels, problem):
    with pytest.raises(InputError) as caught:
        checked_legend(legend, channels, "legend.json")
    assert str(caught.value).startswith("legend.json: ") and problem in str(caught.value)


@pytest.mark.parametrize("table, problem", [
    ([], "expected a JSON object {class: [layer, ...]}"),
    ({"car": "road"}, "class 'car' has 'road': expected a list of layer names"),  # not the letters r, o, a, d
    ({"car": [1]}, "class 'car' has [1]"),
])
def test_class_layer_tables_are_lists_of_layer_names(table, problem):
    with pytest.raises(InputError) as caught:
        checked_class_layers(table, "layers.json")
    assert str(caught.value).startswith("layers.json: ") and problem in str(caught.value)
    assert checked_class_layers({"car": ["road", "parking"]}, "layers.json") == {"car": ("road", "parking")}


@pytest.mark.parametrize("content, problem", [
    ({"type": "FeatureCollection", "features": [{"geometry": {"type": "Polygon", "coordinates": [[[0, 0], [1, 0],
                                                                                                  [1, 1]]]}}]},
     "feature 0 has no 'layer' property"),
    ([{"layer": "road", "polygon": [[0, 0], [1, 1]]}], "a ring needs 3 or more finite"),
    ({"type": "FeatureCollection", "features": [{"properties": {"layer": "road"},
                                                 "geometry": {"type": "LineString", "coordinates": [[0, 0], [1, 1]]}}]},
     "is a 'LineString', not a Polygon"),
    ({"road": []}, "not a GeoJSON FeatureCollection"),
    ({"type": "FeatureCollection", "features": None}, "features must be a list"),
    ({"type": "FeatureCollection", "features": [{"properties": {"layer": "road"}, "geometry": 5}]},
     "is a None, not a Polygon"),
])
def test_bad_map_polygons_are_named(tmp_path, content, problem):
    path = tmp_path / "map.json"
    path.write_text(json.dumps(content))
    with pytest.raises(InputError, match=f"map.json: .*{problem}"):
        read_polygons(path)


def test_the_map_decides_where_the_scan_sees_nothing_and_the_ground_elsewhere():
    """Flat ground seen out to about 25 m except behind a wall east of the sensor; a
    road everywhere with y < 3 m, a sidewalk above it: seen road and seen sidewalk follow
    the ground (the sidewalk bounded by the map unless map_bounds_ground is off), the
    wall's cells never, unseen road yes, unseen sidewalk no, unseen without a map no."""
    points, _ = cast(NUSCENES, (0.0, 0.0, -1.84), boxes=[((12.0, -2.0, -1.84), (12.5, 2.0, 1.0))])
    points = points[np.hypot(points[:, 0], points[:, 1]) < 25.0]
    ground = estimate_ground(points, radius=40.0)
    shapes = [("road", [np.array([[-60.0, -60.0], [60.0, -60.0], [60.0, 3.0], [-60.0, 3.0]])]),
              ("walkway", [np.array([[-60.0, 3.0], [60.0, 3.0], [60.0, 60.0], [-60.0, 60.0]])])]
    scene_map = map_from_polygons(shapes, np.eye(4), radius=40.0)
    spots = np.array([[5.0, 0.0], [5.0, 6.0], [12.2, 0.0], [20.0, 0.0], [-35.0, 0.0], [-35.0, 10.0]])
    #                 seen road   seen walk   the wall    behind wall  unseen road  unseen walk
    bounded = scene_feasibility(points, ground, scene_map, radius=40.0)
    assert bounded.allows("car", spots).tolist() == [True, False, False, True, True, False]
    assert bounded.allows("pedestrian", spots).tolist() == [False, True, False, False, False, True]
    paper = scene_feasibility(points, ground, scene_map, radius=40.0, map_bounds_ground=False)
    assert paper.allows("car", spots).tolist() == [True, True, False, True, True, False]
    no_map = scene_feasibility(points, ground, None, radius=40.0)
    assert no_map.allows("car", spots).tolist() == [True, True, False, False, False, False]


# --- Thompson sampling ----------------------------------------------------------------


def test_thompson_cells_count_as_the_paper_defines_and_draw_towards_failures(tmp_path):
    cells = ThompsonCells()
    assert (cells.rings, cells.sectors) == (7, 84)
    gt = np.array([[10.0, 0.0], [30.0, 5.0]])
    pred = np.array([[10.5, 0.2], [30.0, 5.0], [-20.0, -20.0], [-20.0, 20.0]])
    scores = np.array([0.9, 0.3, 0.8, 0.4])  # a hit, a miss (too weak), a confident negative, a weak negative
    cells.update(gt, pred, scores)
    success_cell, failure_cell = cells.cell_of(gt[:1])[0], cells.cell_of(pred[2:3])[0]
    assert cells.successes.ravel()[success_cell] == 1 and cells.successes.sum() == 1
    assert cells.failures.ravel()[failure_cell] == 1 and cells.failures.sum() == 1
    cells.update(gt, pred, scores, gt_names=["car", "car"], pred_names=["bus", "car", "car", "car"])
    assert cells.successes.sum() == 1 and cells.failures.sum() == 3  # a bus is no car: now a negative
    for _ in range(20):  # the detector keeps failing in one cell and succeeding in another
        cells.update(gt[:1], np.vstack([pred[:1], pred[2:3]]), [0.9, 0.9])
    rng = np.random.default_rng(0)
    ranks = np.array([np.argsort(np.argsort(-cells.draw(rng))) for _ in range(200)]) / cells.failures.size
    assert np.median(ranks[:, failure_cell]) < 0.1 and np.median(ranks[:, success_cell]) > 0.9
    path = tmp_path / "cells.json"
    cells.save(path)
    again = ThompsonCells.load(path)
    np.testing.assert_array_equal(again.failures, cells.failures)
    np.testing.assert_array_equal(ThompsonCells.from_state_dict(pickle.loads(pickle.dumps(cells.state_dict()))).successes,
                                  cells.successes)
    state = cells.state_dict()
    for text in ('{"format": "something else"}', "[" * 100_000, json.dumps({**state, "max_range": float("inf")}),
                 json.dumps({**state, "range_step": 1e-320})):  # no cell count to allocate
        path.write_text(text)
        with pytest.raises(InputError, match="cells.json: not a Thompson cells state"):
            ThompsonCells.load(path)


def test_a_thompson_file_is_read_again_when_the_trainer_saves_it(tmp_path):
    watched = ThompsonFile(tmp_path / "cells.json", max_range=40.0)
    assert watched.cells().failures.sum() == 0 and watched.cells().max_range == 40.0  # no file yet: fresh cells
    cells = ThompsonCells(max_range=40.0)
    cells.update(np.zeros((0, 2)), np.array([[10.0, 0.0]]), [0.9])
    cells.save(tmp_path / "cells.json")
    first = watched.cells()
    assert first.failures.sum() == 1 and watched.cells() is first  # unchanged file: not read again
    cells.update(np.zeros((0, 2)), np.array([[10.0, 0.0]]), [0.9])
    cells.save(tmp_path / "cells.json")
    os.utime(tmp_path / "cells.json", ns=(0, first_stamp(tmp_path) + 1))  # a later save, whatever the clock
    assert watched.cells().failures.sum() == 2


def first_stamp(folder) -> int:
    return (folder / "cells.json").stat().st_mtime_ns


# --- the whole step on real scans -----------------------------------------------------


@pytest.fixture(scope="module")
def banks(tmp_path_factory) -> dict:
    """Small KITTI and nuScenes banks of the built-in truck and bicycle (KITTI: Truck and
    Cyclist), on grids inside 54 m."""
    folder, samples = tmp_path_factory.mktemp("prepared"), tmp_path_factory.mktemp("samples")
    for class_name, seed in (("truck", 1), ("bicycle", 2)):
        source = write_sample(samples, class_name, seed=seed, points=3000)["reconstruction.ply"]
        write_prepared(prepare(load_reconstruction(source), class_name, up="pca", heading_method="baseline",
                               seed=seed), class_name, "nuscenes", folder)
    objects = checked_objects(*prepared_objects(folder), False, folder)
    grids = {"kitti": {"headings_deg": [-180, 180, 60], "x": [5, 45, 10], "y": [-20, 20, 10]},
             "nuscenes": {"headings_deg": [-180, 180, 90], "x": [-40, 40, 10], "y": [-40, 40, 10]}}
    out = tmp_path_factory.mktemp("banks")
    for dataset, grid in grids.items():
        config = config_from_table({"bank": {"dataset": dataset, "chunk_size": 64}, "grid": grid})
        export_bank(objects, config, out / dataset, workers=2)
    return {dataset: out / dataset for dataset in grids}


def kitti_scene(shared_data, frame: str):
    return read_scene(shared_data / "kitti_scans" / "velodyne" / f"{frame}.bin",
                      shared_data / "kitti_scans" / "label_2" / f"{frame}.txt")


def check_placement(scene, placement, pool, sensor, scan_points=None):
    """Every promise of the placement on one scene (see the module docstring of place.py)."""
    inserted = placement.boxes[placement.inserted]
    assert len(inserted) > 0
    np.testing.assert_array_equal(placement.names[~placement.inserted], scene.names)
    assert set(placement.names[placement.inserted]) <= set(pool.classes)
    # no box overlaps another, the scene's or an inserted one
    overlaps = bev_overlaps(inserted, placement.boxes)
    overlaps[:, np.flatnonzero(placement.inserted)] &= ~np.eye(len(inserted), dtype=bool)
    assert not overlaps.any()
    # every centre and corner stands where its class may
    for box, name in zip(inserted, placement.names[placement.inserted]):
        spots = np.vstack([box[None, :2], footprint_corners(box[None])[0]])
        assert placement.feasibility.allows(name, spots).all(), name
    # the box bottom on the estimated ground; never moved in range, turned by whole columns
    bottoms = inserted[:, 2] - inserted[:, 5] / 2
    np.testing.assert_allclose(bottoms, placement.ground.under_boxes(inserted), atol=1e-9)
    for box, info, turn in zip(inserted, placement.entries, placement.turns):
        stored = np.asarray(info["box3d_lidar"], np.float64)
        assert np.hypot(*box[:2]) == pytest.approx(np.hypot(*stored[:2]), abs=1e-6)
        assert np.hypot(*box[:2]) <= 54.0
        steps = turn / (2 * np.pi / sensor.columns)
        assert steps == pytest.approx(round(steps), abs=1e-9)
    # the inserted points lie in their boxes (range noise: within 12 cm), no scene point in a placed box
    for (start, stop), box in zip(placement.rows, inserted):
        assert stop - start >= 5
        assert inside_box(placement.points[start:stop, :3].astype(np.float64), box, 0.12).all()
    scene_rest = placement.points[placement.rows[-1, 1]:, :3].astype(np.float64)
    for box in inserted:
        assert not inside_box(scene_rest, box).any()
    assert len(scene_rest) == len(scene.points) - placement.scene_in_boxes.sum() - placement.scene_shadowed.sum()


@pytest.mark.parametrize("frame", ["000000", "000001", "000002"])
def test_placement_on_real_kitti_frames(shared_data, banks, frame):
    """Objects placed into the real KITTI frames stand on the ground: each inserted box's
    bottom within 0.1 m of the scan's own returns under its footprint (dev.scan_ground_gap)."""
    scene = kitti_scene(shared_data, frame)
    pool = open_database(banks["kitti"], "kitti")
    config = PlacementConfig(KITTI)
    placement = place_objects(scene.points, scene.boxes, scene.names, pool, {"Truck": 3, "Cyclist": 4}, config,
                              np.random.default_rng(1))
    check_placement(scene, placement, pool, KITTI)
    judged = [scan_ground_gap(scene.points, box) for box in placement.boxes[placement.inserted]]
    gaps = [gap for gap, how in judged if how != "none"]
    assert len(gaps) >= 3
    np.testing.assert_array_less(np.abs(gaps), 0.1)


def test_same_seed_same_scene_other_seed_other_places(shared_data, banks):
    scene = kitti_scene(shared_data, "000001")
    pool = open_database(banks["kitti"], "kitti")
    runs = [place_objects(scene.points, scene.boxes, scene.names, pool, {"Cyclist": 5}, PlacementConfig(KITTI),
                          np.random.default_rng(seed)) for seed in (3, 3, 4)]
    assert runs[0].points.tobytes() == runs[1].points.tobytes()
    np.testing.assert_array_equal(runs[0].boxes, runs[1].boxes)
    assert not np.array_equal(runs[0].boxes, runs[2].boxes)


def test_an_object_hidden_behind_a_wall_is_dropped_and_its_shadow_given_back(banks):
    """An analytic scene walled in at 4 m all round, but for a gap: nothing can be seen
    beyond the wall, so an object placed there (the map allows it) has no point left and
    is dropped; the scene keeps every point."""
    wall = [((-4.2, -4.2, -1.84), (-4.0, 4.2, 2.0)), ((4.0, -4.2, -1.84), (4.2, 4.2, 2.0)),
            ((-4.2, -4.2, -1.84), (4.2, -4.0, 2.0)), ((-4.2, 4.0, -1.84), (4.2, 4.2, 2.0))]
    points, _ = cast(NUSCENES, (0.0, 0.0, -1.84), boxes=wall)
    scene = np.column_stack([points, np.zeros((len(points), 2))]).astype(np.float32)
    road = map_from_polygons([("road", [np.array([[-60.0, -60.0], [60.0, -60.0], [60.0, 60.0], [-60.0, 60.0]])])],
                             np.eye(4))
    pool = open_database(banks["nuscenes"], "nuscenes")
    placement = place_objects(scene, np.zeros((0, 9)), [], pool, {"truck": 2}, PlacementConfig(NUSCENES),
                              np.random.default_rng(0), scene_map=road)
    assert placement.inserted.sum() == 0 and placement.missing == {"truck": 2}
    assert placement.refused["truck"]["occluded"] == 2
    assert len(placement.points) == len(scene) and not placement.scene_shadowed.any()


def test_why_objects_were_not_placed_is_tallied_by_check(banks):
    """A flat analytic scene whose only road lies 500 m away: every candidate stands where
    a truck may not (the map bounds the ground), and no other check is reached."""
    points, _ = cast(NUSCENES, (0.0, 0.0, -1.84))
    scene = np.column_stack([points, np.zeros((len(points), 2))]).astype(np.float32)
    far_road = map_from_polygons([("road", [np.array([[500.0, 0.0], [510.0, 0.0], [510.0, 10.0], [500.0, 10.0]])])],
                                 np.eye(4))
    config = PlacementConfig(NUSCENES)
    placement = place_objects(scene, np.zeros((0, 9)), [], open_database(banks["nuscenes"], "nuscenes"),
                              {"truck": 2, "bicycle": 0}, config, np.random.default_rng(0), scene_map=far_road)
    assert placement.missing == {"truck": 2}
    assert placement.refused == {"truck": {"feasible": 2 * config.tries, "ego": 0, "overlap": 0, "standing": 0,
                                           "no cell": 0, "occluded": 0}}


def test_placement_on_the_nuscenes_sample_with_a_road_map(shared_data, banks):
    """The real nuScenes sample (100 returns, its boxes from the mmdet3d info, its ego
    pose): where the scan sees nothing the map decides, so every placed truck stands on
    the road polygon given in the world frame."""
    folder = shared_data / "nuscenes_format_sample"
    scene = read_scene(folder / "samples" / "LIDAR_TOP" / "n015-2018-08-02-17-16-37+0800__LIDAR_TOP__1533201470948018.pcd.bin",
                       folder / "nus_info.pkl")
    assert scene.dataset == "nuscenes" and scene.boxes.shape == (37, 9)
    # a 14 m wide road along the sensor's x axis, in world coordinates
    corners = np.array([[-60.0, -7.0], [60.0, -7.0], [60.0, 7.0], [-60.0, 7.0]])
    world = (np.column_stack([corners, np.zeros(4), np.ones(4)]) @ scene.lidar_to_world.T)[:, :2]
    scene_map = map_from_polygons([("road", [world])], scene.lidar_to_world)
    pool = open_database(banks["nuscenes"], "nuscenes")
    placement = place_objects(scene.points, scene.boxes, scene.names, pool, {"truck": 3, "bicycle": 3},
                              PlacementConfig(NUSCENES), np.random.default_rng(2), scene_map=scene_map)
    check_placement(scene, placement, pool, NUSCENES)
    for box in placement.boxes[placement.inserted]:
        assert (np.abs(np.vstack([box[None, :2], footprint_corners(box[None])[0]])[:, 1]) <= 7.0 + 0.13).all()


def test_a_class_the_database_lacks_is_refused(shared_data, banks):
    scene = kitti_scene(shared_data, "000001")
    pool = open_database(banks["kitti"], "kitti")
    with pytest.raises(InputError, match=r"kitti_dbinfos_pgt.pkl: no 'Car' entry within 54 m .*\(it has Truck, Cyclist"):
        place_objects(scene.points, scene.boxes, scene.names, pool, {"Car": 1}, PlacementConfig(KITTI),
                      np.random.default_rng(0))


def test_pool_reads_both_conventions_the_same(banks):
    """The bank's OpenPCDet and mmdet3d halves give the same entries in the sensor frame."""
    pools = [open_database(banks["kitti"], "kitti", convention) for convention in ("openpcdet", "mmdet3d")]
    first, second = (pool.classes["Cyclist"] for pool in pools)
    np.testing.assert_allclose(first.boxes, second.boxes, atol=1e-5)
    for a, b in zip(first.infos[:5], second.infos[:5]):
        np.testing.assert_allclose(pools[0].load(a), pools[1].load(b), atol=1e-5)
    assert isinstance(pools[0], EntryPool)


def test_an_entry_file_that_does_not_hold_its_points_is_named_unread(tmp_path):
    """An entry's file against its info's point count, from its size before any read: a
    (sparse) 8 GiB file is named at once, not read into memory."""
    (tmp_path / "db").mkdir()
    infos = {"Car": [{"name": "Car", "path": "db/0.bin", "box3d_lidar": np.array([10.0, 0, -1, 4, 2, 1.5, 0]),
                      "num_points_in_gt": 10}]}
    (tmp_path / "dbinfos.pkl").write_bytes(pickle.dumps(infos))
    pool = open_database(tmp_path / "dbinfos.pkl", "kitti")
    np.zeros((12, 4), np.float32).tofile(tmp_path / "db" / "0.bin")
    with pytest.raises(InputError, match="0.bin: 12 rows of 4 float32 point columns, but its info declares 10"):
        pool.load(infos["Car"][0])
    with open(tmp_path / "db" / "0.bin", "wb") as stream:
        stream.truncate(8 * 2**30)
    with pytest.raises(InputError, match="0.bin: 536870912 rows of 4 float32 point columns, but its info declares 10"):
        pool.load(infos["Car"][0])


def test_an_info_pickles_convention_is_read_from_it_and_checked(banks):
    """A bank's pickles given as plain info pickles: each read in its own convention
    (mmdet3d's infos carry a group_id each), the same entries as the bank folder gives;
    stated wrongly, refused (its objects would float or sink by half their height)."""
    folder = open_database(banks["kitti"], "kitti", "mmdet3d")
    for fmt in ("openpcdet", "mmdet3d"):
        pickle_path = banks["kitti"] / fmt / "kitti_dbinfos_pgt.pkl"
        pool = open_database(pickle_path, "kitti")
        assert pool.convention == fmt
        np.testing.assert_allclose(pool.classes["Cyclist"].boxes, folder.classes["Cyclist"].boxes, atol=1e-5)
        other = "mmdet3d" if fmt == "openpcdet" else "openpcdet"
        with pytest.raises(InputError, match=f"kitti_dbinfos_pgt.pkl: holds .* not {other}'s"):
            open_database(pickle_path, "kitti", other)


# --- the command ----------------------------------------------------------------------


def test_place_objects_command_writes_the_scene_boxes_and_picture(shared_data, banks, tmp_path):
    """As a user runs it, also the way ``blender -b -P`` does: the outputs agree with each
    other (rows of each inserted object inside its box, the scene's boxes first)."""
    frame = shared_data / "kitti_scans"
    args = ["--scan", frame / "velodyne" / "000001.bin", "--info", frame / "label_2" / "000001.txt",
            "--bank", banks["kitti"], "--objects", "Cyclist=3", "--objects", "Truck=1"]
    result = run_script("place_objects.py", *args, "--out", tmp_path / "a", check=True)
    assert "| Cyclist | 3 | 3 | 0 |" in result.stdout and not result.stderr
    run_script("place_objects.py", *args, "--out", tmp_path / "b", blender_style=True, check=True)
    for name in ("scan.bin", "boxes.json", "birdseye.png"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    points, record = read_placement(tmp_path / "a")
    assert record["columns"] == ["x", "y", "z", "intensity"] and record["box_values"][-1] == "heading"
    assert [box["inserted"] for box in record["boxes"]] == [False] * 3 + [True] * 4
    for box in record["boxes"][3:]:
        start, stop = box["rows"]
        assert inside_box(points[start:stop, :3].astype(np.float64), np.array(box["box"]), 0.12).all()
        assert box["entry"].startswith("pgt_gt_database/") and box["object"]
    assert (tmp_path / "a" / "birdseye.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_label_file_of_another_frame_is_a_warning(shared_data, banks, tmp_path):
    """Frame 000002's labels on scan 000001: placed (a renamed scan is fine), with one
    warning line naming the label file and both frames."""
    frame = shared_data / "kitti_scans"
    label = frame / "label_2" / "000002.txt"
    result = run_script("place_objects.py", "--scan", frame / "velodyne" / "000001.bin", "--info", label,
                        "--bank", banks["kitti"], "--objects", "Cyclist=1", "--out", tmp_path, check=True)
    assert result.stderr == (f"warning: {label}: the labels and calibration of frame 000002 are used for the scan "
                             f"000001.bin; give label_2/000001.txt unless the scan was renamed\n")


def test_a_scene_where_nothing_was_placed_is_a_warning_saying_why(shared_data, banks, tmp_path):
    """Cyclists allowed on a sidewalk 500 m away only: the scene is written unchanged, the
    table and boxes.json say why, and one warning line names the scan and the reasons."""
    frame = shared_data / "kitti_scans"
    (tmp_path / "map.json").write_text('[{"layer": "sidewalk", "polygon": [[500, 0], [510, 0], [510, 10], [500, 10]]}]')
    (tmp_path / "layers.json").write_text('{"Cyclist": ["sidewalk"]}')
    scan = frame / "velodyne" / "000001.bin"
    result = run_script("place_objects.py", "--scan", scan, "--info", frame / "label_2" / "000001.txt",
                        "--bank", banks["kitti"], "--objects", "Cyclist=2", "--map-polygons", tmp_path / "map.json",
                        "--class-layers", tmp_path / "layers.json", "--out", tmp_path / "out", check=True)
    assert "| Cyclist | 2 | 0 | 2 | 256 stood where the class may not |" in result.stdout
    assert result.stderr == (f"warning: {scan}: no object placed (Cyclist: 256 stood where the class may not); "
                             f"another --seed, a larger --max-distance or fewer objects may place some\n")
    _, record = read_placement(tmp_path / "out")
    assert record["refused"]["Cyclist"]["feasible"] == 256 and record["missing"] == {"Cyclist": 2}


def test_without_matplotlib_the_placement_has_no_picture(shared_data, banks, tmp_path):
    """As under ``blender -b -P`` (Blender's Python has no matplotlib): the scene and its
    boxes are written, the picture is not, and the command says so."""
    import subprocess
    import sys

    frame = shared_data / "kitti_scans"
    code = ("import sys, runpy; sys.modules['matplotlib'] = None; sys.argv = sys.argv[1:]; "
            "runpy.run_path(sys.argv[0], run_name='__main__')")
    script = str(Path(__file__).resolve().parents[1] / "headless_scripts" / "place_objects.py")
    result = subprocess.run([sys.executable, "-c", code, script, "--scan", str(frame / "velodyne" / "000002.bin"),
                             "--info", str(frame / "label_2" / "000002.txt"), "--bank", str(banks["kitti"]),
                             "--objects", "Cyclist=2", "--out", str(tmp_path)], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "no birdseye.png (matplotlib is not installed)" in result.stdout
    assert sorted(path.name for path in tmp_path.iterdir()) == ["boxes.json", "scan.bin"]

