"""The thin Blender layer: properties, operators, panels. Everything heavy is in core."""

import bpy

from . import operators, properties, ui

classes = properties.classes + operators.classes + ui.classes


def register():
    for cls in classes:
        bpy.utils.register_class(cls)
    properties.register()
    ui.register()


def unregister():
    ui.unregister()
    properties.unregister()
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
