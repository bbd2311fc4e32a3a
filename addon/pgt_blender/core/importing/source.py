"""Checks and fingerprints shared by the importers."""

import hashlib
from pathlib import Path

import numpy as np

from ..errors import InputError

_CHUNK = 1 << 20


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
    positions = np.ascontiguousarray(positions, dtype=np.float32).reshape(-1, 3)
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
