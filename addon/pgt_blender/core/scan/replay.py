"""Real labelled scans replayed in simulation: each labelled object becomes a mesh of its
class scaled to its box, the scene is scanned as the real sensor saw it, and every
real point gets the (ring, column) cell it came from, so simulated and real returns
can be compared cell by cell (bench_fidelity.py) and the ray-drop model fitted
(ray_drop.py, fit_sensor.py).

Frames: the real scan's sensor frame (sensors.py); labels are boxes in it as
``(class, centre (3,), dims (3,) length width height, heading rad)``
(intensity/objects.kitti_label_boxes).
"""

from pathlib import Path

import numpy as np

from ..boxes import inside_box
from ..errors import InputError
from ..files import listed
from ..samples import sample_vehicle
from . import sensor_fit
from .physical_intensity import fit_intensity_law
from .ray_drop import DROPPED, ELSEWHERE, cell_outcomes, fit_drop_model
from .raycast import trace_rays
from .sensors import Sensor
from .targets import mesh_target

# The engine hit_outcomes casts with, the one the presets' ray drop and intensity law were fitted on.
OUTCOME_ENGINE = "bvh"

KITTI_QUANTUM = 0.01  # KITTI intensities come in steps of 0.01
# KITTI class (lower case) -> mesh under the Chrono vehicle folder (../shared/data/chrono_vehicles/data/vehicle).
CHRONO_MESHES = {"car": "sedan/sedan_chassis_vis.obj", "van": "VW_microbus/van_chassis.obj",
                 "truck": "truck/truck_chassis.obj"}
# KITTI class -> built-in sample vehicle (samples.py).
SAMPLE_MESHES = {"truck": "truck", "cyclist": "bicycle"}


def class_meshes(choice: str) -> dict:
    """KITTI class (lower case) -> (vertices (V, 3), faces (F, 3), name, see-through (F,)
    bool) in the mesh's own frame. ``choice``: "samples" (SAMPLE_MESHES), the Chrono
    vehicle folder (holding every CHRONO_MESHES path) or a folder of ``<class>.obj|.ply``.
    Colors are not kept: replayed objects have the default reflectivity, the reference
    the fitted sensor models are relative to (ray_drop.py, physical_intensity.py).
    InputError naming ``choice`` when it is no such folder or holds no mesh."""
    from ..importing.mesh import read_material_mesh

    if choice == "samples":
        return {kind: (vehicle.vertices, vehicle.faces, f"sample {name}", np.zeros(len(vehicle.faces), bool))
                for kind, name in SAMPLE_MESHES.items() for vehicle in [sample_vehicle(name)]}
    if not Path(choice).is_dir():
        raise InputError(choice, "no such folder (meshes: 'samples', the Chrono vehicle folder or a folder of "
                                 "<class>.obj|.ply)")
    if all((Path(choice) / path).is_file() for path in CHRONO_MESHES.values()):
        paths = {kind: Path(choice) / path for kind, path in CHRONO_MESHES.items()}
    else:
        paths = {path.stem.lower(): path for pattern in ("*.[oO][bB][jJ]", "*.[pP][lL][yY]")
                 for path in listed(choice, pattern)}
        if not paths:
            raise InputError(choice, "holds no <class>.obj or <class>.ply mesh")
    return {kind: (mesh.vertices, mesh.faces, path.name, mesh.see_through)
            for kind, path in paths.items() for mesh in [read_material_mesh(path)]}


def box_mesh() -> tuple:
    """The unit cube as a class mesh: the stand-in for a class without one."""
    import trimesh

    box = trimesh.creation.box()
    return box.vertices, box.faces, "box", np.zeros(len(box.faces), bool)


def placed(vertices: np.ndarray, centre, dims, heading: float) -> np.ndarray:
    """(V, 3) ``vertices`` scaled to fill ``dims`` and placed at the box, sensor frame."""
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    local = (vertices - (low + high) / 2) / np.maximum(high - low, 1e-9) * dims
    cos, sin = np.cos(heading), np.sin(heading)
    return local @ np.array([[cos, sin, 0.0], [-sin, cos, 0.0], [0.0, 0.0, 1.0]]) + centre


def labelled_scene(labels: list, meshes: dict, glass: bool = True, engine: str = "auto") -> tuple:
    """(target, owner, chosen): one ScanTarget of every label's class mesh (the unit box
    without one) at its box, built for ``engine``, ``owner`` (F,) the label index of each
    input face (index it with a return's ``face`` or a polygon's ``target.source_index``),
    and the mesh tuple chosen per label. ``glass`` False scans see-through faces as solid."""
    chosen = [meshes.get(kind.lower(), box_mesh()) for kind, *_ in labels]
    vertices, faces, start = [], [], 0
    for (mesh_vertices, mesh_faces, *_), (_, centre, dims, heading) in zip(chosen, labels):
        faces.append(mesh_faces + start)
        vertices.append(placed(mesh_vertices, centre, dims, heading))
        start += len(mesh_vertices)
    owner_of_face = np.repeat(np.arange(len(chosen)), [len(mesh[1]) for mesh in chosen])
    see_through = np.concatenate([mesh[3] for mesh in chosen])
    target = mesh_target(np.concatenate(vertices), np.concatenate(faces), "scene", engine=engine,
                         face_see_through=see_through if glass else None)
    return target, owner_of_face, chosen


