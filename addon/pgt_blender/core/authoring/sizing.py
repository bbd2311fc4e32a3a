"""Instance size: scale the aligned object to a real-world box (paper section 3.1).

The paper draws an instance size from the class mean of the target dataset with
Gaussian noise, sigma 0.1, clipped to +-1 sigma. Here the noise is *relative*
(size = mean x (1 + e), e ~ N(0, 0.1) clipped to [-0.1, 0.1]) so it applies alike to
datasets that publish no std (KITTI, Lyft).
"""

import warnings

import numpy as np

from ..classes import CLASS_SIZES
from ..errors import InputError

SIZE_NOISE = 0.1
FLAT = 1e-6  # a box side under this share of the longest is a flat object's float noise
# Per-axis factors that differ more than this reshape the object rather than size it: a
# part (a tyre) or another class, since a whole vehicle's proportions are its class's
# within about a third (the Chrono cars against nuScenes' mean car: 1.24).
MAX_STRETCH = 2.0


def class_dims(dataset: str, class_name: str, source="size") -> np.ndarray:
    """(3,) mean (length, width, height) in metres; InputError(source) listing what exists."""
    if dataset not in CLASS_SIZES:
        raise InputError(source, f"unknown dataset '{dataset}' (have: {', '.join(CLASS_SIZES)})")
    sizes = CLASS_SIZES[dataset]
    if class_name not in sizes:
        raise InputError(source, f"{dataset} has no class '{class_name}' (have: {', '.join(sizes)})")
    return np.array(sizes[class_name], np.float64)


def sample_dims(dataset: str, class_name: str, seed: int, uniform: bool = False,
                noise: float = SIZE_NOISE, source="size") -> np.ndarray:
    """(3,) class mean x (1 + e), e ~ N(0, ``noise``) clipped to +-``noise``, one e
    per axis, or one for all three when ``uniform``. Same seed, same size."""
    draws = np.random.default_rng(seed).normal(scale=noise, size=1 if uniform else 3)
    return class_dims(dataset, class_name, source) * (1 + np.clip(draws, -noise, noise))


def scale_to(dims, target, uniform: bool = False, source="size") -> tuple:
    """The (4, 4) scale about the origin taking a box of ``dims`` to ``target`` (both
    (3,), dims in the object's current units) and the box it gives.

    Anisotropic: each axis its own factor, the box becomes ``target``. Uniform: one
    factor, the geometric mean of the three ratios (the proportions stay, the volume
    matches the target's)."""
    dims, target = np.asarray(dims, np.float64), np.asarray(target, np.float64)
    if (target <= 0).any() or not np.isfinite([*dims, *target]).all() or not (dims > FLAT * dims.max()).all():
        raise InputError(source, f"cannot scale a box of {dims.tolist()} to {target.tolist()}: sizes must be positive "
                                 f"(a side under {FLAT:g} of the longest is flat: float noise, not a size)")
    factors = target / dims
    if uniform:
        factors = np.full(3, np.exp(np.log(factors).mean()))
    elif factors.max() > MAX_STRETCH * factors.min():
        warnings.warn(f"{source}: sizing stretches one axis {factors.max() / factors.min():.1f}x more than another "
                      f"(box {np.round(dims / dims.max(), 2).tolist()} of its length against "
                      f"{np.round(target / target.max(), 2).tolist()}): a part of a vehicle, or another class?",
                      stacklevel=2)
    return np.diag([*factors, 1.0]), dims * factors
