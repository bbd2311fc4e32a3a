"""LiDAR intensity for colored points: the trained rgb -> int generator; a scan keeps
its physical intensity when PyTorch or a checkpoint is missing (``scan_intensity``).

Input per object: xyz (N, 3) in its box frame (origin at the box centre, +x the heading,
+z up, metres), the box dims (3,) l w h in metres, sRGB (N, 3) in [0, 1] and the class
name. Output: (N,) float32 intensities in [0, 1], the fraction of the dataset's maximum
(``scan.physical_intensity.dataset_intensity`` scales them to the dataset's numbers).

The network sees a *support* cloud of the checkpoint's P points (farthest point sampled,
as in training; an object of fewer points repeats them) and writes a value at every one
of the N points, so objects of any size are estimated whole. Load a checkpoint once
(``IntensityEstimator.load``) and pass many objects to ``predict_many``: they go through
the network in batches; ``last_rate`` then holds the points per second it reached.
"""

import functools
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..classes import DATASETS
from ..errors import InputError
from ..learning import CLOUD_POINTS_FIELD, TORCH_REQUIREMENT, checked_config, load_checkpoint
from ..scan.physical_intensity import dataset_intensity
from . import model
from .losses import farthest_point_centres

BATCH_OBJECTS = 64  # objects per forward pass in predict_many


@dataclass
class IntensityEstimator:
    """A loaded rgb -> int generator (torch nn.Module, eval mode), its training config
    (dict, as in config.json) and the file it came from."""

    network: object
    config: dict
    path: Path
    last_rate: float = 0.0  # points per second of the latest predict / predict_many

    @classmethod
    def load(cls, path, dataset: str | None = None) -> "IntensityEstimator":
        """The estimator saved at ``path`` (training's intensity.pt, or the training's
        output folder holding it). InputError when torch is missing, the file is
        missing, damaged or not such a checkpoint, or it was trained on another
        ``dataset``'s intensities (when one is given)."""
        path = Path(path)
        if path.is_dir() and (path / "intensity.pt").exists():
            path = path / "intensity.pt"

        def build(saved):
            config = checked_config(saved, {
                "classes": (lambda v: isinstance(v, list) and v and all(isinstance(c, str) for c in v),
                            "a list of class names"),
                "dataset": (lambda v: v in DATASETS, f"one of {', '.join(DATASETS)}"),
                "points": CLOUD_POINTS_FIELD})
            network = model.generator(len(config["classes"]), 3, 1)
            network.load_state_dict(saved["state_dict"])
            return cls(network.eval(), config, path)

        estimator = load_checkpoint(model.require_torch(path), path, model.FORMAT, "intensity-estimator",
                                    "train one with headless_scripts/train_intensity.py", build)
        if dataset is not None and dataset != estimator.dataset:
            raise InputError(path, f"was trained on {estimator.dataset} intensities, not {dataset}'s")
        return estimator

    @property
    def classes(self) -> tuple:
        """The class names it was trained for."""
        return tuple(self.config["classes"])

    def require_classes(self, names) -> None:
        """InputError naming the checkpoint for a class in ``names`` it was not trained for."""
        missing = sorted(set(names) - set(self.classes))
        if missing:
            raise InputError(self.path, f"has no class '{missing[0]}' (trained for {', '.join(self.classes)})")

    @property
    def dataset(self) -> str:
        """The dataset (and so sensor and intensity scale) its real objects came from."""
        return self.config["dataset"]

    def predict(self, xyz, dims, rgb, class_name: str, name: str = "object") -> np.ndarray:
        """(N,) float32 intensities in [0, 1] for one object (see the module docstring)."""
        return self.predict_many([(xyz, dims, rgb, class_name)], [name])[0]

    def predict_many(self, objects: list, names: list | None = None) -> list:
        """[(N_i,) float32 in [0, 1]] for ``objects`` [(xyz, dims, rgb, class_name)], in
        batches of BATCH_OBJECTS; ``names`` (default object<i>) name them in errors."""
        import torch

        names = names or [f"object{i}" for i in range(len(objects))]
        start = time.perf_counter()
        prepared = [self._prepared(obj, name) for obj, name in zip(objects, names)]
        order = np.argsort([len(xyz) for xyz, _, _ in prepared], kind="stable")  # alike sizes share a batch
        results = [None] * len(prepared)
        with torch.inference_mode():
            for first in range(0, len(order), BATCH_OBJECTS):
                rows = order[first:first + BATCH_OBJECTS]
                for row, values in zip(rows, self._batch(torch, [prepared[row] for row in rows])):
                    results[row] = values
        self.last_rate = sum(len(values) for values in results) / max(time.perf_counter() - start, 1e-9)
        return results

    def _prepared(self, obj, name: str) -> tuple:
        """(normalised xyz (N, 3) float32, rgb (N, 3) float32, class index); InputError
        for bad arrays or a class the checkpoint does not know."""
        xyz, dims, rgb, class_name = obj
        xyz, dims, rgb = checked_object(xyz, dims, rgb, name)
        self.require_classes([class_name])
        return (xyz / (dims / 2)).astype(np.float32), rgb.astype(np.float32), self.classes.index(class_name)

    def _batch(self, torch, prepared: list) -> list:
        """Network outputs for a list of ``_prepared`` objects, split per object."""
        points = self.config["points"]
        support = _supports([xyz for xyz, _, _ in prepared], points)
        links = model.neighbourhoods(np.stack([xyz[pick] for (xyz, _, _), pick in zip(prepared, support)]))
        values = np.stack([rgb[pick] for (_, rgb, _), pick in zip(prepared, support)])
        query = model.queries(links, [(xyz, rgb) for xyz, rgb, _ in prepared])
        classes = torch.tensor([index for _, _, index in prepared])
        out = self.network(model.as_tensors(torch, links), torch.from_numpy(values), classes,
                           model.as_tensors(torch, query))
        return np.split(out[:, 0].numpy().astype(np.float32), np.cumsum([len(x) for x, _, _ in prepared])[:-1])


