"""Synthetic captures with known answers, for tests, benchmarks and trying the importers:
orbit cameras, splat clouds on spheres and tables with spherical-harmonic colors, and
writers of the files real tools produce (a 3DGS output folder, a nerfstudio splatfacto
PLY, a Plenoxels checkpoint). Frame: z up, source units; every draw seeded.
"""

from pathlib import Path

import numpy as np

from ..importing.cameras import write_cameras_json
from ..importing.ply import write_ply
from ..importing.sh import coefficient_attributes, dc_colors
from ..reconstruction import CameraView


def look_at(centre, target, name: str, width: int = 320, height: int = 240, fx: float = 300.0) -> CameraView:
    """A PINHOLE camera at ``centre`` looking at ``target`` with the image's up towards
    +z (or +y when looking straight up or down), principal point at the image centre."""
    centre, target = np.asarray(centre, np.float64), np.asarray(target, np.float64)
    forward = (target - centre) / np.linalg.norm(target - centre)
    up = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    world_from_camera = np.eye(4)
    world_from_camera[:3, :3] = np.column_stack([right, np.cross(forward, right), forward])
    world_from_camera[:3, 3] = centre
    return CameraView(name=name, width=width, height=height, fx=fx, fy=fx, cx=width / 2, cy=height / 2,
                      world_from_camera=world_from_camera, model="PINHOLE", params=(fx, fx, width / 2, height / 2))


def orbit_cameras(count: int, radius: float, elevation_deg: float, target=(0.0, 0.0, 0.0), **intrinsics) -> list:
    """``count`` cameras evenly spaced in azimuth on a circle of ``radius`` at
    ``elevation_deg`` above ``target``, each looking at it (names view_000.png ...)."""
    azimuth = 2 * np.pi * np.arange(count) / count
    elevation = np.radians(elevation_deg)
    offsets = radius * np.column_stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                                        np.full(count, np.sin(elevation))])
    target = np.asarray(target, np.float64)
    return [look_at(target + offset, target, f"view_{index:03d}.png", **intrinsics)
            for index, offset in enumerate(offsets)]


def fibonacci_sphere(count: int) -> np.ndarray:
    """(count, 3) float64 nearly uniform unit vectors (golden-angle spiral)."""
    index = np.arange(count) + 0.5
    z = 1 - 2 * index / count
    azimuth = np.pi * (1 + 5 ** 0.5) * index
    ring = np.sqrt(1 - z * z)
    return np.column_stack([ring * np.cos(azimuth), ring * np.sin(azimuth), z])


def table_scene(rng: np.random.Generator, sphere_points: int = 12000, table_points: int = 12000,
                clutter_points: int = 2000) -> dict:
    """A ball of radius 0.5 resting on a 4 x 4 table (z = 0) at the origin, and a box of
    clutter on the table 1.5 away: {"positions": (N, 3) float32, "foreground": (N,) bool
    (the ball), "ball_centre": (3,)}."""
    ball_centre = np.array([0.0, 0.0, 0.5])
    ball = ball_centre + 0.5 * fibonacci_sphere(sphere_points)
    table = np.column_stack([rng.uniform(-2, 2, (table_points, 2)), np.zeros(table_points)])
    table = table[np.linalg.norm(table[:, :2], axis=1) > 0.02]  # nothing under the ball's contact point
    clutter = rng.uniform([1.3, -0.2, 0.05], [1.7, 0.2, 0.45], (clutter_points, 3))
    positions = np.concatenate([ball, table, clutter]).astype(np.float32)
    foreground = np.zeros(len(positions), bool)
    foreground[:len(ball)] = True
    return {"positions": positions, "foreground": foreground, "ball_centre": ball_centre}


def ball_masks(cameras: list, centre, radius: float) -> list:
    """Per camera the (height, width) bool mask of the pixels whose centre ray meets the
    ball (exact ray-sphere test): what a perfect segmenter returns for the ball."""
    masks = []
    for view in cameras:
        u, v = np.meshgrid(np.arange(view.width) + 0.5, np.arange(view.height) + 0.5)
        rays = np.stack([(u - view.cx) / view.fx, (v - view.cy) / view.fy, np.ones_like(u)], axis=-1)
        rays = rays @ view.world_from_camera[:3, :3].T
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        towards = np.asarray(centre) - view.centre
        along = rays @ towards
        masks.append((along > 0) & (towards @ towards - along ** 2 <= radius ** 2))
    return masks


