"""COLMAP sparse model folder -> Reconstruction, through pycolmap.

Binary models are walked first (``check_binary_model``): pycolmap trusts the counts in
the files and allocates what they claim, so a truncated or damaged file could ask for
gigabytes. Every count is checked against the bytes left before anything is read.
"""

import struct
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..reconstruction import CameraView, Reconstruction
from ..files import regular_file
from .source import checked_camera, checked_positions, sha256_of_files, unusable_as_float32

MODEL_FILES = ("cameras", "images", "points3D")


def model_files(folder: Path) -> list:
    """The three model files of ``folder`` (all .bin, else all .txt, as COLMAP reads
    them); InputError naming what is missing."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "not a folder; a COLMAP model is a folder with cameras, images, points3D")
    for extension in (".bin", ".txt"):
        files = [folder / (name + extension) for name in MODEL_FILES]
        present = [f.exists() for f in files]
        if all(present):
            return [regular_file(f) for f in files]
        if any(present):
            missing = ", ".join(f.name for f, ok in zip(files, present) if not ok)
            raise InputError(folder, f"COLMAP model is missing {missing}")
    hint = " (try its sparse/0 sub-folder)" if (folder / "sparse" / "0").is_dir() else ""
    raise InputError(folder, f"no COLMAP model files (cameras, images, points3D as .bin or .txt){hint}")


def load_colmap(folder: Path, with_cameras: bool = True) -> Reconstruction:
    """Points with RGB, ``track_length`` (int32) and ``reprojection_error`` (pixels),
    and, with ``with_cameras``, one CameraView per registered image, in the model's
    world frame."""
    import pycolmap  # imported here: only this importer needs the compiled library

    folder = Path(folder)
    files = model_files(folder)
    if files[0].suffix == ".bin":
        check_binary_model(files)
    try:
        model = pycolmap.Reconstruction(str(folder))
    except Exception as error:  # pycolmap raises bare RuntimeError/ValueError for bad files
        raise InputError(folder, f"COLMAP model could not be read: {_first_line(error)}") from None
    points = list(model.points3D.values())
    # pycolmap exposes points one object at a time; sparse models are ~1e3-1e6 points.
    positions = np.array([p.xyz for p in points], np.float64).reshape(-1, 3)
    colors = np.ones((len(points), 4), np.float32)
    colors[:, :3] = np.array([p.color for p in points], np.float32).reshape(-1, 3) / 255.0
    errors = np.array([p.error for p in points], np.float64)
    unusable = unusable_as_float32(errors)
    if unusable.any():
        raise InputError(files[2], f"{int(unusable.sum())} of {len(points)} points have a reprojection error that is "
                                   f"NaN or beyond float32")
    attributes = {
        "track_length": np.array([p.track.length() for p in points], np.int32),
        "reprojection_error": errors.astype(np.float32),
    }
    cameras = [checked_camera(folder, _camera_view(image)) for image in model.images.values()
               if image.has_pose] if with_cameras else []
    return Reconstruction(
        positions=checked_positions(folder, positions),
        kind="colmap", source=folder, sha256=sha256_of_files(files),
        colors=colors, attributes=attributes, cameras=sorted(cameras, key=lambda c: c.name),
    )


def _camera_view(image) -> CameraView:
    camera = image.camera
    world_from_camera = np.eye(4)
    world_from_camera[:3] = image.cam_from_world().inverse().matrix()
    return CameraView(
        name=image.name, width=int(camera.width), height=int(camera.height),
        fx=float(camera.focal_length_x), fy=float(camera.focal_length_y),
        cx=float(camera.principal_point_x), cy=float(camera.principal_point_y),
        world_from_camera=world_from_camera,
        model=camera.model.name, params=tuple(float(p) for p in camera.params),
    )


def _first_line(error: Exception) -> str:
    text = str(error).strip() or type(error).__name__
    return text.splitlines()[-1] if "\n" in text else text


# COLMAP's camera models (src/colmap/sensor/models.h): model id -> number of parameters.
CAMERA_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 16}


class _Reader:
    """Little-endian reads from one file's bytes that never pass its end."""

    def __init__(self, path: Path):
        self.path, self.data, self.at = path, path.read_bytes(), 0

    def take(self, layout: str) -> tuple:
        size = struct.calcsize("<" + layout)
        if self.at + size > len(self.data):
            raise InputError(self.path, f"truncated: ends at byte {len(self.data):,} inside a record")
        values = struct.unpack_from("<" + layout, self.data, self.at)
        self.at += size
        return values

    def skip(self, count: int, record: int, what: str) -> None:
        """Skip ``count`` records of ``record`` bytes, refusing a count the file cannot hold."""
        if count * record > len(self.data) - self.at:
            raise InputError(self.path, f"claims {count:,} {what} but only {len(self.data) - self.at:,} bytes follow "
                                        f"(damaged or truncated)")
        self.at += count * record

    def string(self) -> None:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise InputError(self.path, "truncated: an image name has no end")
        self.at = end + 1

    def count(self, what: str, smallest_record: int) -> int:
        (number,) = self.take("Q")
        if number * smallest_record > len(self.data) - self.at:
            raise InputError(self.path, f"claims {number:,} {what} but only {len(self.data) - self.at:,} bytes "
                                        f"follow (damaged or truncated)")
        return number

    def done(self) -> None:
        if self.at != len(self.data):
            raise InputError(self.path, f"{len(self.data) - self.at:,} bytes after the last record (damaged)")


def check_binary_model(files: list) -> None:
    """Walk cameras.bin, images.bin and points3D.bin (COLMAP's binary layout); InputError
    naming the file at the first count or size that does not fit. No allocation depends
    on a number read from a file."""
    cameras = _Reader(files[0])
    for _ in range(cameras.count("cameras", 24)):
        _, model, _, _ = cameras.take("iiQQ")
        if model not in CAMERA_PARAMS:
            raise InputError(files[0], f"unknown camera model id {model}")
        cameras.skip(CAMERA_PARAMS[model], 8, "camera parameters")
    cameras.done()
    images = _Reader(files[1])
    for _ in range(images.count("images", 73)):
        images.take("I7dI")
        images.string()
        (points,) = images.take("Q")
        images.skip(points, 24, "image points")
    images.done()
    points = _Reader(files[2])
    for _ in range(points.count("points", 51)):
        *_, track = points.take("Q3d3BdQ")
        points.skip(track, 8, "track elements")
    points.done()
