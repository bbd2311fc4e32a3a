"""The Bank section: a scene's authored objects as the bank's inputs, the export run
chunk by chunk, the bank report (beside a real database, with the bank's quality score
against it, when the section names one), and a preview of a finished bank in the
viewport.

Gathering the inputs (core/bank/inputs.py) is done in bulk. An object's mesh data is its object frame (authoring wrote it so); its box is the last
authoring step's dims. Meshes give their triangles, point objects their points (and
Gaussian splats their scale, rotation and opacity attributes); colors
come from the per-point color attribute (sRGB), as the prepared-object route reads them
from the PLY, so the same objects by either route make the same bank.
"""

import math
from contextlib import ExitStack
from pathlib import Path

import bpy
import numpy as np

from ..core.bank import export
from ..core.bank.config import (DATASET_CONSTANT_INTENSITY, DATASET_GRIDS, FORMATS, BankConfig, config_from_table,
                                config_table, load_config)
from ..core.bank.folder import exporting, info_path_root, read_manifest
from ..core.bank.inputs import BankObject, checked_objects, incomplete_reason
from ..core.bank.report import real_reference, write_report
from ..core.errors import InputError
from ..core.files import read_float32_rows
from ..core.gt_database import load_infos
from ..core.reconstruction import Reconstruction
from ..core.scan.sensors import BIN_COLUMNS, INTENSITY_MAX
from ..core.scan.targets import has_gaussians
from .authoring import current_dims, is_reconstruction, status
from .objects import box_empty, remove_datablocks, replace_collection
from .properties import field_path
from .scanning import (mesh_triangles, mesh_vertices, point_colors, points_object, ramp, splat_attributes,
                       warn_unscanned)


def scene_bank_objects(scene: bpy.types.Scene) -> tuple[list, list]:
    """(BankObjects of the complete reconstructions in ``scene`` by name, incomplete
    ones as (name, reason))."""
    objects, incomplete = [], []
    for obj in sorted(scene.objects, key=lambda o: o.name):
        if not is_reconstruction(obj):
            continue
        reason = incomplete_reason(obj.pgt.class_name, bool(status(obj)["size"]))
        if reason:
            incomplete.append((obj.name, reason))
            continue
        warn_unscanned(obj)
        mesh = obj.data
        faces = mesh_triangles(mesh)[0] if len(mesh.polygons) else np.zeros((0, 3), np.int32)
        splats = {} if len(faces) else splat_attributes(mesh)
        geometry = Reconstruction(mesh_vertices(mesh), "mesh" if len(faces) else "point_ply",
                                  Path(bpy.data.filepath or "scene") / obj.name, obj.pgt.source_sha256,
                                  faces=faces, colors=point_colors(mesh),
                                  attributes=splats if has_gaussians(splats) else {})
        objects.append(BankObject(obj.name, obj.pgt.class_name, current_dims(obj), geometry))
    return objects, incomplete


def bank_config(settings, checkpoint: str = "") -> BankConfig:
    """The BankConfig of the Bank section (``Scene.pgt_bank``): its config file when one
    is set, else its fields over the defaults; ``checkpoint`` (the preferences' intensity
    checkpoint) makes the intensities learned, as in the Scan section."""
    if settings.config_file:
        return load_config(field_path(settings.config_file))
    if settings.dataset not in DATASET_GRIDS:  # "": a stored index this version has no item for
        raise InputError("Bank", "no dataset chosen: choose one in the Bank section")
    formats = tuple(name for name in FORMATS if getattr(settings, name))
    if not formats:
        raise InputError("Bank", "no format chosen: tick OpenPCDet or mmdetection3d")
    (x_low, x_high, _), (y_low, y_high, _) = DATASET_GRIDS[settings.dataset]
    learned = checkpoint and settings.dataset not in DATASET_CONSTANT_INTENSITY
    # heading_step is float32 radians: 30 deg reads back as 30.000001, a grid without its last heading
    fields = BankConfig(dataset=settings.dataset, sensor="" if settings.sensor == "DATASET" else settings.sensor,
                        formats=formats, seed=settings.seed, sweeps=settings.sweeps, chunk_size=settings.chunk_size,
                        headings_deg=(-180.0, 180.0, round(math.degrees(settings.heading_step), 4)),
                        x=(x_low, x_high, settings.grid_step), y=(y_low, y_high, settings.grid_step),
                        engine=settings.engine, intensity_checkpoint=checkpoint if learned else "")
    return config_from_table(config_table(fields), "Bank")  # held to a config file's bounds


def real_database(settings):
    """(absolute path, convention or None: read from the infos) of the Bank section's Real
    database, or None."""
    if not settings.real_database:
        return None
    convention = None if settings.real_convention == "AUTO" else settings.real_convention
    return field_path(settings.real_database), convention


def write_bank_report(out, real=None, reference=None) -> Path:
    """Write the report of the bank in ``out``; with ``real`` (real_database's pair),
    beside that database's statistics (``reference``: report.real_reference, read here
    when not given) and with the bank's quality score against it (score_bank.py's table;
    the Fréchet distance only where torch imports, its encoder cached in the bank's
    .work folder). Returns report.md's path; InputError, with no report file written,
    for a bad bank or database."""
    if real is None:
        return write_report(out)[0]
    from ..core.quality.score import quality_available, score_bank

    path, convention = real
    if reference is None:
        reference = real_reference(path, read_manifest(out)["config"], convention=convention)
    return write_report(out, reference, score_bank(out, path, convention, learned=quality_available()))[0]


