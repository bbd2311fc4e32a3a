"""Object classes and their dataset sizes (metres), from REFERENCE.md section 3.

Sizes are (length, width, height): length along the heading (+x), width along +y,
height along +z. Class names are the datasets' own, lower case.
"""

# nuScenes mean and std.
NUSCENES_SIZES = {
    "car": ((4.62, 1.96, 1.73), (0.46, 0.16, 0.24)),
    "truck": ((6.94, 2.52, 2.84), (2.11, 0.45, 0.84)),
    "construction_vehicle": ((6.68, 2.85, 3.21), (3.23, 1.07, 0.93)),
    "bus": ((11.22, 2.95, 3.50), (2.06, 0.33, 0.49)),
    "trailer": ((12.56, 2.94, 3.89), (4.50, 0.54, 0.77)),
    "motorcycle": ((2.11, 0.78, 1.46), (0.33, 0.17, 0.29)),
    "bicycle": ((1.70, 0.61, 1.29), (0.26, 0.16, 0.35)),
    "pedestrian": ((0.73, 0.67, 1.77), (0.19, 0.14, 0.19)),
    "traffic_cone": ((0.41, 0.41, 1.08), (0.14, 0.13, 0.27)),
    "barrier": ((0.50, 2.52, 0.99), (0.17, 0.62, 0.15)),
}

# Mean sizes by dataset (KITTI car, pedestrian, cyclist and Lyft: OpenPCDet's anchor
# sizes; KITTI truck and van: the means of KITTI's training labels as tabulated by
# Frustum PointNets, g_type_mean_size; no std published).
CLASS_SIZES = {
    "nuscenes": {name: mean for name, (mean, _) in NUSCENES_SIZES.items()},
    "kitti": {"car": (3.9, 1.6, 1.56), "pedestrian": (0.8, 0.6, 1.73), "cyclist": (1.76, 0.6, 1.73),
              "truck": (10.14, 2.59, 3.25), "van": (5.07, 1.90, 2.21)},
    "lyft": {
        "car": (4.75, 1.92, 1.71), "truck": (10.24, 2.84, 3.44), "bus": (12.70, 2.92, 3.42),
        "emergency_vehicle": (6.52, 2.42, 2.34), "other_vehicle": (8.17, 2.75, 3.20),
        "motorcycle": (2.35, 0.96, 1.59), "bicycle": (1.76, 0.63, 1.44),
        "pedestrian": (0.80, 0.76, 1.76), "animal": (0.73, 0.35, 0.5),
    },
}
DATASETS = tuple(CLASS_SIZES)

# The paper's minority classes: the ones pgt_blender builds banks for.
MINORITY_CLASSES = ("truck", "bus", "trailer", "construction_vehicle", "motorcycle", "bicycle")
