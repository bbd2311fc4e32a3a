"""Heading (front/back) correction in the object frame.

PCA leaves x pointing to either end of the object (and, for a near-square footprint,
along either side). These functions return the (4, 4) rotation about +z that puts
the front at +x; the automatic choices give a *score*, positive when the front is
already at +x:

* manual: :func:`quarter_turns` (flip = 2 turns, +-90 degrees = +-1 turn) and
  :func:`front_towards` (a picked point or direction becomes the front);
* geometric baseline: :func:`profile_front_score`, "the front end is the lower one"
  (bonnet, cab, bucket), the rule the learned classifier has to beat; for trailers
  (``RUNNING_GEAR_CLASSES``), whose two ends are equally high, :func:`running_gear_front_score`,
  "the wheels are behind the middle" (:func:`baseline_score` picks);
* learned: :mod:`.heading_classifier` (PointNet, needs torch), with the baseline as
  its floor: where the classifier is unsure (:func:`front_decision`), the baseline
  decides; for trailers the running gear decides outright (held out, the classifier,
  trained on no trailer, gets the sample trailer wrong: bench/heading.md).
"""

from pathlib import Path

import numpy as np

from ..errors import InputError

# A front probability within this of 0.5 is the classifier's guess: held out, the
# baseline was right more often on such clouds, and deciding them by the baseline kept
# every held-out mesh within one view of the baseline or better (bench/heading.md).
CLASSIFIER_DOUBT = 0.2
# A semi-trailer rests on its tractor in front and on its axles behind the middle; its
# floor is at about a third of its height (1.1-1.3 m of 4 m), so the lowest quarter of
# the box holds only running gear (and thin landing-gear legs in front). Built and
# tested on the one synthetic semi-trailer of the samples (nuScenes' class name).
RUNNING_GEAR_CLASSES = ("trailer",)
RUNNING_GEAR = "running gear"
RUNNING_GEAR_BAND = 0.25
RUNNING_GEAR_MIN_POINTS = 3  # a wheel seen at all: a scan at 35 m returns a handful of points from it


def quarter_turns(turns: int) -> np.ndarray:
    """(4, 4) rotation by ``turns`` x 90 degrees about +z (counter-clockwise seen from
    above, so one turn moves the front from +x to +y), with exact zeros and ones."""
    cos, sin = ((1, 0), (0, 1), (-1, 0), (0, -1))[turns % 4]
    rotation = np.eye(4)
    rotation[:2, :2] = [[cos, -sin], [sin, cos]]
    return rotation


def front_towards(direction, source="direction") -> np.ndarray:
    """(4, 4) quarter-turn rotation that makes the box side facing ``direction``
    ((3,) in the object frame, e.g. the 3D cursor location) the front (+x). The
    direction snaps to the nearest of +x, +y, -x, -y. InputError(source) for a vertical
    or non-finite direction."""
    x, y = np.asarray(direction, np.float64)[:2]
    if not np.isfinite([x, y]).all() or (x == 0 and y == 0):
        raise InputError(source, "the front direction must have a horizontal component")
    facing = int(np.round(np.arctan2(y, x) / (np.pi / 2))) % 4  # 0: +x, 1: +y, 2: -x, 3: -y
    return quarter_turns(-facing)


def profile_front_score(points: np.ndarray, end_share: float = 0.25) -> float:
    """Baseline front/back score of object-frame ``points`` (N, 3), in [-1, 1]:
    (top of the rear end - top of the front end) / box height, each end being the
    ``end_share`` of the length at that end and its top the 90th height percentile.
    Positive: the +x end is lower, so it is taken as the front."""
    points = np.asarray(points, np.float64)
    x, z = points[:, 0], points[:, 2]
    low, high = x.min(), x.max()
    cut = end_share * (high - low)
    front, rear = z[x >= high - cut], z[x <= low + cut]
    height = np.ptp(z)
    if not len(front) or not len(rear) or height == 0:
        return 0.0
    return float((np.percentile(rear, 90) - np.percentile(front, 90)) / height)