class BankRun:
    """One bank export of ``scene``'s authored objects driven chunk by chunk, so that a
    modal operator keeps Blender responsive: ``step`` writes the next chunk (its
    ``chunk_size`` entries, well under a second on the built-in samples), ``finish``
    assembles the bank and writes its report. Stopping between steps leaves a folder
    that an export with "Resume" continues to the same bytes (core/bank/folder.py); the
    folder is held (folder.exporting) until ``stop``, so another export into it, in
    this Blender or another process, is refused. InputError for what cannot make a bank,
    or a Real database that cannot be read, before anything is written."""

    def __init__(self, scene: bpy.types.Scene, settings, checkpoint: str = ""):
        if not settings.output:
            raise InputError("Bank", "no output folder chosen")
        objects, incomplete = scene_bank_objects(scene)
        config = bank_config(settings, checkpoint)
        source = bpy.data.filepath or scene.name
        checked = checked_objects(objects, incomplete, settings.skip_incomplete, source)
        self.real = real_database(settings)
        self.reference = real_reference(self.real[0], config.to_dict(), convention=self.real[1]) if self.real else None
        self.out = Path(field_path(settings.output))
        self.existed = self.out.exists()
        read = [bpy.data.filepath, settings.config_file and field_path(settings.config_file),
                self.real and self.real[0]]
        with ExitStack() as held:  # the folder stays held until ``stop``
            held.enter_context(exporting(self.out))
            self.plan = export.plan_bank(checked, config, self.out, resume=settings.existing == "RESUME",
                                         overwrite=settings.existing == "OVERWRITE", inputs=read)
            self._held = held.pop_all()
        self.total, self.done = self.plan.pending_entries, 0
        self._chunks = export.run_plan(self.plan, workers=1)

    def step(self) -> bool:
        """Write the next chunk; False when every chunk is written."""
        chunk = next(self._chunks, None)
        if chunk is None:
            return False
        self.done += chunk.entries
        return True

    def finish(self) -> Path:
        """Assemble the info pickles and the manifest (kept as ``manifest``), write the
        report (write_bank_report); its path."""
        self.manifest = export.assemble(self.out, existed=self.existed)
        return write_bank_report(self.out, self.real, self.reference)

    def summary(self) -> str:
        """What the finished bank holds, as export_bank.py prints it: entries kept and
        poses dropped below the minimum points."""
        return f"{export.kept_summary(self.manifest)}; wrote {self.out}"

    def stop(self) -> None:
        """End the run (finished, stopped or failed) and let go of its folder."""
        self._chunks.close()
        self._held.close()


PREVIEW_COLLECTION = "PGT Bank Preview"


def preview_bank(scene: bpy.types.Scene, folder, count: int) -> tuple:
    """Load ``count`` entries of the bank in ``folder``, spread evenly over it, as point
    objects (the points at their place in the sensor frame, intensity as an attribute and
    as color) each with its box (a cube empty: centre, dims, heading), into the "PGT Bank
    Preview" collection, replacing an earlier preview once the new one is built
    (objects.replace_collection). Returns the collection and the point objects."""
    folder = Path(folder)
    manifest = read_manifest(folder)
    fmt = manifest["config"]["formats"][0]
    pickle = folder / manifest["info_pickles"][fmt]
    infos = [info for entries in load_infos(pickle).values() for info in entries]
    if not infos:
        raise InputError(folder, "the bank has no entries")
    chosen = [infos[i] for i in np.unique(np.linspace(0, len(infos) - 1, min(count, len(infos))).round().astype(int))]
    dataset = manifest["config"]["dataset"]
    root, paths = info_path_root(pickle), []
    for info in chosen:  # relative to the data root when the bank has one; never outside the bank
        path = (root / info["path"]).resolve()
        if not path.is_relative_to(folder.resolve()):
            raise InputError(pickle, f"entry path {info['path']!r} leads outside the bank: the pickle is damaged")
        paths.append(path)
    entries = [(info, read_float32_rows(path, len(BIN_COLUMNS[dataset]), rows=int(info["num_points_in_gt"])))
               for info, path in zip(chosen, paths)]
    made = []
    try:
        for info, rows in entries:
            box = np.asarray(info["box3d_lidar"], np.float64)
            origin = box[:3] - ([0.0, 0.0, box[5] / 2] if fmt == "mmdet3d" else 0.0)  # where the file's points start
            returns = np.zeros(len(rows), [("x", "f8"), ("y", "f8"), ("z", "f8"), ("intensity", "f4")])
            for axis, name in enumerate("xyz"):
                returns[name] = rows[:, axis] + origin[axis]
            returns["intensity"] = rows[:, 3]
            name = Path(info["path"]).stem
            points_object(name, returns, ramp(np.clip(rows[:, 3] / INTENSITY_MAX[dataset], 0.0, 1.0)), made)
            box_empty(name, box, made)
    except BaseException:
        remove_datablocks(made)
        raise
    shown = [obj for obj in made if isinstance(obj, bpy.types.Object)]
    return replace_collection(scene, PREVIEW_COLLECTION, shown), [obj for obj in shown if obj.type == "MESH"]
