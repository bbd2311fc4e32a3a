"""Checks and fingerprints shared by the importers."""

import hashlib
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..reconstruction import CameraView

_CHUNK = 1 << 20
MAX_IMAGE_SIDE = 65536  # px: Blender's largest render resolution, which an imported view's camera takes
FLOAT32_MAX = float(np.finfo(np.float32).max)


def sha256_of_files(paths) -> str:
    """Hex sha256 over the bytes of ``paths`` in the given order (file names excluded,
    so a renamed or moved copy keeps its checksum)."""
    digest = hashlib.sha256()
    for path in paths:
        with open(path, "rb") as stream:
            while chunk := stream.read(_CHUNK):
                digest.update(chunk)
    return digest.hexdigest()


def checked_positions(path: Path, positions: np.ndarray, what: str = "points") -> np.ndarray:
    """``positions`` as a C-contiguous (N, 3) float32 array, or InputError when it is
    empty or holds NaN/Inf (one bad coordinate would poison every later step)."""
    positions = np.ascontiguousarray(positions, dtype=np.float32)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise InputError(path, f"{what} are not 3-D coordinates (read as an array of shape {positions.shape})")
    if len(positions) == 0:
        raise InputError(path, f"no {what}: the file holds an empty cloud")
    finite = np.isfinite(positions).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise InputError(
            path,
            f"{len(bad)} of {len(positions)} {what} have NaN/Inf coordinates "
            f"(first at index {bad[0]})",
        )
    return positions


def unusable_as_float32(values: np.ndarray) -> np.ndarray:
    """Bool per value: NaN or infinite, here or once stored as float32 (as the importers
    keep attributes)."""
    return ~(np.abs(values) <= FLOAT32_MAX)


def checked_camera(path: Path, view: CameraView) -> CameraView:
    """``view``, or InputError naming ``path`` and the view for an image size outside 1 ..
    MAX_IMAGE_SIDE px, a focal length that is not positive and finite, or a principal
    point or pose that is not finite (each would break the view's Blender camera)."""
    where = f"camera of image {view.name!r}"
    if not (1 <= view.width <= MAX_IMAGE_SIDE and 1 <= view.height <= MAX_IMAGE_SIDE):
        raise InputError(path, f"{where}: image size {view.width} x {view.height} px is outside 1 .. {MAX_IMAGE_SIDE}")
    if not (np.isfinite([view.fx, view.fy]).all() and view.fx > 0 and view.fy > 0):
        raise InputError(path, f"{where}: focal lengths {view.fx:g}, {view.fy:g} px must be positive finite numbers")
    if not np.isfinite([view.cx, view.cy]).all():
        raise InputError(path, f"{where}: principal point {view.cx:g}, {view.cy:g} px must be finite")
    if not np.isfinite(view.world_from_camera).all():
        raise InputError(path, f"{where}: its pose is not finite")
    return view
