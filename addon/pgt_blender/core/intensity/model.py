"""The intensity estimator's networks: class-aware point backbones (PointNet++-style) for
the CycleGAN's two generators and two discriminators. Needs PyTorch.

The paper uses class-aware PointNeXt; this is its smallest relative, sized to train in
minutes on a CPU. All clouds are in the normalised box frame (box frame points divided
by dims / 2, so the box is [-1, 1]^3, +x the heading).

Backbone (shared design): per-point input features = the point's values (K = 3 sRGB or
K = 1 intensity) and its class's learned embedding (CLASS_EMBEDDING numbers).

- SA1: M1 farthest-point centres of the P points; each groups its K1 nearest points
  within R1 (padded with the centre); a shared MLP on [features, offset / R1], max-pooled.
- SA2: the same on the M1 centres: M2 centres, K2 neighbours within R2.

Generator: FP2 interpolates the SA2 features (plus their max over the object, the
global context) back to the M1 centres (3 nearest, inverse distance) and mixes them
with the SA1 features; FP1 interpolates those to every query point, where a head MLP
on [features, the point's values, class embedding, xyz] gives its K_out values through
a sigmoid, so outputs lie in [0, 1]. Query points are the P input points in training;
at inference they are all points of the object, however many.

Discriminator (LSGAN, PatchGAN-like): SA1 and SA2 on values and class only, one score
per SA2 centre (M2 local regions). It sees geometry only through which points are
grouped together, never as coordinates: rgb reconstructions and LiDAR objects cover an
object differently, and a discriminator that saw where points lie could tell the
domains apart without looking at their values.

Neighbourhoods depend only on xyz, never on the values a generator changes, so they are
computed once in numpy (``neighbourhoods``) and passed in as index tensors.
"""

import functools

import numpy as np

from .. import learning
from .losses import farthest_point_centres, squared_distances

FORMAT = "pgt_blender.intensity_estimator/1"  # intensity.pt: the rgb -> int generator and its config
CLASS_EMBEDDING = 8
SA1 = (64, 16, 0.4)  # centres M1, neighbours K1, radius R1 (normalised box frame)
SA2 = (16, 16, 0.8)
ARCHITECTURE = (f"class-aware PointNet++: class embedding {CLASS_EMBEDDING}; SA1 {SA1[0]} centres, "
                f"{SA1[1]} nearest within {SA1[2]}, MLP 32-64; SA2 {SA2[0]} centres, {SA2[1]} within {SA2[2]}, "
                "MLP 64-128; generator FP2 MLP 64 (+ global max), FP1 3-NN head MLP 64-32-K sigmoid; "
                "discriminator SA MLPs 32-32 and 64-64 on values only, LeakyReLU 0.2, score MLP 32-1 per SA2 centre")


def require_torch(path):
    """The torch module, or InputError(path) saying the intensity estimator needs it."""
    return learning.require_torch(path, "the intensity estimator")


def ball_query(xyz: np.ndarray, centres: np.ndarray, count: int, radius: float) -> np.ndarray:
    """(B, M, count) int64: for each centre (``centres`` (B, M) indices into ``xyz``
    (B, N, 3)) its ``count`` nearest points within ``radius``, the rest filled with the
    centre itself (repeats change no max-pooled feature)."""
    centre_xyz = np.take_along_axis(xyz, centres[..., None], axis=1)
    squared = squared_distances(centre_xyz, xyz)
    nearest = np.argpartition(squared, count - 1, axis=-1)[..., :count]
    outside = np.take_along_axis(squared, nearest, axis=-1) > radius**2
    return np.where(outside, centres[..., None], nearest)


def three_nearest(query: np.ndarray, reference: np.ndarray) -> tuple:
    """Interpolation links from ``reference`` (..., M, 3) to ``query`` (..., Q, 3): the
    indices (..., Q, 3) int64 of each query's 3 nearest references and their inverse
    distance weights (..., Q, 3) float32, summing to 1."""
    squared = squared_distances(query, reference)
    nearest, distances = [], []
    for _ in range(3):  # three argmin passes: several times faster than argpartition
        index = np.argmin(squared, axis=-1)[..., None]
        nearest.append(index)
        distances.append(np.sqrt(np.take_along_axis(squared, index, axis=-1)))
        np.put_along_axis(squared, index, np.inf, axis=-1)
    inverse = 1.0 / (np.concatenate(distances, axis=-1) + 1e-8)
    return np.concatenate(nearest, axis=-1), (inverse / inverse.sum(axis=-1, keepdims=True)).astype(np.float32)


