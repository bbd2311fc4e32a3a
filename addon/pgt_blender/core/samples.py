"""Built-in sample objects: parametric vehicles of the paper's minority classes and
synthetic "reconstructions" of them, as ground truth for tests and input for the demo.

Object frame (the product's): +x forward (the heading), +y left, +z up, metres,
origin at the centre of the object's axis-aligned box; the ground is z = -height / 2.

Each vehicle is the boolean union (manifold3d through trimesh) of boxes and wheels,
so it is one closed surface with no internal faces, sized exactly to the nuScenes
class mean. The front is recognisable: a cab, bucket, landing gear or handlebars.
"""

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .classes import MINORITY_CLASSES, NUSCENES_SIZES
from .reconstruction import Reconstruction

_TYRE = (0.08, 0.08, 0.09)
_GLASS = (0.15, 0.22, 0.30)
_METAL = (0.45, 0.46, 0.48)


@dataclass(frozen=True)
class Part:
    """A box (``size`` = x, y, z extents) or a wheel (a cylinder along y: ``size`` =
    diameter, width, diameter), centred at ``center``, pitched by ``pitch_deg`` about
    +y (nose down is positive), with an sRGB ``color``. Ground is z = 0 here."""

    kind: str
    center: tuple
    size: tuple
    color: tuple
    pitch_deg: float = 0.0


def _wheels(x_positions, y_offset, radius, width):
    return [Part("wheel", (x, side * y_offset, radius), (2 * radius, width, 2 * radius), _TYRE)
            for x in x_positions for side in (1, -1)]


def _box(x0, x1, y_half, z0, z1, color, pitch_deg=0.0):
    return Part("box", ((x0 + x1) / 2, 0.0, (z0 + z1) / 2), (x1 - x0, 2 * y_half, z1 - z0), color, pitch_deg)


def vehicle_parts(class_name: str) -> list:
    """The parts of the sample vehicle for ``class_name`` (ground at z = 0, metres)."""
    (length, width, height), _ = NUSCENES_SIZES[class_name]
    front, back, half_w = length / 2, -length / 2, width / 2
    if class_name == "truck":  # box truck: low cab in front of a tall cargo box
        body = (0.92, 0.92, 0.90)
        return _wheels((front - 1.2, back + 1.4), half_w - 0.35, 0.5, 0.4) + [
            _box(back, front - 0.1, half_w - 0.1, 0.45, 0.85, _METAL),  # chassis
            _box(back, front - 2.0, half_w, 0.85, height, body),  # cargo box
            _box(front - 1.9, front, half_w - 0.05, 0.6, height * 0.78, (0.75, 0.12, 0.10)),  # cab
            _box(front - 0.3, front + 0.02, half_w - 0.15, 1.55, height * 0.74, _GLASS),  # windscreen
        ]
    if class_name == "bus":  # long body, bumper and mirrors at the front, short front overhang
        body = (0.95, 0.78, 0.10)
        return _wheels((front - 2.4, back + 3.1), half_w - 0.4, 0.5, 0.35) + [
            _box(back, front - 0.25, half_w, 0.35, height, body),
            _box(back, front, half_w - 0.1, 0.35, 0.9, _METAL),  # bumper line, proud at the front
            _box(front - 0.3, front - 0.2, half_w - 0.1, 1.2, height - 0.3, _GLASS),  # windscreen
            _box(front - 0.45, front - 0.3, half_w + 0.0, 2.2, 2.5, _METAL),  # mirror arms (full width)
        ]
    if class_name == "trailer":  # semi-trailer: rear tandem axle, landing gear and kingpin in front
        body = (0.80, 0.80, 0.82)
        return _wheels((back + 1.4, back + 2.5), half_w - 0.45, 0.5, 0.5) + [
            _box(back, front, half_w, 1.25, height, body),
            _box(front - 2.6, front - 2.4, half_w - 0.3, 0.0, 1.25, _METAL),  # landing gear legs
            _box(front - 1.2, front - 0.6, 0.25, 1.0, 1.25, _METAL),  # kingpin plate
            _box(back, back + 3.2, half_w - 0.2, 0.95, 1.25, _METAL),  # running gear frame
        ]
    if class_name == "construction_vehicle":  # wheel loader: bucket in front, cab, rear engine
        body = (0.95, 0.70, 0.05)
        return _wheels((front - 1.9, back + 1.6), half_w - 0.45, 0.75, 0.6) + [
            _box(back, front - 1.4, half_w - 0.5, 0.6, 1.7, body),  # frame and engine
            _box(back + 0.2, back + 2.0, half_w - 0.55, 1.7, 2.3, body),  # engine cover
            _box(-0.6, 1.0, 0.8, 1.7, height, _GLASS),  # cab
            _box(front - 2.2, front - 0.5, 0.2, 0.8, 1.4, body, -12.0),  # lift arm
            _box(front - 0.7, front, half_w, 0.05, 1.1, _METAL),  # bucket, full width
        ]
    if class_name == "motorcycle":
        body = (0.70, 0.08, 0.10)
        return _wheels((front - 0.32, back + 0.32), 0.0, 0.32, 0.14) + [
            _box(-0.55, 0.55, 0.16, 0.35, 0.80, body),  # engine and tank
            _box(-0.75, 0.10, 0.15, 0.80, 0.92, (0.05, 0.05, 0.05)),  # seat
            _box(0.55, 0.72, 0.06, 0.32, 1.15, _METAL, -25.0),  # front fork
            _box(0.55, 0.68, half_w, 1.12, 1.20, _METAL),  # handlebars, full width
            _box(0.50, 0.62, 0.18, 1.20, height, _GLASS),  # windscreen
        ]
    if class_name == "bicycle":
        body = (0.10, 0.30, 0.75)
        return _wheels((front - 0.35, back + 0.35), 0.0, 0.35, 0.05) + [
            _box(-0.30, 0.45, 0.02, 0.78, 0.82, body),  # top tube
            _box(-0.15, 0.35, 0.02, 0.35, 0.80, body, -40.0),  # down tube
            _box(-0.40, 0.0, 0.02, 0.33, 0.37, body),  # chain stay
            _box(-0.30, -0.26, 0.02, 0.35, 1.00, body),  # seat post
            _box(-0.42, -0.18, 0.08, 1.00, 1.06, (0.05, 0.05, 0.05)),  # saddle
            _box(0.43, 0.47, 0.02, 0.35, height - 0.05, _METAL),  # head tube and stem
            _box(0.40, 0.50, half_w, height - 0.05, height, _METAL),  # handlebars, full width
        ]
    raise KeyError(f"no sample vehicle for class '{class_name}' (have: {', '.join(MINORITY_CLASSES)})")


