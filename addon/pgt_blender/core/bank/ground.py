"""The ground a bank entry stands on: height and slope per pose, instead of one flat
plane at -mounting_height (real objects stand on graded, cambered roads: their box
bottoms spread over metres at range).

Model, sensor frame, drawn per entry from its own generator (grid.py):

- road grade ``g ~ N(0, grade_deg)`` between the sensor and the object: the ground
  under the box is at ``z = -mounting_height + d * tan(g)``, d the horizontal distance
  from the sensor to the box centre (m);
- local slope: ``pitch ~ N(0, slope_deg)`` (nose up > 0) and ``roll ~ N(0, slope_deg)``
  (left side up > 0), both clipped to 3 sigma: the object stands tilted on it, its
  box stays yaw-only as the datasets' boxes are, so a tilted object's ends may leave it.

The defaults come from ``fit_ground`` on the shared real KITTI frames
(``headless_scripts/fit_ground.py``): per labelled box, a plane fitted to the scan's
ground returns 0.3-4 m around its footprint gives the ground height under it and its
slope; ``grade_deg`` is the RMS of atan(height offset / distance) and ``slope_deg`` the
RMS of pitch and roll, over boxes with at least MIN_GROUND_POINTS ground returns.
"""

import numpy as np

from ..boxes import box_frame
from ..scan.raycast import Ground

MIN_GROUND_POINTS = 50
RING = (0.3, 4.0)  # m from the box footprint: the ground returns a fit uses
BAND = (-1.5, 0.5)  # m around the box bottom: returns that can be ground


def sample_ground(x: float, y: float, grade_deg: float, slope_deg: float, rng: np.random.Generator) -> Ground:
    """A draw of the model above for a box centred at (x, y) m; three normal draws."""
    grade, pitch, roll = np.clip(rng.normal(0.0, 1.0, 3), -3.0, 3.0) * np.radians([grade_deg, slope_deg, slope_deg])
    return Ground(float(np.hypot(x, y) * np.tan(grade)), float(pitch), float(roll))


def fit_ground(points: np.ndarray, centre: np.ndarray, dims: np.ndarray, heading: float) -> dict:
    """The ground under one labelled box from a scan: ``points`` (N, 3) sensor frame,
    the box's ``centre`` (3,), ``dims`` (l, w, h) and ``heading`` (rad).

    Returns {"height": z of the ground plane under the box centre (m, sensor frame),
    "pitch", "roll" (degrees, along and across the heading), "points": ground returns
    used, "bottom_gap": box bottom minus ground (m)}; height/pitch/roll None with fewer
    than 3 returns. The plane z = a x + b y + c (box frame) is fitted by least squares,
    five times dropping returns more than 10 cm off it."""
    local = box_frame(points, centre, heading)
    gap = np.hypot(*np.maximum(np.abs(local[:, :2]) - dims[:2] / 2, 0.0).T)
    bottom = -dims[2] / 2
    near = local[(gap > RING[0]) & (gap < RING[1]) & (local[:, 2] > bottom + BAND[0]) & (local[:, 2] < bottom + BAND[1])]
    keep = np.ones(len(near), bool)
    coefficients = None
    for _ in range(5):
        if keep.sum() < 3:
            return {"height": None, "pitch": None, "roll": None, "points": int(keep.sum()), "bottom_gap": None}
        design = np.column_stack([near[:, 0], near[:, 1], np.ones(len(near))])
        coefficients = np.linalg.lstsq(design[keep], near[keep, 2], rcond=None)[0]
        keep = np.abs(near[:, 2] - design @ coefficients) < 0.1
    height = float(coefficients[2] + centre[2])
    return {"height": height, "pitch": float(np.degrees(np.arctan(coefficients[0]))),
            "roll": float(np.degrees(np.arctan(coefficients[1]))), "points": int(keep.sum()),
            "bottom_gap": float(centre[2] + bottom - height)}


def fit_kitti_frames(folder, mounting_height: float) -> dict:
    """``fit_ground`` for every labelled box (DontCare aside) of the KITTI frames in
    ``folder`` (velodyne/*.bin, label_2, calib), and the model fitted from them.

    Returns {"boxes": [{"frame", "type", "distance" (m), "offset" (ground height +
    mounting_height, m), "grade" (degrees: atan(offset / distance)), and fit_ground's
    keys}], "grade_deg", "slope_deg", "used": boxes with >= MIN_GROUND_POINTS returns}."""
    from scipy.spatial import cKDTree

    from ..intensity.objects import kitti_frames

    boxes = []
    for scan, rows, labels in kitti_frames(folder):
        points = rows[:, :3]
        tree = cKDTree(points[:, :2])
        for kind, centre, dims, heading in labels:
            # Only returns within the ring's reach of the box, in scan order: the same fit,
            # without a pass over the whole scan per box.
            near = tree.query_ball_point(centre[:2], np.hypot(*dims[:2]) / 2 + RING[1], return_sorted=True)
            fit = fit_ground(points[near], centre, dims, heading)
            distance = float(np.hypot(*centre[:2]))
            offset = None if fit["height"] is None else fit["height"] + mounting_height
            boxes.append({"frame": scan.stem, "type": kind, "distance": distance, "offset": offset,
                          "grade": None if offset is None else float(np.degrees(np.arctan(offset / distance))),
                          **fit})
    used = [box for box in boxes if box["points"] >= MIN_GROUND_POINTS]
    rms = (lambda values: float(np.sqrt(np.mean(np.square(values)))) if values else None)
    return {"boxes": boxes, "used": len(used), "grade_deg": rms([box["grade"] for box in used]),
            "slope_deg": rms([box[key] for box in used for key in ("pitch", "roll")])}
