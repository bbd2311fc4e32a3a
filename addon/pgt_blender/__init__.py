"""pgt_blender: pseudo-LiDAR object banks from 3D reconstructions (PGT-Aug).

Blender loads this package as ``bl_ext.<repo>.pgt_blender``; tests and headless
scripts import it as ``pgt_blender``. ``core`` never imports bpy, so importing the
package outside Blender is safe; the Blender layer loads only on ``register()``.
"""


def register():
    from .blender import register as register_blender

    register_blender()


def unregister():
    from .blender import unregister as unregister_blender

    unregister_blender()