def _part_mesh(part: Part):
    import trimesh

    transform = trimesh.transformations.rotation_matrix(np.radians(part.pitch_deg), (0, 1, 0))
    transform[:3, 3] = part.center
    if part.kind == "box":
        return trimesh.creation.box(extents=part.size, transform=transform)
    # trimesh cylinders run along z: turn the axis onto y.
    to_y = trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0))
    return trimesh.creation.cylinder(radius=part.size[0] / 2, height=part.size[1],
                                     sections=48, transform=transform @ to_y)


def _inside_part(points: np.ndarray, part: Part, tolerance: float) -> np.ndarray:
    """(N,) bool: which points lie in the closed part, widened by ``tolerance``."""
    pitch = np.radians(part.pitch_deg)
    local = points - np.asarray(part.center)
    cos, sin = np.cos(pitch), np.sin(pitch)
    # rotate by -pitch about y into the part's own axes
    x = cos * local[:, 0] - sin * local[:, 2]
    z = sin * local[:, 0] + cos * local[:, 2]
    half = np.asarray(part.size) / 2 + tolerance
    if part.kind == "box":
        return (np.abs(x) <= half[0]) & (np.abs(local[:, 1]) <= half[1]) & (np.abs(z) <= half[2])
    return (x * x + z * z <= half[0] ** 2) & (np.abs(local[:, 1]) <= half[1])


@dataclass
class SampleVehicle:
    """A closed vehicle mesh in the object frame and the colors of its parts.

    vertices: (V, 3) float64 metres; faces: (F, 3) int64; dims: (length, width, height).
    """

    class_name: str
    vertices: np.ndarray
    faces: np.ndarray
    dims: np.ndarray
    parts: list = field(repr=False)
    # maps part-frame points (ground at z = 0) to the object frame: x * scale + offset
    scale: np.ndarray = field(repr=False, default=None)
    offset: np.ndarray = field(repr=False, default=None)

    def trimesh(self):
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)

    def colors_at(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) sRGB color of the part each surface point (object frame) belongs to."""
        local = (points - self.offset) / self.scale
        colors = np.zeros((len(points), 3))
        unassigned = np.ones(len(points), bool)
        for part in self.parts:
            hit = unassigned & _inside_part(local, part, 1e-3)
            colors[hit] = part.color
            unassigned &= ~hit
        return colors


def sample_vehicle(class_name: str) -> SampleVehicle:
    """The sample vehicle of ``class_name``, its box exactly the nuScenes class mean."""
    import trimesh

    parts = vehicle_parts(class_name)
    union = trimesh.boolean.union([_part_mesh(p) for p in parts], engine="manifold")
    low, high = union.bounds
    dims = np.array(NUSCENES_SIZES[class_name][0])
    scale = dims / (high - low)  # corrects the few millimetres parts stick out
    offset = -(low + high) / 2 * scale
    return SampleVehicle(class_name, union.vertices * scale + offset, np.asarray(union.faces),
                         dims, parts, scale, offset)


@dataclass
class SyntheticReconstruction:
    """Colored surface points of a sample vehicle as a reconstruction would deliver them.

    positions: (N, 3) float32 in the *source frame*; colors: (N, 3) float32 sRGB [0, 1].
    source_from_object: (4, 4) float64 similarity (rotation, uniform scale, translation)
    taking object-frame metres to the source frame; is_outlier: (N,) bool.
    """

    class_name: str
    seed: int
    positions: np.ndarray
    colors: np.ndarray
    source_from_object: np.ndarray
    is_outlier: np.ndarray
    vehicle: SampleVehicle = field(repr=False)

    def to_reconstruction(self) -> Reconstruction:
        """As an imported colored point cloud; its checksum covers positions and colors."""
        rgba = np.column_stack([self.colors, np.ones(len(self.colors), np.float32)])
        digest = hashlib.sha256(self.positions.tobytes() + self.colors.tobytes()).hexdigest()
        return Reconstruction(positions=self.positions, kind="point_ply", colors=rgba, sha256=digest,
                              source=Path(f"sample_{self.class_name}_seed{self.seed}"))


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed (3, 3) rotation (normalised Gaussian quaternion)."""
    w, x, y, z = (q := rng.normal(size=4)) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def observed(points: np.ndarray, dims, noise: float, floater_share: float, rng: np.random.Generator,
             centre=0.0) -> np.ndarray:
    """``points`` (N, 3) as a noisy reconstruction holds them (a new float64 array):
    Gaussian noise on each (sigma = ``noise`` x the diagonal of the box ``dims`` (3,)),
    then a ``floater_share`` of them replaced by floaters uniform in a box 1.5x ``dims``
    about ``centre``; drawn from ``rng`` in that order."""
    noisy = points + rng.normal(scale=noise * np.linalg.norm(dims), size=np.shape(points))
    floaters = rng.random(len(noisy)) < floater_share
    noisy[floaters] = rng.uniform(-0.75, 0.75, (floaters.sum(), 3)) * dims + centre
    return noisy