def neighbourhoods(xyz: np.ndarray, with_points: bool = False) -> dict:
    """The index arrays of both set abstraction levels for clouds ``xyz`` (B, P, 3),
    normalised box frame, P >= M1 (numpy; index arrays int64, weights float32):

    xyz (B, P, 3) float32; centres1 (B, M1) and groups1 (B, M1, K1) into P; centres2
    (B, M2) and groups2 (B, M2, K2) into M1; up_index, up_weight (B, M1, 3): each SA1
    centre's 3 nearest SA2 centres; ``with_points`` adds point_index, point_weight
    (B, P, 3): each point's 3 nearest SA1 centres (``support_queries`` needs them)."""
    (m1, k1, r1), (m2, k2, r2) = SA1, SA2
    xyz = np.asarray(xyz, np.float32)
    centres1 = farthest_point_centres(xyz, m1)
    xyz1 = np.take_along_axis(xyz, centres1[..., None], axis=1)
    centres2 = farthest_point_centres(xyz1, m2)
    up_index, up_weight = three_nearest(xyz1, np.take_along_axis(xyz1, centres2[..., None], axis=1))
    links = {"xyz": xyz, "centres1": centres1, "groups1": ball_query(xyz, centres1, k1, r1),
             "centres2": centres2, "groups2": ball_query(xyz1, centres2, k2, r2),
             "up_index": up_index, "up_weight": up_weight}
    if with_points:
        links["point_index"], links["point_weight"] = three_nearest(xyz, xyz1)
    return links


def queries(links: dict, objects: list) -> dict:
    """Query points at which a generator writes values, flat over objects (numpy):
    ``objects`` [(xyz (N_i, 3), values (N_i, K))] normalised box frame, the i-th one
    an object whose support cloud is row i of ``links``.

    xyz (Q, 3), values (Q, K), row (Q,) the object, index (Q, 3) into the flattened
    (B * M1) SA1 centres and weight (Q, 3)."""
    m1 = SA1[0]
    centres = np.take_along_axis(links["xyz"], links["centres1"][..., None], axis=1)
    index, weight = [], []
    for row, (points, _) in enumerate(objects):
        nearest, share = three_nearest(np.asarray(points, np.float32), centres[row])
        index.append(nearest + row * m1)
        weight.append(share)
    return {"xyz": np.concatenate([p for p, _ in objects]).astype(np.float32),
            "values": np.concatenate([v for _, v in objects]).astype(np.float32),
            "row": np.repeat(np.arange(len(objects)), [len(p) for p, _ in objects]),
            "index": np.concatenate(index), "weight": np.concatenate(weight)}


def support_queries(links: dict) -> dict:
    """``queries`` at the support points of ``links`` (``neighbourhoods`` with_points)
    themselves (training), Q = B * P in row order, without "values": the caller adds
    the (Q, K) values of each pass."""
    batch, points = links["xyz"].shape[:2]
    offsets = np.arange(batch)[:, None, None] * SA1[0]
    return {"xyz": links["xyz"].reshape(-1, 3), "row": np.repeat(np.arange(batch), points),
            "index": (links["point_index"] + offsets).reshape(-1, 3), "weight": links["point_weight"].reshape(-1, 3)}


def as_tensors(torch, arrays: dict) -> dict:
    """numpy arrays -> CPU tensors (no copy where possible)."""
    return {key: torch.from_numpy(np.ascontiguousarray(value)) for key, value in arrays.items()}


