"""Run mmdetection3d 1.4.0's own ground-truth sampling (the ``ObjectSample`` transform
and its ``DataBaseSampler``) on a scene, as its training pipeline does.

    .venv-mmdet3d/bin/python tests/detectors/mmdet3d_sample.py REQUEST.json

Runs in its own virtualenv (numpy >= 2; see mmdet3d-constraints.txt) and imports
nothing of pgt_blender. The request (JSON):

- ``config``: a config shipped with mmdet3d, relative to ``mmdet3d/.mim/configs``;
- ``child_config``: the documented change, a child config as Python whose ``_base_``
  names ``MMDET3D_CONFIGS/<config>`` (that folder's path is put in): loaded from a file
  as training loads it, its ``ObjectSample`` step taken from the pipeline training
  reads (``train_dataloader``'s, inside any dataset wrappers), its paths relative to the
  working directory as the stock ``data_root`` is; or, for ``place``:
- ``data_root``: the dataset root (the config's ``data_root``, here a test folder) and
  ``db_sampler``: keys set on the config's ``db_sampler`` dict, plus ``data_root``;
- ``scene``: ``points_file`` (float32 .bin, the dataset's columns), ``boxes``
  (gravity-centre LiDAR boxes x y z dx dy dz yaw [vx vy]), ``names``;
- ``place`` (optional): keys of a step that replaces ObjectSample and takes its
  ``db_sampler`` (a PGTPlacement step), with ``custom_imports``: the config is then
  loaded as a child config naming the stock one as ``_base_`` and adding those
  ``custom_imports``, so mmengine imports the step's module as in training;
- ``seed``, ``repeats``: numpy's global seed (the sampler shuffles with it) and how
  many times the scene is sampled (the sampler's state carries over, as in training);
- ``out``: an .npz to write.

The scene's points go through the config's own loading steps before ObjectSample
(LoadPointsFromFile, LoadPointsFromMultiSweeps with no sweep list), so they have the
columns the pipeline gives the sampler. For repeat ``i`` the .npz holds ``points_i``
(the transform's output, sampled points first), ``boxes_i`` (gravity-centre boxes,
scene's first), ``names_i`` and ``scene_boxes`` (how many boxes were the scene's).
Errors: one line on stderr, exit code 1.
"""

import copy
import json
import sys
from pathlib import Path

import numpy as np


def main(request_path: str) -> int:
    import mmdet3d
    import mmdet3d.datasets.transforms  # noqa: F401  (registers the transforms; register_all_modules
    from mmdet3d.registry import TRANSFORMS  # would also import the evaluation devkits, not installed)
    from mmdet3d.structures import LiDARInstance3DBoxes
    from mmengine.config import Config
    request = json.loads(Path(request_path).read_text())
    configs = Path(mmdet3d.__file__).parent / ".mim" / "configs"
    child = Path(request["out"]).with_suffix(".config.py")
    if "place" in request:
        child.write_text(f"_base_ = [{str(configs / request['config'])!r}]\n"
                         f"custom_imports = {request['place']['custom_imports']!r}\n")
        pipeline = copy.deepcopy(Config.fromfile(str(child)).train_pipeline)
        step = next(step for step in pipeline if step["type"] == "ObjectSample")
        step["db_sampler"].update(request["db_sampler"], data_root=request["data_root"])
    else:
        child.write_text(request["child_config"].replace("MMDET3D_CONFIGS/", f"{configs}/"))
        dataset = Config.fromfile(str(child)).train_dataloader["dataset"]
        while "pipeline" not in dataset:  # RepeatDataset, CBGSDataset
            dataset = dataset["dataset"]
        pipeline = copy.deepcopy(dataset["pipeline"])
        step = next((step for step in pipeline if step["type"] == "ObjectSample"), None)
        if step is None:
            raise ValueError("the pipeline training reads has no ObjectSample step: the change did not reach it")
    loading = [TRANSFORMS.build(s) for s in pipeline if s["type"] in ("LoadPointsFromFile", "LoadPointsFromMultiSweeps")]
    if "place" in request:
        step = {**request["place"]["step"], "db_sampler": step["db_sampler"]}
    object_sample = TRANSFORMS.build(step)
    classes = list(object_sample.db_sampler.cat2label)

    scene = request["scene"]
    boxes = np.asarray(scene["boxes"], np.float32).reshape(-1, len(scene["boxes"][0]) if scene["boxes"] else 7)
    labels = np.array([classes.index(name) for name in scene["names"]], np.int64)
    np.random.seed(request["seed"])
    arrays = {"scene_boxes": np.array(len(boxes))}
    for repeat in range(request["repeats"]):
        results = {"lidar_points": {"lidar_path": scene["points_file"]}, "timestamp": 0.0}
        for transform in loading:
            results = transform(results)
        results["gt_bboxes_3d"] = LiDARInstance3DBoxes(boxes, box_dim=boxes.shape[1], origin=(0.5, 0.5, 0.5))
        results["gt_labels_3d"] = labels.copy()
        results = object_sample(results)
        arrays[f"points_{repeat}"] = results["points"].tensor.numpy()
        sampled = results["gt_bboxes_3d"]
        arrays[f"boxes_{repeat}"] = np.concatenate([sampled.gravity_center.numpy(), sampled.tensor.numpy()[:, 3:]],
                                                   axis=1)
        arrays[f"names_{repeat}"] = np.array([classes[label] for label in results["gt_labels_3d"]])
    np.savez(request["out"], **arrays)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main(sys.argv[1]))
    except Exception as error:  # the test shows the sampler's own complaint, in one line
        print(f"mmdet3d: {type(error).__name__}: {error}".replace("\n", " "), file=sys.stderr)
        sys.exit(1)
