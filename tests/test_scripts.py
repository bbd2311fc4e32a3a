"""headless_scripts/ as a user runs them: subprocesses of the venv's Python."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_script(name, *args, cwd=None):
    return subprocess.run([sys.executable, str(ROOT / "headless_scripts" / name), *map(str, args)],
                          capture_output=True, text=True, timeout=600, cwd=cwd)


def last_json_line(stdout):
    return json.loads(next(line for line in reversed(stdout.splitlines()) if line.startswith("{")))


def test_import_colmap_json_and_blend(statue, tmp_path):
    blend = tmp_path / "scene.blend"
    result = run_script("import_reconstruction.py", statue, "--out", blend, "--json")
    assert result.returncode == 0, result.stderr
    summary = last_json_line(result.stdout)
    assert (summary["points"], summary["cameras"], summary["faces"]) == (1816, 40, 0)
    assert {"Col", "track_length", "reprojection_error"} <= set(summary["attributes"])
    assert blend.stat().st_size > 0


def test_import_splat_json(donut):
    result = run_script("import_reconstruction.py", donut, "--json")
    summary = last_json_line(result.stdout)
    assert summary["points"] == 45624 and summary["kind"] == "gaussian_splat"
    assert {"opacity", "scale", "rotation"} <= set(summary["attributes"])


def test_import_bad_input_exits_non_zero_and_writes_nothing(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n")
    blend = tmp_path / "out.blend"
    result = run_script("import_reconstruction.py", bad, "--out", blend, "--json")
    assert result.returncode == 1
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert errors == [f"error: {bad}: the header declares 2 data rows (2 vertex) but the body has 1"]
    assert not blend.exists() and "{" not in result.stdout


@pytest.mark.parametrize("script", ["import_reconstruction.py", "demo.py", "bench_import.py", "build_extension.py"])
def test_help(script):
    result = run_script(script, "--help")
    assert result.returncode == 0 and result.stdout.startswith("usage:")


def test_blender_style_arguments_after_double_dash(donut):
    """``blender -b -P script.py -- ARGS``: Blender's own arguments precede ``--``."""
    code = ("import sys, runpy; sys.argv = ['blender', '-b', '-P', sys.argv[1], '--', sys.argv[2], '--json'];"
            "runpy.run_path(sys.argv[3], run_name='__main__')")
    script = ROOT / "headless_scripts" / "import_reconstruction.py"
    result = subprocess.run([sys.executable, "-c", code, str(script), str(donut)],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert last_json_line(result.stdout)["points"] == 45624


def test_demo(tmp_path):
    result = run_script("demo.py", "--out", tmp_path / "demo")
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "demo" / "demo.blend").exists()
    assert len(list((tmp_path / "demo" / "samples").glob("*_reconstruction.ply"))) == 6
    assert str(tmp_path / "demo" / "demo.blend") in result.stdout
    rows = [line.split() for line in result.stdout.splitlines() if line.endswith("]") and "_reconstruction" in line]
    errors = [float(row[2]) for row in rows]
    assert len(rows) == 6 and all(min(e, abs(180 - e)) < 1.0 for e in errors)  # aligned, up to the front


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
