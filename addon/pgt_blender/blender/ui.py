"""The PGT sidebar tab in the 3D viewport and the File > Import entries."""

import bpy

from . import authoring, properties, scanning
from .operators import IMPORTERS


def short_label(operator) -> str:
    return operator.bl_label.replace("Import ", "")


class _PGTPanel:
    """A section of the PGT tab in the 3D viewport's sidebar."""

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "PGT"


class VIEW3D_PT_pgt_import(_PGTPanel, bpy.types.Panel):
    bl_label = "Import"
    bl_idname = "VIEW3D_PT_pgt_import"

    def draw(self, context):
        layout = self.layout
        column = layout.column(align=True)
        for operator in IMPORTERS:
            column.operator(operator.bl_idname, text=short_label(operator), icon="IMPORT")
        layout.operator("object.pgt_add_sample", icon="AUTO")
        obj = context.active_object
        if obj is None or obj.pgt.source_kind == "none":
            layout.label(text="Active object: not a reconstruction")
            return
        box = layout.box()
        settings = obj.pgt
        kind = settings.bl_rna.properties["source_kind"].enum_items.get(settings.source_kind)
        box.label(text=f"{obj.name}: {kind.name if kind else 'a kind this version does not know'}",
                  icon="OUTLINER_OB_POINTCLOUD" if obj.type == "MESH" and not obj.data.polygons else "MESH_DATA")
        if obj.type == "MESH":
            box.label(text=f"{len(obj.data.vertices):,} points, {len(obj.data.polygons):,} faces, "
                           f"{sum(c.type == 'CAMERA' for c in obj.children)} cameras")
        # Read-only: the source is what was imported, and the class is set by Set Size
        # (with the size the bank relies on), never typed here.
        box.label(text=settings.source_path, icon="FILE")
        box.label(text=f"sha256 {settings.source_sha256[:16]}")
        box.label(text=f"Class: {settings.class_name} ({properties.label(settings.dataset)})" if settings.class_name
                  else "Class: set in the Size panel")


def reconstruction(context):
    """The active object when it is an imported reconstruction, else None."""
    obj = context.active_object
    return obj if authoring.is_reconstruction(obj) else None


def status_text(obj) -> str:
    """One line: what is done and what is left for ``obj`` (a size without a class: the
    bank leaves it out), or what is wrong with its step record."""
    problem = authoring.record_problem(obj)
    if problem:
        return problem
    done = authoring.status(obj)
    parts = ["aligned" if done["aligned"] else "not aligned",
             f"heading: {done['heading']}" if done["heading"] else "heading unset",
             f"size: {done['size']}{'' if obj.pgt.class_name else ', no class'}" if done["size"] else "size unset"]
    return " | ".join(parts)


def status_icon(obj, not_done: str) -> str:
    """CHECKMARK when every step of ``obj`` is done and it has a class (it can go into a
    bank), ERROR for a damaged step record, else ``not_done``."""
    if authoring.record_problem(obj):
        return "ERROR"
    return "CHECKMARK" if all(authoring.status(obj).values()) and obj.pgt.class_name else not_done


def refinement_text(obj) -> str:
    """What the last alignment's refinement did: the tilt it removed from the starting up
    (the prior, or without one the PCA minor axis, which it names; over 45 degrees that
    axis was not up at all, a bus's width, and the planes gave up) and the surface noise
    (source units). Not refined: why, when the step record says (older records say only
    whether)."""
    align = next((step for step in reversed(authoring.steps(obj)) if step["step"] == "align"), {})
    if not align.get("refined"):
        reasons = {True: ": too little flat surface to refine to", False: " (Refine was off)"}
        return "Not refined to the surface" + reasons.get(align.get("refine"), "")
    tilt = align["tilt_deg"]
    if align["up_from"] != "planes":
        turned = f"tilt removed {tilt:.2f}°"
    elif tilt <= 45:
        turned = f"tilt removed {tilt:.2f}° from the PCA minor axis"
    else:
        turned = f"up from the surface planes (the PCA minor axis lay {tilt:.1f}° off)"
    return f"Refined: {turned}, noise {align['noise']:.3g} (source units)"


class _AuthoringPanel(_PGTPanel):
    @classmethod
    def poll(cls, context):
        return reconstruction(context) is not None


class VIEW3D_PT_pgt_align(_AuthoringPanel, bpy.types.Panel):
    bl_label = "Align"
    bl_idname = "VIEW3D_PT_pgt_align"

    def draw(self, context):
        obj = reconstruction(context)
        layout = self.layout
        layout.label(text=status_text(obj), icon=status_icon(obj, "INFO"))
        layout.prop(context.scene.pgt_authoring, "up")
        layout.prop(context.scene.pgt_authoring, "refine")
        layout.operator("object.pgt_align", icon="ORIENTATION_GIMBAL")
        if not authoring.record_problem(obj) and authoring.status(obj)["aligned"]:
            layout.label(text="Box " + " x ".join(f"{d:.3g}" for d in obj.pgt.dims))
            layout.label(text=refinement_text(obj))


def _class_field(layout, settings, needed: bool):
    """The Class field and what is wrong with it: a class the dataset lacks was cleared
    (the note says so, in every section showing the field); none chosen, where ``needed``."""
    layout.prop(settings, "class_name", icon="VIEWZOOM")
    problem = properties.class_problem(settings)
    if settings.class_note and not settings.class_name:
        layout.label(text=settings.class_note, icon="ERROR")
    elif problem and needed:
        layout.label(text=problem[:1].upper() + problem[1:], icon="ERROR")


