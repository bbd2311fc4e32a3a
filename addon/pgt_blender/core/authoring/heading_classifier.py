"""Learned front/back classifier (the paper's heading classifier), needs PyTorch.

The paper's main text names PointNet++; its supplement describes what is built here,
a conventional PointNet: a shared per-point MLP 6 -> 64 -> 128 (3 input channels
there; the box's proportions added here, see Input), max-pooled to a
128-dim feature, then an MLP 128 -> 64 -> 1 logit, "the front is at +x", batch
normalisation after every layer but the last, as PointNet has it. Without it a
leave-one-out fold (the van held out) never left chance at 3000 steps (the former
default): every ReLU of the 64-unit layer died; with it that fold's training loss
falls from the first hundred steps, and the held-out accuracy rose from 0.85 to 0.88
on dense samples and from 0.73 to 0.81 on scans at 3 % noise (docs/benchmarks.md). Trained
with binary cross-entropy on object-frame point sets whose front is known, each
flipped 180 degrees about z with p = 0.5 (x, y -> -x, -y, label flips) and never
otherwise rotated: a rotation-sensitive network is what tells front from back.

Input: object-frame points (metres; +x forward, +y left, +z up, origin at the box
centre) divided by half the box dims, so the box is [-1, 1]^3, resampled to the
checkpoint's fixed point count by a seeded generator; each point also carries the
box's proportions, dims / max(dims) (six input channels). The division alone hides
them, and they tell a narrow, tall two-wheeler from a flat car, whose fronts look
different (docs/benchmarks.md, "Heading accuracy": they lifted the held-out
accuracy on scans from 0.65 to 0.72).

Training sets (:class:`PointSet`): surface samples of meshes (the built-in sample
vehicles, Chrono meshes, any closed or open mesh with its front at +x), scans of the
same meshes by the project's own LiDAR simulation (:func:`scanned_point_sets`:
partial, one-sided views at several ranges and headings, what a detector's sampler
holds), and objects of an mmdetection3d / OpenPCDet ground-truth database. Each
batch item is a kind of set (dense, scan, database) drawn uniformly, then a set of
that kind: with one dense set and two dozen views per mesh, drawing sets uniformly
let the scans drown the dense samples (held out: 0.72 on scans and 0.78 on dense
samples, against 0.76 and 0.83 balanced). Augmentations besides the flip, none of
them a rotation: point count (log-uniform, so densities from a far LiDAR object to
a dense reconstruction), Gaussian jitter, anisotropic scale and a left-right mirror
(y -> -y, p = 0.5: the front stays the front, and a scan sees either side; 0.79
held out on scans and 0.85 on dense samples with it).

torch is imported inside the functions that need it, so the rest of the core works
without it; without it they raise :class:`InputError` with a one-line reason.
"""

import hashlib
import platform
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import gt_database, learning
from ..errors import InputError

DEFAULT_CHECKPOINT = Path(__file__).resolve().parents[2] / "models" / "heading_pointnet.pt"
FORMAT = "pgt_blender.heading_pointnet/3"  # /2: no batch normalisation; /1: three input channels
ARCHITECTURE = ("PointNet: shared MLP 6-64-128 (batch norm, ReLU), max-pool -> 128-dim feature, "
                "MLP 128-64 (batch norm, ReLU) -1 -> logit")
# Chrono meshes without a front (a tyre): left out of mesh folders.
NO_FRONT = ("sedan_tire.obj",)
# Surface points drawn once per mesh; training draws its point sets from this pool.
POOL_POINTS = 16384
# Scans of each training mesh (scanned_point_sets): straight ahead of the sensor at
# these ranges, turned to this many evenly spaced headings, so every side is seen.
SCAN_RANGES_M = (10.0, 20.0, 35.0)
SCAN_HEADINGS = 8
SCAN_MIN_POINTS = 16
# Training steps: held out (one mesh left out, seed 0) 250, 500, 1000 and 3000 steps gave
# 0.82, 0.83, 0.79 and 0.77 on scans at 0 % noise: more steps learn the training meshes.
STEPS = 500


