"""The scan's output: one row per LiDAR return, the same for every scan mode.

Columns (sensor frame, see sensors.py):

| column    | type    | unit    | meaning                                                     |
|-----------|---------|---------|-------------------------------------------------------------|
| x, y, z   | float64 | m       | the return, sensor frame (float32 in written files)         |
| intensity | float32 | dataset | nuScenes/Lyft 0..255 (whole numbers), KITTI 0..1             |
| ring      | int16   | -       | beam index, 0 = lowest elevation                            |
| column    | int32   | -       | azimuth step within the revolution, 0 = first fired         |
| azimuth   | float32 | rad     | the cell's centre azimuth (phi'), from +x counter-clockwise |
| time      | float32 | s       | firing time after the start of its sweep                    |
| range     | float64 | m       | distance from the sensor origin                             |
| true_range| float64 | m       | the hit's distance before range noise (= range without it)  |
| face      | int32   | -       | the mesh face (or surfel / input point) that returned it    |
| time_lag  | float32 | s       | age of its sweep: 0 for the current one (nuScenes time_lag) |
| sweep     | int16   | -       | 0 = current sweep, k = k sweeps earlier                     |
"""

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..boxes import inside_box
from ..files import atomic_output
from .sensors import BIN_COLUMNS

RETURN_DTYPE = np.dtype([
    ("x", "f8"), ("y", "f8"), ("z", "f8"), ("intensity", "f4"), ("ring", "i2"), ("column", "i4"),
    ("azimuth", "f4"), ("time", "f4"), ("range", "f8"), ("true_range", "f8"), ("face", "i4"), ("time_lag", "f4"),
    ("sweep", "i2"),
])
OUTPUT_SUFFIXES = (".bin", ".ply", ".npy")


def return_dtype(columns=None) -> np.dtype:
    """RETURN_DTYPE, or its x, y, z and the ``columns`` named (in its order): the rows
    of a scan that asks only for those (raycast.ScanOptions.columns)."""
    if columns is None:
        return RETURN_DTYPE
    unknown = set(columns) - set(RETURN_DTYPE.names)
    if unknown:
        raise ValueError(f"scan options: no return column {', '.join(sorted(unknown))}")
    return np.dtype([(name, RETURN_DTYPE[name]) for name in RETURN_DTYPE.names
                     if name in ("x", "y", "z") or name in columns])


@dataclass
class Scan:
    """Returns of one object scan plus what it cost.

    returns: (N,) RETURN_DTYPE rows sorted by (sweep, ring, column) (only x, y, z and
             the columns the scan asked for: return_dtype).
    box:     (9,) float64 x, y, z (box centre), dx, dy, dz (length along the heading,
             width, height), heading (rad, from +x counter-clockwise), vx, vy (m/s),
             sensor frame, for the current sweep (OpenPCDet's box3d_lidar layout).
    rays:    rays cast (ray-cast modes) or points projected (range view).
    seconds: wall time of the scan.
    poses:   (4, 4) float64 sensor_from_object of each sweep, sweep 0 first: where the
             object stood then, in the key frame (the current sweep's sensor frame).
    origins: (3,) float64 per sweep: where the (moving) sensor fired that sweep from, key
             frame; returns are motion-compensated into the key frame. Empty: all at 0.
    cast_seconds: the part of ``seconds`` spent casting rays (raycast.trace_rays: the
             window, the engine's call, the float64 refinement); 0 for the range view.
    """

    returns: np.ndarray
    box: np.ndarray
    rays: int
    seconds: float
    dataset: str = "nuscenes"
    poses: list = field(default_factory=list)
    origins: list = field(default_factory=list)
    cast_seconds: float = 0.0

    @property
    def hits(self) -> int:
        return len(self.returns)

    @property
    def efficiency(self) -> float:
        """Hits per ray cast: how much of the work returned a point."""
        return self.hits / self.rays if self.rays else 0.0

    @property
    def xyz(self) -> np.ndarray:
        return np.column_stack([self.returns["x"], self.returns["y"], self.returns["z"]])

    @property
    def true_xyz(self) -> np.ndarray:
        """(N, 3) float64 sensor frame: each return where its ray hit, before range noise
        (along the ray from its sweep's origin)."""
        origin = np.asarray(self.origins, np.float64)[self.returns["sweep"]] if self.origins else np.zeros(3)
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(self.returns["range"] > 0, self.returns["true_range"] / self.returns["range"], 1.0)
        return origin + (self.xyz - origin) * scale[:, None]

    def box_frame_points(self, bounds: np.ndarray) -> np.ndarray:
        """(N, 3) float64: each return in the frame of the object's box ``bounds`` (2, 3,
        object frame) at the pose its sweep saw: origin at the box centre, +x forward."""
        local = np.empty((self.hits, 3))
        for sweep, pose in enumerate(self.poses):
            mine = self.returns["sweep"] == sweep
            local[mine] = (self.xyz[mine] - pose[:3, 3]) @ pose[:3, :3]
        return local - bounds.mean(axis=0)

    def inside_warning(self, name: str) -> str | None:
        """A warning for a sensor (the key frame's origin) within the object's current
        box: its rays start inside the object, which no real scan does; None otherwise."""
        if not inside_box(np.zeros((1, 3)), self.box)[0]:
            return None
        return (f"{name}: the sensor lies inside the object's box (centre {self.box[0]:.2f}, {self.box[1]:.2f} m): "
                f"the rays start inside the object; place it farther away")

    def stats(self) -> dict:
        return {"points": self.hits, "rays": self.rays, "efficiency": round(self.efficiency, 4),
                "ms": round(self.seconds * 1e3, 3)}

    def dataset_array(self) -> np.ndarray:
        """(N, C) float32 in the dataset's point-file columns (sensors.BIN_COLUMNS)."""
        return np.column_stack([self.returns[name] for name in BIN_COLUMNS[self.dataset]]).astype(np.float32)


def write_scan(scan: Scan, path) -> None:
    """Write ``scan`` by suffix: .bin = float32 dataset columns (KITTI x y z intensity;
    nuScenes/Lyft x y z intensity time_lag), .ply = every column, .npy = the structured
    rows. Written atomically: a failure leaves no partial file."""
    from ..importing.ply import write_ply

    path = Path(path)
    if path.suffix == ".ply":
        write_ply(path, {name: scan.returns[name] for name in RETURN_DTYPE.names})
        return
    if path.suffix not in OUTPUT_SUFFIXES:
        raise ValueError(f"{path}: output must end in {', '.join(OUTPUT_SUFFIXES)}")
    with atomic_output(path) as stream:
        if path.suffix == ".bin":
            scan.dataset_array().tofile(stream)
        else:
            np.save(stream, scan.returns)
