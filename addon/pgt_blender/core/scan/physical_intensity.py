"""The scan's intensity until a learned estimator is given: a physical law with per-sensor
constants fitted to real scans (a model, not a measurement)::

    intensity = intensity_max * clip(scale * reflectivity * |cos(incidence)|
                                     * min(1, REFERENCE_RANGE / range) ** range_exponent
                                     * exp(spread * z - spread**2 / 2), 0, 1)

Lambertian return of a surface of ``reflectivity`` in [0, 1]. The received power falls
as 1/range^2, but Velodyne and Hesai units calibrate most of that away on board, so only
a residual falloff beyond REFERENCE_RANGE is kept. ``z`` is a standard normal draw per
return (seeded with the scan's noise): real surfaces are not one color (paint, dirt,
plates, lights), and without the spread every point of a face would share one value.
The log-normal factor has mean 1, so ``scale`` sets the mean. nuScenes and Lyft store
whole numbers 0..255, KITTI floats 0..1 (sensors.INTENSITY_MAX).

``(scale, range_exponent, spread)`` is a sensor's ``intensity_law`` (sensors.py; empty:
DEFAULT_LAW, the unfitted model). ``fit_intensity_law`` fits it to real object points
against simulated hits of the same kind of objects (fit_returns.py).
"""

import numpy as np

REFERENCE_RANGE = 10.0  # m
DEFAULT_LAW = (1.0, 1.0, 0.0)  # scale, range_exponent, spread
MIN_FAR_OBJECTS = 5  # real objects beyond REFERENCE_RANGE needed to fit the range exponent
MAX_RANGE_EXPONENT = 2.0  # the full 1/range^2 of an uncalibrated receiver


def relative_intensity(reflectivity: np.ndarray, cos_incidence: np.ndarray, ranges: np.ndarray,
                       law: tuple = DEFAULT_LAW, normal: np.ndarray | None = None) -> np.ndarray:
    """(N,) float64 in [0, 1] for per-return reflectivity, cosine of incidence and range (m)
    under ``law``; ``normal`` (N,) standard normal draws for the spread (None: no spread)."""
    scale, range_exponent, spread = law or DEFAULT_LAW
    value = scale * reflectivity * np.abs(cos_incidence) * _falloff(ranges, range_exponent)
    if normal is not None and spread > 0:
        value = value * np.exp(spread * normal - spread**2 / 2)
    return np.clip(value, 0.0, 1.0)


def _falloff(ranges: np.ndarray, exponent: float) -> np.ndarray:
    """The law's range factor: min(1, REFERENCE_RANGE / range) ** exponent."""
    return np.minimum(1.0, REFERENCE_RANGE / np.maximum(ranges, 1e-9)) ** exponent


def dataset_intensity(relative: np.ndarray, dataset: str) -> np.ndarray:
    """Scale [0, 1] intensities to the dataset's range and precision, float32."""
    from .sensors import INTENSITY_MAX

    scaled = relative * INTENSITY_MAX[dataset]
    return (np.round(scaled) if INTENSITY_MAX[dataset] > 1 else scaled).astype(np.float32)


def _within_variance(logs: np.ndarray, groups: np.ndarray) -> float:
    """Variance of ``logs`` about their group's mean, pooled over the groups."""
    _, group = np.unique(groups, return_inverse=True)
    means = np.bincount(group, logs) / np.bincount(group)
    return float(np.mean((logs - means[group]) ** 2))


def fit_intensity_law(real_values: np.ndarray, real_ranges: np.ndarray, real_objects: np.ndarray,
                      sim_power: np.ndarray, sim_objects: np.ndarray, floor: float) -> tuple:
    """(scale, range_exponent, spread) for real object points ``real_values`` (N,) in
    [0, 1] at ``real_ranges`` (m) on objects ``real_objects`` (N,) (any ids), given
    simulated hits on objects of the same kind with ``sim_power`` (M,) = reflectivity x
    |cos incidence| on objects ``sim_objects`` (M,):

    - range_exponent: minus the slope of each object's mean ln value on the ln of its
      mean range / REFERENCE_RANGE, over the objects beyond REFERENCE_RANGE (objects,
      not points, are the independent samples; 0 with fewer than MIN_FAR_OBJECTS),
      clipped to [0, MAX_RANGE_EXPONENT]: reflectivity and incidence do not change with
      range, so the real falloff is the law's;
    - spread: the log-variance real points have about their object's mean beyond what
      the simulated powers have about theirs (object color differences are the
      reflectivity's, not the spread's);
    - scale: the real mean (falloff removed) over the simulated power's mean, so the
      law's mean intensity is the real one.

    Values below ``floor`` (half the dataset's quantum) count as it in logarithms."""
    real_values, real_ranges = np.asarray(real_values, np.float64), np.asarray(real_ranges, np.float64)
    sim_power = np.asarray(sim_power, np.float64)
    logs = np.log(np.maximum(real_values, floor))
    _, group = np.unique(real_objects, return_inverse=True)
    counts = np.bincount(group)
    object_log, object_range = np.bincount(group, logs) / counts, np.bincount(group, real_ranges) / counts
    far = object_range > REFERENCE_RANGE
    exponent = 0.0
    if far.sum() >= MIN_FAR_OBJECTS and np.ptp(np.log(object_range[far])) > 0.1:
        slope = np.polyfit(np.log(object_range[far] / REFERENCE_RANGE), object_log[far], 1)[0]
        exponent = float(np.clip(-slope, 0.0, MAX_RANGE_EXPONENT))
    falloff = _falloff(real_ranges, exponent)
    sim_logs = np.log(np.maximum(sim_power, floor))
    excess = _within_variance(logs - np.log(falloff), real_objects) - _within_variance(sim_logs, sim_objects)
    scale = float(np.mean(real_values / falloff) / np.mean(sim_power))
    return scale, exponent, float(np.sqrt(max(excess, 0.0)))