def real_rings(rows: np.ndarray, source="scan") -> np.ndarray:
    """(N,) ring (0 = lowest) of each point of a raw scan stored laser by laser: its laser
    from scan order, ranked by the elevation fitted on the scan itself (sensor_fit.py).
    InputError naming ``source`` when the scan's lasers cannot be told apart."""
    fit = sensor_fit.fit_lasers([rows], [source])
    return np.argsort(np.argsort(fit.elevations_deg))[sensor_fit.scan_order_lasers(rows, source)]


def azimuth_columns(points: np.ndarray, sensor: Sensor) -> np.ndarray:
    """(N,) int64 column of each point by its azimuth (from +x, in [0, 360) degrees, in
    steps of the sensor's): the same rule for real and simulated points."""
    degrees = np.mod(np.degrees(np.arctan2(points[:, 1], points[:, 0])), 360.0)
    return np.minimum(np.floor(degrees / sensor.azimuth_step_deg).astype(np.int64), sensor.columns - 1)


def hit_outcomes(rows: np.ndarray, labels: list, sensor: Sensor, meshes: dict, source="scan") -> tuple:
    """One real frame replayed noiseless: (hits, real_label). ``rows`` (N, 3+) float64 the
    frame's points. ``hits`` holds arrays over every simulated hit on a labelled object:
    "outcome" (ray_drop.cell_outcomes: KEPT, DROPPED, ELSEWHERE), "label",
    "reflectivity", "cos_incidence", "range" (m); ``real_label`` (N,) the label whose box
    holds each real point, -1 for none. Errors name ``source``, the scan's file."""
    target, owner_of_face, _ = labelled_scene(labels, meshes, engine=OUTCOME_ENGINE)
    trace = trace_rays(target, sensor, np.eye(4), window=False, engine=OUTCOME_ENGINE)
    owner = owner_of_face[target.source_index[trace.polygons]]
    points = sensor.return_points(trace.cells, trace.ranges)
    sim_cells = trace.cells // sensor.columns * sensor.columns + azimuth_columns(points, sensor)
    real_cells = real_rings(rows, source) * sensor.columns + azimuth_columns(rows, sensor)
    outcome = np.full(len(owner), -1, np.int8)
    real_label = np.full(len(rows), -1, np.int64)
    for index, (_, centre, dims, heading) in enumerate(labels):
        inside = inside_box(rows[:, :3], np.concatenate([centre, dims, [heading]]))
        real_label[inside] = index
        mine = owner == index
        outcome[mine] = cell_outcomes(sim_cells[mine], real_cells, inside, sensor.columns)
    hits = {"outcome": outcome, "label": owner, "reflectivity": target.reflectivity[trace.polygons],
            "cos_incidence": trace.cos_incidence, "range": trace.ranges}
    return hits, real_label


def replay_frames(frames, sensor: Sensor, meshes: dict) -> list:
    """``frames``: (scan path, rows (N, 4+) float64 x y z intensity, labels) as
    intensity/objects.kitti_frames yields them. Per frame with labels: "frame" (the scan's
    file name without suffix), "labels", "hits" (hit_outcomes, plus "object": an id unique over frames) and
    "real" (its points inside the boxes: "value" intensity 0..1, "range" m, "label",
    "object")."""
    replayed = []
    for scan, rows, labels in frames:
        if not labels:
            continue
        hits, real_label = hit_outcomes(rows, labels, sensor, meshes, scan)
        first_object = sum(len(frame["labels"]) for frame in replayed)
        hits["object"] = first_object + hits["label"]
        inside = real_label >= 0
        replayed.append({"frame": Path(scan).stem, "labels": labels, "hits": hits,
                         "real": {"value": rows[inside, 3] / sensor.intensity_max, "label": real_label[inside],
                                  "range": np.linalg.norm(rows[inside, :3], axis=1),
                                  "object": first_object + real_label[inside]}})
    return replayed


def pooled(frames: list, part: str) -> dict:
    """The ``part`` ("hits" or "real") arrays of replayed ``frames``, concatenated."""
    return {key: np.concatenate([frame[part][key] for frame in frames]) for key in frames[0][part]}


def fit_frames_ray_drop(frames: list) -> tuple:
    """ray_drop.fit_drop_model on the judged hits of replayed ``frames``."""
    hits = pooled(frames, "hits")
    judged = hits["outcome"] != ELSEWHERE
    return fit_drop_model(hits["outcome"][judged] == DROPPED, hits["reflectivity"][judged],
                          hits["cos_incidence"][judged], hits["range"][judged])


def fit_frames_intensity_law(frames: list, sensor: Sensor, real: dict | None = None) -> tuple:
    """physical_intensity.fit_intensity_law of replayed ``frames``' simulated hits against
    ``real`` points ("value" 0..1, "range", "object"; None: the frames' own object points)
    of ``sensor``'s dataset (its quantum sets the log floor)."""
    hits = pooled(frames, "hits")
    real = real or pooled(frames, "real")
    floor = 0.5 / sensor.intensity_max if sensor.intensity_max > 1 else KITTI_QUANTUM / 2
    return fit_intensity_law(real["value"], real["range"], real["object"],
                             hits["reflectivity"] * np.abs(hits["cos_incidence"]), hits["object"], floor)
