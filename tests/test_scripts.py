"""headless_scripts/ as a user runs them: subprocesses of the venv's Python."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pgt_blender.core.bank.export import CHUNK_STAGES

from .conftest import file_size_limit, run_script

ROOT = Path(__file__).resolve().parents[1]


def last_json_line(stdout):
    return json.loads(next(line for line in reversed(stdout.splitlines()) if line.startswith("{")))


def test_import_colmap_json_and_blend(statue, tmp_path):
    blend = tmp_path / "scene.blend"
    result = run_script("import_reconstruction.py", statue, "--out", blend, "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)  # all of it: Blender's "Saved as" goes to stderr
    assert (summary["points"], summary["cameras"], summary["faces"]) == (1816, 40, 0)
    assert {"Col", "track_length", "reprojection_error"} <= set(summary["attributes"])
    assert blend.stat().st_size > 0


def test_import_reconstruction_names_a_failed_save_in_one_line(statue, tmp_path):
    """A .blend that cannot be written (a full disk, here a file-size limit): exit 1 and
    one line naming it (Blender's own line, naming its temporary, is held back); no file
    left."""
    blend = tmp_path / "scene.blend"
    result = run_script("import_reconstruction.py", statue, "--out", blend, preexec_fn=file_size_limit(100_000))
    assert result.returncode == 1 and result.stderr.count("\n") == 1, result.stderr
    assert result.stderr.startswith(f"error: {blend}: cannot write the .blend"), result.stderr
    assert not list(tmp_path.iterdir())


def test_import_splat_json(donut):
    result = run_script("import_reconstruction.py", donut, "--json")
    summary = last_json_line(result.stdout)
    assert summary["points"] == 45624 and summary["kind"] == "gaussian_splat"
    assert {"opacity", "scale", "rotation"} <= set(summary["attributes"])


def test_import_capture_kinds_from_the_command_line(tmp_path):
    """A 3DGS output folder with view color and mask foreground, a splatfacto PLY and a
    Plenoxels checkpoint with plane foreground: each imports and reports its capture."""
    from pgt_blender.core.capture import samples
    from pgt_blender.core.importing.cameras import write_cameras_json
    from pgt_blender.core.importing.ply import write_ply

    scene = samples.table_scene(np.random.default_rng(0), 3000, 3000, 500)
    cameras = samples.orbit_cameras(8, 4.0, 30.0, target=scene["ball_centre"])
    count = len(scene["positions"])
    columns = samples.splat_columns(scene["positions"], np.zeros((count, 3, 16), np.float32), np.full(count, 0.9),
                                    np.full((count, 3), 0.01))
    run = tmp_path / "run"
    samples.write_3dgs_run(run, columns, cameras)
    masks = tmp_path / "masks"
    masks.mkdir()
    for view, mask in zip(cameras, samples.ball_masks(cameras, scene["ball_centre"], 0.5)):
        np.save(masks / view.name.replace(".png", ".npy"), mask)
    result = run_script("import_reconstruction.py", run, "--view-color", "--foreground", "masks", "--masks", masks,
                        "--json")
    assert result.returncode == 0, result.stderr
    summary = last_json_line(result.stdout)
    assert summary["kind"] == "gaussian_splat" and summary["object"] == "run" and summary["cameras"] == 8
    assert {"view_hit", "view_count"} <= set(summary["attributes"])
    assert summary["points"] == summary["capture"]["foreground"]["kept"] < count
    write_ply(tmp_path / "splat.ply", samples.splatfacto_columns(columns))
    summary = last_json_line(run_script("import_reconstruction.py", tmp_path / "splat.ply", "--json").stdout)
    assert summary["points"] == count and "nx" not in summary["attributes"]
    links = np.arange(64, dtype=np.int32).reshape(4, 4, 4)
    samples.write_svox2(tmp_path / "grid.npz", links, np.linspace(-1, 10, 64), np.zeros((64, 12)), [1, 1, 1],
                        [0, 0, 0])
    write_cameras_json(tmp_path / "cameras.json", cameras)
    result = run_script("import_reconstruction.py", tmp_path / "grid.npz", "--foreground", "plane", "--json",
                        "--cameras", tmp_path / "cameras.json", "--no-cameras")
    assert result.returncode == 0, result.stderr
    summary = last_json_line(result.stdout)
    assert summary["kind"] == "plenoxels" and summary["cameras"] == 0 and summary["capture"]["cameras"] == 8
    assert {"density", "opacity", "f_dc_0", "f_rest_8"} <= set(summary["attributes"])


COMMANDS = sorted(p.stem for p in (ROOT / "addon" / "pgt_blender" / "commands").glob("[!_]*.py"))


@pytest.mark.parametrize("script", sorted(p.name for p in (ROOT / "headless_scripts").glob("*.py")))
def test_help(script):
    result = run_script(script, "--help")
    assert result.returncode == 0 and result.stdout.startswith("usage:")


def test_blender_style_arguments_after_double_dash(donut):
    """``blender -b -P script.py -- ARGS``: Blender's own arguments precede ``--``."""
    result = run_script("import_reconstruction.py", donut, "--json", blender_style=True)
    assert result.returncode == 0, result.stderr
    assert last_json_line(result.stdout)["points"] == 45624


def test_demo(tmp_path):
    result = run_script("demo.py", "--out", tmp_path / "demo")
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "demo" / "demo.blend").exists()
    assert len(list((tmp_path / "demo" / "samples").glob("*_reconstruction.ply"))) == 6
    assert str(tmp_path / "demo" / "demo.blend") in result.stdout
    table = [line for line in result.stdout.splitlines() if "_reconstruction " in line and "[" in line]
    rows = [line.split() for line in table]
    errors = [float(row[2]) for row in rows]
    assert "heading by: classifier" in result.stdout  # torch is a test dependency
    assert len(rows) == 6 and all(e < 1.0 for e in errors)  # aligned, front at +x (180: front/back wrong)
    scanned = [int(line.split("]")[1].split()[0]) for line in table]
    # every object scanned at 15 m: the bicycle's tubes and wheels give a few dozen returns,
    # the buses and trucks hundreds (floaters no longer add their own)
    assert len(scanned) == 6 and min(scanned) > 20 and sorted(scanned)[2] > 200


