"""Step 5: the pseudo-LiDAR object bank: authored objects scanned over a grid of poses
and written as detector ground-truth databases (OpenPCDet, mmdetection3d)."""
