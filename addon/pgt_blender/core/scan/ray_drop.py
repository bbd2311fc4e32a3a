"""Ray drop: the chance that a ray which meets a surface brings no return back.

Real LiDARs miss returns off dark paint, at grazing incidence and far away: the echo
is too weak. The model is a logistic in the log of the echo's power relative to a
surface of reflectivity 1 met head-on at REFERENCE_RANGE (physical_intensity.py)::

    power = max(reflectivity * |cos incidence|, MIN_POWER) * (REFERENCE_RANGE / range)^2
    logit p_drop = a - k * ln(power)

``(a, k)`` is a sensor's ``ray_drop`` (sensors.py; empty: no model). Tying range,
reflectivity and incidence into one power keeps two parameters: a free term per factor
fitted the shared frames better but predicted held-out frames worse.

Fit (``fit_drop_model``): real labelled scans are re-scanned with a mesh of each object's
class at its box (replay.py); each simulated hit on an object is paired with the real
scan's cell of the same ring and azimuth column (``cell_outcomes``). A real return
inside the box within one column is a kept ray, no real return at all in the cell a
dropped one; a real return elsewhere in the cell (the mesh is not the real shape, or
something unlabelled stands in front) says nothing about drop and is left out. The
coefficients maximise the Bernoulli likelihood of kept / dropped.
"""

import numpy as np

from .physical_intensity import REFERENCE_RANGE

MIN_POWER = 1e-3  # reflectivity x |cos|: below this a return is as good as lost anyway
KEPT, DROPPED, ELSEWHERE = 0, 1, 2
_COLUMN_TOLERANCE = 1  # real and simulated azimuth columns may differ by one (offsets, jitter)


def _features(reflectivity, cos_incidence, ranges) -> np.ndarray:
    """(N, 2) float64: 1 and -ln(power) (the module docstring)."""
    power = np.maximum(np.asarray(reflectivity, np.float64) * np.abs(cos_incidence), MIN_POWER) \
        * (REFERENCE_RANGE / np.asarray(ranges, np.float64)) ** 2
    return np.column_stack([np.ones(len(power)), -np.log(power)])


def drop_probability(model: tuple, reflectivity, cos_incidence, ranges) -> np.ndarray:
    """(N,) float64 in (0, 1): each return's drop probability under ``model`` (a, k)
    for per-return reflectivity in [0, 1], cosine of incidence and range (m)."""
    logit = _features(reflectivity, cos_incidence, ranges) @ np.asarray(model, np.float64)
    return 1.0 / (1.0 + np.exp(-logit))


def fit_drop_model(dropped: np.ndarray, reflectivity, cos_incidence, ranges) -> tuple:
    """(a, k) maximising the likelihood of ``dropped`` (N,) bool, by Newton steps on the
    logistic log-likelihood (concave: one optimum). ValueError without both kept and
    dropped rays."""
    dropped = np.asarray(dropped, bool)
    if dropped.all() or not dropped.any():
        raise ValueError(f"a drop fit needs kept and dropped rays, got {dropped.sum()} dropped of {len(dropped)}")
    features = _features(reflectivity, cos_incidence, ranges)
    model = np.zeros(2)
    for _ in range(100):
        p = 1.0 / (1.0 + np.exp(-features @ model))
        hessian = (features * (p * (1 - p))[:, None]).T @ features + 1e-9 * np.eye(2)
        step = np.linalg.solve(hessian, features.T @ (dropped - p))
        model += step
        if np.abs(step).max() < 1e-10:
            break
    return tuple(float(value) for value in model)


def cell_outcomes(sim_cells: np.ndarray, real_cells: np.ndarray, real_in_box: np.ndarray, columns: int) -> np.ndarray:
    """(M,) int8 KEPT, DROPPED or ELSEWHERE for each simulated hit on an object.

    sim_cells (M,) and real_cells (N,) are ``ring * columns + column`` with the column
    taken from each point's azimuth the same way for both; real_in_box (N,) bool marks
    the real returns inside the object's box."""
    rings, column = np.divmod(np.asarray(sim_cells, np.int64), columns)
    in_box = np.unique(real_cells[real_in_box])
    near = np.zeros(len(rings), bool)
    for shift in range(-_COLUMN_TOLERANCE, _COLUMN_TOLERANCE + 1):
        near |= np.isin(rings * columns + np.mod(column + shift, columns), in_box)
    any_return = np.isin(sim_cells, real_cells)
    return np.where(near, KEPT, np.where(any_return, ELSEWHERE, DROPPED)).astype(np.int8)