def checked_object(xyz, dims, rgb, name: str) -> tuple:
    """(xyz (N, 3), dims (3,), rgb (N, 3)) float64; InputError naming ``name`` for
    mismatched shapes, NaN or colors outside 0..1."""
    xyz, dims, rgb = (np.asarray(a, np.float64) for a in (xyz, dims, rgb))
    if xyz.ndim != 2 or xyz.shape[1] != 3 or len(xyz) == 0:
        raise InputError(name, f"points have shape {xyz.shape}, expected (N, 3) with N > 0")
    if rgb.shape != xyz.shape:
        raise InputError(name, f"colors have shape {rgb.shape}, expected {xyz.shape} (one sRGB row per point)")
    if dims.shape != (3,) or not (dims > 0).all():
        raise InputError(name, f"box dims must be three positive lengths, not {dims.tolist()}")
    if not (np.isfinite(xyz).all() and np.isfinite(rgb).all()):
        raise InputError(name, "points or colors are NaN or infinite")
    if rgb.min() < 0 or rgb.max() > 1:
        raise InputError(name, f"colors span {rgb.min():g}..{rgb.max():g}, expected sRGB in 0..1")
    return xyz, dims, rgb


def _supports(clouds: list, points: int) -> list:
    """Per cloud (N_i, 3) the (points,) indices of its support cloud: farthest point
    sampling as in training (one padded batch), or for a cloud of fewer points every
    point repeated in turn."""
    supports = [np.resize(np.arange(len(xyz)), points) for xyz in clouds]
    large = [i for i, xyz in enumerate(clouds) if len(xyz) >= points]
    if large:
        lengths = np.array([len(clouds[i]) for i in large])
        padded = np.zeros((len(large), lengths.max(), 3), np.float32)
        for row, i in enumerate(large):
            padded[row, :lengths[row]] = clouds[i]
        for row, picks in zip(large, farthest_point_centres(padded, points, lengths)):
            supports[row] = picks
    return supports


def cached_estimator(path, dataset: str | None = None) -> IntensityEstimator:
    """``IntensityEstimator.load(path, dataset)``, loaded once per version of the file (its
    modification time and size) and kept while it is unchanged."""
    path = Path(path).resolve()
    status = path.stat() if path.is_file() else None
    return _cached(path, dataset, status and (status.st_mtime_ns, status.st_size))


@functools.lru_cache(maxsize=4)
def _cached(path: Path, dataset: str | None, stamp: tuple) -> IntensityEstimator:
    return IntensityEstimator.load(path, dataset)


def scan_intensity(scan, bounds: np.ndarray, element_rgb: np.ndarray, class_name: str, checkpoint=None,
                   rows=None, name: str = "object") -> tuple:
    """(values (K,) float32 in the dataset's scale, note): the intensities of the returns
    ``rows`` (a bool mask or indices; default all) of ``scan`` (scan.returns.Scan), and a
    one-line note on what made them. The one way any route applies a learned estimate.

    ``checkpoint``: an IntensityEstimator, a path to intensity.pt (loaded once while the
    file is unchanged) or None. With one and PyTorch: one prediction over all the rows,
    every sweep at once (the object as a ground-truth database stores it), each return
    in the box frame of the pose its sweep saw (``bounds`` (2, 3) object frame, m) with
    the sRGB color ``element_rgb`` (E, 3) of the face or point it hit. Without a
    checkpoint, or without PyTorch, the scan's own physical intensities. InputError for
    a missing or damaged checkpoint, one without ``class_name`` or of another dataset,
    and bad arrays."""
    rows = np.arange(scan.hits) if rows is None else rows
    physical = scan.returns["intensity"][rows]
    if checkpoint is None:
        return physical, "physical law (no intensity checkpoint given)"
    if not isinstance(checkpoint, IntensityEstimator):
        path = Path(checkpoint).resolve()
        try:
            model.require_torch(path)
        except InputError:
            return physical, f"physical law: PyTorch ({TORCH_REQUIREMENT}) is not installed, so {path} was not used"
        checkpoint = cached_estimator(path, scan.dataset)
    elif checkpoint.dataset != scan.dataset:
        raise InputError(checkpoint.path, f"was trained on {checkpoint.dataset} intensities, not {scan.dataset}'s")
    faces = scan.returns["face"][rows]
    relative = checkpoint.predict(scan.box_frame_points(bounds)[rows], bounds[1] - bounds[0],
                                  np.asarray(element_rgb, np.float32)[faces, :3], class_name, name)
    return dataset_intensity(relative, scan.dataset), f"learned ({checkpoint.last_rate:,.0f} points/s)"
