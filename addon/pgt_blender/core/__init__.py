"""The pgt_blender core: numpy in, numpy out, never imports bpy.

Pipeline steps, each a module or sub-package, data flowing one way:

1. ``importing``  -- reconstruction files -> :class:`~.reconstruction.Reconstruction`
2. ``authoring``  -- up axis, heading and size: the object frame and its box
3. ``scan``       -- rotating-LiDAR returns of an object (BVH or Embree ray casts)
4. ``intensity``  -- learned LiDAR intensity from real objects
5. ``bank``       -- the object bank the detectors' samplers load, its report and mixes
6. ``placement``  -- bank entries into real scenes: ground, map, collision, occlusion, bandit

``quality`` scores a bank against a real database; ``capture`` turns a capture's
output into a clean coloured object before step 2.

``samples`` builds the parametric vehicles and synthetic reconstructions used as
demo input and as ground truth for tests.
"""