def test_bench_import_runs(tmp_path):
    result = run_script("bench_import.py", "--sizes", "1000", "--repeats", "1", "--out", tmp_path / "import")
    assert result.returncode == 0, result.stderr
    rows = json.loads((tmp_path / "import.json").read_text())["rows"]
    assert [(r["kind"], r["points"]) for r in rows] == [("point_ply", 1000), ("gaussian_splat", 1000)]
    assert (tmp_path / "import.png").stat().st_size > 0


def test_bench_alignment_quick(tmp_path):
    result = run_script("bench_alignment.py", "--quick", "--out", tmp_path / "alignment")
    assert result.returncode == 0, result.stderr
    assert "| varied |" in result.stdout and (tmp_path / "alignment.png").stat().st_size > 0
    assert json.loads((tmp_path / "alignment.json").read_text())


def test_bench_fidelity_on_the_shared_kitti_scans(shared_data, tmp_path):
    result = run_script("bench_fidelity.py", shared_data / "kitti_scans", "--out", tmp_path / "fidelity", check=True)
    results = json.loads((tmp_path / "fidelity.json").read_text())
    assert results["totals"]["objects"] == 6 and (tmp_path / "fidelity.png").stat().st_size > 0
    assert {row["class"] for row in results["objects"]} == {"Pedestrian", "Truck", "Car", "Cyclist", "Misc"}
    assert results["totals"]["mean_ring_jaccard"] >= 0.8  # the fitted kitti table hits the rings the scans do
    assert "| Truck | truck_chassis.obj | 69.7 |" in result.stdout
    truck = next(row for row in results["objects"] if row["class"] == "Truck")
    assert 0.65 <= truck["ratio"] <= 1.35  # the meshed truck, with the fitted ray drop, within +-35 % of real
    assert "W1" in result.stdout and results["machine"]["cores"]
    if shared_data.resolve().is_relative_to(ROOT.parent):  # reports name no one machine's folders
        assert results["inputs"]["folder"] == f"../{(shared_data / 'kitti_scans').resolve().relative_to(ROOT.parent)}"


