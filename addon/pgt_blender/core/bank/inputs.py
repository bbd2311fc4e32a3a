"""The bank's inputs: authored objects, from a folder of prepared objects or (through
the Blender layer) from a .blend. Both routes end in the same BankObject, so the same
objects give the same bank.

Frame: the object frame of authoring (+x forward, +y left, +z up, metres, origin at the
centre of the box). The box is the authored one, ``dims`` (3,) = length, width, height,
centred on the origin: not the geometry's bounds, which may hold floaters.
"""

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..boxes import centred_bounds
from ..errors import InputError
from ..files import listed, no_dead_link
from ..reconstruction import Reconstruction
from ..scan.targets import require_scannable


@dataclass
class BankObject:
    """One authored object: ``name`` (unique, used in file names), its ``class_name``
    (as authored, e.g. nuScenes' "truck"), ``dims`` (3,) float64 metres and its geometry
    as a Reconstruction in the object frame (a mesh, Gaussian splats scanned as
    Gaussians, or points that become surfels)."""

    name: str
    class_name: str
    dims: np.ndarray
    geometry: Reconstruction

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64: the box's min and max corners, object frame."""
        return centred_bounds(self.dims)

    def summary(self) -> dict:
        """What the bank depends on; ``sha256`` is of the geometry itself (positions,
        faces, colors, and a splat's scales, rotations and opacities), so either input
        route gives the same summary."""
        geometry = self.geometry
        digest = hashlib.sha256()
        splat = [geometry.attributes.get(key) for key in ("scale", "rotation", "opacity")]
        for array in (geometry.positions, geometry.faces, geometry.colors, *splat):
            if array is not None:
                digest.update(np.ascontiguousarray(array).tobytes())
        return {"name": self.name, "class": self.class_name, "dims": self.dims.tolist(),
                "points": int(len(geometry.positions)), "faces": int(len(geometry.faces)),
                "colors": geometry.colors is not None, "sha256": digest.hexdigest()}


def safe_name(name: str) -> str:
    """``name`` with anything but letters, digits, '-' and '.' replaced by '_' (file names)."""
    return re.sub(r"[^A-Za-z0-9.-]", "_", name)


def incomplete_reason(class_name: str, sized: bool) -> str | None:
    """Why an object cannot go into a bank, or None when it can."""
    missing = [what for what, ok in (("class", bool(class_name)), ("size", sized)) if not ok]
    return f"no {' and no '.join(missing)} set" if missing else None


def prepared_objects(folder) -> tuple[list, list]:
    """The prepared objects of ``folder`` (prepare_objects.py output: <name>.ply + <name>.json
    sidecar), sorted by name, and the incomplete ones as (path, reason): no sidecar, or a
    sidecar without class or size step. InputError for an unreadable sidecar or file."""
    from ..authoring.prepare import read_sidecar
    from ..importing import load_reconstruction

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "not a folder of prepared objects")
    objects, incomplete = [], []
    for path in listed(folder, "*.ply"):
        sidecar = path.with_suffix(".json")
        if not no_dead_link(sidecar).is_file():
            incomplete.append((path, "no sidecar JSON (prepare it with prepare_objects.py)"))
            continue
        record = read_sidecar(sidecar)
        class_name, dims = record.get("class", ""), record.get("dims")
        sized = any(step.get("step") == "size" for step in record.get("steps", []))
        reason = incomplete_reason(class_name, sized and dims is not None)
        if reason:
            incomplete.append((path, reason))
            continue
        geometry = load_reconstruction(path, with_cameras=False)
        objects.append(BankObject(path.stem, class_name, np.asarray(dims, np.float64), geometry))
    return objects, incomplete


def checked_objects(objects: list, incomplete: list, skip_incomplete: bool, source) -> list:
    """``objects`` (from ``source``, a folder or .blend) sorted by name, when they can make
    a bank: InputError listing the incomplete ones (unless skipped), when there is none,
    when two share a file name, for a box that is not three positive lengths, or for
    geometry no scan can be made of (targets.require_scannable: an emptied Blender mesh,
    NaN points, faces all of zero area, splat fields edited to NaN)."""
    if incomplete and not skip_incomplete:
        listed = "; ".join(f"{Path(path).name}: {reason}" for path, reason in incomplete)
        raise InputError(source, f"{len(incomplete)} incomplete object(s), set class and size or skip them "
                                 f"(--skip-incomplete, the Bank panel's Skip incomplete): {listed}")
    if not objects:
        raise InputError(source, "no complete object to put in the bank")
    names = [safe_name(obj.name) for obj in objects]
    clashes = sorted({name for name in names if names.count(name) > 1})
    if clashes:
        raise InputError(source, f"objects share the name(s) {', '.join(clashes)}; rename them")
    for obj in objects:
        if obj.dims.shape != (3,) or not np.all(obj.dims > 0):
            raise InputError(source, f"{obj.name}: box dims {obj.dims.tolist()} are not three positive lengths")
        try:  # before the output folder is made: a chunk would fail after it
            require_scannable(obj.geometry.positions, obj.geometry.faces, obj.name, obj.geometry.attributes)
        except InputError as error:
            raise InputError(source, f"{obj.name}: {error.problem}") from None
    return sorted(objects, key=lambda obj: obj.name)
