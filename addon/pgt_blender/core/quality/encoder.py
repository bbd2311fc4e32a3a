"""The quality encoder: a small PointNet++-style network (torch, CPU, imported only
here) trained on a real database's object sets (sets.ClassSet) to tell its classes and
their distance bins apart, so its features carry what distinguishes real LiDAR objects;
metrics.frechet compares bank and real features.

Input per object: SET_POINTS box-normalised points with their intensity (x, y, z, i).
One set abstraction as the paper's FID: GROUPS centres (the first GROUPS points of the
random draw), each with its NEIGHBOURS nearest points (the paper's 32), an MLP on the
offsets and intensity max-pooled per group, a second MLP on (group feature, centre)
max-pooled over groups: the FEATURES-long feature. Two linear heads: class, and
distance bin (DISTANCE_BIN m rings, the last open-ended), trained with cross-entropy.

Checkpoint (learning.save_checkpoint): {"format": FORMAT, "state": state dict,
"classes": [...], "dataset": str, "key": the sha256 of the real info pickle and the
training settings the cache compares}.
"""

from pathlib import Path

import numpy as np

from ..learning import load_checkpoint, require_torch, save_checkpoint

FORMAT = "pgt_blender.quality_encoder/1"
GROUPS, NEIGHBOURS, FEATURES = 16, 32, 32
DISTANCE_BIN, DISTANCE_BINS = 10.0, 8  # m, and their number
STEPS, BATCH, LEARNING_RATE, JITTER = 300, 32, 1e-3, 0.01
KIND = "quality encoder"


def _network_class():
    """The nn.Module class, built on first use so that this module imports without torch."""
    import torch
    from torch import nn

    class Encoder(nn.Module):
        def __init__(self, classes: int):
            super().__init__()
            self.local = nn.Sequential(nn.Linear(4, 32), nn.ReLU(), nn.Linear(32, 64), nn.ReLU())
            self.group = nn.Sequential(nn.Linear(64 + 3, 64), nn.ReLU(), nn.Linear(64, FEATURES), nn.ReLU())
            self.classes = nn.Linear(FEATURES, classes)
            self.distance = nn.Linear(FEATURES, DISTANCE_BINS)

        def features(self, points):
            """(B, P, 4) x y z intensity -> (B, FEATURES)."""
            xyz = points[..., :3]
            centres = xyz[:, :GROUPS]
            neighbours = torch.cdist(centres, xyz).topk(NEIGHBOURS, largest=False).indices  # (B, G, K)
            rows = torch.arange(len(points))[:, None, None]
            grouped = points[rows, neighbours]  # (B, G, K, 4)
            offsets = torch.cat([grouped[..., :3] - centres[:, :, None], grouped[..., 3:]], dim=-1)
            local = self.local(offsets).amax(dim=2)  # (B, G, 64)
            return self.group(torch.cat([local, centres], dim=-1)).amax(dim=1)

        def forward(self, points):
            features = self.features(points)
            return self.classes(features), self.distance(features)

    return Encoder


def object_inputs(class_set) -> np.ndarray:
    """(n, SET_POINTS, 4) float32 x y z intensity of a ClassSet."""
    return np.concatenate([class_set.xyz, class_set.intensity[..., None]], axis=-1).astype(np.float32)


