"""Checks and fingerprints shared by the importers."""

import hashlib
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..reconstruction import CameraView

_CHUNK = 1 << 20
MAX_IMAGE_SIDE = 65536  # px: Blender's largest render resolution, which an imported view's camera takes
FLOAT32_MAX = float(np.finfo(np.float32).max)
MAX_FOCAL_PX = 1e8  # a 2 m lens on a 36 mm sensor over 65,536 px is 3.6e6 px; more is a unit or file mistake


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
    MAX_IMAGE_SIDE px, a focal length that is not positive and within MAX_FOCAL_PX, or a
    principal point or pose that is not finite once stored as float32, as Blender keeps
    it (each would break the view's Blender camera)."""
    where = f"camera of image {view.name!r}"
    if not (1 <= view.width <= MAX_IMAGE_SIDE and 1 <= view.height <= MAX_IMAGE_SIDE):
        raise InputError(path, f"{where}: image size {view.width} x {view.height} px is outside 1 .. {MAX_IMAGE_SIDE}")
    if not (0 < view.fx <= MAX_FOCAL_PX and 0 < view.fy <= MAX_FOCAL_PX):  # NaN compares False
        raise InputError(path, f"{where}: focal lengths {view.fx:g}, {view.fy:g} px must be positive numbers up to "
                               f"{MAX_FOCAL_PX:g}")
    if unusable_as_float32(np.array([view.cx, view.cy])).any():
        raise InputError(path, f"{where}: principal point {view.cx:g}, {view.cy:g} px must be finite")
    if unusable_as_float32(view.world_from_camera).any():
        raise InputError(path, f"{where}: its pose is not finite (as float32)")
    return view
