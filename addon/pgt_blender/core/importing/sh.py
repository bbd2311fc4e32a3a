"""Real spherical harmonics of degree 0-3 as 3D Gaussian Splatting and Plenoxels use them.

Both evaluate a color channel as ``max(sum_k coefficient_k * basis_k(d) + 0.5, 0)``
with the same basis, constants and signs (graphdeco-inria/gaussian-splatting
utils/sh_utils.py ``eval_sh``; sxyu/svox2 svox2/utils.py ``eval_sh_bases``), where
``d`` is the unit direction from the camera centre to the element, in the
reconstruction's frame. Basis order (x, y, z the components of d):

| k | basis | k | basis |
|---|---|---|---|
| 0 | C0 | 8 | C2[4] (xx - yy) |
| 1 | -C1 y | 9 | C3[0] y (3xx - yy) |
| 2 | C1 z | 10 | C3[1] xy z |
| 3 | -C1 x | 11 | C3[2] y (4zz - xx - yy) |
| 4 | C2[0] xy | 12 | C3[3] z (2zz - 3xx - 3yy) |
| 5 | C2[1] yz | 13 | C3[4] x (4zz - xx - yy) |
| 6 | C2[2] (2zz - xx - yy) | 14 | C3[5] z (xx - yy) |
| 7 | C2[3] xz | 15 | C3[6] x (xx - 3yy) |

Coefficients are held as (N, 3, K) arrays: element, color channel (R, G, B), basis
index, K = (degree + 1)^2. A 3DGS PLY stores them as ``f_dc_0..2`` (k = 0 of R, G, B)
and ``f_rest_i``, i = channel * (K - 1) + (k - 1): all R coefficients, then G, then B
(GaussianModel.save_ply writes features_rest transposed to (N, 3, K-1), flattened).
"""

import numpy as np

SH_C0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
COEFFICIENT_COUNTS = (1, 4, 9, 16)  # K for degree 0, 1, 2, 3


def sh_basis(directions: np.ndarray, count: int) -> np.ndarray:
    """(M, count) float32 basis values at ``directions`` (M, 3) unit vectors; ``count``
    one of COEFFICIENT_COUNTS."""
    if count not in COEFFICIENT_COUNTS:
        raise ValueError(f"{count} spherical-harmonic coefficients; expected one of {COEFFICIENT_COUNTS}")
    d = np.asarray(directions, np.float32)
    basis = np.empty((len(d), count), np.float32)
    basis[:, 0] = SH_C0
    if count == 1:
        return basis
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    basis[:, 1], basis[:, 2], basis[:, 3] = -SH_C1 * y, SH_C1 * z, -SH_C1 * x
    if count == 4:
        return basis
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    basis[:, 4] = SH_C2[0] * xy
    basis[:, 5] = SH_C2[1] * yz
    basis[:, 6] = SH_C2[2] * (2 * zz - xx - yy)
    basis[:, 7] = SH_C2[3] * xz
    basis[:, 8] = SH_C2[4] * (xx - yy)
    if count == 9:
        return basis
    basis[:, 9] = SH_C3[0] * y * (3 * xx - yy)
    basis[:, 10] = SH_C3[1] * xy * z
    basis[:, 11] = SH_C3[2] * y * (4 * zz - xx - yy)
    basis[:, 12] = SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy)
    basis[:, 13] = SH_C3[4] * x * (4 * zz - xx - yy)
    basis[:, 14] = SH_C3[5] * z * (xx - yy)
    basis[:, 15] = SH_C3[6] * x * (xx - 3 * yy)
    return basis


def sh_colors(coefficients: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(M, 3) float32 RGB in [0, 1] seen along ``directions`` (M, 3, unit, camera to
    element) for ``coefficients`` (M, 3, K): max(SH + 0.5, 0) as both renderers compute
    it, then clipped at 1 as a pixel shows it."""
    basis = sh_basis(directions, coefficients.shape[2])
    return np.clip(np.einsum("mk,mck->mc", basis, coefficients) + 0.5, 0.0, 1.0)


def dc_colors(coefficients: np.ndarray) -> np.ndarray:
    """(N, 3) float32 color of the DC term alone, clip(0.5 + C0 * k0, 0, 1)."""
    return np.clip(0.5 + SH_C0 * coefficients[:, :, 0], 0.0, 1.0).astype(np.float32)


def coefficient_attributes(coefficients: np.ndarray) -> dict:
    """{name: (N,) float32} in the 3DGS PLY naming (``f_dc_c``, ``f_rest_i``, see above)."""
    count = coefficients.shape[2]
    names = {f"f_dc_{c}": coefficients[:, c, 0] for c in range(3)}
    names.update({f"f_rest_{c * (count - 1) + k - 1}": coefficients[:, c, k]
                  for c in range(3) for k in range(1, count)})
    return {name: np.ascontiguousarray(values, np.float32) for name, values in names.items()}


def coefficients_from_attributes(attributes: dict) -> np.ndarray | None:
    """(N, 3, K) float32 coefficients from ``f_dc_*`` / ``f_rest_*`` attributes (the
    layout above), or None when the element carries no ``f_dc_*``."""
    if not all(f"f_dc_{c}" in attributes for c in range(3)):
        return None
    rest = sum(1 for name in attributes if name.startswith("f_rest_"))
    count = rest // 3 + 1
    if count not in COEFFICIENT_COUNTS or rest % 3:
        raise ValueError(f"{rest} f_rest_* attributes; degree 1, 2 or 3 need 9, 24 or 45")
    size = len(attributes["f_dc_0"])
    coefficients = np.empty((size, 3, count), np.float32)
    for c in range(3):
        coefficients[:, c, 0] = attributes[f"f_dc_{c}"]
        for k in range(1, count):
            coefficients[:, c, k] = attributes[f"f_rest_{c * (count - 1) + k - 1}"]
    return coefficients
