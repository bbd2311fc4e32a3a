"""Scan bank entries: each object on the ground at its grid pose, over its sweeps, and
keep the returns inside its box, as the datasets' database builders do (OpenPCDet and
mmdet3d keep a ground-truth box's points; a moving object's older sweeps that fall
behind the current box are not in the database either).

Box membership is decided on where each ray hit, before range noise: the object's own
returns all stay (a surface on the box's face would otherwise lose half its returns to
noise, while a real annotated box has room around the object), so kept points may lie
outside the box by the range noise (sigma 2 cm on the presets).

The target (BVH, or Gaussians for a splat) of each size variant is built once per
worker and reused for every pose: ``TargetCache``.
"""

import time
from dataclasses import replace

import numpy as np

from ..boxes import inside_box
from ..scan.raycast import Ground, ScanOptions
from ..scan.sweeps import Motion, scan_many
from ..scan.gaussians import transform_gaussians
from ..scan.targets import element_colors, has_gaussians, target_from_reconstruction
from .config import BankConfig
from .grid import size_variants, sweeps_of
from .inputs import BankObject

BOX_TOLERANCE = 1e-3  # m: a return on the box's faces counts as inside despite rounding


class TargetCache:
    """ScanTargets of (object, size variant), built on first use (without Blender's BVH
    for the Embree engine); holds one object's variants at a time (entries come object
    by object)."""

    def __init__(self, objects: list, config: BankConfig):
        self.objects, self.config = objects, config
        self._object, self._targets, self._rgb = None, {}, None
        self.build_seconds = 0.0  # spent building targets, all told

    def _switch(self, object_index: int) -> None:
        if object_index != self._object:
            self._object, self._targets, self._rgb = object_index, {}, None

    def get(self, object_index: int, variant: int) -> tuple:
        """(ScanTarget, box bounds (2, 3)) of the variant, object frame, metres."""
        self._switch(object_index)
        if variant not in self._targets:
            start = time.perf_counter()
            obj: BankObject = self.objects[object_index]
            dims = size_variants(self.config, object_index, obj.dims)[variant]
            scale = (dims / obj.dims).astype(np.float32)
            geometry = replace(obj.geometry, positions=obj.geometry.positions * scale)
            if has_gaussians(geometry.attributes):  # the splats stretch with their means
                shapes = transform_gaussians(geometry.attributes["scale"], geometry.attributes["rotation"],
                                             np.diag(scale.astype(np.float64)))
                geometry.attributes = {**geometry.attributes, "scale": shapes[0], "rotation": shapes[1]}
            target = target_from_reconstruction(geometry, self.config.radius_scale, self.config.engine == "bvh")
            self._targets[variant] = (target, np.stack([-dims / 2, dims / 2]))
            self.build_seconds += time.perf_counter() - start
        return self._targets[variant]

    def element_rgb(self, object_index: int) -> np.ndarray:
        """(E, 3) float32 sRGB of what a return's ``face`` indexes (targets.element_colors),
        worked out once per object."""
        self._switch(object_index)
        if self._rgb is None:
            self._rgb = element_colors(self.objects[object_index].geometry)
        return self._rgb


def scan_entries(cache: TargetCache, sensor, entries: np.ndarray, config: BankConfig) -> list:
    """[(Scan of every sweep, (N,) bool mask of its returns inside the current box)] of
    grid.ENTRY_DTYPE rows, in their order; ``scan.box`` is the (9,) box, sensor frame.
    The entries of each (object, size variant) are cast together (sweeps.scan_many)."""
    options = ScanOptions(range_noise=config.range_noise, max_incidence_deg=config.max_incidence_deg,
                          drop_rate=config.drop_rate, ray_drop=config.ray_drop, engine=config.engine)
    scans = [None] * len(entries)
    pairs = entries[["object", "variant"]]
    for pair in np.unique(pairs):
        index = np.flatnonzero(pairs == pair)
        batch = entries[index]
        target, bounds = cache.get(int(pair["object"]), int(pair["variant"]))
        found = scan_many(target, sensor, batch["x"], batch["y"], batch["heading"],
                          Motion(batch["speed"], batch["acceleration"]), sweeps_of(config), options,
                          batch["noise_seed"], bounds, BOX_TOLERANCE, Motion(batch["ego_speed"], batch["ego_acceleration"]),
                          Ground(batch["ground_height"], batch["pitch"], batch["roll"]))
        for position, scan in zip(index, found):
            scans[position] = (scan, inside_box(scan.true_xyz, scan.box, BOX_TOLERANCE))
    return scans
