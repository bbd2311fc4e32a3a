"""Fit what a LiDAR's returns look like, ray drop and intensity, on real labelled frames.

    pgt-fit-returns KITTI_FOLDER --meshes CHRONO_VEHICLE_DIR|samples|FOLDER [--sensor kitti]
        [--intensity-points FILE... --intensity-sensor nuscenes [--values-per-point 5]]
        [--out models.toml] [--json]
    .venv/bin/python headless_scripts/fit_returns.py (the same arguments)

Every labelled object of the KITTI folder's frames (velodyne, label_2, calib) is
replaced by a mesh of its class scaled to its box (``--meshes``: the presets used the
Chrono vehicle folder ../shared/data/chrono_vehicles/data/vehicle, as bench_fidelity.py
does; default reflectivity), and the
frame is scanned without noise (pgt_blender/core/scan/replay.py). Then:

- ray drop (core/scan/ray_drop.py): each simulated hit is called kept or dropped by the
  real scan's cell; the model is fitted on them;
- intensity law (core/scan/physical_intensity.py): the real points inside the boxes
  against the simulated hits' reflectivity x |cos|. ``--intensity-points`` fits the law
  of ``--intensity-sensor`` instead, from the intensities of those raw point files
  (e.g. the nuScenes sample, which has no full frames to replay) against the same
  simulated hits.

It prints per object the kept / dropped counts and, per frame held out from the fit,
the real drop rate beside the predicted one and the intensity W1 of the law beside a
constant at the training frames' mean; then writes ``ray_drop`` and ``intensity_law``
as a sensor TOML (``base`` = the sensor) that --sensor and the bank config take.
"""

import json
from pathlib import Path

import numpy as np


from scipy.stats import wasserstein_distance

from .. import cli
from ..core.errors import InputError
from ..core.files import apart_from_inputs, atomic_output, read_float32_rows
from ..core.intensity.objects import kitti_frames
from ..core.scan import ray_drop, replay
from ..core.scan.physical_intensity import relative_intensity
from ..core.scan.sensors import PRESETS, sensor_from_name



def fitted_models(frames: list, sensor, real: dict | None, folder: Path) -> tuple:
    """(ray drop, intensity law) fitted on replayed ``frames`` (replay.py)."""
    try:
        return replay.fit_frames_ray_drop(frames), replay.fit_frames_intensity_law(frames, sensor, real)
    except ValueError as error:
        raise InputError(folder, str(error)) from None


def held_out(frames: list, sensor, folder: Path) -> list:
    """Per frame: the drop and intensity models fitted on the other frames, scored on it."""
    rows = []
    for index, frame in enumerate(frames if len(frames) > 1 else []):
        others = frames[:index] + frames[index + 1:]
        model, law = fitted_models(others, sensor, None, folder)
        constant = float(replay.pooled(others, "real")["value"].mean())
        hits, real = frame["hits"], frame["real"]
        judged = hits["outcome"] != ray_drop.ELSEWHERE
        predicted = ray_drop.drop_probability(model, hits["reflectivity"][judged], hits["cos_incidence"][judged],
                                              hits["range"][judged])
        normal = np.random.default_rng(index).standard_normal(len(hits["range"]))
        values = relative_intensity(hits["reflectivity"], hits["cos_incidence"], hits["range"], law, normal)
        for label, (kind, *_) in enumerate(frame["labels"]):
            mine, sim = real["label"] == label, hits["label"] == label
            if mine.any() and sim.any():
                rows.append({"frame": frame["frame"], "class": kind, "real_points": int(mine.sum()),
                             "w1_law": wasserstein_distance(values[sim], real["value"][mine]),
                             "w1_constant": wasserstein_distance([constant], real["value"][mine])})
        rows.append({"frame": frame["frame"], "class": "(frame)", "hits": int(judged.sum()),
                     "real_drop": float(np.mean(hits["outcome"][judged] == ray_drop.DROPPED)),
                     "predicted_drop": float(predicted.mean())})
    return rows


def intensity_points(paths: list, values_per_point: int, sensor) -> dict:
    """Real values (0..1) and ranges of raw point files' points at the sensor's ranges."""
    rows = np.concatenate([read_float32_rows(path, values_per_point).astype(np.float64) for path in paths])
    ranges = np.linalg.norm(rows[:, :3], axis=1)
    usable = (ranges >= sensor.min_range) & (ranges <= sensor.max_range)
    if not usable.any():
        raise InputError(paths[0], f"no point lies within the {sensor.name} sensor's ranges")
    return {"value": rows[usable, 3] / sensor.intensity_max, "range": ranges[usable],
            "object": np.zeros(usable.sum(), np.int64)}  # no boxes: one population


