"""Fit a LiDAR's per-laser elevations, vertical offsets and columns to its raw scans.

    pgt-fit-sensor SCAN.bin|FOLDER ... [--base kitti] [--out sensor.toml]
    .venv/bin/python headless_scripts/fit_sensor.py SCAN.bin|FOLDER ... [--base kitti] [--out sensor.toml]
        [--values-per-point 4] [--json]

Scans are raw float32 files stored laser by laser (KITTI velodyne/*.bin: x, y, z,
intensity); a folder stands for its *.bin files. The model and the fit are in
pgt_blender/core/scan/sensor_fit.py. It prints each laser's fit and z residual, then,
with two or more scans, each scan's elevation error when the table is fitted on the
others (leave one out) beside the --base preset's, and writes a sensor TOML (``base``
plus the fitted keys) that --sensor and the bank config take. What returns look like
(ray drop, intensity) is fitted on labelled frames by fit_returns.py. Bad input: a one-line
error and exit code 1.
"""

import json
from pathlib import Path

import numpy as np


from .. import cli
from ..core.errors import InputError
from ..core.files import apart_from_inputs, atomic_output, listed, read_float32_rows
from ..core.scan import sensor_fit
from ..core.scan.sensors import PRESETS


def scan_files(paths: list) -> list:
    """The scans ``paths`` name (a folder: its *.bin files), each once: a scan given twice
    would be held out against itself."""
    files = {}
    for path in paths:
        found = listed(path, "*.bin") if path.is_dir() else [path]
        if not found:
            raise InputError(path, "holds no *.bin scans")
        for file in found:
            files.setdefault(file.resolve(), file)
    return list(files.values())


def rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


def leave_one_out(scans: list, base) -> list:
    """Per scan: RMS elevation error (deg) of the table fitted on the other scans, and of
    the ``base`` sensor's table (matched to the lasers by elevation rank)."""
    rows = []
    for index, scan in enumerate(scans):
        fit = sensor_fit.fit_lasers([other for other_index, other in enumerate(scans) if other_index != index])
        rank = np.argsort(np.argsort(fit.elevations_deg))
        base_errors = sensor_fit.elevation_errors(fit, scan, np.asarray(base.elevations_deg)[rank],
                                                  np.asarray(base.vertical_offsets_m)[rank])
        rows.append({"fitted_rms_deg": rms(sensor_fit.elevation_errors(fit, scan)), "base_rms_deg": rms(base_errors)})
    return rows


def toml_text(sensor, fit, files: list, base: str, held_out: list) -> str:
    def numbers(values, digits):
        return "[" + ", ".join(f"{value:.{digits}f}" for value in values) + "]"

    worst = max((row["fitted_rms_deg"] for row in held_out), default=None)
    return "\n".join([
        f"# fit_sensor.py on {len(files)} scan(s): {', '.join(path.name for path in files)}",
        f"# z residual per laser: median {np.median(fit.residual_m) * 1e3:.2f} mm, "
        f"max {fit.residual_m.max() * 1e3:.2f} mm"
        + ("" if worst is None else f"; leave-one-out elevation error <= {worst:.4f} deg RMS"),
        f'base = "{base}"',
        f"columns = {sensor.columns}",
        f"elevations_deg = {numbers(sensor.elevations_deg, 4)}",
        f"vertical_offsets_m = {numbers(sensor.vertical_offsets_m, 5)}",
        f"firing_us = {numbers(sensor.firing_us, 4)}",
        ""])


def main(argv: list) -> int:
    parser = cli.parser("fit_sensor.py", __doc__)
    parser.add_argument("scans", type=Path, nargs="+", help="raw scans (.bin) or folders of them")
    parser.add_argument("--base", choices=sorted(PRESETS), default="kitti", help="the preset the fit refines")
    parser.add_argument("--out", type=cli.output_file(".toml"), help="write the fitted sensor TOML here")
    parser.add_argument("--values-per-point", type=cli.whole(3, 64), default=4,
                        help="float32 values per point (KITTI: 4)")
    parser.add_argument("--json", action="store_true", help="print the fit as one JSON object")
    args = parser.parse_args(argv)
    apart_from_inputs(args.out, args.scans)
    files = scan_files(args.scans)
    scans = [read_float32_rows(path, args.values_per_point).astype(np.float64) for path in files]
    fit = sensor_fit.fit_lasers(scans, files)
    base = PRESETS[args.base]
    if base.beams != len(fit.elevations_deg):  # the fit refines the preset laser for laser
        alike = " or ".join(sorted(name for name, preset in PRESETS.items() if preset.beams == len(fit.elevations_deg)))
        raise InputError(args.scans[0], f"the scans have {len(fit.elevations_deg)} lasers, the {args.base} preset "
                                        f"{base.beams}: " + (f"refine --base {alike}" if alike else
                                                             "no preset has as many lasers"))
    sensor = sensor_fit.fitted_sensor(base, fit, args.out.stem if args.out else base.name)
    held_out = leave_one_out(scans, base) if len(scans) > 1 else []
    result = {"scans": [str(path) for path in files], "columns": fit.columns,
              "lasers": [{"laser": index, "elevation_deg": float(elevation), "vertical_offset_m": float(offset),
                          "residual_m": float(residual), "points": int(points)}
                         for index, (elevation, offset, residual, points)
                         in enumerate(zip(fit.elevations_deg, fit.vertical_offsets_m, fit.residual_m, fit.points))],
              "leave_one_out": held_out}
    if args.out:
        with atomic_output(args.out) as stream:
            stream.write(toml_text(sensor, fit, files, args.base, held_out).encode())
    if args.json:
        print(json.dumps(result))
        return 0
    print(cli.markdown_table(
        ["laser (scan order)", "elevation deg", "vertical offset m", "z residual mm", "points"],
        [[row["laser"], f"{row['elevation_deg']:.4f}", f"{row['vertical_offset_m']:.4f}",
          f"{row['residual_m'] * 1e3:.2f}", row["points"]] for row in result["lasers"]], "rrrrr"))
    print(f"\ncolumns per revolution: {fit.columns} (the {args.base} preset: {base.columns})")
    for path, row in zip(files, held_out):
        print(f"held out {path.name}: elevation error {row['fitted_rms_deg']:.4f} deg RMS fitted on the others, "
              f"{row['base_rms_deg']:.3f} deg with the {args.base} preset")
    if args.out:
        print(f"wrote {args.out}")
    return 0