def test_bench_scan_quick(tmp_path):
    result = run_script("bench_scan.py", "--quick", "--out", tmp_path / "scan")
    assert result.returncode == 0, result.stderr
    results = json.loads((tmp_path / "scan.json").read_text())
    assert results["machine"]["bpy"] and (tmp_path / "scan.png").stat().st_size > 0
    assert "| bvh windowed |" in (tmp_path / "scan.md").read_text()
    exact = [row for row in results["rows"] if row["method"] in ("bvh windowed", "embree")]
    assert {row["method"] for row in exact} == {"bvh windowed", "embree"}  # embreex: a dev dependency
    assert all(row["false"] == row["missed"] == 0 and row["error_max_m"] < 1e-6 for row in exact)


def test_bench_gaussian_scan_quick(tmp_path, shared_data):  # splats fitted to the Chrono sedan
    result = run_script("bench_gaussian_scan.py", "--quick", "--out", tmp_path / "gaussians")
    assert result.returncode == 0, result.stderr
    overall = {row["method"]: row for row in json.loads((tmp_path / "gaussians.json").read_text())["overall"]}
    assert set(overall) == {"gaussians 20k", "surfels 20k"} and (tmp_path / "gaussians.png").stat().st_size > 0
    assert all(row["missed_pct"] < 1 and row["error_median_m"] < 0.02 for row in overall.values())


def test_bench_bank_quick(tmp_path, shared_data):  # its trucks are the Chrono mesh
    result = run_script("bench_bank.py", "--quick", "--out", tmp_path / "bank")
    assert result.returncode == 0, result.stderr
    results = json.loads((tmp_path / "bank.json").read_text())
    rows = results["throughput"]
    assert {row["workers"] for row in rows} >= {1} and all(row["kept"] > 0 and row["kept_per_s"] > 0 for row in rows)
    # the export's own stage clock: every stage reported, casts part of scans
    assert all(set(row["stages_ms_per_entry"]) == set(CHUNK_STAGES) and
               0 < row["stages_ms_per_entry"]["casts"] <= row["stages_ms_per_entry"]["scans"] for row in rows)
    assert all(0 < row["user_engine_ratio"] <= row["engine_ratio"] for row in rows)
    writes = results["file_writes"]  # the floor under the writes stage: alone, all cores at once, after deleting
    assert all(writes[case]["system_us"] > 0 for case in ("concurrent", "after_deleting")) and writes["system_us"] > 0
    assert "| chrono truck 11k |" in (tmp_path / "bank.md").read_text() and (tmp_path / "bank.png").stat().st_size > 0


def test_bench_cluster_quick(tmp_path, shared_data):  # the Chrono truck on local Ray clusters of 1 and 2 nodes
    pytest.importorskip("ray")
    result = run_script("bench_cluster.py", "--quick", "--out", tmp_path / "cluster")
    assert result.returncode == 0, result.stderr
    results = json.loads((tmp_path / "cluster.json").read_text())
    assert results["same_bank"] and results["efficiency"] > 0
    (one,), (two,) = (row["chunks_per_node"] for row in results["setups"][1:])
    assert len(one) == 1 and len(two) == 2 and sum(two) == one[0] > 0
    assert "| Ray, 2 nodes x 1 CPU |" in (tmp_path / "cluster.md").read_text()
    assert (tmp_path / "cluster.png").stat().st_size > 0


def test_bench_intensity_quick(tmp_path, shared_data):  # fitted to the real KITTI scans
    pytest.importorskip("torch")
    result = run_script("bench_intensity.py", "--quick", "--out", tmp_path / "intensity")
    assert result.returncode == 0, result.stderr
    rows = json.loads((tmp_path / "intensity.json").read_text())["rows"]
    assert {row["method"] for row in rows} == {"constant class mean", "physical default", "histogram matching",
                                               "learned (CycleGAN)"}
    assert all(row["w1_points"] >= 0 and row["real_points"] > 0 for row in rows)
    assert (tmp_path / "intensity.png").stat().st_size > 0


