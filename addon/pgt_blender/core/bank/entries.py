"""Scan bank entries: each object on the ground at its grid pose, over its sweeps, and
keep the returns inside its box, as the datasets' database builders do (OpenPCDet and
mmdet3d keep a ground-truth box's points; a moving object's older sweeps that fall
behind the current box are not in the database either).

Box membership is decided on where each ray hit, before range noise: the object's own
returns all stay (a surface on the box's face would otherwise lose half its returns to
noise, while a real annotated box has room around the object), so kept points may lie
outside the box by the range noise (sigma 2 cm on the presets).

The target (BVH / Embree scene, or Gaussians for a splat) of each object is built once
per worker and reused for every pose and size variant: ``TargetCache``.
"""

import time
from dataclasses import dataclass, replace

import numpy as np

from ..boxes import centred_bounds
from ..scan.raycast import Ground, ScanOptions
from ..scan.sensors import BIN_COLUMNS
from ..scan.sweeps import Motion, scan_many
from ..scan.gaussians import transform_gaussians
from ..scan.targets import element_colors, has_gaussians, resolve_engine, target_from_reconstruction
from .config import BankConfig
from .grid import size_variants, sweeps_of
from .inputs import BankObject

BOX_TOLERANCE = 1e-3  # m: a return on the box's faces counts as inside despite rounding


@dataclass(frozen=True)
class Variant:
    """A size variant of a bank object: the ScanTarget to cast on, the variant's box
    ``bounds`` (2, 3), object frame, m, and ``scale`` (3,): the variant is the target
    stretched by it along the object's axes (raycast.trace_rays), or None when the
    target is the variant's own (splats, whose Gaussians are stretched as such)."""

    target: object
    bounds: np.ndarray
    scale: np.ndarray | None


class TargetCache:
    """The size variants of each object, made on first use, their targets built for the
    bank's engine: one target per object serves all its variants (each a stretch of its
    rays), one per variant for splats; holds one object at a time (entries come object
    by object)."""

    def __init__(self, objects: list, config: BankConfig):
        self.objects, self.config = objects, config
        self.engine = resolve_engine(config.engine)  # what the targets are built for and cast with
        self._object, self._variants, self._shared, self._rgb = None, {}, None, None
        self.build_seconds = 0.0  # spent making variants (their targets), all told

    def _switch(self, object_index: int) -> None:
        if object_index != self._object:
            self._object, self._variants, self._shared, self._rgb = object_index, {}, None, None

    def get(self, object_index: int, variant: int) -> Variant:
        """The object's size variant ``variant``, made once."""
        self._switch(object_index)
        if variant not in self._variants:
            start = time.perf_counter()
            self._variants[variant] = self._make(object_index, variant)
            self.build_seconds += time.perf_counter() - start
        return self._variants[variant]

    def _make(self, object_index: int, variant: int) -> Variant:
        obj: BankObject = self.objects[object_index]
        dims = size_variants(self.config, object_index, obj.dims)[variant]
        bounds = centred_bounds(dims)
        if not has_gaussians(obj.geometry.attributes):
            if self._shared is None:
                self._shared = self._target(obj.geometry)
            return Variant(self._shared, bounds, dims / obj.dims)
        scale = (dims / obj.dims).astype(np.float32)
        shapes = transform_gaussians(obj.geometry.attributes["scale"], obj.geometry.attributes["rotation"],
                                     np.diag(scale.astype(np.float64)))  # the splats stretch with their means
        geometry = replace(obj.geometry, positions=obj.geometry.positions * scale,
                           attributes={**obj.geometry.attributes, "scale": shapes[0], "rotation": shapes[1]})
        return Variant(self._target(geometry), bounds, None)

    def _target(self, geometry):
        return target_from_reconstruction(geometry, self.config.radius_scale, self.engine)

    def element_rgb(self, object_index: int) -> np.ndarray:
        """(E, 3) float32 sRGB of what a return's ``face`` indexes (targets.element_colors),
        worked out once per object."""
        self._switch(object_index)
        if self._rgb is None:
            self._rgb = element_colors(self.objects[object_index].geometry)
        return self._rgb


def scan_entries(cache: TargetCache, sensor, entries: np.ndarray, config: BankConfig) -> list:
    """The Scan of every sweep of each grid.ENTRY_DTYPE row, in their order, its returns
    those inside the current box (``scan.box``, (9,) sensor frame), with the columns of
    the dataset's files (all of them for a learned intensity, which reads more). The
    entries that share a ray target (an object's size variants, or one splat variant)
    are cast together (sweeps.scan_many)."""
    options = ScanOptions(range_noise=config.range_noise, max_incidence_deg=config.max_incidence_deg,
                          drop_rate=config.drop_rate, ray_drop=config.ray_drop, engine=cache.engine,
                          columns=None if config.intensity_checkpoint else BIN_COLUMNS[config.dataset])
    pairs, which = np.unique(entries[["object", "variant"]], return_inverse=True)
    variants = [cache.get(int(pair["object"]), int(pair["variant"])) for pair in pairs]
    bounds = np.array([variant.bounds for variant in variants])  # (V, 2, 3)
    scans = [None] * len(entries)
    for target in {id(variant.target): variant.target for variant in variants}.values():
        alike = [number for number, variant in enumerate(variants) if variant.target is target]
        index = np.flatnonzero(np.isin(which, alike))
        batch, own = entries[index], which[index]
        # a splat variant is a target of its own (no scale); a mesh's variants all stretch one target
        scale = None if variants[alike[0]].scale is None else np.array([variants[number].scale for number in own])
        found = scan_many(target, sensor, batch["x"], batch["y"], batch["heading"],
                          Motion(batch["speed"], batch["acceleration"]), sweeps_of(config), options,
                          batch["noise_seed"], bounds[own], BOX_TOLERANCE,
                          Motion(batch["ego_speed"], batch["ego_acceleration"]),
                          Ground(batch["ground_height"], batch["pitch"], batch["roll"]), scale)
        for position, scan in zip(index, found):
            scans[position] = scan
    return scans
