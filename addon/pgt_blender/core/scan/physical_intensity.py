"""The default LiDAR intensity until a learned estimator is given (a documented model,
not a measurement):

    intensity = intensity_max * reflectivity * |cos(incidence)| * min(1, REFERENCE_RANGE / range)

Lambertian return of a surface of ``reflectivity`` in [0, 1]. The received power falls
as 1/range^2, but Velodyne and Hesai units calibrate most of that away on board, so only
a residual 1/range falloff beyond REFERENCE_RANGE is kept. nuScenes and Lyft store
whole numbers 0..255, KITTI floats 0..1 (sensors.INTENSITY_MAX).
"""

import numpy as np

REFERENCE_RANGE = 10.0  # m


def relative_intensity(reflectivity: np.ndarray, cos_incidence: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """(N,) float64 in [0, 1] for per-return reflectivity, cosine of incidence and range (m)."""
    falloff = np.minimum(1.0, REFERENCE_RANGE / np.maximum(ranges, 1e-9))
    return np.clip(reflectivity * np.abs(cos_incidence) * falloff, 0.0, 1.0)


def dataset_intensity(relative: np.ndarray, dataset: str) -> np.ndarray:
    """Scale [0, 1] intensities to the dataset's range and precision, float32."""
    from .sensors import INTENSITY_MAX

    scaled = relative * INTENSITY_MAX[dataset]
    return (np.round(scaled) if INTENSITY_MAX[dataset] > 1 else scaled).astype(np.float32)