@dataclass(frozen=True)
class PointSet:
    """Object-frame points of one object with its front at +x.

    points: (N, 3) float64 metres, origin at the box centre; dims: (3,) box (length,
    width, height) metres; source: where it came from, with a checksum (the
    checkpoint's config records each source and how many sets it gave);
    features: (N, C) float32 columns after x, y, z in a database's file (intensity, ...),
    (N, 0) for mesh samples; class_name: the database's class, "" for meshes; kind:
    "dense" (a mesh's surface samples), "scan" (a LiDAR view of a mesh) or "database"
    (a ground-truth database's object): training draws each kind equally often."""

    name: str
    points: np.ndarray
    dims: np.ndarray
    source: str
    features: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))
    class_name: str = ""
    kind: str = "dense"


@dataclass
class HeadingClassifier:
    """A trained model (torch ``nn.Module``, eval mode) and its training config (dict)."""

    model: object
    config: dict


def require_torch(path):
    """The torch module, or InputError(path) saying the heading classifier needs it."""
    return learning.require_torch(path, "the heading classifier")


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def point_set_from_mesh(mesh, name: str, source: str, seed: int = 0) -> PointSet:
    """``POOL_POINTS`` area-weighted surface points of a trimesh ``mesh`` whose front is
    at +x (+z up, metres), centred on its bounds' centre."""
    import trimesh

    low, high = mesh.bounds
    surface, _ = trimesh.sample.sample_surface(mesh, POOL_POINTS, seed=seed)
    return PointSet(name, surface - (low + high) / 2, high - low, source)


def scanned_point_sets(mesh, name: str, source: str, sensor="nuscenes", ranges=SCAN_RANGES_M,
                       headings: int = SCAN_HEADINGS) -> list:
    """What a LiDAR sees of a trimesh ``mesh`` (front at +x, +z up, metres): one point set
    per (range, heading), the mesh standing on the ground ``range`` m straight ahead of
    ``sensor`` (a preset name or Sensor) turned by the heading, scanned by the project's
    ray caster (core/scan, noiseless, one sweep). Points are the returns in the mesh's
    object frame (origin at its box centre, like :func:`point_set_from_mesh`): partial,
    one-sided, ring-structured views; ``dims`` the whole mesh's box, as a labelled
    object's. Views with fewer than ``SCAN_MIN_POINTS`` returns are left out."""
    from ..scan.raycast import scan_object
    from ..scan.sensors import sensor_from_name
    from ..scan.targets import mesh_target

    sensor = sensor_from_name(sensor) if isinstance(sensor, str) else sensor
    target = mesh_target(mesh.vertices, mesh.faces, name)
    low, high = mesh.bounds
    sets = []
    for distance in ranges:
        for turn in range(headings):
            degrees = 360.0 * turn / headings
            scan = scan_object(target, sensor, float(distance), 0.0, np.radians(degrees))
            if len(scan.returns) < SCAN_MIN_POINTS:
                continue
            sensor_points = np.column_stack([scan.returns[axis] for axis in "xyz"])
            object_from_sensor = np.linalg.inv(scan.poses[0])
            points = sensor_points @ object_from_sensor[:3, :3].T + object_from_sensor[:3, 3]
            sets.append(PointSet(f"{name}@{distance:g}m/{degrees:g}deg", points - (low + high) / 2, high - low,
                                 f"{source} scans:{sensor.name}", kind="scan"))
    return sets


def sample_meshes(classes=None) -> list:
    """(name, trimesh, source) of the built-in sample vehicles (default: the minority
    classes), front at +x, metres."""
    from ..classes import MINORITY_CLASSES
    from ..samples import sample_vehicle

    meshes = []
    for class_name in classes or MINORITY_CLASSES:
        vehicle = sample_vehicle(class_name)
        digest = _sha256(vehicle.vertices.tobytes() + vehicle.faces.tobytes())
        meshes.append((class_name, vehicle.trimesh(), f"sample:{class_name} sha256:{digest}"))
    return meshes