def running_gear_front_score(points: np.ndarray, dims) -> float | None:
    """Front/back score of a trailer's object-frame ``points`` (N, 3; box centred on the
    origin, extents ``dims`` (3,)), about [-0.5, 0.5]: minus the mean x of the points in
    the lowest ``RUNNING_GEAR_BAND`` of the box height, over the length. Positive: the
    running gear sits behind the middle along +x, so +x is the front. None when fewer
    than ``RUNNING_GEAR_MIN_POINTS`` points are that low (nothing of the wheels was seen)
    or the box is flat (no height to have a bottom in)."""
    points = np.asarray(points, np.float64)
    length, _, height = np.asarray(dims, np.float64)
    if not height > 1e-9 * length:  # flat (a PCA leaves rounding-level heights), empty or NaN
        return None
    low = points[points[:, 2] <= (RUNNING_GEAR_BAND - 0.5) * height, 0]
    if len(low) < RUNNING_GEAR_MIN_POINTS:
        return None
    return float(-low.mean() / length)


def baseline_score(points: np.ndarray, dims, class_name: str = "") -> tuple:
    """(score, rule): the geometric front/back score of object-frame ``points`` (N, 3) in
    their box ``dims`` (3,), positive when the front is at +x, and the rule that gave it:
    ``RUNNING_GEAR`` (:func:`running_gear_front_score`) for ``RUNNING_GEAR_CLASSES`` when
    it sees the wheels, else "baseline" (:func:`profile_front_score`)."""
    if class_name in RUNNING_GEAR_CLASSES:
        score = running_gear_front_score(points, dims)
        if score is not None:
            return score, RUNNING_GEAR
    return profile_front_score(points), "baseline"


def consults_classifier(rule: str) -> bool:
    """Whether the classifier may decide where the geometric ``rule`` gave the score: not
    over a trailer's running gear (held out, the classifier got the trailer wrong)."""
    return rule != RUNNING_GEAR


def transformed_dims(transform: np.ndarray, dims) -> np.ndarray:
    """(3,) box extents after ``transform`` (4, 4), for transforms that keep the box
    axis-aligned (quarter turns, axis scales): |M| @ dims."""
    return np.abs(np.asarray(transform)[:3, :3]) @ np.asarray(dims, np.float64)


def front_decision(probability: float | None, score: float, rule: str = "baseline") -> tuple:
    """(front at +x, decided by): the classifier's front ``probability`` unless it is
    None (not asked), lies within ``CLASSIFIER_DOUBT`` of 0.5 or the rule is not one the
    classifier may overrule (:func:`consults_classifier`); else the geometric ``score``
    of ``rule`` (:func:`baseline_score`). Decided by "classifier" or ``rule``."""
    if probability is not None and consults_classifier(rule) and abs(probability - 0.5) > CLASSIFIER_DOUBT:
        return probability >= 0.5, "classifier"
    return score >= 0, rule


def automatic_front(points: np.ndarray, dims, method: str = "classifier", checkpoint=None,
                    source="points", class_name: str = "") -> tuple:
    """(turns, score, decided by): 0 quarter turns when the front is already at +x,
    else 2 (the 180 degree flip), by ``method``: "baseline" (:func:`baseline_score` for
    ``class_name``, front at +x when >= 0) or "classifier" (front probability, front at
    +x when >= 0.5, the baseline deciding where the classifier is unsure and a trailer's
    running gear always: :func:`front_decision`; InputError when torch or the checkpoint
    is missing). The score is the deciding method's. Only the points inside the box (2 %
    margin) are looked at: floaters outside it would dominate a max-pooling network and
    the end profiles alike."""
    points = np.asarray(points)
    inside = (np.abs(points) <= np.asarray(dims) / 2 * 1.02).all(axis=1)
    points = points[inside] if inside.any() else points
    if method not in ("baseline", "classifier"):
        raise InputError(source, f"unknown heading method '{method}' (have: baseline, classifier)")
    score, rule = baseline_score(points, dims, class_name)
    probability = None
    if method == "classifier" and consults_classifier(rule):
        from .heading_classifier import DEFAULT_CHECKPOINT, front_probability

        probability = front_probability(points, dims, checkpoint or DEFAULT_CHECKPOINT, source=source)
    front, decided_by = front_decision(probability, score, rule)
    return (0 if front else 2), (probability if decided_by == "classifier" else score), decided_by


def best_available_method(checkpoint=None) -> tuple:
    """("classifier", "") when torch imports and the checkpoint exists, else
    ("baseline", why not)."""
    from .heading_classifier import DEFAULT_CHECKPOINT

    try:
        import torch  # noqa: F401
    except ImportError:
        return "baseline", "torch is not installed"
    if not Path(checkpoint or DEFAULT_CHECKPOINT).exists():
        return "baseline", f"no checkpoint at {checkpoint or DEFAULT_CHECKPOINT}"
    return "classifier", ""
