"""A real ground-truth database cut from raw KITTI scans, for when only scans and
labels are at hand (the shared KITTI frames): OpenPCDet's layout, written by the bank's
own record writer (bank/formats.database_record).

OUT/kitti_dbinfos_train.pkl = {label type: [info]} and OUT/gt_database/<frame>_<type>_<i>.bin
(float32 x y z intensity about the box centre), one entry per label_2 box (DontCare
skipped) with at least ``min_points`` points inside it.
"""

import pickle
from pathlib import Path

import numpy as np

from ..boxes import inside_box
from ..files import atomic_output
from ..intensity.objects import kitti_frames
from ..bank.formats import database_record

PICKLE = "kitti_dbinfos_train.pkl"


def kitti_scan_database(folder, out, min_points: int = 1) -> Path:
    """Write the database of the KITTI ``folder``'s labelled objects into ``out``;
    returns the info pickle's path."""
    out = Path(out)
    (out / "gt_database").mkdir(parents=True, exist_ok=True)
    infos = {}
    for frame, (scan, rows, labels) in enumerate(kitti_frames(folder)):
        for index, (kind, centre, dims, heading) in enumerate(labels):
            box = np.array([*centre, *dims, heading, 0.0, 0.0])
            inside = inside_box(rows[:, :3], box)
            if inside.sum() < max(min_points, 1):
                continue
            relative = f"gt_database/{scan.stem}_{kind}_{index}.bin"
            data, info = database_record("openpcdet", "kitti", rows[inside], box,
                                         {"name": kind, "path": relative, "image_idx": frame, "pgt_object": "",
                                          "gt_idx": index})
            info.pop("pgt_object")
            with atomic_output(out / relative) as stream:
                stream.write(data.tobytes())
            infos.setdefault(kind, []).append(info)
    with atomic_output(out / PICKLE) as stream:
        stream.write(pickle.dumps(infos))
    return out / PICKLE
