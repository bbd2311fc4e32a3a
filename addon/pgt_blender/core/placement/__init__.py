"""Step 6: placing bank entries into real scenes (the paper's §3.4 and its supplement's
ray tracing, distance filtering and bandit placement). numpy in, numpy out; no bpy.

Frames and units: everything is in the scan's own LiDAR frame (the dataset's sensor
frame: KITTI x forward, y left; nuScenes x right, y forward; z up, metres, the sensor
at the origin, the ground near z = -mounting height). Boxes are OpenPCDet's centre
boxes ``x y z dx dy dz heading [vx vy]`` (heading from +x counter-clockwise). Maps
come in the world frame and are turned into the sensor frame with the scan's
``lidar_to_world`` pose (4 x 4).

Modules, data flowing one way:

- ``scenes``      a real scene: points, boxes, names, pose (KITTI files, info pickles)
- ``ground``      ground height and normal under any (x, y), fitted to the scan
- ``maps``        layers an object may stand on, rasterised around the sensor
- ``feasibility`` where a class may stand: map where the scan sees little, ground elsewhere
- ``entries``     the database's entries by range, turned about the sensor axis and lifted
- ``collision``   bird's-eye box overlap and scene points inside a box
- ``occlusion``   range-view ray tracing between scene and inserted points
- ``bandit``      Thompson sampling of the cells objects go to
- ``place``       the whole step: candidates, checks, the augmented scene
"""