@pytest.fixture(scope="module")
def truck_sample(tmp_path_factory):
    from pgt_blender.core.samples import write_sample

    return write_sample(tmp_path_factory.mktemp("samples"), "truck", points=6000)


def test_scan_object_bin_equals_the_core_scan(chrono_meshes, tmp_path):
    import numpy as np

    from pgt_blender.core.importing import load_reconstruction
    from pgt_blender.core.scan.sensors import PRESETS
    from pgt_blender.core.scan.sweeps import Motion, scan_sweeps
    from pgt_blender.core.scan.targets import target_from_reconstruction

    truck = next(p for p in chrono_meshes if p.name == "truck_chassis.obj")
    out = tmp_path / "truck.bin"
    result = run_script("scan_object.py", "--object", truck, "--sensor", "nuscenes", "--x", 14, "--y", -3,
                        "--heading", 20, "--sweeps", 10, "--speed", 6, "--out", out)
    assert result.returncode == 0, result.stderr
    assert "points from" in result.stdout and f"wrote {out}" in result.stdout
    target = target_from_reconstruction(load_reconstruction(truck))
    expected = scan_sweeps(target, PRESETS["nuscenes"], 14.0, -3.0,
                           np.radians(20.0), Motion(6.0), 10)
    assert out.read_bytes() == expected.dataset_array().tobytes()


@pytest.mark.parametrize("surface", ["auto", "range-view"])
def test_scan_object_reports_the_authored_box(truck_sample, tmp_path, surface):
    """A prepared object (with its sidecar) stands on the ground in its authored box, as
    in the bank, and that box is the one printed: not the bounds of its points, which
    floaters and noise widen."""
    import json

    from pgt_blender.core.authoring.prepare import prepare, write_prepared
    from pgt_blender.core.importing import load_reconstruction

    authored = prepare(load_reconstruction(truck_sample["reconstruction.ply"]), "truck", up="+z",
                       heading_method="none")
    paths = write_prepared(authored, "truck", "nuscenes", tmp_path / "prepared")
    dims = json.loads(paths[".json"].read_text())["dims"]
    result = run_script("scan_object.py", "--object", paths[".ply"], "--x", 12, "--y", 0, "--surface", surface,
                        "--out", tmp_path / "scan.npy")
    assert result.returncode == 0, result.stderr
    box = [float(value) for value in result.stdout.split("box [x, y, z, dx, dy, dz, heading, vx, vy] = [")[1]
           .split("]")[0].split(",")]
    assert box[3:6] == pytest.approx(dims, abs=1e-3)


@pytest.mark.parametrize("surface, suffix", [("auto", ".ply"), ("range-view", ".npy")])
def test_scan_object_point_clouds(truck_sample, tmp_path, surface, suffix):
    import numpy as np

    out = tmp_path / f"scan{suffix}"
    result = run_script("scan_object.py", "--object", truck_sample["reconstruction.ply"], "--sensor", "kitti",
                        "--x", 12, "--y", 0, "--surface", surface, "--out", out)
    assert result.returncode == 0 and not result.stderr, result.stderr
    assert out.stat().st_size > 0 and int(result.stdout.split(": ", 1)[1].split()[0]) > 0
    if suffix == ".npy":
        assert np.load(out)["intensity"].max() <= 1.0  # KITTI intensities


def test_scan_object_warns_of_a_sensor_inside_the_object(truck_sample, tmp_path):
    """x = 0 puts the sensor inside the truck: the scan is written, with a warning."""
    out = tmp_path / "scan.bin"
    result = run_script("scan_object.py", "--object", truck_sample["mesh.ply"], "--x", 0, "--y", 0.5, "--out", out)
    assert result.returncode == 0 and out.stat().st_size > 0
    name = truck_sample["mesh.ply"].name
    assert result.stderr.startswith(f"warning: {name}: the sensor lies inside the object's box (centre 0.00, 0.50 m)")
    assert result.stderr.count("\n") == 1


