"""The in-memory form every importer produces and every later step consumes.

Frames: positions and camera poses stay in the *source frame* of the file, in its
units (a miniature reconstructed by COLMAP has arbitrary scale). Authoring maps the
source frame to the object frame (+x forward, +y left, +z up, metres).
"""

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

SOURCE_KINDS = ("colmap", "gaussian_splat", "point_ply", "mesh")


@dataclass
class CameraView:
    """One registered photo of a reconstruction.

    Intrinsics are pinhole, in pixels, for an image of ``width`` x ``height``;
    ``model`` and ``params`` keep the source's full camera model (distortion
    included, which a Blender camera cannot represent).

    ``world_from_camera`` is a (4, 4) float64 rigid transform from the OpenCV/COLMAP
    camera frame (x right, y down, z forward along the optical axis) to the source
    frame of the points.
    """

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_from_camera: np.ndarray
    model: str = "PINHOLE"
    params: tuple = ()


@dataclass
class Reconstruction:
    """A reconstruction as it arrived.

    positions:  (N, 3) float32, source frame and units.
    faces:      (F, 3) int32 triangle vertex indices; (0, 3) for point clouds.
    colors:     (N, 4) float32 sRGB + alpha in [0, 1], or None.
    attributes: name -> (N,) or (N, k) array per point (float32 or int32),
                e.g. ``track_length``, ``opacity``, ``scale`` (N, 3), ``rotation`` (N, 4, w x y z).
    cameras:    registered views (COLMAP only).
    kind:       one of SOURCE_KINDS.
    source:     the file or folder it came from; ``sha256`` of its content.
    """

    positions: np.ndarray
    kind: str
    source: Path
    sha256: str
    faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int32))
    colors: np.ndarray | None = None
    attributes: dict = field(default_factory=dict)
    cameras: list = field(default_factory=list)

    @property
    def name(self) -> str:
        """A display name: the file stem, or the model folder's meaningful parent."""
        if self.kind == "colmap":
            parts = [p for p in self.source.parts if p not in ("sparse", "0")]
            return parts[-1] if parts else "colmap"
        return self.source.stem

    def summary(self) -> dict:
        """What arrived, as plain JSON-ready values."""
        return {
            "path": str(self.source),
            "kind": self.kind,
            "points": int(len(self.positions)),
            "faces": int(len(self.faces)),
            "cameras": len(self.cameras),
            "colors": self.colors is not None,
            "attributes": sorted(self.attributes),
            "sha256": self.sha256,
        }