def mesh_folder_meshes(directory) -> list:
    """(name, trimesh, source) of every ``*.obj`` under ``directory`` (sorted, except
    ``NO_FRONT``), each in metres with X forward, Y left, Z up, e.g. the Chrono meshes."""
    from ..scan.targets import require_scannable

    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(directory, "no such mesh folder")
    paths = sorted(p for p in directory.rglob("*.obj") if p.name not in NO_FRONT)
    if not paths:
        raise InputError(directory, "holds no .obj meshes")
    meshes = []
    for path in paths:
        raw = _read_obj(path, process=False)  # as the file holds it: processing drops a NaN vertex silently
        if len(raw.faces) == 0:
            raise InputError(path, "the mesh has no faces")
        require_scannable(raw.vertices, raw.faces, path)  # the training scans it
        mesh = _read_obj(path, process=True)  # the mesh trained on
        if mesh.extents.min() <= 1e-6 * mesh.extents.max():
            raise InputError(path, f"the mesh is flat (extents {np.round(mesh.extents, 6).tolist()} m): "
                                   "a vehicle has a front, a side and a top to learn from")
        meshes.append((path.stem, mesh, f"mesh:{path.name} sha256:{_sha256(path.read_bytes())}"))
    return meshes


def _read_obj(path: Path, process: bool):
    """The trimesh.Trimesh of an .obj file; InputError naming it when trimesh cannot read it."""
    import trimesh

    try:
        return trimesh.load(path, force="mesh", process=process)
    except Exception as error:  # trimesh raises many types for a broken file
        raise InputError(path, f"cannot read the mesh ({error})") from None


def sample_point_sets(classes=None) -> list:
    """Point sets of the built-in sample vehicles (default: the minority classes)."""
    return [point_set_from_mesh(mesh, name, source) for name, mesh, source in sample_meshes(classes)]


def mesh_folder_point_sets(directory) -> list:
    """Point sets of every mesh of :func:`mesh_folder_meshes`."""
    return [point_set_from_mesh(mesh, name, source) for name, mesh, source in mesh_folder_meshes(directory)]


def read_gt_database(path, convention: str | None = None, min_points: int = 5) -> list:
    """The objects of an mmdetection3d or OpenPCDet ground-truth database
    (gt_database.read_objects) as point sets, their front at +x."""
    return [PointSet(obj.name, obj.points, obj.dims, obj.source, obj.features, obj.class_name, "database")
            for obj in gt_database.read_objects(path, convention, min_points)]


def normalise(points: np.ndarray, dims) -> np.ndarray:
    """(..., N, 6) float32 network input of object-frame ``points`` (..., N, 3) metres
    in a box of ``dims`` (3,): the points divided by half the dims (the box is
    [-1, 1]^3), then the box's proportions dims / max(dims), the same on every point."""
    dims = np.asarray(dims, np.float64)
    scaled = np.asarray(points) / (dims / 2)
    proportions = np.broadcast_to(dims / dims.max(), scaled.shape)
    return np.concatenate([scaled, proportions], axis=-1).astype(np.float32)


