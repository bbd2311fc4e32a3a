"""The PGT sidebar tab in the 3D viewport and the File > Import entries."""

import bpy

from .operators import IMPORTERS


def short_label(operator) -> str:
    return operator.bl_label.replace("Import ", "")


class VIEW3D_PT_pgt_import(bpy.types.Panel):
    bl_label = "Import"
    bl_idname = "VIEW3D_PT_pgt_import"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "PGT"

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
        box.label(text=f"{obj.name}: {settings.bl_rna.properties['source_kind'].enum_items[settings.source_kind].name}",
                  icon="OUTLINER_OB_POINTCLOUD" if obj.type == "MESH" and not obj.data.polygons else "MESH_DATA")
        if obj.type == "MESH":
            box.label(text=f"{len(obj.data.vertices):,} points, {len(obj.data.polygons):,} faces, "
                           f"{sum(c.type == 'CAMERA' for c in obj.children)} cameras")
        box.prop(settings, "source_path", text="")
        box.label(text=f"sha256 {settings.source_sha256[:16]}")
        box.prop(settings, "class_name")


def menu_import(self, context):
    for operator in IMPORTERS:
        self.layout.operator(operator.bl_idname, text=f"PGT: {short_label(operator)}")


classes = (VIEW3D_PT_pgt_import,)


def register():
    bpy.types.TOPBAR_MT_file_import.append(menu_import)


def unregister():
    bpy.types.TOPBAR_MT_file_import.remove(menu_import)
