"""The placement folder (``place_objects.py --out DIR``), written and read here.

- ``scan.bin``: the augmented scene, float32 rows in the input scan's columns; the
  inserted objects' points first, object by object, then the scene's remaining points
  (what the stock samplers also put first);
- ``boxes.json``: ``dataset``, ``scan`` (the input), ``frame``, ``columns``,
  ``box_values`` (x y z dx dy dz heading [vx vy]: centre boxes in the scan's LiDAR
  frame, m and rad), ``seed``, ``missing`` {class: objects not placed}, ``refused``
  {class: {check: count}} why (place.REFUSALS: tries refused by each check, objects that
  found no free cell or were too thin once occluded),
  ``scene_points_removed`` {inside_boxes, shadowed} and ``boxes``: every box, the
  scene's first, each {``class``, ``box``, ``inserted``, ``ground_height`` (z of the
  estimated ground it stands on: the mean under its centre and corners, m), and for inserted ones ``entry`` (its info's
  ``path``), ``object`` (the bank's ``pgt_object``, when there is one), ``turn_deg``
  (how far it was turned about the sensor's axis) and ``rows`` [start, stop) in
  scan.bin};
- ``birdseye.png`` (birdseye.py; not written without matplotlib, as in Blender's own
  Python).

Each file is written atomically, all three after everything is computed.
"""

import json
from pathlib import Path

import numpy as np

from ..errors import InputError, finite_number
from ..files import TEXT_LIMIT, atomic_output, output_path, read_float32_rows, regular_file
from ..scan.sensors import BIN_COLUMNS

FRAME = "the scan's LiDAR frame: metres, z up, the sensor at the origin (KITTI x forward y left, nuScenes x right " \
        "y forward)"
SCAN, BOXES, BIRDSEYE = "scan.bin", "boxes.json", "birdseye.png"


def boxes_record(placement, scene, seed: int) -> dict:
    """The boxes.json content of a Placement of a scenes.Scene."""
    values = ["x", "y", "z", "dx", "dy", "dz", "heading", "vx", "vy"][:placement.boxes.shape[1]]
    boxes = []
    inserted_index = 0
    for box, name, inserted, ground in zip(placement.boxes, placement.names, placement.inserted,
                                           placement.ground_height):
        record = {"class": str(name), "box": [float(v) for v in box], "inserted": bool(inserted),
                  "ground_height": float(ground)}
        if inserted:
            info = placement.entries[inserted_index]
            record.update({"entry": str(info["path"]), "object": info.get("pgt_object"),
                           "turn_deg": float(np.degrees(placement.turns[inserted_index])),
                           "rows": [int(v) for v in placement.rows[inserted_index]]})
            inserted_index += 1
        boxes.append(record)
    return {"dataset": scene.dataset, "scan": str(scene.source), "frame": FRAME,
            "columns": list(BIN_COLUMNS[scene.dataset]), "box_values": values, "seed": seed,
            "missing": placement.missing, "refused": placement.refused,
            "scene_points_removed": {"inside_boxes": int(placement.scene_in_boxes.sum()),
                                     "shadowed": int(placement.scene_shadowed.sum())},
            "boxes": boxes}


def check_placement_folder(out) -> None:
    """InputError naming a file of the folder ``out`` that cannot be written (a folder in
    its place, one that takes no new file): checked before the placement, so that a
    re-run that fails leaves the earlier three files as they were."""
    for name in (SCAN, BOXES, BIRDSEYE):
        output_path(Path(out) / name)


def write_placement(out, placement, scene, seed: int, birdseye_png: bytes | None) -> dict:
    """Write the folder (module docstring) into ``out`` (made when missing; no picture
    when ``birdseye_png`` is None); returns the paths written by name."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    contents = {out / SCAN: np.ascontiguousarray(placement.points, np.float32).tobytes(),
                out / BOXES: json.dumps(boxes_record(placement, scene, seed), indent=1).encode()}
    if birdseye_png is not None:
        contents[out / BIRDSEYE] = birdseye_png
    for path, data in contents.items():
        with atomic_output(path) as stream:
            stream.write(data)
    return {path.name: path for path in contents}


def read_placement(folder) -> tuple:
    """(points (N, C) float32, record) of a placement folder; InputError naming the file
    at fault: missing or damaged, or a field its readers index that is not what
    ``boxes_record`` writes (record_problem)."""
    folder = Path(folder)
    path = folder / BOXES
    if path.exists():  # a pipe would never end, a huge file fill the memory; a missing one is named below
        regular_file(path, TEXT_LIMIT)
    try:
        record = json.loads(path.read_text())
    except OSError as error:
        raise InputError(path, f"cannot read the file ({error.strerror or error}): not a placement folder") from None
    except (ValueError, RecursionError) as error:  # bad JSON or UTF-8, too deep
        raise InputError(path, f"not a placement record ({type(error).__name__}: {error})") from None
    problem = record_problem(record)
    if problem:
        raise InputError(path, f"not a placement record: {problem}")
    points = read_float32_rows(folder / SCAN, len(record["columns"]), "point columns")
    for index, box in enumerate(record["boxes"]):
        rows = box.get("rows")
        if rows is not None and not rows[0] <= rows[1] <= len(points):
            raise InputError(path, f"box {index}: rows {rows!r} are not within the scan's {len(points)} points")
    return points, record


def record_problem(record) -> str:
    """What in a boxes.json record is not as ``boxes_record`` writes it, or "": an
    object with ``scan`` and ``dataset`` strings, ``columns`` distinct names with x, y
    and z, and ``boxes`` objects each with a ``class``, a ``box`` of 7 or more finite
    numbers with positive dims, and for an inserted one ``rows`` [start, stop] integers
    >= 0 and an ``entry`` or ``object`` name."""
    if not isinstance(record, dict):
        return f"expected a JSON object, got {type(record).__name__}"
    for key in ("scan", "dataset"):
        if not isinstance(record.get(key), str):
            return f"{key} must be a string, got {record.get(key)!r}"
    columns = record.get("columns")
    if not (isinstance(columns, list) and all(isinstance(c, str) and c for c in columns)
            and len(set(columns)) == len(columns) and {"x", "y", "z"} <= set(columns)):
        return f"columns must be distinct names including x, y and z, got {columns!r}"
    boxes = record.get("boxes")
    if not isinstance(boxes, list):
        return "boxes must be a list"
    for index, box in enumerate(boxes):
        problem = _box_problem(box)
        if problem:
            return f"box {index}: {problem}"
    return ""


def _box_problem(box) -> str:
    if not isinstance(box, dict):
        return f"expected an object, got {type(box).__name__}"
    if not isinstance(box.get("class"), str):
        return f"class must be a string, got {box.get('class')!r}"
    values = box.get("box")
    if not (isinstance(values, list) and len(values) >= 7 and all(map(finite_number, values))
            and min(values[3:6]) > 0):
        return f"box must be 7 or more finite numbers with positive dims, got {values!r}"
    rows = box.get("rows")
    if rows is None:
        return ""
    if not (isinstance(rows, list) and len(rows) == 2 and all(isinstance(v, int) and not isinstance(v, bool)
                                                              and v >= 0 for v in rows)):
        return f"rows must be two integers [start, stop] >= 0, got {rows!r}"
    if not (isinstance(box.get("object"), str) and box["object"] or isinstance(box.get("entry"), str)):
        return "an inserted box needs the entry or object it came from"
    return ""