@functools.cache
def _module_classes():
    """(Generator, Discriminator) nn.Module classes, built on first use so that this
    module imports without torch."""
    import torch
    from torch import nn

    def mlp(sizes, activation):
        layers = []
        for i in range(len(sizes) - 1):
            layers += [nn.Linear(sizes[i], sizes[i + 1]), activation()]
        return nn.Sequential(*layers)

    def gather(features, index):
        """features (B, N, C), index (B, ...) -> (B, ..., C)."""
        rows = torch.arange(len(features)).view(-1, *([1] * (index.dim() - 1)))
        return features[rows, index]

    def abstract(net, features, xyz, centres, groups, radius):
        """One set abstraction: MLP over each centre's group, max-pooled -> (B, M, C)."""
        grouped = gather(features, groups)
        if xyz is not None:
            offsets = (gather(xyz, groups) - gather(xyz, centres)[:, :, None]) / radius
            grouped = torch.cat([grouped, offsets], dim=-1)
        return net(grouped).amax(dim=2)

    def interpolate(features, index, weight):
        """features (B, M, C) at index (B, Q, 3) with weight (B, Q, 3) -> (B, Q, C)."""
        return (gather(features, index) * weight[..., None]).sum(-2)

    class Generator(nn.Module):
        """values in one domain -> values in the other at every query point."""

        def __init__(self, classes: int, channels_in: int, channels_out: int):
            super().__init__()
            width = channels_in + CLASS_EMBEDDING
            self.embedding = nn.Embedding(classes, CLASS_EMBEDDING)
            self.sa1 = mlp([width + 3, 32, 64], nn.ReLU)
            self.sa2 = mlp([64 + 3, 64, 128], nn.ReLU)
            self.fp2 = mlp([128 + 128 + 64, 64], nn.ReLU)
            self.head = nn.Sequential(mlp([64 + width + 3, 64, 32], nn.ReLU), nn.Linear(32, channels_out), nn.Sigmoid())

        def forward(self, links: dict, values, class_index, query: dict):
            """links: ``neighbourhoods`` tensors; values (B, P, K_in) at the support points;
            class_index (B,); query: ``queries`` tensors -> (Q, K_out) in [0, 1]."""
            embedding = self.embedding(class_index)
            xyz = links["xyz"]
            features = torch.cat([values, embedding[:, None].expand(-1, xyz.shape[1], -1)], dim=-1)
            f1 = abstract(self.sa1, features, xyz, links["centres1"], links["groups1"], SA1[2])
            xyz1 = gather(xyz, links["centres1"])
            f2 = abstract(self.sa2, f1, xyz1, links["centres2"], links["groups2"], SA2[2])
            context = f2.amax(dim=1, keepdim=True).expand(-1, f1.shape[1], -1)
            h1 = self.fp2(torch.cat([interpolate(f2, links["up_index"], links["up_weight"]), context, f1], dim=-1))
            flat = h1.reshape(-1, h1.shape[-1])  # query indices run over all objects' centres
            point = (flat[query["index"]] * query["weight"][..., None]).sum(-2)
            return self.head(torch.cat([point, query["values"], embedding[query["row"]], query["xyz"]], dim=-1))

    class Discriminator(nn.Module):
        """A domain's values -> (B, M2) LSGAN scores, one per SA2 region."""

        def __init__(self, classes: int, channels_in: int):
            super().__init__()
            width = channels_in + CLASS_EMBEDDING
            self.embedding = nn.Embedding(classes, CLASS_EMBEDDING)
            self.sa1 = mlp([width, 32, 32], lambda: nn.LeakyReLU(0.2))
            self.sa2 = mlp([32, 64, 64], lambda: nn.LeakyReLU(0.2))
            self.score = nn.Sequential(nn.Linear(64, 32), nn.LeakyReLU(0.2), nn.Linear(32, 1))

        def forward(self, links: dict, values, class_index):
            embedding = self.embedding(class_index)[:, None].expand(-1, values.shape[1], -1)
            f1 = abstract(self.sa1, torch.cat([values, embedding], dim=-1), None,
                          links["centres1"], links["groups1"], SA1[2])
            f2 = abstract(self.sa2, f1, None, links["centres2"], links["groups2"], SA2[2])
            return self.score(f2)[..., 0]

    return Generator, Discriminator


def generator(classes: int, channels_in: int, channels_out: int):
    """A new generator (torch nn.Module) for ``classes`` classes, K_in -> K_out values."""
    return _module_classes()[0](classes, channels_in, channels_out)


def discriminator(classes: int, channels_in: int):
    """A new discriminator (torch nn.Module) for ``classes`` classes and K_in values."""
    return _module_classes()[1](classes, channels_in)