@pytest.mark.parametrize("suffix", [".bin", ".npy", ".ply"])
def test_scan_object_names_why_a_write_failed(truck_sample, tmp_path, suffix):
    """A write that fails in numpy (a full disk, here a file-size limit) says why, in one
    line naming the output, and leaves no file."""
    out = tmp_path / f"scan{suffix}"
    result = run_script("scan_object.py", "--object", truck_sample["mesh.ply"], "--x", 12, "--y", 0, "--out", out,
                        preexec_fn=file_size_limit(1000))
    assert result.returncode == 1 and result.stderr.count("\n") == 1, result.stderr
    assert result.stderr.startswith(f"error: {out}: ") and "None" not in result.stderr, result.stderr
    assert not list(tmp_path.iterdir())


def test_scan_object_usage_errors_exit_2(truck_sample, tmp_path):
    result = run_script("scan_object.py", "--object", truck_sample["mesh.ply"], "--x", 1, "--y", 1,
                        "--out", tmp_path / "scan.txt")
    assert result.returncode == 2 and "scan.txt: expected a file name ending in .bin or .ply or .npy" in result.stderr


def test_fit_ground_prints_the_banks_ground_model(shared_data, tmp_path):
    result = run_script("fit_ground.py", shared_data / "kitti_scans", "--json")
    fit = json.loads(result.stdout)
    assert result.returncode == 0 and fit["used"] == 4 and len(fit["boxes"]) == 6
    result = run_script("fit_ground.py", tmp_path)
    assert result.returncode == 1 and result.stderr.strip() == \
        f"error: {tmp_path}: no velodyne/*.bin scans (expected a KITTI folder with velodyne, label_2, calib)"


def test_train_intensity_end_to_end_on_the_shared_data(shared_data, truck_sample, tmp_path):
    """KITTI scans + the mmdet3d GT database + the built-in samples, a few steps; then
    scan_object.py paints a scan with the model it wrote."""
    pytest.importorskip("torch")
    import csv

    import numpy as np

    out = tmp_path / "model"
    result = run_script("train_intensity.py", "--out", out, "--real", shared_data / "kitti_scans",
                        "--real", shared_data / "mmdet3d_kitti_gtdb" / "kitti_dbinfos_train.pkl",
                        "--gt-convention", "mmdet3d", "--steps", 12, "--checkpoint-every", 6)
    assert result.returncode == 0, result.stderr
    assert "of truck (kitti)" in result.stdout
    rows = list(csv.DictReader((out / "losses.csv").open()))
    assert len(rows) == 12 and float(rows[-1]["generator"]) < float(rows[0]["generator"])
    scans = {}
    for name, extra in (("physical", []), ("learned", ["--intensity-checkpoint", out / "intensity.pt"])):
        scans[name] = tmp_path / f"{name}.npy"
        result = run_script("scan_object.py", "--object", truck_sample["mesh.ply"], "--sensor", "kitti",
                            "--x", 12, "--y", 0, "--heading", 30, "--class", "truck", *extra, "--out", scans[name])
        assert result.returncode == 0, result.stderr
    physical, learned = (np.load(scans[name]) for name in ("physical", "learned"))
    assert np.array_equal(physical[["x", "y", "z", "ring"]], learned[["x", "y", "z", "ring"]])
    assert not np.array_equal(physical["intensity"], learned["intensity"]) and learned["intensity"].max() <= 1
    result = run_script("scan_object.py", "--object", truck_sample["mesh.ply"], "--sensor", "nuscenes", "--x", 12,
                        "--y", 0, "--class", "truck", "--intensity-checkpoint", out / "intensity.pt",
                        "--out", tmp_path / "wrong.npy")
    assert result.returncode == 1 and "trained on kitti intensities" in result.stderr
    assert not (tmp_path / "wrong.npy").exists()


