"""Distances between a bank's and a real database's objects of one class (sets.ClassSet).

Feature-free, after Achlioptas et al. 2018 and Yang et al. 2019 (PointFlow), on
box-normalised SET_POINTS-point objects (unit: half a box side):

- chamfer(a, b): mean over a's points of the squared distance to b's nearest point,
  plus the same from b to a;
- mmd: minimum matching distance, the mean over real objects of the Chamfer distance
  to their nearest bank object (fidelity: lower is better);
- coverage: the share of real objects that are the nearest real object of at least
  one bank object (diversity: higher is better, 1 at most);
- one_nn_accuracy: leave-one-out 1-nearest-neighbour accuracy (Chamfer) telling bank
  from real, on equal-sized sets (the larger subsampled, seeded): 0.5 when they are
  indistinguishable, 1 when every object's neighbour is of its own set;
- w1_points: Wasserstein-1 between the distributions of log(points * (d / 10 m)^2),
  d the box-centre distance: a fixed object's points fall as 1/d^2, so this compares
  the points-per-entry-against-distance curves even where the two sets sit at
  different distances (natural-log units: 0.1 is about 10 % more or fewer points);
- w1_intensity: Wasserstein-1 between every point's intensity over the dataset's
  maximum, from the INTENSITY_BINS histograms (unit: the dataset's full scale);
- w1_fill: how the objects fill their boxes: the mean over the three box axes of the
  Wasserstein-1 between the per-object fills (half the range of its box-normalised
  points along the axis; unit: box half-sides, i.e. the share of the box side). Boxes
  larger than their objects lower every fill (20 % too large: at most 1/1.2);
- w1_grade: where the boxes stand: Wasserstein-1 between the box bottoms' elevation
  angles seen from the foot of the sensor (degrees, sets.ClassSet.grade). Boxes all on
  one flat plane give 0 for every entry, while real ones spread with the road's grade;
  boxes grown about their centre sink below the ground.

Learned (the paper's FID): frechet(f, g) = |mu_f - mu_g|^2 + Tr(S_f + S_g - 2 (S_f S_g)^1/2)
of the encoder's features (encoder.py), with a percentile bootstrap interval.
"""

import numpy as np
from scipy.stats import wasserstein_distance

REFERENCE_DISTANCE = 10.0  # m: w1_points compares counts scaled to this distance
BOOTSTRAP = 200  # resamples of the Fréchet interval
INTERVAL = 0.95


def chamfer_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) float64 Chamfer distances between (n, P, 3) and (m, Q, 3) point
    sets; one (m, P, Q) block per object of ``a``."""
    b = np.asarray(b, np.float64)
    b_norms = (b ** 2).sum(-1)  # (m, Q)
    result = np.empty((len(a), len(b)))
    for row, points in enumerate(np.asarray(a, np.float64)):
        squared = (points ** 2).sum(-1)[None, :, None] + b_norms[:, None, :] - 2 * np.einsum("pk,mqk->mpq", points, b)
        squared = np.maximum(squared, 0.0)
        result[row] = squared.min(2).mean(1) + squared.min(1).mean(1)
    return result


def mmd_coverage(bank_to_real: np.ndarray) -> tuple:
    """(mmd, coverage) from the (bank, real) Chamfer matrix."""
    mmd = float(bank_to_real.min(0).mean())
    coverage = len(np.unique(bank_to_real.argmin(1))) / bank_to_real.shape[1]
    return mmd, float(coverage)


def one_nn_accuracy(bank_xyz: np.ndarray, real_xyz: np.ndarray, seed: int = 0) -> float:
    """Leave-one-out 1-NN accuracy between equal-sized bank and real sets (the larger
    drawn down to the smaller's size, seeded); NaN when either set has fewer than two
    objects (with one each, each one's nearest is the other's: 0 by construction, which
    would read as better than the ideal 0.5)."""
    size = min(len(bank_xyz), len(real_xyz))
    if size < 2:
        return float("nan")
    rng = np.random.default_rng(seed)
    bank = bank_xyz[np.sort(rng.choice(len(bank_xyz), size, replace=False))]
    real = real_xyz[np.sort(rng.choice(len(real_xyz), size, replace=False))]
    both = np.concatenate([bank, real])
    distances = chamfer_matrix(both, both)
    np.fill_diagonal(distances, np.inf)
    labels = np.repeat([0, 1], size)
    return float((labels[distances.argmin(1)] == labels).mean())


def scaled_log_points(points: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """log(points * (distance / REFERENCE_DISTANCE)^2): counts at the reference distance."""
    return np.log(np.maximum(points, 1) * (np.maximum(distance, 1e-3) / REFERENCE_DISTANCE) ** 2)


def w1_points(bank, real) -> float:
    """W1 of scaled_log_points between two ClassSets."""
    return float(wasserstein_distance(scaled_log_points(bank.points, bank.distance),
                                      scaled_log_points(real.points, real.distance)))


def w1_fill(bank, real) -> float:
    """Mean over the box axes of the W1 between two ClassSets' fills (box half-sides)."""
    return float(np.mean([wasserstein_distance(bank.fill[:, axis], real.fill[:, axis]) for axis in range(3)]))


def w1_grade(bank, real) -> float:
    """W1 between two ClassSets' box-bottom grades (degrees)."""
    return float(wasserstein_distance(bank.grade, real.grade))


def w1_histograms(a: np.ndarray, b: np.ndarray) -> float:
    """W1 between two histograms over equal bins spanning [0, 1]: the area between their
    normalised cumulative sums; NaN when either is empty."""
    if a.sum() == 0 or b.sum() == 0:
        return float("nan")
    return float(np.abs(np.cumsum(a / a.sum()) - np.cumsum(b / b.sum())).sum() / len(a))


def _moments(features: np.ndarray) -> tuple:
    mean = features.mean(0)
    covariance = np.cov(features, rowvar=False) if len(features) > 1 else np.zeros((features.shape[1],) * 2)
    return mean, covariance


def _psd_sqrt(matrix: np.ndarray) -> np.ndarray:
    values, vectors = np.linalg.eigh(matrix)
    return (vectors * np.sqrt(np.clip(values, 0.0, None))) @ vectors.T


def frechet(features_a: np.ndarray, features_b: np.ndarray) -> float:
    """Fréchet distance between Gaussians fitted to (n, D) and (m, D) features; the
    trace of (S_a S_b)^1/2 from the eigenvalues of the symmetric S_a^1/2 S_b S_a^1/2."""
    mean_a, cov_a = _moments(features_a)
    mean_b, cov_b = _moments(features_b)
    root = _psd_sqrt(cov_a)
    cross = np.sqrt(np.clip(np.linalg.eigvalsh(root @ cov_b @ root), 0.0, None)).sum()
    return float(((mean_a - mean_b) ** 2).sum() + np.trace(cov_a) + np.trace(cov_b) - 2 * cross)


def frechet_interval(features_a: np.ndarray, features_b: np.ndarray, seed: int = 0,
                     resamples: int = BOOTSTRAP) -> tuple:
    """(low, high): the central INTERVAL of frechet over ``resamples`` bootstrap draws,
    both sets drawn with replacement to their own sizes from a seeded Generator."""
    rng = np.random.default_rng(seed)
    draws = [frechet(features_a[rng.integers(0, len(features_a), len(features_a))],
                     features_b[rng.integers(0, len(features_b), len(features_b))]) for _ in range(resamples)]
    tail = (1 - INTERVAL) / 2 * 100
    low, high = np.percentile(draws, [tail, 100 - tail])
    return float(low), float(high)
