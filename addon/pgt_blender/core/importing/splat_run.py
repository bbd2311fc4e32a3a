"""A 3D Gaussian Splatting output folder (graphdeco-inria/gaussian-splatting ``train.py
--model_path RUN``), as scene/__init__.py and gaussian_model.py write it:

```
RUN/cfg_args                                   the run's arguments, a Namespace(...) repr:
                                               source_path='<the COLMAP dataset it trained on>'
RUN/cameras.json                               the test and train cameras (cameras.py)
RUN/input.ply                                  the COLMAP points it started from
RUN/point_cloud/iteration_N/point_cloud.ply    the splats after N iterations
```

The splats of the highest N are read; their cameras come from ``cameras.json``, else
from the COLMAP model the run trained on (``source_path``/sparse/0 when that path is
absolute, or RUN/sparse/0).
"""

import os
import re
from pathlib import Path

from ..errors import InputError
from ..files import TEXT_LIMIT, listed, regular_file
from .cameras import load_cameras, read_cameras_json
from .colmap import MODEL_FILES

_ITERATION = re.compile(r"iteration_(\d+)$")
_SOURCE_PATH = re.compile(r"source_path=(['\"])(.*?)\1")


def run_ply(folder) -> Path | None:
    """``point_cloud.ply`` of the highest iteration in the run ``folder``, or None when
    ``folder`` is not a 3DGS output folder. InputError when that newest one is no
    regular file (a link leading nowhere, a pipe, a folder) or ``point_cloud/`` cannot
    be read: an older iteration or a COLMAP reading in its place would be a silent
    mistake."""
    point_cloud = Path(folder) / "point_cloud"
    if not point_cloud.is_dir():
        return None
    iterations = [(int(match.group(1)), entry / "point_cloud.ply") for entry in listed(point_cloud, "iteration_*")
                  if (match := _ITERATION.search(entry.name)) and os.path.lexists(entry / "point_cloud.ply")]
    return regular_file(max(iterations)[1]) if iterations else None


def run_of(ply) -> Path | None:
    """The run folder of a splat PLY at RUN/point_cloud/iteration_N/point_cloud.ply, else None."""
    ply = Path(ply)
    if ply.name == "point_cloud.ply" and _ITERATION.search(ply.parent.name) and ply.parent.parent.name == "point_cloud":
        return ply.parents[2]
    return None


def run_cameras(run) -> list:
    """The cameras of a 3DGS run (see the module docstring); [] when it has none."""
    run = Path(run)
    if os.path.lexists(run / "cameras.json"):  # whatever it is: read_cameras_json names what is wrong with it
        return read_cameras_json(run / "cameras.json")
    for model in _colmap_candidates(run):
        if all((model / f"{name}.bin").exists() or (model / f"{name}.txt").exists() for name in MODEL_FILES):
            return load_cameras(model)
    return []


def _colmap_candidates(run: Path) -> list:
    candidates = [run / "sparse" / "0"]
    try:  # optional: one that cannot be read (none, a pipe, a huge file) names no source
        match = _SOURCE_PATH.search(regular_file(run / "cfg_args", TEXT_LIMIT).read_text(encoding="utf-8",
                                                                                          errors="replace"))
    except (OSError, InputError):
        match = None
    if match and Path(match.group(2)).is_absolute():  # a relative one was relative to a working folder unknown here
        candidates.insert(0, Path(match.group(2)) / "sparse" / "0")
    return candidates