def splat_columns(positions: np.ndarray, coefficients: np.ndarray, opacity: np.ndarray, scale: np.ndarray,
                  rotation: np.ndarray | None = None) -> dict:
    """PLY columns of a 3DGS ``point_cloud.ply`` (GaussianModel.save_ply's order: x y z nx
    ny nz f_dc_* f_rest_* opacity scale_* rot_*) from activated values: ``opacity`` in
    (0, 1) (stored as its logit), ``scale`` (N, 3) (stored as its log), ``rotation``
    (N, 4) w x y z (default identity), ``coefficients`` (N, 3, K)."""
    size = len(positions)
    rotation = np.tile([1.0, 0.0, 0.0, 0.0], (size, 1)) if rotation is None else rotation
    columns = {axis: positions[:, i].astype(np.float32) for i, axis in enumerate("xyz")}
    columns.update({name: np.zeros(size, np.float32) for name in ("nx", "ny", "nz")})
    columns.update(coefficient_attributes(coefficients))
    columns["opacity"] = np.log(opacity / (1 - opacity)).astype(np.float32)
    columns.update({f"scale_{i}": np.log(scale[:, i]).astype(np.float32) for i in range(3)})
    columns.update({f"rot_{i}": rotation[:, i].astype(np.float32) for i in range(4)})
    return columns


def write_3dgs_run(run: Path, columns: dict, cameras: list, iterations=(7000, 30000)) -> Path:
    """A 3DGS output folder: ``columns`` (``splat_columns``) as the splats of every
    iteration in ``iterations`` (the earlier ones cut to half, so that reading the wrong
    one shows), ``cameras.json``, ``cfg_args``; returns the highest iteration's PLY."""
    run = Path(run)
    for iteration in sorted(iterations):
        folder = run / "point_cloud" / f"iteration_{iteration}"
        folder.mkdir(parents=True, exist_ok=True)
        size = len(columns["x"]) if iteration == max(iterations) else len(columns["x"]) // 2
        write_ply(folder / "point_cloud.ply", {name: values[:size] for name, values in columns.items()})
    write_cameras_json(run / "cameras.json", cameras)
    (run / "cfg_args").write_text("Namespace(sh_degree=3, source_path='data/capture', model_path='output/run', "
                                  "images='images', resolution=-1, white_background=False, eval=False)")
    return run / "point_cloud" / f"iteration_{max(iterations)}" / "point_cloud.ply"


def splatfacto_columns(columns: dict, rgb: bool = False) -> dict:
    """The same splats as nerfstudio's ``ns-export gaussian-splat`` writes them
    (scripts/exporter.py ExportGaussianSplat: x y z, zero nx ny nz, f_dc_* f_rest_* or,
    with ``rgb`` (``--ply-color-mode rgb``), uchar red green blue of the DC color,
    opacity, scale_*, rot_*)."""
    out = {name: columns[name] for name in ("x", "y", "z", "nx", "ny", "nz")}
    if rgb:
        dc = np.stack([columns[f"f_dc_{c}"] for c in range(3)], axis=1)[:, :, None]
        out.update(zip(("red", "green", "blue"), (dc_colors(dc) * 255).astype(np.uint8).T))
    else:
        out.update({name: values for name, values in columns.items() if name.startswith(("f_dc_", "f_rest_"))})
    out.update({name: columns[name] for name in ("opacity", "scale_0", "scale_1", "scale_2",
                                                 "rot_0", "rot_1", "rot_2", "rot_3")})
    return out


def write_svox2(path: Path, links: np.ndarray, density: np.ndarray, sh: np.ndarray, radius, center,
                basis_type: int = 1) -> None:
    """A Plenoxels checkpoint as svox2's ``SparseGrid.save`` writes one (np.savez of
    radius, center, links, density_data, sh_data as float16, basis_type)."""
    np.savez(path, radius=np.asarray(radius, np.float32), center=np.asarray(center, np.float32),
             links=links.astype(np.int32), density_data=density.astype(np.float32).reshape(-1, 1),
             sh_data=sh.astype(np.float16), basis_type=basis_type)