class VIEW3D_PT_pgt_heading(_AuthoringPanel, bpy.types.Panel):
    bl_label = "Heading"
    bl_idname = "VIEW3D_PT_pgt_heading"

    def draw(self, context):
        layout, settings = self.layout, context.scene.pgt_authoring
        row = layout.row(align=True)
        row.operator("object.pgt_turn", text="Flip 180", icon="LOOP_BACK").turns = 2
        row.operator("object.pgt_turn", text="+90", icon="LOOP_FORWARDS").turns = 1
        row.operator("object.pgt_turn", text="-90", icon="LOOP_BACK").turns = -1
        layout.operator("object.pgt_front_from_cursor", icon="PIVOT_CURSOR")
        layout.prop(settings, "heading_method")
        if settings.heading_method == "classifier":
            layout.prop(settings, "checkpoint")
        _class_field(layout, settings, needed=False)  # a trailer is headed by its running gear
        layout.operator("object.pgt_auto_heading", icon="AUTO")


class VIEW3D_PT_pgt_size(_AuthoringPanel, bpy.types.Panel):
    bl_label = "Size"
    bl_idname = "VIEW3D_PT_pgt_size"

    def draw(self, context):
        layout, settings = self.layout, context.scene.pgt_authoring
        layout.prop(settings, "size_mode", expand=True)
        layout.prop(settings, "dataset")  # every mode records the class, which the bank needs
        _class_field(layout, settings, needed=True)
        if settings.size_mode == "class":
            layout.prop(settings, "seed")
        elif settings.size_mode == "exact":
            layout.prop(settings, "exact_dims")
        if settings.size_mode != "keep":
            layout.prop(settings, "uniform")
        layout.operator("object.pgt_set_size", icon="FULLSCREEN_ENTER")


class VIEW3D_PT_pgt_scan(_PGTPanel, bpy.types.Panel):
    bl_label = "Scan"
    bl_idname = "VIEW3D_PT_pgt_scan"

    def draw(self, context):
        layout, settings = self.layout, context.scene.pgt_scan
        layout.prop(settings, "sensor")
        if settings.sensor == "CUSTOM":
            layout.prop(settings, "sensor_file")
        column = layout.column(align=True)
        for name in ("distance", "azimuth", "heading"):
            column.prop(settings, name)
        layout.prop(settings, "color_by", expand=True)
        obj = context.active_object
        if obj is not None and obj.type == "MESH" and not obj.data.polygons and not scanning.is_splat(obj.data):
            layout.prop(settings, "surfel_scale")  # a splat scans as Gaussians of its own scales
        layout.operator("object.pgt_scan", icon="LIGHT_SPOT")
        if settings.stats:  # named: a later scan without returns leaves it, and it shows beside any object
            layout.label(text=f"{settings.stats_of}: {settings.stats}", icon="INFO")
        layout.operator("object.pgt_apply_intensity", icon="SHADING_TEXTURE")


class VIEW3D_PT_pgt_objects(_PGTPanel, bpy.types.Panel):
    """Every reconstruction in the scene with what is left to do."""

    bl_label = "Objects"
    bl_idname = "VIEW3D_PT_pgt_objects"

    def draw(self, context):
        layout = self.layout
        layout.operator("object.pgt_author_selected", icon="MODIFIER")
        column = layout.column(align=True)
        for obj in context.scene.objects:
            if authoring.is_reconstruction(obj):
                row = column.row()
                row.label(text=obj.name, icon=status_icon(obj, "DOT"))
                row.label(text=status_text(obj))


class VIEW3D_PT_pgt_bank(_PGTPanel, bpy.types.Panel):
    """The bank of the scene's authored objects: settings, export in the background, preview."""

    bl_label = "Bank"
    bl_idname = "VIEW3D_PT_pgt_bank"

    def draw(self, context):
        layout, settings = self.layout, context.scene.pgt_bank
        layout.prop(settings, "config_file")
        fields = layout.column()
        fields.enabled = not settings.config_file  # a config file replaces the fields
        for name in ("dataset", "sensor", "sweeps", "heading_step", "grid_step", "engine", "seed", "chunk_size"):
            fields.prop(settings, name)
        row = fields.row(align=True)
        row.prop(settings, "openpcdet", toggle=True)
        row.prop(settings, "mmdet3d", toggle=True)
        layout.operator("scene.pgt_save_bank_config", icon="FILE_TICK")
        layout.prop(settings, "output")
        layout.prop(settings, "existing")
        layout.prop(settings, "skip_incomplete")
        layout.prop(settings, "real_database")
        real = layout.row()  # only read with a database set
        real.enabled = bool(settings.real_database)
        real.prop(settings, "real_convention")
        if settings.running:
            layout.progress(factor=settings.progress, text=f"{100 * settings.progress:.0f} %")
            layout.operator("scene.pgt_stop_bank", icon="CANCEL")
        else:
            layout.operator("scene.pgt_export_bank", icon="EXPORT")
        if settings.status:
            layout.label(text=settings.status, icon="INFO")
        row = layout.row(align=True)
        row.operator("scene.pgt_open_bank_report", icon="TEXT")
        row.operator("scene.pgt_preview_bank", icon="HIDE_OFF")
        layout.prop(settings, "preview_count")


def menu_import(self, context):
    for operator in IMPORTERS:
        self.layout.operator(operator.bl_idname, text=f"PGT: {short_label(operator)}")


classes = (VIEW3D_PT_pgt_import, VIEW3D_PT_pgt_align, VIEW3D_PT_pgt_heading, VIEW3D_PT_pgt_size,
           VIEW3D_PT_pgt_scan, VIEW3D_PT_pgt_objects, VIEW3D_PT_pgt_bank)


def register():
    bpy.types.TOPBAR_MT_file_import.append(menu_import)


def unregister():
    bpy.types.TOPBAR_MT_file_import.remove(menu_import)
