"""Step 4: LiDAR intensity for pseudo objects, learned without paired data (PGT-Aug's
CycleGAN estimator with the group intensity loss).

objects.py (real LiDAR objects and scanned RGB objects, fixed-size sets) -> the model,
its training and the estimator the scanner and bank export call. Without torch or a
checkpoint, scans keep core.scan.physical_intensity.
"""