def distance_bins(distance: np.ndarray) -> np.ndarray:
    return np.minimum((distance // DISTANCE_BIN).astype(np.int64), DISTANCE_BINS - 1)


class QualityEncoder:
    """A trained encoder: ``classes`` it was trained on, ``dataset``, ``key``."""

    def __init__(self, network, classes: list, dataset: str, key: str):
        self.network, self.classes, self.dataset, self.key = network, classes, dataset, key

    def features(self, class_set, batch: int = 256) -> np.ndarray:
        """(n, FEATURES) float64 features of a ClassSet's objects."""
        torch = require_torch(None, f"the {KIND}")
        inputs = object_inputs(class_set)
        with torch.no_grad():
            parts = [self.network.features(torch.from_numpy(inputs[start:start + batch])).numpy()
                     for start in range(0, len(inputs), batch)]
        return np.concatenate(parts).astype(np.float64) if parts else np.zeros((0, FEATURES))

    def save(self, path) -> None:
        torch = require_torch(path, f"the {KIND}")
        save_checkpoint(torch, path, {"format": FORMAT, "state": self.network.state_dict(),
                                      "classes": list(self.classes), "dataset": self.dataset, "key": self.key})

    @classmethod
    def load(cls, path) -> "QualityEncoder":
        """The encoder at ``path``; InputError when missing, damaged or not an encoder."""
        torch = require_torch(path, f"the {KIND}")

        def build(payload):
            network = _network_class()(len(payload["classes"]))
            network.load_state_dict(payload["state"])
            return cls(network.eval(), list(payload["classes"]), payload["dataset"], payload["key"])

        return load_checkpoint(torch, path, FORMAT, KIND, "score_bank.py trains one when --encoder is not given",
                               build)


def train_encoder(real_sets: dict, dataset: str, key: str, seed: int = 0, steps: int = STEPS,
                  progress=None) -> QualityEncoder:
    """Train on ``real_sets`` ({class: ClassSet}): ``steps`` Adam steps of BATCH objects,
    classes drawn equally often, each object mirrored in y at random (vehicles are
    left-right symmetric) and jittered by N(0, JITTER) box units. Deterministic for a
    seed: torch's generator and the numpy draws are seeded, one CPU thread."""
    torch = require_torch(None, f"the {KIND}")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # bitwise-reproducible reductions
    try:
        torch.manual_seed(seed)
        rng = np.random.default_rng(seed)
        classes = sorted(real_sets)
        inputs = [object_inputs(real_sets[name]) for name in classes]
        bins = [distance_bins(real_sets[name].distance) for name in classes]
        network = _network_class()(len(classes))
        optimiser = torch.optim.Adam(network.parameters(), lr=LEARNING_RATE)
        loss_function = torch.nn.CrossEntropyLoss()
        for _ in range(steps):
            labels = rng.integers(0, len(classes), BATCH)
            rows = [rng.integers(0, len(inputs[label])) for label in labels]
            batch = np.stack([inputs[label][row] for label, row in zip(labels, rows)])
            batch[..., 1] *= rng.choice([-1.0, 1.0], (BATCH, 1)).astype(np.float32)
            batch[..., :3] += rng.normal(0.0, JITTER, batch[..., :3].shape).astype(np.float32)
            class_logits, distance_logits = network(torch.from_numpy(batch))
            targets = torch.from_numpy(np.array([bins[label][row] for label, row in zip(labels, rows)]))
            loss = loss_function(class_logits, torch.from_numpy(labels)) + loss_function(distance_logits, targets)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            if progress is not None:
                progress(1)
        return QualityEncoder(network.eval(), classes, dataset, key)
    finally:
        torch.set_num_threads(threads)


def cached_encoder(path: Path, real_sets: dict, dataset: str, key: str, seed: int = 0, progress=None):
    """The encoder at ``path`` when it was trained with ``key``, else a new one trained
    (train_encoder) and saved there. A file that is not a readable encoder is replaced;
    a cache that cannot be written (a bank on a read-only share) is a warning: the
    encoder is still returned."""
    import warnings

    from ..errors import InputError

    if Path(path).is_file():
        try:
            found = QualityEncoder.load(path)
            if found.key == key:
                return found
        except InputError:
            pass
    encoder = train_encoder(real_sets, dataset, key, seed, progress=progress)
    try:
        encoder.save(path)
    except OSError as error:
        warnings.warn(f"{path}: the quality encoder is not cached ({error.strerror or error}); the next score "
                      f"trains it again", stacklevel=2)
    return encoder
