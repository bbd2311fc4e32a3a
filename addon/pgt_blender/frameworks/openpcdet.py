"""The placement as an OpenPCDet data augmentor: an ``AUG_CONFIG_LIST`` entry named
``pgt_placement`` with the keys of ``gt_sampling`` (DB_INFO_PATH, PREPARE, SAMPLE_GROUPS,
NUM_POINT_FEATURES, ...) and a ``PLACEMENT`` block:

    - NAME: pgt_placement
      DB_INFO_PATH: [nuscenes_dbinfos_mixed.pkl]
      PREPARE: {filter_by_min_points: [truck:5, ...]}
      SAMPLE_GROUPS: [truck:3, ...]
      NUM_POINT_FEATURES: 5
      ...
      PLACEMENT:
        SENSOR: nuscenes          # preset or .toml: occlusion cells and column steps
        MAX_DISTANCE: 54.0        # the paper's distance filter (m)
        OCCLUSION: True           # range-view ray tracing
        MIN_POINTS: 5             # an object left with fewer points is dropped
        THOMPSON_STATE: cells.json  # optional: a bandit.ThompsonCells state, reread when it changes

``register()`` (call it before building the dataset) adds the entry to OpenPCDet's
``DataAugmentor``, built as its ``gt_sampling`` builds the stock sampler. The sampler
is ``PGTPlacementSampler`` (``sampler_class()``), OpenPCDet's own ``DataBaseSampler`` (loading, PREPARE
filters, SAMPLE_GROUPS and LIMIT_WHOLE_SCENE counts unchanged) whose paste at the
stored pose is replaced by core.placement.place_objects: each asked object goes to a
feasible spot on the scan's ground, turned about the sensor axis, with collision and
occlusion. Entries are read as the stock sampler reads them; an entry with one more
column than the scene keeps its key-frame points only, as the stock sampler does.
Random draws come from a generator seeded from numpy's global state, which OpenPCDet
seeds per data-loader worker. Not supported: IMG_AUG_TYPE (camera copy-paste) and
USE_SHARED_MEMORY. Maps need the scan's world pose, which OpenPCDet's data dicts do
not carry, so here the map is left to core.placement users; the ground decides.
"""

from functools import cache
from pathlib import Path

import numpy as np

from ..core.placement.bandit import ThompsonFile
from ..core.placement.entries import EntryPool
from ..core.placement.place import PlacementConfig, place_objects
from ..core.scan.sensors import sensor_from_name


def register(data_augmentor=None) -> None:
    """Give OpenPCDet's DataAugmentor (default: imported from pcdet) the ``pgt_placement``
    augmentor, built like its gt_sampling."""
    if data_augmentor is None:
        from pcdet.datasets.augmentor.data_augmentor import DataAugmentor as data_augmentor

    def pgt_placement(self, config=None):
        return sampler_class()(root_path=self.root_path, sampler_cfg=config, class_names=self.class_names,
                               logger=self.logger)

    data_augmentor.pgt_placement = pgt_placement


@cache
def sampler_class():
    """PGTPlacementSampler, defined on first use: pcdet is imported only then."""
    from pcdet.datasets.augmentor.database_sampler import DataBaseSampler

    class PGTPlacementSampler(DataBaseSampler):
        """OpenPCDet's DataBaseSampler with the placement (the module docstring)."""

        def __init__(self, root_path, sampler_cfg, class_names, logger=None):
            if sampler_cfg.get("IMG_AUG_TYPE") or sampler_cfg.get("USE_SHARED_MEMORY", False):
                raise ValueError("pgt_placement supports neither IMG_AUG_TYPE nor USE_SHARED_MEMORY")
            super().__init__(root_path, sampler_cfg, class_names, logger)
            settings = sampler_cfg.get("PLACEMENT", {})
            self.placement_config = PlacementConfig(
                sensor_from_name(settings.get("SENSOR", "nuscenes")),
                max_distance=float(settings.get("MAX_DISTANCE", 54.0)),
                occlusion=bool(settings.get("OCCLUSION", True)), min_points=int(settings.get("MIN_POINTS", 5)))
            self.pool = EntryPool(self.db_infos, self.root_path, "openpcdet", int(sampler_cfg.NUM_POINT_FEATURES),
                                  self.placement_config.max_distance, min_points=0, load=self._read_entry,
                                  source=Path(self.root_path) / sampler_cfg.DB_INFO_PATH[0])
            self.thompson = ThompsonFile(Path(self.root_path) / settings["THOMPSON_STATE"],
                                         self.placement_config.max_distance) if settings.get("THOMPSON_STATE") else None

        def _read_entry(self, info: dict) -> np.ndarray:
            """The stock sampler's read: float32 rows of NUM_POINT_FEATURES, moved by the box centre."""
            points = np.fromfile(str(self.root_path / info["path"]), dtype=np.float32).reshape(
                [-1, self.sampler_cfg.NUM_POINT_FEATURES])
            assert points.shape[0] == info["num_points_in_gt"]
            points[:, :3] += np.asarray(info["box3d_lidar"][:3], np.float32)
            return points

        def __call__(self, data_dict):
            gt_names = data_dict["gt_names"].astype(str)
            counts = {}
            for class_name, sample_group in self.sample_groups.items():
                if self.limit_whole_scene:
                    sample_group["sample_num"] = str(int(self.sample_class_num[class_name])
                                                     - np.sum(class_name == gt_names))
                if int(sample_group["sample_num"]) > 0 and len(self.pool.classes[class_name].ranges):
                    counts[class_name] = int(sample_group["sample_num"])
            points = data_dict["points"]
            rng = np.random.default_rng(np.random.randint(2 ** 31))
            placement = place_objects(points, data_dict["gt_boxes"], gt_names, self.pool, counts,
                                      self.placement_config, rng, bandit=self.thompson and self.thompson.cells(),
                                      source=data_dict.get("frame_id", "scan"))
            inserted = placement.rows[:, 1].max() if len(placement.rows) else 0
            objects = placement.points[:inserted]
            if objects.shape[1] != points.shape[1]:  # multi-sweep entries into a single-sweep scene
                objects = objects[np.abs(objects[:, -1]) < 1e-6, :points.shape[1]]
            mask = np.concatenate([data_dict["gt_boxes_mask"], np.ones(placement.inserted.sum(), bool)])
            data_dict["points"] = np.concatenate([objects, placement.points[inserted:]]).astype(points.dtype)
            data_dict["gt_boxes"] = placement.boxes[mask].astype(data_dict["gt_boxes"].dtype)
            data_dict["gt_names"] = placement.names[mask]
            if placement.inserted.any() and self.sampler_cfg.get("USE_ROAD_PLANE", False):
                data_dict.pop("calib", None)  # as the stock sampler: the road plane is used up
                data_dict.pop("road_plane", None)
            data_dict.pop("gt_boxes_mask")
            return data_dict

    return PGTPlacementSampler

