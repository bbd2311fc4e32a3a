"""The in-memory form every importer produces and every later step consumes.

Frames: positions and camera poses stay in the *source frame* of the file, in its
units (a miniature reconstructed by COLMAP has arbitrary scale). Authoring maps the
source frame to the object frame (+x forward, +y left, +z up, metres).
"""

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

SOURCE_KINDS = ("colmap", "gaussian_splat", "plenoxels", "point_ply", "mesh")
# COLMAP camera models whose distortion ``CameraView.project`` applies (their parameters: COLMAP's
# src/colmap/sensor/models.h).
PROJECTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


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

    @property
    def centre(self) -> np.ndarray:
        """(3,) camera centre in the source frame."""
        return self.world_from_camera[:3, 3]

    def camera_from_world(self) -> np.ndarray:
        """(4, 4) float64 source frame -> OpenCV camera frame."""
        rotation = self.world_from_camera[:3, :3]
        inverse = np.eye(4)
        inverse[:3, :3] = rotation.T
        inverse[:3, 3] = -rotation.T @ self.world_from_camera[:3, 3]
        return inverse

    def project(self, points_camera: np.ndarray) -> tuple:
        """Pixels of ``points_camera`` (M, 3), OpenCV camera frame, z > 0: ``(uv, ok)``
        with uv (M, 2) float32 (u right, v down, pixel centres at +0.5) through the
        pinhole and the distortion of ``model`` (one of PROJECTED_MODELS, else
        ValueError), and ok (M,) False where the distortion polynomial folds back
        (points far outside the image, beyond twice the corners' radius)."""
        if self.model not in PROJECTED_MODELS:
            raise ValueError(f"camera model {self.model} has no projection here (supported: "
                             f"{', '.join(PROJECTED_MODELS)})")
        x = points_camera[:, 0] / points_camera[:, 2]
        y = points_camera[:, 1] / points_camera[:, 2]
        params = self.params
        k1 = k2 = p1 = p2 = 0.0
        if self.model == "SIMPLE_RADIAL":
            k1 = params[3]
        elif self.model == "RADIAL":
            k1, k2 = params[3], params[4]
        elif self.model == "OPENCV":
            k1, k2, p1, p2 = params[4:8]
        ok = np.ones(len(x), bool)
        if k1 or k2 or p1 or p2:
            r2 = x * x + y * y
            corner = (max(self.cx, self.width - self.cx) / self.fx) ** 2 + (max(self.cy, self.height - self.cy) / self.fy) ** 2
            ok = r2 <= 2.0 * corner
            radial = 1 + k1 * r2 + k2 * r2 * r2
            x, y = (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                    y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)
        uv = np.column_stack([self.fx * x + self.cx, self.fy * y + self.cy]).astype(np.float32)
        return uv, ok


@dataclass
class Reconstruction:
    """A reconstruction as it arrived.

    positions:  (N, 3) float32, source frame and units.
    faces:      (F, 3) int32 triangle vertex indices; (0, 3) for point clouds.
    colors:     (N, 4) float32 sRGB + alpha in [0, 1], or None.
    attributes: name -> (N,) or (N, k) array per point (float32, int32, or bool for flags),
                e.g. ``track_length``, ``opacity``, ``scale`` (N, 3), ``rotation`` (N, 4, w x y z),
                ``view_hit`` (bool, see core/capture).
    cameras:    registered views (COLMAP models, 3DGS runs, cameras given with a splat or
                Plenoxels file).
    capture:    what core/capture did to it (view color, foreground), JSON-ready; empty if nothing.
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
    capture: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        """A display name: the file stem, or the model folder's meaningful parent."""
        if self.kind == "colmap":
            parts = [p for p in self.source.parts if p not in ("sparse", "0")]
            return parts[-1] if parts else "colmap"
        if self.source.name == "point_cloud.ply" and self.source.parent.name.startswith("iteration_"):
            return self.source.parents[2].name  # a 3DGS run: <run>/point_cloud/iteration_N/point_cloud.ply
        return self.source.stem

    def subset(self, keep: np.ndarray) -> "Reconstruction":
        """The same reconstruction with only the elements where ``keep`` (N,) bool is
        True (point clouds only: faces would need re-indexing)."""
        if len(self.faces):
            raise ValueError("subset of a mesh")
        return Reconstruction(
            positions=self.positions[keep], kind=self.kind, source=self.source, sha256=self.sha256,
            colors=None if self.colors is None else self.colors[keep],
            attributes={name: values[keep] for name, values in self.attributes.items()},
            cameras=self.cameras, capture=dict(self.capture),
        )

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
            **({"capture": self.capture} if self.capture else {}),
        }
