"""Training cameras of a capture: a 3D Gaussian Splatting ``cameras.json`` or a COLMAP model.

``cameras.json`` is what graphdeco-inria/gaussian-splatting writes beside its output
(scene/__init__.py, one entry per test and train camera, from
utils/camera_utils.py ``camera_to_JSON``):

| key | meaning |
|---|---|
| ``id`` | index in the file |
| ``img_name`` | the image's file name without its extension |
| ``width``, ``height`` | the COLMAP image size in pixels |
| ``position`` | camera centre in the model frame |
| ``rotation`` | 3x3 rows: camera-to-world rotation (its columns are the OpenCV camera axes) |
| ``fx``, ``fy`` | focal lengths in pixels (``fov2focal`` of the training FoV) |

3DGS trains on undistorted PINHOLE / SIMPLE_PINHOLE images with the principal point
at the image centre, so the views here are PINHOLE with cx = width / 2, cy = height / 2.
"""

import json
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import TEXT_LIMIT, atomic_output, regular_file
from ..reconstruction import CameraView
from .source import MAX_IMAGE_SIDE, checked_camera

_KEYS = ("img_name", "width", "height", "position", "rotation", "fx", "fy")


def read_cameras_json(path) -> list:
    """The CameraViews of a 3DGS ``cameras.json``; InputError naming the file and the
    entry for anything that is not a valid camera (missing key, non-finite or
    non-positive size or focal length, a rotation that is not a rotation)."""
    path = regular_file(path, TEXT_LIMIT)
    try:
        entries = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as error:  # ValueError: bad JSON, UTF-8 or a huge integer
        raise InputError(path, f"not a readable cameras.json ({type(error).__name__}: {error})") from None
    if not isinstance(entries, list) or not entries:
        raise InputError(path, "a cameras.json holds a non-empty list of cameras")
    return [_camera(path, index, entry) for index, entry in enumerate(entries)]


def _camera(path: Path, index: int, entry) -> CameraView:
    where = f"camera {index}"
    if not isinstance(entry, dict):
        raise InputError(path, f"{where} is not an object")
    missing = [key for key in _KEYS if key not in entry]
    if missing:
        raise InputError(path, f"{where} has no {', '.join(missing)}")
    try:
        width, height = int(entry["width"]), int(entry["height"])
        fx, fy = float(entry["fx"]), float(entry["fy"])
        position = np.array(entry["position"], np.float64).reshape(3)
        rotation = np.array(entry["rotation"], np.float64).reshape(3, 3)
    except (TypeError, ValueError, OverflowError):
        raise InputError(path, f"{where}: width, height, fx, fy must be numbers, position 3 and "
                               f"rotation 3x3 numbers") from None
    if width != entry["width"] or height != entry["height"] or not (0 < width <= MAX_IMAGE_SIDE
                                                                    and 0 < height <= MAX_IMAGE_SIDE):
        raise InputError(path, f"{where}: width and height must be whole numbers of pixels, 1 .. {MAX_IMAGE_SIDE}")
    if not (np.isfinite(position).all() and np.isfinite(rotation).all()):
        raise InputError(path, f"{where}: position and rotation must be finite")
    if not (np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4) and np.linalg.det(rotation) > 0):
        raise InputError(path, f"{where}: rotation is not a rotation matrix (orthonormal, determinant 1)")
    world_from_camera = np.eye(4)
    world_from_camera[:3, :3], world_from_camera[:3, 3] = rotation, position
    return checked_camera(path, CameraView(name=str(entry["img_name"]), width=width, height=height, fx=fx, fy=fy,
                                           cx=width / 2, cy=height / 2, world_from_camera=world_from_camera,
                                           model="PINHOLE", params=(fx, fy, width / 2, height / 2)))


def write_cameras_json(path, cameras: list) -> None:
    """Write ``cameras`` (PINHOLE, principal point at the centre) in the 3DGS layout."""
    entries = [{"id": index, "img_name": Path(view.name).stem, "width": view.width, "height": view.height,
                "position": view.world_from_camera[:3, 3].tolist(),
                "rotation": view.world_from_camera[:3, :3].tolist(), "fx": view.fx, "fy": view.fy}
               for index, view in enumerate(cameras)]
    with atomic_output(path) as stream:
        stream.write(json.dumps(entries).encode("utf-8"))


def load_cameras(path) -> list:
    """Cameras from ``path``: a 3DGS ``cameras.json`` (any ``.json``) or a COLMAP model
    folder (cameras, images, points3D); InputError otherwise."""
    from .colmap import load_colmap

    path = Path(path)
    if path.is_dir():
        return load_colmap(path, with_cameras=True).cameras
    if not path.exists():
        raise InputError(path, "no such file or folder (cameras: a cameras.json or a COLMAP model folder)")
    if path.suffix.lower() != ".json":
        raise InputError(path, "cameras come from a 3DGS cameras.json or a COLMAP model folder")
    return read_cameras_json(path)
