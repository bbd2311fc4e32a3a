"""The placement as an mmdetection3d transform, ``PGTPlacement``, in place of
``ObjectSample`` in a training pipeline; loaded the framework's way:

    custom_imports = dict(imports=['pgt_blender.frameworks.mmdet3d'], allow_failed_imports=False)
    ...
    dict(type='PGTPlacement',
         db_sampler=db_sampler,        # the config's own DataBaseSampler settings
         sensor='nuscenes',            # preset or .toml: occlusion cells and column steps
         max_distance=54.0,            # the paper's distance filter (m)
         occlusion=True,               # range-view ray tracing
         min_points=5,                 # an object left with fewer points is dropped
         thompson_state=None),         # optional: a bandit.ThompsonCells JSON, reread when it changes

The transform builds mmdetection3d's own ``DataBaseSampler`` from ``db_sampler`` (its
info file, ``prepare`` filters, ``classes``, ``sample_groups``, ``points_loader``) and
asks, per class, for as many objects as ObjectSample would (the group's number less the
scene's boxes of that class, times ``rate``). Instead of pasting entries at their stored
pose it places them with core.placement.place_objects: on the scan's ground, turned
about the sensor axis, clear of the scene's boxes and points, with occlusion. Entries
are read with the sampler's ``points_loader`` and moved by their stored bottom centre,
as mmdetection3d does; boxes go in and out as ``LiDARInstance3DBoxes`` (bottom origin).
Random draws come from a generator seeded from numpy's global state (which mmengine
seeds per worker).
"""

from pathlib import Path

import numpy as np
from mmcv.transforms import BaseTransform
from mmdet3d.registry import TRANSFORMS

from ..core.placement.bandit import ThompsonFile
from ..core.placement.entries import EntryPool
from ..core.placement.place import PlacementConfig, place_objects
from ..core.scan.sensors import sensor_from_name


@TRANSFORMS.register_module()
class PGTPlacement(BaseTransform):
    """Place database entries into the scene (the module docstring)."""

    def __init__(self, db_sampler: dict, sensor: str = "nuscenes", max_distance: float = 54.0,
                 occlusion: bool = True, min_points: int = 5, thompson_state: str | None = None) -> None:
        db_sampler = dict(db_sampler)
        db_sampler.setdefault("type", "DataBaseSampler")
        self.db_sampler = TRANSFORMS.build(db_sampler)
        self.config = PlacementConfig(sensor_from_name(sensor), max_distance=max_distance, occlusion=occlusion,
                                      min_points=min_points)
        self.pool = EntryPool(self.db_sampler.db_infos, None, "mmdet3d", max_distance=max_distance, min_points=0,
                              load=self._read_entry, source=self.db_sampler.info_path)
        self.thompson = None if thompson_state is None else ThompsonFile(thompson_state, max_distance)

    def _read_entry(self, info: dict) -> np.ndarray:
        """ObjectSample's read: the sampler's points_loader, moved by the stored bottom centre."""
        sampler = self.db_sampler
        path = str(Path(sampler.data_root) / info["path"]) if sampler.data_root else info["path"]
        points = sampler.points_loader({"lidar_points": {"lidar_path": path}})["points"]
        points.translate(info["box3d_lidar"][:3])
        return points.tensor.numpy()

    def transform(self, input_dict: dict) -> dict:
        sampler = self.db_sampler
        boxes_3d, labels = input_dict["gt_bboxes_3d"], np.asarray(input_dict["gt_labels_3d"])
        counts = {}
        for class_name, most in zip(sampler.sample_classes, sampler.sample_max_nums):
            wanted = int(np.round(sampler.rate * int(most - np.sum(labels == sampler.cat2label[class_name]))))
            if wanted > 0 and len(self.pool.classes[class_name].ranges):
                counts[class_name] = wanted
        boxes = boxes_3d.numpy().astype(np.float64)
        boxes[:, 2] += boxes[:, 5] / 2  # bottom -> centre
        names = [sampler.label2cat[int(label)] for label in labels]
        points = input_dict["points"]
        placement = place_objects(points.tensor.numpy(), boxes, names, self.pool, counts, self.config,
                                  np.random.default_rng(np.random.randint(2 ** 31)),
                                  bandit=self.thompson and self.thompson.cells(),
                                  source=input_dict.get("lidar_path", "scan"))
        placed = placement.boxes.copy()
        placed[:, 2] -= placed[:, 5] / 2  # centre -> bottom
        input_dict["gt_bboxes_3d"] = boxes_3d.new_box(placed.astype(np.float32))
        input_dict["gt_labels_3d"] = np.concatenate(
            [labels, [sampler.cat2label[name] for name in placement.names[placement.inserted]]]).astype(np.int64)
        input_dict["points"] = points.new_point(placement.points)
        return input_dict
