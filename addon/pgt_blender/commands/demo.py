"""The main job on the built-in samples: generate a synthetic reconstruction of each
minority-class vehicle (randomly posed, scaled, noisy, with floaters), import it into a
Blender scene, author it (align, detect the front, set a nuScenes class size), scan it
with the nuScenes LiDAR at 15 m (surfels, the Scan panel's operator), save the scene,
report each object against its ground truth, then export a small object bank of the
authored objects at nuScenes settings (OpenPCDet + mmdet3d) with its report.

    pgt-demo [--out demo_output] [--seed 0]
    .venv/bin/python headless_scripts/demo.py [--out demo_output] [--seed 0]
    blender -b -P headless_scripts/demo.py -- [--out ...]

The samples carry no cameras, so the up direction is given from their truth file, as
a user who knows the capture's up axis (or COLMAP's cameras) would give it.
"""

import json
import os
import time
from pathlib import Path


import bpy
import numpy as np

from ..blender import authoring, headless, objects
from .. import cli
from ..core.authoring.heading import best_available_method
from ..core.authoring.prepare import align_step
from ..core.bank import export
from ..core.bank.config import BankConfig
from ..core.bank.inputs import checked_objects
from ..core.bank.report import write_report
from ..core.classes import MINORITY_CLASSES
from ..core.importing import load_reconstruction
from ..core.samples import write_sample


def author(obj, truth: dict, method: str) -> dict:
    """Align with the true up, detect the front, set the class size; compare with truth."""
    source_from_object = np.array(truth["source_from_object"])
    up = source_from_object[:3, 2]
    authoring.apply_step(obj, align_step(authoring.positions(obj), None, up, obj.pgt.source_path))
    settings = bpy.context.scene.pgt_authoring
    settings.heading_method, settings.class_name = method, truth["class"]
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.pgt_auto_heading()
    bpy.ops.object.pgt_set_size()
    rotation = np.array(obj.pgt.object_from_source)[:3, :3]
    rotation = rotation / np.linalg.norm(rotation, axis=1, keepdims=True)  # drop the size scale
    truth_rotation = source_from_object[:3, :3].T / np.cbrt(np.linalg.det(source_from_object[:3, :3]))
    cosine = (np.trace(rotation @ truth_rotation.T) - 1) / 2
    return {"error_deg": float(np.degrees(np.arccos(np.clip(cosine, -1, 1)))),
            "heading": authoring.status(obj)["heading"], "dims": list(obj.pgt.dims)}


def scan(obj, distance: float = 15.0) -> dict:
    """Scan the authored object with the nuScenes preset, broadside at ``distance`` m."""
    settings = bpy.context.scene.pgt_scan
    settings.sensor, settings.distance, settings.azimuth, settings.heading = "nuscenes", distance, 0.0, np.pi / 2
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.pgt_scan()
    scanned = bpy.data.objects[f"{obj.name} Scan"]
    return {"scan_points": len(scanned.data.vertices), "scan_stats": settings.stats}


def main(argv: list) -> int:
    parser = cli.parser("demo.py", __doc__)
    parser.add_argument("--out", type=cli.OUTPUT_FOLDER, default="demo_output", help="output folder")
    parser.add_argument("--seed", type=cli.SEED, default=0, help="seed of the synthetic samples")
    args = parser.parse_args(argv)
    out = args.out.resolve()
    headless.ensure_registered()
    headless.start_scene()
    method, _ = best_available_method()
    rows = []
    for class_name in MINORITY_CLASSES:
        paths = write_sample(out / "samples", class_name, seed=args.seed)
        obj = objects.add_reconstruction(bpy.context.scene, load_reconstruction(paths["reconstruction.ply"]))
        truth = json.loads(paths["truth.json"].read_text())
        rows.append({**headless.object_summary(obj), **author(obj, truth, method), **scan(obj)})
    blend = out / "demo.blend"
    headless.save_blend(blend)
    print(f"\nheading by: {method}; error = angle to the true object frame (180 deg: front/back wrong)")
    print("scan: nuScenes HDL-32E, object broadside 15 m away, surfels of the authored points")
    print(f"{'object':34} {'points':>7} {'error deg':>9}  {'box [l, w, h] m':20}  scan")
    for row in rows:
        dims = ", ".join(f"{d:.2f}" for d in row["dims"])
        print(f"{row['object']:34} {row['points']:7d} {row['error_deg']:9.2f}  [{dims:18}]  {row['scan_stats']}")
    bank, manifest, seconds = export_demo_bank(out / "bank")
    print(f"\nbank: {export.kept_summary(manifest)} in {seconds:.0f} s "
          f"({manifest['entries'] / seconds:.0f} entries/s); nuScenes HDL-32E, 10 sweeps, x and y "
          f"{DEMO_BANK.x[0]:g}..{DEMO_BANK.x[1]:g} m every {DEMO_BANK.x[2]:g} m, headings every "
          f"{DEMO_BANK.headings_deg[2]:g} deg")
    print(f"\nsamples: {out / 'samples'}\nscene:   {blend}\nbank:    {bank} (report: {bank / 'report.md'})")
    return 0


# The paper's nuScenes settings on a coarser grid (20 m instead of 5 m) to stay quick.
DEMO_BANK = BankConfig(x=(-50.0, 50.0, 20.0), y=(-50.0, 50.0, 20.0))


def export_demo_bank(out: Path) -> tuple:
    """Export the scene's authored objects as a bank in ``out`` on every core, with its report."""
    from ..blender.bank import scene_bank_objects

    found, incomplete = scene_bank_objects(bpy.context.scene)
    started = time.perf_counter()
    manifest = export.export_bank(checked_objects(found, incomplete, False, out), DEMO_BANK, out,
                                  workers=os.cpu_count(), overwrite=True)
    seconds = time.perf_counter() - started
    write_report(out)
    return out, manifest, seconds
