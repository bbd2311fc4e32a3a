"""Build dist/pgt_blender-<version>.zip: the add-on, blender_manifest.toml and the
runtime wheels Blender does not ship (pyproject's dependencies minus numpy).

    .venv/bin/python headless_scripts/build_extension.py [--platform linux-x64 ...]
    blender -b -P headless_scripts/build_extension.py -- [--platform ...]

Wheels are fetched with pip (cp311, --no-deps, versions from constraints.txt) and the
package is built and validated by Blender's own extension CLI (blender_ext.py).
"""

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BLENDER_SHIPS = {"numpy"}
# Blender platform -> pip platform tags of its cp311 wheels.
PIP_PLATFORMS = {
    "linux-x64": ["manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64",
                  "manylinux2014_x86_64"],
    "windows-x64": ["win_amd64"],
    "macos-arm64": ["macosx_11_0_arm64", "macosx_12_0_arm64", "macosx_13_0_arm64", "macosx_14_0_arm64"],
    "macos-x64": ["macosx_10_15_x86_64", "macosx_11_0_x86_64", "macosx_13_0_x86_64"],
}


def blender_ext_cli() -> Path:
    """Blender's extension CLI, from the running Blender or the bpy wheel."""
    import bpy

    return Path(bpy.utils.system_resource("SCRIPTS")) / "addons_core" / "bl_pkg" / "cli" / "blender_ext.py"


def bundled_requirements() -> list:
    """pyproject's runtime dependencies that Blender lacks, as pip requirement strings."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    return [r for r in project["dependencies"] if re.split(r"[<>=!~ ;\[]", r)[0] not in BLENDER_SHIPS]


def download_wheels(platform: str, destination: Path) -> list:
    tags = [arg for tag in PIP_PLATFORMS[platform] for arg in ("--platform", tag)]
    subprocess.run(
        [sys.executable, "-m", "pip", "download", "--disable-pip-version-check", "-q", "--no-deps",
         "--only-binary=:all:", "--python-version", "3.11", "--implementation", "cp", *tags,
         "-c", str(ROOT / "constraints.txt"), "-d", str(destination), *bundled_requirements()],
        check=True,
    )
    return sorted(destination.glob("*.whl"))


def stage(directory: Path, platforms: list, wheels: list) -> None:
    """Lay out the package as Blender's builder expects: manifest beside __init__.py."""
    shutil.copytree(ROOT / "addon" / "pgt_blender", directory,  # dev.py serves the repository's scripts only
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "dev.py"))
    manifest = (ROOT / "blender_manifest.toml").read_text()
    header, table, rest = manifest.partition("\n[")  # top-level keys must precede tables
    listing = lambda items: "[" + ", ".join(f'"{item}"' for item in items) + "]"  # noqa: E731
    extra = f"platforms = {listing(platforms)}\n"
    if wheels:
        (directory / "wheels").mkdir()
        for wheel in wheels:
            shutil.copy2(wheel, directory / "wheels" / wheel.name)
        extra += f"wheels = {listing('./wheels/' + w.name for w in wheels)}\n"
    (directory / "blender_manifest.toml").write_text(header + "\n" + extra + table + rest)


def build(platforms: list, output: Path, bundle_wheels: bool = True) -> Path:
    """Build and validate the extension zip at ``output``; returns its path."""
    cli = blender_ext_cli()
    with tempfile.TemporaryDirectory() as temporary:
        wheels = []
        if bundle_wheels:
            for platform in platforms:
                wheels += download_wheels(platform, Path(temporary) / "wheels" / platform)
        package = Path(temporary) / "pgt_blender"
        stage(package, platforms, wheels)
        output.parent.mkdir(parents=True, exist_ok=True)
        partial = output.with_name(output.name + ".partial.zip")
        subprocess.run([sys.executable, str(cli), "build", "--source-dir", str(package),
                        "--output-filepath", str(partial)], check=True, stdout=subprocess.DEVNULL)
        subprocess.run([sys.executable, str(cli), "validate", str(partial)], check=True)
        partial.replace(output)
    return output


def main(argv: list) -> int:
    parser = argparse.ArgumentParser(prog="build_extension.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--platform", action="append", choices=sorted(PIP_PLATFORMS),
                        help="platform to bundle wheels for (repeatable; default linux-x64)")
    parser.add_argument("--out", type=Path, help="zip path (default dist/pgt_blender-<version>.zip)")
    args = parser.parse_args(argv)
    version = tomllib.loads((ROOT / "blender_manifest.toml").read_text())["version"]
    output = args.out or ROOT / "dist" / f"pgt_blender-{version}.zip"
    try:
        build(args.platform or ["linux-x64"], output)
    except subprocess.CalledProcessError as error:
        step = "wheel download (pip)" if "pip" in error.cmd else "Blender extension build"
        print(f"error: {output}: {step} failed with exit code {error.returncode}", file=sys.stderr)
        return 1
    print(f"built {output} ({output.stat().st_size / 1e6:.1f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]))