def toml_text(sensor_name: str, model: tuple, law: tuple, folder: Path) -> str:
    return "\n".join([f"# fit_returns.py on {folder}", f'base = "{sensor_name}"',
                      f"ray_drop = [{model[0]:.4f}, {model[1]:.4f}]  # (a, k), ray_drop.py",
                      f"intensity_law = [{law[0]:.4f}, {law[1]:.4f}, {law[2]:.4f}]  "
                      f"# (scale, range_exponent, spread), physical_intensity.py", ""])


def main(argv: list) -> int:
    parser = cli.parser("fit_returns.py", __doc__)
    parser.add_argument("folder", type=Path, help="KITTI folder with velodyne, label_2, calib")
    parser.add_argument("--sensor", default="kitti", help="the frames' sensor: preset or TOML")
    parser.add_argument("--meshes", required=True,
                        help="class meshes: 'samples', the Chrono vehicle folder (chrono_vehicles/data/vehicle) "
                             "or a folder of <class>.obj|.ply")
    parser.add_argument("--intensity-points", type=Path, nargs="+", help="raw point files for the intensity law")
    parser.add_argument("--intensity-sensor", default="nuscenes", choices=sorted(PRESETS),
                        help="the sensor --intensity-points come from")
    parser.add_argument("--values-per-point", type=cli.whole(4, 64), default=5,
                        help="float32 values per --intensity-points row")
    parser.add_argument("--out", type=cli.output_file(".toml"), help="write the fitted models as a sensor TOML here")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    args = parser.parse_args(argv)
    apart_from_inputs(args.out, [args.folder, args.sensor, *(args.intensity_points or [])])
    sensor = sensor_from_name(args.sensor)
    frames = replay.replay_frames(kitti_frames(args.folder), sensor, replay.class_meshes(args.meshes))
    if not frames:
        raise InputError(args.folder, "has no labelled frames")
    law_sensor, real = sensor, None
    if args.intensity_points:
        law_sensor = PRESETS[args.intensity_sensor]
        real = intensity_points(args.intensity_points, args.values_per_point, law_sensor)
    model, law = fitted_models(frames, law_sensor, real, args.folder)
    objects = []
    for frame in frames:
        counts = np.zeros((len(frame["labels"]), 3), np.int64)
        np.add.at(counts, (frame["hits"]["label"], frame["hits"]["outcome"]), 1)
        objects += [{"frame": frame["frame"], "class": kind, "distance_m": float(np.hypot(*centre[:2])),
                     "kept": int(kept), "dropped": int(dropped), "elsewhere": int(elsewhere)}
                    for (kind, centre, *_), (kept, dropped, elsewhere) in zip(frame["labels"], counts)]
    scored = held_out(frames, sensor, args.folder) if real is None else []
    result = {"ray_drop": model, "intensity_law": law, "intensity_sensor": law_sensor.name, "objects": objects,
              "held_out": scored}
    if args.out:
        with atomic_output(args.out) as stream:
            stream.write(toml_text(law_sensor.name, model, law, args.folder).encode())
    if args.json:
        print(json.dumps(result))
        return 0
    print(cli.markdown_table(["frame", "class", "distance m", "kept", "dropped", "elsewhere (not judged)"],
                             [[row["frame"], row["class"], f"{row['distance_m']:.1f}", row["kept"], row["dropped"],
                               row["elsewhere"]] for row in objects], "llrrrr"))
    print(f"\nray drop ({sensor.name}): logit p = {model[0]:.4f} - {model[1]:.4f} ln(power)")
    print(f"intensity law ({law_sensor.name}): scale {law[0]:.4f}, range exponent {law[1]:.4f}, spread {law[2]:.4f}")
    if scored:
        print("\nheld out (fitted on the other frames):\n" + cli.markdown_table(
            ["frame", "class", "real drop / predicted", "intensity W1 law", "W1 constant mean"],
            [[row["frame"], f"all hits ({row['hits']})", f"{row['real_drop']:.3f} / {row['predicted_drop']:.3f}", "", ""]
             if "real_drop" in row else
             [row["frame"], f"{row['class']} ({row['real_points']} pts)", "", f"{row['w1_law']:.3f}",
              f"{row['w1_constant']:.3f}"] for row in scored], "llrrr"))
    if args.out:
        print(f"wrote {args.out}")
    return 0
