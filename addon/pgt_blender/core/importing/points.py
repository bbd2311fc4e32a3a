"""Point PLY and Gaussian-splat PLY -> Reconstruction (vectorised numpy)."""

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..reconstruction import Reconstruction
from .ply import PlyHeader, read_vertices
from .sh import SH_C0
from .source import FLOAT32_MAX, checked_positions, sha256_of_files, unusable_as_float32

_DC = ("f_dc_0", "f_dc_1", "f_dc_2")
_SHAPE = ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
SPLAT_FIELDS = _DC + _SHAPE  # what a 3DGS PLY has besides x y z (and f_rest_* for SH degree 1-3)
_XYZ = ("x", "y", "z")
_RGB = ("red", "green", "blue")
_NORMAL = ("nx", "ny", "nz")
_MAX_LOG_SCALE = float(np.log(FLOAT32_MAX))  # a larger stored log-scale is an infinite scale


def is_gaussian_splat(path: Path, header: PlyHeader) -> bool:
    """True when the vertex element carries the splat fields (opacity, scale, rot) and a
    color: 3DGS's ``f_dc_*`` or, as nerfstudio's splatfacto export writes with
    ``--ply-color-mode rgb``, ``red green blue``. InputError when it carries some of
    them (f_dc_* or rot_*, which no plain point cloud has) but not all: a damaged or
    cut-down splat file, not a point cloud."""
    vertex = header.element("vertex")
    names = {name for name, _ in vertex.properties} if vertex else set()
    color = _DC if any(name in names for name in _DC) or not set(_RGB) <= names else _RGB
    required = _SHAPE + color
    present = [name for name in required if name in names]
    if len(present) < len(required) and any(name.startswith(("f_dc_", "rot_")) for name in present):
        _require(path, names, required, "a whole Gaussian-splat PLY")
    return len(present) == len(required)


def load_point_ply(path: Path, header: PlyHeader) -> Reconstruction:
    """Points with optional colors (red/green/blue[/alpha], uchar 0..255 or float 0..1)
    and normals (nx, ny, nz -> ``normal``); every other scalar property is kept as an
    attribute under its own name."""
    data = read_vertices(path, header)
    names = set(data)
    _require(path, names, _XYZ, "a point PLY")
    normals = ("normal",) if set(_NORMAL) <= names else ()
    attributes = _leftover_attributes(path, data, _XYZ + _RGB + ("alpha",) + _NORMAL, normals)
    if normals:
        attributes["normal"] = _stack(data, _NORMAL)
    colors = None
    _require_finite(path, data, [name for name in _RGB + ("alpha",) + _NORMAL if name in names], "points")
    if set(_RGB) <= names:
        channels = _RGB + (("alpha",) if "alpha" in names else ())
        colors = np.ones((len(data["x"]), 4), np.float32)
        colors[:, : len(channels)] = _unit_colors(path, data, channels)
    return Reconstruction(
        positions=checked_positions(path, _stack(data, _XYZ)),
        kind="point_ply", source=Path(path), sha256=sha256_of_files([path]),
        colors=colors, attributes=attributes,
    )


def load_gaussian_splat(path: Path, header: PlyHeader) -> Reconstruction:
    """A Gaussian-splat PLY (3DGS ``point_cloud.ply``, nerfstudio splatfacto
    ``splat.ply``) with 3DGS's activations applied:

    - color = clip(0.5 + SH_C0 * f_dc, 0, 1) (the view-independent DC term), or the
      ``red green blue`` of a splatfacto rgb export (uchar / 255, or float as is);
    - ``opacity`` = sigmoid(stored logit), in (0, 1);
    - ``scale`` (N, 3) = exp(stored log-scale), in source units;
    - ``rotation`` (N, 4) = stored quaternion (w, x, y, z) normalised to unit length;
    - ``f_dc_*``, ``f_rest_*`` (SH degree 0..3, layout in ``sh.py``) and any other field
      kept raw, except normals that are all zero (splatfacto writes nx = ny = nz = 0).
    """
    data = read_vertices(path, header)
    names = set(data)
    color = _DC if set(_DC) <= names else _RGB
    _require(path, names, _XYZ + _SHAPE + color, "a Gaussian-splat PLY")
    rest = [f"f_rest_{i}" for i in range(sum(name.startswith("f_rest_") for name in names))]
    if len(rest) not in (0, 9, 24, 45) or not names.issuperset(rest):
        raise InputError(
            path, f"{len(rest)} f_rest_* fields; spherical harmonics of degree 1, 2 or 3 "
            "need 9, 24 or 45 numbered from f_rest_0"
        )
    _require_finite(path, data, color + _SHAPE + tuple(rest) + (_NORMAL if set(_NORMAL) <= names else ()), "splats")
    rotation = _stack(data, ("rot_0", "rot_1", "rot_2", "rot_3")).astype(np.float64)
    length = np.linalg.norm(rotation, axis=1)
    if not (length > 0).all():
        raise InputError(path, f"{int((length <= 0).sum())} splats have a zero-length rotation quaternion")
    empty_normals = _NORMAL if set(_NORMAL) <= names and not any(data[n].any() for n in _NORMAL) else ()
    consumed = _XYZ + _SHAPE + empty_normals + (_RGB if color == _RGB else ())
    attributes = _leftover_attributes(path, data, consumed, ("opacity", "scale", "rotation"))
    attributes["opacity"] = (1.0 / (1.0 + np.exp(-data["opacity"].astype(np.float64)))).astype(np.float32)
    log_scale = _stack(data, ("scale_0", "scale_1", "scale_2")).astype(np.float64)
    huge = int((log_scale > _MAX_LOG_SCALE).any(axis=1).sum())
    if huge:
        raise InputError(path, f"{huge} splats have a log-scale beyond float32 once exponentiated (scale_* above "
                               f"{_MAX_LOG_SCALE:.1f})")
    attributes["scale"] = np.exp(log_scale).astype(np.float32)
    attributes["rotation"] = (rotation / length[:, None]).astype(np.float32)
    colors = np.ones((len(data["x"]), 4), np.float32)
    if color == _DC:
        colors[:, :3] = np.clip(0.5 + SH_C0 * _stack(data, _DC), 0.0, 1.0)
    else:
        colors[:, :3] = _unit_colors(path, data, _RGB)
    return Reconstruction(
        positions=checked_positions(path, _stack(data, _XYZ)),
        kind="gaussian_splat", source=Path(path), sha256=sha256_of_files([path]),
        colors=colors, attributes=attributes,
    )


