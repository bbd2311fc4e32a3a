"""A Plenoxels checkpoint (sxyu/svox2 ``SparseGrid.save``, a ``.npz``) -> voxel points.

The layout read, from svox2/svox2.py ``SparseGrid.save`` / ``load``:

| key | shape, type | meaning |
|---|---|---|
| ``links`` | (Rx, Ry, Rz) int32 | per grid cell the row of its data, -1 for an empty cell; the resolution is its shape |
| ``density_data`` | (C, 1) float32 | density sigma per row (rendered as relu(sigma), per unit length) |
| ``sh_data`` | (C, 3 K) float16 or float32 | SH coefficients per row, channel-major: reshape (C, 3, K) |
| ``radius``, ``center`` | (3,) float32 | the grid spans center +- radius; absent: 1 and 0, as svox2 loads them |
| ``basis_type`` | int | 1 spherical harmonics (the default; absent means 1); 4 and 255 (learned bases) are refused |
| ``data`` | (C, 1 + 3 K) | the older single array: density then SH (svox2 still loads it) |
| ``background_links``, ``background_data`` | | the multi-sphere background model: not part of the object, ignored |

Cell (i, j, k) holds its data at its centre, ``center + radius * (2 (index + 0.5) /
resolution - 1)`` (``SparseGrid.grid2world``). The SH basis, constants and color rule
are 3DGS's (``sh.py``; svox2/utils.py ``eval_sh_bases`` for K = 1, 4, 9, 16).

Each cell with relu(sigma) > 0 becomes a point (cells of zero density are empty space
to the renderer) with ``density`` (sigma, per source unit), ``opacity`` = 1 - exp(-sigma
x side), the share of light one cell side of this density stops (side: the mean of the
cell's three side lengths), its coefficients as ``f_dc_*`` / ``f_rest_*`` in the 3DGS
layout, and the DC color.
"""

import zipfile
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import npy_header
from ..reconstruction import Reconstruction
from .sh import COEFFICIENT_COUNTS, coefficient_attributes, dc_colors
from .source import checked_positions, sha256_of_files

BASIS_SH = 1
_LEARNED_BASES = {4: "a learned 3D-texture basis", 255: "a learned MLP basis"}


def load_plenoxels(path) -> Reconstruction:
    """The occupied cells of an svox2 checkpoint as points (see the module docstring);
    InputError naming ``path`` for a file that is not one."""
    path = Path(path)
    arrays = _read(path)
    links = arrays["links"]
    if links.ndim != 3 or links.dtype.kind not in "iu" or min(links.shape) < 1:
        raise InputError(path, f"links must be a 3-D integer grid, not {links.dtype} {links.shape}")
    if "data" in arrays and "sh_data" not in arrays:
        if arrays["data"].ndim != 2:
            raise InputError(path, f"data {arrays['data'].shape} must be (C, 1 + 3 K)")
        density, sh = arrays["data"][:, :1], arrays["data"][:, 1:]
    else:
        density, sh = arrays["density_data"], arrays["sh_data"]
    rows = len(density) if density.ndim else 0
    count = sh.shape[1] // 3 if sh.ndim == 2 else 0
    if density.shape != (rows, 1) or sh.ndim != 2 or len(sh) != rows or sh.shape[1] != 3 * count \
            or count not in COEFFICIENT_COUNTS:
        raise InputError(path, f"density_data {density.shape} and sh_data {sh.shape} must be (C, 1) and (C, 3 K) "
                               f"with K one of {COEFFICIENT_COUNTS} (SH degree 0-3)")
    basis = arrays.get("basis_type", np.array(BASIS_SH))
    if basis.size != 1 or basis.dtype.kind not in "iu":
        raise InputError(path, f"basis_type must be one integer, not {basis.dtype} {basis.shape}")
    basis = int(basis.ravel()[0])
    if basis != BASIS_SH:
        raise InputError(path, f"basis_type {basis} ({_LEARNED_BASES.get(basis, 'unknown')}): only spherical "
                               f"harmonics (basis_type 1) are read")
    occupied = links >= 0
    if (links < -1).any() or (links[occupied] >= rows).any():
        bad = links[(links < -1) | (links >= rows)]
        raise InputError(path, f"links out of range: {bad.size} cells point outside the {rows} data rows "
                               f"(e.g. {int(bad[0])})")
    radius = _vector(path, arrays, "radius", 1.0)
    center = _vector(path, arrays, "center", 0.0)
    if not (radius > 0).all():
        raise InputError(path, f"radius must be positive, not {radius.tolist()}")
    index = np.argwhere(occupied)
    row = links[occupied]
    sigma = density[row, 0].astype(np.float32)
    coefficients = sh[row].astype(np.float32).reshape(-1, 3, count)
    for name, values in (("density_data", sigma), ("sh_data", coefficients)):
        if not np.isfinite(values).all():
            raise InputError(path, f"{int((~np.isfinite(values)).sum())} {name} values are NaN or Inf")
    resolution = np.array(links.shape, np.float64)
    side = 2.0 * radius / resolution
    filled = sigma > 0
    positions = center + radius * (2.0 * (index[filled] + 0.5) / resolution - 1.0)
    sigma, coefficients = sigma[filled], coefficients[filled]
    attributes = {"density": sigma, "opacity": (-np.expm1(-sigma * side.mean())).astype(np.float32),
                  **coefficient_attributes(coefficients)}
    colors = np.ones((len(sigma), 4), np.float32)
    colors[:, :3] = dc_colors(coefficients)
    return Reconstruction(positions=checked_positions(path, positions, "occupied cells"), kind="plenoxels",
                          source=path, sha256=sha256_of_files([path]), colors=colors, attributes=attributes)


