"""The main job on the built-in samples, as far as the pipeline reaches today:
generate a synthetic reconstruction of each minority-class vehicle, import each into
a Blender scene, save it, and print what arrived.

    .venv/bin/python headless_scripts/demo.py [--out demo_output] [--seed 0]
    blender -b -P headless_scripts/demo.py -- [--out ...]
"""

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "addon"))

import bpy  # noqa: E402

from pgt_blender.blender import headless, objects  # noqa: E402
from pgt_blender.core.classes import MINORITY_CLASSES  # noqa: E402
from pgt_blender.core.importing import load_reconstruction  # noqa: E402
from pgt_blender.core.samples import write_sample  # noqa: E402


def main(argv: list) -> int:
    parser = argparse.ArgumentParser(prog="demo.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("demo_output"), help="output folder")
    parser.add_argument("--seed", type=int, default=0, help="seed of the synthetic samples")
    args = parser.parse_args(argv)
    out = args.out.resolve()
    headless.ensure_registered()
    headless.start_scene()
    rows = []
    for class_name in MINORITY_CLASSES:
        paths = write_sample(out / "samples", class_name, seed=args.seed)
        for role in ("reconstruction.ply", "mesh.ply"):
            obj = objects.add_reconstruction(bpy.context.scene, load_reconstruction(paths[role]))
            obj.pgt.class_name = class_name
            rows.append(headless.object_summary(obj))
    blend = out / "demo.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    print(f"\n{'object':36} {'kind':10} {'points':>7} {'faces':>6}  attributes")
    for row in rows:
        print(f"{row['object']:36} {row['kind']:10} {row['points']:7d} {row['faces']:6d}  {', '.join(row['attributes'])}")
    print(f"\nsamples: {out / 'samples'}\nscene:   {blend}")
    return 0


if __name__ == "__main__":
    sys.exit(main(headless.script_argv()))