def _require_finite(path, data: dict, names, what: str) -> None:
    """InputError naming the properties where some values are NaN or infinite, here or
    once stored as float32 (as the importer keeps them)."""
    bad = {name: int(unusable_as_float32(data[name]).sum()) for name in names if data[name].dtype.kind == "f"}
    bad = {name: count for name, count in bad.items() if count}
    if bad:
        listed = ", ".join(f"{name} ({count})" for name, count in bad.items())
        raise InputError(path, f"{max(bad.values())} of {len(data[names[0]])} {what} have NaN or Inf values in "
                               f"{listed}")


def _unit_colors(path, data: dict, channels) -> np.ndarray:
    """(N, len(channels)) float32 colors in 0..1: integer properties / 255, floats as
    they are. InputError naming the property when a value falls outside 0..1 (float
    colors written 0..255, or ushort colors)."""
    colors = _stack(data, channels) / np.array([255.0 if data[name].dtype.kind in "iu" else 1.0
                                                 for name in channels], np.float32)
    outside = ((colors < 0) | (colors > 1)).sum(axis=0)
    if outside.any():
        name = channels[int(np.flatnonzero(outside)[0])]
        kind = "uchar 0..255" if data[name].dtype.kind in "iu" else "float 0..1"
        raise InputError(path, f"{int(outside.max())} of {len(colors)} points have colors outside {kind} in "
                               f"'{name}' (values {float(data[name].min()):g} to {float(data[name].max()):g})")
    return colors


def _require(path, names, required, what):
    missing = [name for name in required if name not in names]
    if missing:
        raise InputError(path, f"not {what}: missing vertex properties {', '.join(missing)}")


def _stack(data: dict, names) -> np.ndarray:
    return np.column_stack([data[name] for name in names]).astype(np.float32, copy=False)


def _leftover_attributes(path, data: dict, consumed, produced) -> dict:
    """Every property not in ``consumed`` as a per-point attribute: int32 or float32, as
    Blender stores them (NaN or Inf in the file are carried as they are). InputError for
    one named like an attribute the importer makes (``produced``), or holding values
    those types cannot (an integer beyond int32 would wrap, a float beyond float32
    become Inf)."""
    taken = [name for name in produced if name in data and name not in consumed]
    if taken:
        raise InputError(path, f"vertex property '{taken[0]}' has the name of the attribute the importer makes from "
                               f"other properties; rename it")
    attributes = {}
    for name, values in data.items():
        if name in consumed:
            continue
        stored = np.int32 if values.dtype.kind in "iu" else np.float32
        if not np.can_cast(values.dtype, stored):  # a wider type (uint32, double): check its values
            limits = np.iinfo(stored) if stored is np.int32 else np.finfo(stored)
            beyond = np.isfinite(values) & ((values < limits.min) | (values > limits.max))
            if beyond.any():
                raise InputError(path, f"vertex property '{name}' holds {values[beyond][0]} in row "
                                       f"{int(np.flatnonzero(beyond)[0]) + 1}: beyond a Blender "
                                       f"{np.dtype(stored).name} attribute")
        attributes[name] = values.astype(stored, copy=False)
    return attributes