def test_scan_object_without_torch_keeps_the_physical_intensity(truck_sample, tmp_path):
    code = ("import sys, runpy; sys.modules['torch'] = None; sys.argv = sys.argv[1:];"
            "runpy.run_path(sys.argv[0], run_name='__main__')")
    args = ["--object", truck_sample["mesh.ply"], "--sensor", "kitti", "--x", 10, "--y", 2, "--class", "truck"]
    plain = run_script("scan_object.py", *args, "--out", tmp_path / "plain.bin")
    result = subprocess.run([sys.executable, "-c", code, str(ROOT / "headless_scripts" / "scan_object.py"),
                             *map(str, args), "--intensity-checkpoint", tmp_path / "model.pt",
                             "--out", tmp_path / "fallback.bin"], capture_output=True, text=True, timeout=600)
    assert plain.returncode == result.returncode == 0, result.stderr
    assert "intensity: physical law: PyTorch (torch==2.13.0) is not installed" in result.stdout
    assert (tmp_path / "fallback.bin").read_bytes() == (tmp_path / "plain.bin").read_bytes()


def test_an_output_file_in_folders_not_made_yet_gets_them(truck_sample, tmp_path):
    """Every command makes its output file's missing folders (files.atomic_output), as
    the checks before the work allow (files.output_path), not fail after the work."""
    out = tmp_path / "new" / "deeper" / "scan.bin"
    run_script("scan_object.py", "--object", truck_sample["mesh.ply"], "--x", 10, "--y", 2, "--out", out, check=True)
    assert out.stat().st_size > 0


def test_every_command_is_a_console_script_with_a_shim():
    """Each pgt_blender/commands/<name>.py is installed as pgt-<name> (pyproject.toml) and
    has its headless_scripts/<name>.py shim (--help of every script: test_help)."""
    import tomllib

    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts == {f"pgt-{name.replace('_', '-')}": f"pgt_blender.cli:launchers.{name}" for name in COMMANDS}
    assert all((ROOT / "headless_scripts" / f"{name}.py").is_file() for name in COMMANDS)
    console = Path(sys.executable).parent / "pgt-mix-bank"
    result = subprocess.run([str(console), "--real", "missing.pkl", "--bank", "b.pkl", "--out", "o.pkl"],
                            capture_output=True, text=True, timeout=120)
    assert (result.returncode, result.stderr) == (1, "error: missing.pkl: cannot read the file (No such file or directory)\n")


@pytest.mark.parametrize("start", ["shim", "console script"])
def test_ctrl_c_while_a_command_loads_its_libraries_is_one_line(start):
    """Ctrl-C during the second or so a command spends importing scipy, torch or bpy:
    ``error: interrupted``, exit 130, no traceback (cli.launch). The interrupt is raised
    by an import hook on scipy, at the moment a real Ctrl-C there would land."""
    script = {"shim": ROOT / "headless_scripts" / "score_bank.py",
              "console script": Path(sys.executable).parent / "pgt-score-bank"}[start]
    code = ("import runpy, sys\n"
            "class Interrupt:\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            "        if name == 'scipy':\n"
            "            raise KeyboardInterrupt\n"
            "sys.meta_path.insert(0, Interrupt())\n"
            "sys.argv = sys.argv[1:]\n"
            "runpy.run_path(sys.argv[0], run_name='__main__')\n")
    result = subprocess.run([sys.executable, "-c", code, str(script), "--help"], capture_output=True, text=True,
                            timeout=120)
    assert (result.returncode, result.stderr, result.stdout) == (130, "error: interrupted\n", "")


def test_help_states_each_default():
    """cli.parser's --help gives an option's default unless its text already does or
    there is none (None, False, empty, a switch): a user need not read the code for it."""
    from pgt_blender import cli

    parser = cli.parser("x.py", "What x does.\n\nDetails.")
    parser.add_argument("--steps", type=int, default=0, help="optimiser steps")
    parser.add_argument("--workers", type=int, default=8, help="processes (default: all cores)")
    parser.add_argument("--checkpoint", help="a checkpoint")
    parser.add_argument("--quiet", action="store_true", help="print less")
    parser.add_argument("--no-refine", dest="refine", action="store_false", help="skip the refinement")
    parser.add_argument("--names", nargs="*", default=[], help="names")
    text = " ".join(parser.format_help().split())
    assert "What x does. options:" in text and "Details" not in text
    assert "optimiser steps (default: 0)" in text and "(default: all cores) (default" not in text
    assert text.count("(default:") == 2
