"""The pgt_blender core: numpy in, numpy out, never imports bpy.

Pipeline steps, each a module or sub-package, data flowing one way:

1. ``importing``  -- reconstruction files -> :class:`~.reconstruction.Reconstruction`
2. authoring, 3. scanning, 4. intensity, 5. bank export, 6. placement (later issues)

``samples`` builds the parametric vehicles and synthetic reconstructions used as
demo input and as ground truth for tests.
"""
