"""View-agnostic color (the paper's supplement, Algorithm 1): the mean over the training
views of the color each element shows along the ray that hits it.

For each view and each element one of its rays hits (``visibility.py``), the element's
spherical harmonics (``importing/sh.py``) are evaluated along the direction from the
camera centre to the element, and the color, max(SH + 0.5, 0) clipped at 1, is added to
the element's sum; the mean is the sum over the count. Each view counts once per element
it hits (the paper adds one per ray, which weighs the views where the element looks
larger more). Elements no view hits keep their DC color and are flagged.
"""

import numpy as np

from ..importing.sh import sh_colors


class ViewColorSums:
    """Running sums of one reconstruction's per-view colors. ``coefficients`` (N, 3, K)
    or None (no spherical harmonics: only the hits are counted); ``degree`` their SH
    degree (None without them)."""

    def __init__(self, positions: np.ndarray, coefficients: np.ndarray | None):
        self.positions = positions
        self.degree = None if coefficients is None else int(round(np.sqrt(coefficients.shape[2]))) - 1
        self.coefficients = coefficients if coefficients is not None and coefficients.shape[2] > 1 else None
        self.sums = np.zeros((len(positions), 3), np.float64)
        self.counts = np.zeros(len(positions), np.int32)

    def add(self, hits, view) -> None:
        elements = hits.framed[hits.hit]  # each element once per view
        self.counts[elements] += 1
        if self.coefficients is None:
            return
        directions = self.positions[elements].astype(np.float64) - view.centre
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        self.sums[elements] += sh_colors(self.coefficients[elements], directions)

    def colors(self, fallback: np.ndarray) -> np.ndarray:
        """(N, 3) float32: the mean view color where some view hit the element, else
        ``fallback`` (N, 3) (the DC color)."""
        if self.coefficients is None:
            return np.asarray(fallback, np.float32).copy()
        hit = self.counts > 0
        colors = np.array(fallback, np.float32)
        colors[hit] = self.sums[hit] / self.counts[hit, None]
        return colors
