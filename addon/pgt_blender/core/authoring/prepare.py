"""The authoring chain, headless: reconstruction -> aligned, headed, sized object.

Each step is a :class:`Step` (name, the (4, 4) transform it applies to the object's
current frame, the box after it, details). The Blender operators and
:class:`AuthoredObject` apply the very same steps with :func:`apply_transform`, so the
UI and ``prepare_objects.py`` give identical points, boxes and transforms.
"""

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError, finite_number
from ..files import TEXT_LIMIT, atomic_output, regular_file
from ..reconstruction import Reconstruction
from . import heading, sizing
from .alignment import align_axes, camera_up

UP_CHOICES = ("auto", "cameras", "pca", "+x", "-x", "+y", "-y", "+z", "-z")
HEADING_METHODS = ("none", "baseline", "classifier")
STEP_NAMES = ("align", "heading", "size")
SIZE_MODES = ("class", "exact", "keep")
FRAME = ("object frame: +x forward (heading), +y left, +z up, metres, origin at the centre "
         "of the axis-aligned box")


@dataclass
class Step:
    """One authoring step: ``transform`` (4, 4) maps the frame before it to the frame
    after it; ``dims`` (3,) is the box (length, width, height) after it."""

    name: str
    transform: np.ndarray
    dims: np.ndarray
    details: dict = field(default_factory=dict)


