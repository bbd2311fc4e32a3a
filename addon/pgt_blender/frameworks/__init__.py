"""Adapters that run the placement (core/placement) inside the detector frameworks'
training pipelines: ``openpcdet`` (a DATA_AUGMENTOR entry) and ``mmdet3d`` (a
transform loaded with ``custom_imports``). Each is imported only by its framework's
training code, never by Blender or the rest of the package."""