def resample(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` rows of ``points`` (N, 3): a random subset when N >= count, else all N
    padded by random repeats (repeats change no max-pooled feature)."""
    n = len(points)
    if n >= count:
        return points[rng.choice(n, count, replace=False)]
    return np.concatenate([points, points[rng.integers(n, size=count - n)]])


def _network(torch):
    nn = torch.nn
    return nn.Sequential(
        nn.Conv1d(6, 64, 1), nn.BatchNorm1d(64), nn.ReLU(),  # shared per-point MLP
        nn.Conv1d(64, 128, 1), nn.BatchNorm1d(128), nn.ReLU(),
        nn.AdaptiveMaxPool1d(1), nn.Flatten(),  # (B, 128) feature
        nn.Linear(128, 64), nn.BatchNorm1d(64), nn.ReLU(), nn.Linear(64, 1))


def _by_kind(sets: list) -> list:
    """``sets`` grouped by PointSet.kind, kinds in sorted order: what training draws from."""
    return [[item for item in sets if item.kind == kind] for kind in sorted({item.kind for item in sets})]


def _training_batch(kinds: list, config: dict, rng: np.random.Generator):
    """(B, points, 6) float32 network inputs (:func:`normalise`) and (B,) float32 labels
    (1: front at +x) from ``kinds`` (:func:`_by_kind`). Each item: a kind uniformly, then
    a set of that kind uniformly (a mesh's one dense set would otherwise drown among its
    dozens of scanned views)."""
    low, high = np.log(config["count_range"])
    clouds, labels = [], []
    for _ in range(config["batch"]):
        group = kinds[rng.integers(len(kinds))]
        item = group[rng.integers(len(group))]
        count = min(int(np.exp(rng.uniform(low, high))), len(item.points))
        points = item.points[rng.choice(len(item.points), count, replace=False)]
        points = resample(points, config["points"], rng)
        sigma = rng.uniform(0, config["noise_max"]) * np.linalg.norm(item.dims)
        points = points + rng.normal(scale=sigma, size=points.shape)
        points = points * rng.uniform(1 - config["scale_jitter"], 1 + config["scale_jitter"], 3)
        if rng.random() < config["mirror_p"]:  # left-right: a mirrored vehicle keeps its front
            points = points * (1, -1, 1)
        front = rng.random() >= config["flip_p"]
        clouds.append(normalise(points if front else points * (-1, -1, 1), item.dims))
        labels.append(float(front))
    return np.stack(clouds), np.array(labels, np.float32)


def train(sets: list, seed: int = 0, steps: int = STEPS, points: int = 512, batch: int = 32,
          lr: float = 3e-3, threads: int = 1, progress=None) -> HeadingClassifier:
    """Train a classifier on ``sets`` (list of :class:`PointSet`, fronts at +x), each
    batch item a kind of set, then a set of that kind, drawn uniformly. Deterministic:
    same sets, seed and ``threads`` (torch's CPU thread count, restored afterwards) give
    the same weights. Adam with a cosine-decayed ``lr``; ``progress(step, loss)`` is
    called after every step. InputError when training collapsed: the last batch's
    logits all equal or not finite (every ReLU of a layer dead, which batch
    normalisation prevents, or weights overflowed by a far too high ``lr``), a network
    that would say the same of every object and so leave every heading as it is."""
    torch = require_torch("torch")
    if not sets or steps < 1 or batch < 2:  # batch normalisation needs two items to normalise
        raise ValueError("training needs point sets, at least one step and batches of two or more "
                         f"({len(sets)} sets, {steps} steps, batch {batch})")
    sources = {}
    for item in sets:
        sources[item.source] = sources.get(item.source, 0) + 1
    config = {
        "format": FORMAT, "architecture": ARCHITECTURE, "seed": seed, "steps": steps,
        "threads": threads, "points": points, "batch": batch, "lr": lr, "loss": "binary cross-entropy",
        "flip_p": 0.5, "mirror_p": 0.5, "rotation_augmentation": False, "count_range": [32, 4096],
        "set_sampling": "a kind (dense, scan, database) uniformly, then a set of that kind uniformly",
        "noise_max": 0.03, "scale_jitter": 0.1,
        "normalisation": "points / (dims / 2), then dims / max(dims) on every point",
        "sources": [{"source": s, "point_sets": n} for s, n in sorted(sources.items())],
        "versions": {"torch": str(torch.__version__), "numpy": np.__version__, "python": platform.python_version()},
    }
    rng, kinds = np.random.default_rng(seed), _by_kind(sets)
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        with torch.random.fork_rng(devices=[]):  # leave the caller's torch RNG alone
            torch.manual_seed(seed)
            model = _network(torch)
            optimiser = torch.optim.Adam(model.parameters(), lr=lr)
            schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, steps)
            for step in range(steps):
                clouds, labels = _training_batch(kinds, config, rng)
                logits = model(torch.from_numpy(clouds).transpose(1, 2))[:, 0]
                loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, torch.from_numpy(labels))
                optimiser.zero_grad()
                loss.backward()
                optimiser.step()
                schedule.step()
                if progress:
                    progress(step, float(loss.detach()))
    finally:
        torch.set_num_threads(previous_threads)
    final = logits.detach()
    # all equal: every ReLU of a layer dead; not finite: weights overflowed (an inf among finite logits too)
    if not (bool(torch.isfinite(final).all()) and float(final.max() - final.min()) > 1e-6):
        raise InputError("heading classifier training", f"the network collapsed after {steps} steps (seed {seed}, "
                         f"lr {lr}): its output no longer depends on the points or is not finite; train again "
                         "with another seed, fewer steps or a lower lr")
    config["final_loss"] = float(loss.detach())
    return HeadingClassifier(model.eval(), config)


def save_checkpoint(path, classifier: HeadingClassifier) -> None:
    """Write ``{"format", "state_dict", "config"}`` (learning.save_checkpoint)."""
    learning.save_checkpoint(require_torch(path), path, {"format": FORMAT, "state_dict": classifier.model.state_dict(),
                                                        "config": classifier.config})


def load_checkpoint(path=DEFAULT_CHECKPOINT) -> HeadingClassifier:
    """The classifier saved at ``path``; InputError when torch is missing or the file
    is missing or not such a checkpoint (learning.load_checkpoint)."""
    torch = require_torch(path)

    def build(saved):
        config = learning.checked_config(saved, {"points": learning.CLOUD_POINTS_FIELD})
        model = _network(torch)
        model.load_state_dict(saved["state_dict"])
        return HeadingClassifier(model.eval(), config)

    return learning.load_checkpoint(torch, path, FORMAT, "heading-classifier",
                                    "train one with headless_scripts/train_heading.py", build)


def front_probability(points, dims, checkpoint=DEFAULT_CHECKPOINT, resamplings: int = 4, seed: int = 0,
                      source="points") -> float:
    """Probability that the front of object-frame ``points`` (N, 3) metres, in a box of
    ``dims`` (3,) metres, is at +x. ``checkpoint``: a path or a :class:`HeadingClassifier`.

    Deterministic: the mean over ``resamplings`` seeded resamplings of half the logit
    difference of the cloud and its 180-degree flip, so flip antisymmetry holds by
    construction: front_probability(flipped) == 1 - front_probability(points).
    """
    classifier = checkpoint if isinstance(checkpoint, HeadingClassifier) else load_checkpoint(checkpoint)
    import torch  # importable: the classifier exists

    points = np.asarray(points, np.float64)
    dims = np.asarray(dims, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0 or not np.isfinite(points).all():
        raise InputError(source, f"points must be a non-empty finite (N, 3) array, not shape {points.shape}")
    if dims.shape != (3,) or not (dims > 0).all():
        raise InputError(source, f"dims must be three positive extents, not {dims}")
    rng = np.random.default_rng(seed)
    clouds = np.stack([resample(points, classifier.config["points"], rng) for _ in range(resamplings)])
    with torch.no_grad():  # one batch: the resamplings, then their flips
        both = torch.from_numpy(normalise(np.concatenate([clouds, clouds * (-1, -1, 1)]), dims))
        logits = classifier.model(both.transpose(1, 2)).double().numpy()[:, 0]
    score = np.mean(logits[:resamplings] - logits[resamplings:]) / 2
    return float(1 / (1 + np.exp(-score)))