def synthetic_reconstruction(class_name: str, seed: int = 0, points: int = 20000,
                             noise: float = 0.005, outlier_share: float = 0.03,
                             scale_range: tuple = (0.05, 5.0)) -> SyntheticReconstruction:
    """Sample ``points`` surface points of the class's vehicle with their part colors,
    add Gaussian noise (sigma = ``noise`` x box diagonal) and color noise, replace an
    ``outlier_share`` of them by floaters in a box 1.5x the object's, then apply a random
    rotation, log-uniform scale in ``scale_range`` and translation. Same seed, same bytes
    (``observed``'s model, with the color noise drawn between its two steps: the samples'
    bytes are fixed, the shipped heading checkpoint records them)."""
    import trimesh

    rng = np.random.default_rng(seed)
    vehicle = sample_vehicle(class_name)
    surface, _ = trimesh.sample.sample_surface(vehicle.trimesh(), points, seed=rng.integers(2**31))
    colors = vehicle.colors_at(surface)
    diagonal = np.linalg.norm(vehicle.dims)
    positions = surface + rng.normal(scale=noise * diagonal, size=surface.shape)
    colors = colors + rng.normal(scale=0.03, size=colors.shape)
    is_outlier = rng.random(points) < outlier_share
    count = int(is_outlier.sum())
    positions[is_outlier] = rng.uniform(-0.75, 0.75, size=(count, 3)) * vehicle.dims
    colors[is_outlier] = rng.random((count, 3))
    scale = np.exp(rng.uniform(*np.log(scale_range)))
    source_from_object = np.eye(4)
    source_from_object[:3, :3] = scale * random_rotation(rng)
    source_from_object[:3, 3] = rng.normal(scale=3.0 * scale, size=3)
    positions = positions @ source_from_object[:3, :3].T + source_from_object[:3, 3]
    return SyntheticReconstruction(class_name, seed, positions.astype(np.float32),
                                   np.clip(colors, 0, 1).astype(np.float32),
                                   source_from_object, is_outlier, vehicle)


def write_sample(directory, class_name: str, seed: int = 0, points: int = 20000) -> dict:
    """Write ``<class>_reconstruction.ply`` (binary point PLY, uchar colors, source
    frame), ``<class>_mesh.ply`` (the closed vehicle, object frame) and
    ``<class>_truth.json`` (class, dims [l, w, h] m, row-major 4x4 ``source_from_object``,
    seed) into ``directory``; returns their paths by role."""
    import json

    from .importing.ply import write_ply

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    sample = synthetic_reconstruction(class_name, seed=seed, points=points)
    paths = {role: directory / f"{class_name}_{role}" for role in
             ("reconstruction.ply", "mesh.ply", "truth.json")}
    rgb = np.round(sample.colors * 255).astype(np.uint8)
    write_ply(paths["reconstruction.ply"], {
        "x": sample.positions[:, 0], "y": sample.positions[:, 1], "z": sample.positions[:, 2],
        "red": rgb[:, 0], "green": rgb[:, 1], "blue": rgb[:, 2]})
    sample.vehicle.trimesh().export(paths["mesh.ply"])
    paths["truth.json"].write_text(json.dumps({
        "class": class_name, "seed": seed, "points": points,
        "dims": sample.vehicle.dims.tolist(),
        "source_from_object": sample.source_from_object.tolist(),
        "outliers": int(sample.is_outlier.sum()),
    }, indent=2))
    return paths