_NUMERIC = ("links", "density_data", "sh_data", "data", "radius", "center")  # integer or float arrays where present


def _read(path: Path) -> dict:
    """Every array of the archive (no pickled objects: ``allow_pickle=False``), each
    member's declared size checked against its bytes before it is read."""
    try:
        with open(path, "rb") as stream:
            is_zip = stream.read(4) in (b"PK\x03\x04", b"PK\x05\x06")  # np.load would read a .npy or pickle too
        if not is_zip:
            raise InputError(path, "not an .npz archive (a zip of .npy arrays)")
        with np.load(path, allow_pickle=False) as archive:
            for member in archive.zip.infolist():
                _check_member_size(path, archive.zip, member)
            arrays = {name: archive[name] for name in archive.files}
    except InputError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        raise InputError(path, f"not a readable .npz archive ({type(error).__name__}: {error})") from None
    wrong = [f"{key} ({arrays[key].dtype})" for key in _NUMERIC
             if key in arrays and arrays[key].dtype.kind not in "iuf"]
    if wrong:
        raise InputError(path, f"arrays that must hold numbers do not: {', '.join(wrong)}")
    missing = [key for key in ("links",) if key not in arrays]
    if "data" not in arrays:
        missing += [key for key in ("density_data", "sh_data") if key not in arrays]
    if missing:
        raise InputError(path, f"not a Plenoxels (svox2) checkpoint: no {', '.join(missing)} "
                               f"(has {', '.join(sorted(arrays)) or 'nothing'})")
    return arrays


def _check_member_size(path: Path, archive: zipfile.ZipFile, member: zipfile.ZipInfo) -> None:
    """InputError when an .npy member's header declares more bytes than the member
    holds: numpy would allocate what the header says before reading."""
    if not member.filename.endswith(".npy"):
        return
    with archive.open(member) as stream:
        shape, dtype = npy_header(stream, path, f"member {member.filename}: ")
    declared = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if declared > member.file_size:
        raise InputError(path, f"member {member.filename} declares {shape} {dtype} ({declared:,} bytes) but holds "
                               f"{member.file_size:,}")


def _vector(path: Path, arrays: dict, key: str, default: float) -> np.ndarray:
    if key not in arrays:
        return np.full(3, default)
    values = np.asarray(arrays[key], np.float64).ravel()
    if values.size == 1:
        values = np.repeat(values, 3)
    if values.size != 3 or not np.isfinite(values).all():
        raise InputError(path, f"{key} must be 3 finite numbers, not {arrays[key].tolist()}")
    return values
