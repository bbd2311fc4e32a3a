"""Step 3: simulated rotating-LiDAR scans of an authored object.

sensors.py (beam tables as data) -> targets.py (one ray target per object: mesh or surfels
built for Embree or Blender's BVH, or the splats themselves)
-> raycast.py (windowed ray cast of a placed object) | range_view.py (the paper's
projection of dense points) -> sweeps.py (moving objects over several sweeps)
-> returns.py (the rows, the files). physical_intensity.py is the default intensity.
"""
