"""The frame of a nerfstudio splatfacto export: its run's ``dataparser_transforms.json``.

nerfstudio trains in its own frame: the data parser orients, centres and scales the data
(nerfstudio/data/dataparsers/base_dataparser.py ``save_dataparser_transform`` writes
``{"transform": 3x4 [R | t], "scale": s}``), and ``ns-export gaussian-splat`` writes the
splats in that frame. A point of the original data (for COLMAP data, the COLMAP model's
world: the transform includes ns-process-data's ``applied_transform``) sits at
``s (R x + t)`` there (``transform_poses_to_original_space`` inverts exactly this). The
COLMAP cameras the run trained on are moved the same way: centre c -> s (R c + t),
camera axes (OpenCV) -> R axes.
"""

import json
from dataclasses import replace

import numpy as np

from ..errors import InputError
from ..files import TEXT_LIMIT, regular_file
from .source import unusable_as_float32

DATAPARSER_TRANSFORMS = "dataparser_transforms.json"


def read_dataparser_transform(path) -> tuple:
    """(R (3, 3), t (3,), s) of a ``dataparser_transforms.json``; InputError naming the
    file unless R is a rotation and s a positive finite number."""
    path = regular_file(path, TEXT_LIMIT)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        transform = np.array(data["transform"], np.float64).reshape(3, 4)
        scale = float(data["scale"])
    except (OSError, KeyError, TypeError, ValueError, OverflowError, RecursionError) as error:
        raise InputError(path, f"not a nerfstudio dataparser transform: {{'transform': 3x4, 'scale': s}} "
                               f"({type(error).__name__}: {error})") from None
    rotation, translation = transform[:, :3], transform[:, 3]
    if not (np.isfinite(transform).all() and np.isfinite(scale) and scale > 0):
        raise InputError(path, "transform and scale must be finite, scale positive")
    if not (np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4) and np.linalg.det(rotation) > 0):
        raise InputError(path, "the transform's 3x3 part is not a rotation")
    return rotation, translation, scale


def to_model_frame(cameras: list, path) -> list:
    """``cameras`` of the original data moved into the frame of the run whose
    ``dataparser_transforms.json`` is ``path``."""
    rotation, translation, scale = read_dataparser_transform(path)
    moved = []
    for view in cameras:
        world_from_camera = np.eye(4)
        world_from_camera[:3, :3] = rotation @ view.world_from_camera[:3, :3]
        with np.errstate(over="ignore", invalid="ignore"):  # named below
            world_from_camera[:3, 3] = scale * (rotation @ view.world_from_camera[:3, 3] + translation)
        if unusable_as_float32(world_from_camera).any():  # Blender keeps float32 matrices
            raise InputError(path, f"moves camera {view.name!r} beyond the floating-point range: "
                                   f"scale and translation are not this run's")
        moved.append(replace(view, world_from_camera=world_from_camera))
    # Blender keeps float32 matrices: a scale that small leaves every camera at one point
    before, after = (np.array([view.world_from_camera[:3, 3] for view in views], np.float32)
                     for views in (cameras, moved))
    if len(cameras) > 1 and np.ptp(before, axis=0).any() and not np.ptp(after, axis=0).any():
        raise InputError(path, f"moves every camera onto one point (scale {scale:g}): scale is not this run's")
    return moved
