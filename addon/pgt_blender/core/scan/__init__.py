"""Step 3: simulated rotating-LiDAR scans of an authored object.

sensors.py (beam tables as data) -> targets.py (one BVH per object: mesh or surfels)
-> raycast.py (windowed ray cast of a placed object) | range_view.py (the paper's
projection of dense points) -> sweeps.py (moving objects over several sweeps)
-> returns.py (the rows, the files). physical_intensity.py is the default intensity.
"""