def apply_transform(positions: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """(N, 3) float32 ``positions`` mapped by the (4, 4) ``transform``, computed in float64."""
    points = np.asarray(positions, np.float64)
    return (points @ transform[:3, :3].T + transform[:3, 3]).astype(np.float32)


def apply_to_splats(scales: np.ndarray, rotations: np.ndarray, transform: np.ndarray) -> tuple:
    """Gaussian splats' (N, 3) scales and (N, 4) w x y z rotations after ``transform``
    (4, 4) moves their means (scan/gaussians.transform_gaussians), float32."""
    from ..scan.gaussians import transform_gaussians

    return transform_gaussians(scales, rotations, transform[:3, :3])


def up_vector(choice: str, world_from_cameras=(), source="points"):
    """(3,) up direction in the source frame for an UP_CHOICES entry, or None for the
    PCA minor axis. ``world_from_cameras``: (C, 4, 4) OpenCV camera poses, whose mean
    up "auto" prefers when there are any."""
    if choice not in UP_CHOICES:
        raise InputError(source, f"unknown up '{choice}' (have: {', '.join(UP_CHOICES)})")
    if choice in ("auto", "cameras") and len(world_from_cameras):
        return camera_up(world_from_cameras, source)
    if choice == "cameras":
        raise InputError(source, "has no cameras to take the up direction from")
    if choice in ("auto", "pca"):
        return None
    axis = np.zeros(3)
    axis["xyz".index(choice[1])] = 1.0 if choice[0] == "+" else -1.0
    return axis


def align_step(positions, weights=None, up=None, source="points", refine: bool = True, faces=None) -> Step:
    """Axis alignment of the current points, refined to the object's surface planes
    unless ``refine`` is False (see :mod:`.alignment`). Details: where up and yaw came
    from, the inlier count, whether refinement was asked for and whether the frame was
    refined (asked for, it is not when the object has too little flat surface), the tilt
    the refinement removed (degrees) and the estimated surface noise (source units).
    ``faces``: (F, 3) indices of a mesh's triangles, whose normals the refinement then
    uses."""
    found = align_axes(positions, weights, up, source, refine, faces)
    return Step("align", found.transform, found.dims,
                {"up_from": found.up_from, "yaw_from": found.yaw_from, "inliers": int(found.inliers.sum()),
                 "refine": refine, "refined": found.refined, "tilt_deg": found.tilt_deg, "noise": found.noise})


def turn_step(turns: int, dims) -> Step:
    """Manual heading: ``turns`` quarter turns about +z (2 = flip front and back)."""
    rotation = heading.quarter_turns(turns)
    return Step("heading", rotation, heading.transformed_dims(rotation, dims), {"by": "manual", "turns": turns % 4})


def front_step(direction, dims, source="direction") -> Step:
    """Manual heading: the box side facing ``direction`` (object frame) becomes the front."""
    rotation = heading.front_towards(direction, source)
    return Step("heading", rotation, heading.transformed_dims(rotation, dims), {"by": "manual", "turns": None})


def heading_label(details: dict) -> str:
    """How a heading step's ``details`` decided: its method ("manual", "baseline",
    "classifier"), and after a slash the rule that decided for it where that differs
    ("classifier/baseline": unsure; "classifier/running gear": a trailer)."""
    decided_by = details.get("decided_by", details["by"])
    return details["by"] if decided_by == details["by"] else f"{details['by']}/{decided_by}"


def automatic_heading_step(positions, dims, method: str, checkpoint=None, source="points",
                           class_name: str = "") -> Step:
    """Baseline or classifier front/back decision for an object of ``class_name`` (see
    :func:`.heading.automatic_front`); the step records the class ("" for none)."""
    turns, score, decided_by = heading.automatic_front(positions, dims, method, checkpoint, source, class_name)
    step = turn_step(turns, dims)
    step.details.update({"by": method, "decided_by": decided_by, "score": float(score), "class": class_name})
    return step


def size_step(dims, mode: str, dataset: str = "nuscenes", class_name: str = "", seed: int = 0,
              uniform: bool = False, exact=None, source="size") -> Step:
    """Scale to a sampled class size ("class"), to ``exact`` (l, w, h) metres, or not
    at all ("keep": the source is already metric)."""
    details = {"mode": mode, "dataset": dataset, "class": class_name}
    if mode == "keep":
        return Step("size", np.eye(4), np.asarray(dims, np.float64), details)
    if mode == "class":
        target = sizing.sample_dims(dataset, class_name, seed, uniform, source=source)
        details.update(seed=seed, uniform=uniform)
    elif mode == "exact":
        target = np.asarray(exact, np.float64)
        details.update(uniform=uniform)
    else:
        raise InputError(source, f"unknown size mode '{mode}' (have: {', '.join(SIZE_MODES)})")
    scale, new_dims = sizing.scale_to(dims, target, uniform, source)
    return Step("size", scale, new_dims, {**details, "target": target.tolist()})


@dataclass
class AuthoredObject:
    """A reconstruction on its way to the object frame.

    positions: (N, 3) float32, the current frame (the object frame once aligned).
    splat_shapes: Gaussian splats' (N, 3) scales and (N, 4) w x y z rotations, float32,
        in the current frame (each step moves them as it moves the points:
        apply_to_splats), or None for other reconstructions.
    object_from_source: (4, 4) float64, the product of every step's transform.
    """

    source: Reconstruction
    positions: np.ndarray
    object_from_source: np.ndarray = field(default_factory=lambda: np.eye(4))
    dims: np.ndarray | None = None
    steps: list = field(default_factory=list)
    splat_shapes: tuple | None = None

    @classmethod
    def from_reconstruction(cls, recon: Reconstruction) -> "AuthoredObject":
        shapes = None
        if recon.attributes.get("scale") is not None and recon.attributes.get("rotation") is not None:
            shapes = (recon.attributes["scale"], recon.attributes["rotation"])
        return cls(recon, np.asarray(recon.positions, np.float32), splat_shapes=shapes)

    def apply(self, step: Step) -> "AuthoredObject":
        self.positions = apply_transform(self.positions, step.transform)
        if self.splat_shapes is not None:
            self.splat_shapes = apply_to_splats(*self.splat_shapes, step.transform)
        self.object_from_source = step.transform @ self.object_from_source
        self.dims = np.asarray(step.dims, np.float64)
        self.steps.append(step)
        return self

    def sidecar(self, class_name: str, dataset: str) -> dict:
        """The JSON record of the object: what it is, its box, how it got there."""
        return {
            "class": class_name, "dataset": dataset,
            "dims": self.dims.tolist(),
            "transform": self.object_from_source.tolist(),
            "transform_is": "object_from_source, row-major 4x4: source file frame and units -> object frame",
            "frame": FRAME,
            "source": str(self.source.source), "source_kind": self.source.kind,
            "source_sha256": self.source.sha256, "points": int(len(self.positions)),
            "steps": [{"step": s.name, "transform": s.transform.tolist(), "dims": s.dims.tolist(), **s.details}
                      for s in self.steps],
        }


def prepare(recon: Reconstruction, class_name: str, dataset: str = "nuscenes", up: str = "auto",
            heading_method: str = "classifier", size: str = "class", exact=None,
            uniform: bool = False, seed: int = 0, checkpoint=None, refine: bool = True) -> AuthoredObject:
    """Align, head and size ``recon`` in one go; the same steps as the Blender panel."""
    if heading_method not in HEADING_METHODS:
        raise InputError(recon.source, f"unknown heading method '{heading_method}' "
                                       f"(have: {', '.join(HEADING_METHODS)})")
    authored = AuthoredObject.from_reconstruction(recon)
    weights = recon.attributes.get("opacity")
    poses = np.array([c.world_from_camera for c in recon.cameras]).reshape(-1, 4, 4)
    authored.apply(align_step(authored.positions, weights, up_vector(up, poses, recon.source), recon.source, refine,
                              recon.faces if len(recon.faces) else None))
    if heading_method != "none":  # a flat or empty box is refused by the classifier and the sizing
        authored.apply(automatic_heading_step(authored.positions, authored.dims, heading_method, checkpoint,
                                              recon.source, class_name))
    return authored.apply(size_step(authored.dims, size, dataset, class_name, seed, uniform, exact, recon.source))


def write_prepared(authored: AuthoredObject, class_name: str, dataset: str, directory) -> dict:
    """Write ``<name>.ply`` (object-frame points, colors and per-point scalars, or the
    mesh) and ``<name>.json`` (:meth:`AuthoredObject.sidecar`) into ``directory``; each
    file appears complete or not at all. Returns their paths by suffix."""
    from ..importing.ply import write_ply

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    name = authored.source.name
    paths = {".ply": directory / f"{name}.ply", ".json": directory / f"{name}.json"}
    recon = authored.source
    if len(recon.faces):
        import trimesh

        data = trimesh.Trimesh(authored.positions, recon.faces, process=False).export(file_type="ply")
        with atomic_output(paths[".ply"]) as stream:
            stream.write(data)
    else:
        write_ply(paths[".ply"], _point_columns(authored))
    text = json.dumps(authored.sidecar(class_name, dataset), indent=2)
    with atomic_output(paths[".json"]) as stream:
        stream.write(text.encode())
    return paths


def read_sidecar(path) -> dict:
    """The sidecar ``<name>.json`` that write_prepared wrote, checked: a JSON object whose
    ``class`` (when present) is a string, ``dims`` three positive finite metres and
    ``steps`` a list of objects. InputError naming the file and the field otherwise."""
    path = regular_file(path, TEXT_LIMIT)
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as error:  # ValueError: bad JSON, UTF-8 or a huge integer
        raise InputError(path, f"not a prepared-object sidecar ({type(error).__name__}: {error})") from None
    if not isinstance(record, dict):
        raise InputError(path, "not a prepared-object sidecar: expected a JSON object")
    if not isinstance(record.get("class", ""), str):
        raise InputError(path, f"class must be a string, got {record['class']!r}")
    dims = record.get("dims")
    if dims is not None and not (isinstance(dims, list) and len(dims) == 3 and all(
            finite_number(v) and v > 0 for v in dims)):
        raise InputError(path, f"dims must be three positive lengths [l, w, h] in metres, got {dims!r}")
    checked_steps(record.get("steps", []), path)
    return record


def checked_steps(steps, source, field: str = "steps") -> list:
    """``steps``, a step record (the sidecar's ``steps``, a Blender object's
    ``pgt.steps_json``), when each entry is an object naming its ``step`` (align,
    heading, size) with a (4, 4) finite ``transform``, three finite ``dims`` >= 0 and
    what the step's readers take: align ``refined`` (then ``tilt_deg`` and ``noise``),
    heading ``by``, size ``mode``. InputError naming ``source``,
    ``field`` and the first bad entry otherwise."""
    if not isinstance(steps, list):
        raise InputError(source, f"{field} must be a list of steps, got {type(steps).__name__}")
    for index, step in enumerate(steps):
        problem = _step_problem(step)
        if problem:
            raise InputError(source, f"{field}[{index}]: {problem}")
    return steps


def _step_problem(step) -> str:
    """What is wrong with one entry of a step record, or ""."""
    if not isinstance(step, dict):
        return f"expected an object, got {type(step).__name__}"
    if step.get("step") not in STEP_NAMES:
        return f"step must be one of {', '.join(STEP_NAMES)}, got {step.get('step')!r}"
    transform = step.get("transform")
    if not (isinstance(transform, list) and len(transform) == 4 and all(
            isinstance(row, list) and len(row) == 4 and all(map(finite_number, row)) for row in transform)):
        return "transform must be a 4 x 4 list of finite numbers"
    dims = step.get("dims")
    if not (isinstance(dims, list) and len(dims) == 3 and all(finite_number(v) and v >= 0 for v in dims)):
        return f"dims must be three finite lengths >= 0, got {dims!r}"
    named_by = {"heading": "by", "size": "mode"}.get(step["step"])
    if named_by and not isinstance(step.get(named_by), str):
        return f"{named_by} must be a string, got {step.get(named_by)!r}"
    for flag in ("refine", "refined") if step["step"] == "align" else ():
        if not isinstance(step.get(flag, False), bool):
            return f"{flag} must be true or false, got {step[flag]!r}"
    if step.get("refined") and not all(finite_number(step.get(key)) for key in ("tilt_deg", "noise")):
        return "a refined alignment needs finite tilt_deg and noise"
    return ""


def _point_columns(authored: AuthoredObject) -> dict:
    """PLY columns: x, y, z, then for a Gaussian splat its whole 3DGS record in the
    object frame (f_dc_* and f_rest_* as read, opacity as a logit, scale_* as logs and
    rot_* of the moved splats: a Gaussian-splat PLY again), else uchar colors and the
    frame-independent scalars (opacity, track length, ...)."""
    columns = {axis: authored.positions[:, i] for i, axis in enumerate("xyz")}
    recon = authored.source
    attributes = {name: values for name, values in recon.attributes.items() if values.ndim == 1}
    if authored.splat_shapes is not None and recon.kind == "gaussian_splat":
        scales, rotations = authored.splat_shapes
        opacity = np.clip(attributes.pop("opacity").astype(np.float64), 1e-7, 1 - 1e-7)
        columns.update(attributes)
        columns["opacity"] = np.log(opacity / (1 - opacity)).astype(np.float32)
        columns.update({f"scale_{i}": np.log(np.maximum(scales[:, i], 1e-30)).astype(np.float32) for i in range(3)})
        columns.update({f"rot_{i}": rotations[:, i] for i in range(4)})
        return columns
    if recon.colors is not None:
        rgb = np.round(recon.colors[:, :3] * 255).astype(np.uint8)
        columns.update(red=rgb[:, 0], green=rgb[:, 1], blue=rgb[:, 2])
    columns.update(attributes)
    return columns
