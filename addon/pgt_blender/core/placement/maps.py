"""Maps: the layers an object may stand on (road, lane, car park, sidewalk...),
rasterised around the sensor.

The raster is square, axis-aligned with the sensor frame and centred on the sensor:
``radius`` m out (the paper: 51.2 m) at ``resolution`` m per pixel (the paper: 0.128 m,
so 800 x 800 pixels). Pixel (row i, column j) covers x in ``-radius + [j, j + 1) *
resolution`` and y in ``-radius + [i, i + 1) * resolution``. Outside it nothing is
allowed.

Two sources, both in the world frame, turned into the sensor frame by the scan's
``lidar_to_world`` (4 x 4):

- **polygons** (``read_polygons``): a GeoJSON FeatureCollection whose features are
  Polygons or MultiPolygons with a ``layer`` property, or a JSON list of
  ``{"layer": name, "polygon": [[x, y], ...]}``; coordinates in metres. Holes (later
  rings of a GeoJSON polygon) are cut out (even-odd rule);
- **a semantic image** (``map_from_image``, the Lyft-style raster): an (H, W) label
  or (H, W, 3) colour image, a ``legend`` {layer: label value or [r, g, b]}, and its
  pose ``ImagePose``: the world x, y of the image's top-left corner, metres per pixel
  and the yaw of its columns' axis from world +x (rows run the other way, towards
  -y when yaw is 0: Lyft's MapMask is x0 = 0, y0 = H * resolution, yaw 0).

Which layers a class may stand on: ``CLASS_LAYERS`` by default (configurable).
"""

import json
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..files import TEXT_LIMIT, regular_file

RADIUS = 51.2  # m: the paper's map extent around the ego
RESOLUTION = 0.128  # m per pixel: the paper's

# Layer names of the nuScenes map expansion and the usual synonyms in other maps.
_ROAD = ("drivable_area", "road", "road_segment", "road_block", "lane", "intersection")
_PARKING = ("carpark_area", "car_park", "parking")
_BIKE = ("bike_lane", "cycle_lane", "cycleway")
_WALK = ("walkway", "sidewalk", "ped_crossing", "crosswalk")
_VEHICLES = ("car", "truck", "bus", "trailer", "construction_vehicle", "emergency_vehicle", "other_vehicle", "van",
             "tram", "misc")
_TWO_WHEELERS = ("bicycle", "motorcycle", "cyclist")
_ON_FOOT = ("pedestrian", "person_sitting", "animal")
_ROADSIDE = ("traffic_cone", "barrier")
# class (lower case) -> the layers it may stand on: vehicles on roads and car parks,
# two-wheelers also on bike lanes, pedestrians on walkways, crossings and car parks,
# cones and barriers on roads and walkways.
CLASS_LAYERS = {
    **{name: _ROAD + _PARKING for name in _VEHICLES},
    **{name: _ROAD + _PARKING + _BIKE for name in _TWO_WHEELERS},
    **{name: _WALK + _PARKING for name in _ON_FOOT},
    **{name: _ROAD + _WALK for name in _ROADSIDE},
}


@dataclass
class MapRaster:
    """``masks`` (L, H, W) bool, one per layer of ``layers``, in the sensor frame (the
    module docstring's pixel grid)."""

    layers: tuple
    masks: np.ndarray
    resolution: float
    radius: float

    def pixels(self, xy: np.ndarray) -> tuple:
        """(row, column) (N,) int64 of (N, 2) sensor-frame points, and (N,) bool inside the raster."""
        return square_cells(xy, self.radius, self.resolution, self.masks.shape[1])

    def layer_mask(self, layers) -> np.ndarray:
        """(H, W) bool: pixels on any of ``layers`` (names the map lacks add nothing)."""
        chosen = [i for i, name in enumerate(self.layers) if name in set(layers)]
        return self.masks[chosen].any(axis=0) if chosen else np.zeros(self.masks.shape[1:], bool)

    def allows(self, layers, xy: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """(N,) bool: each (N, 2) point stands on one of ``layers`` (or on ``mask``, that
        layer_mask precomputed)."""
        mask = self.layer_mask(layers) if mask is None else mask
        rows, columns, inside = self.pixels(xy)
        return inside & mask[rows, columns]


def square_cells(xy: np.ndarray, radius: float, cell: float, size: int) -> tuple:
    """(row, column) (N,) int64 and (N,) bool inside, of (N, 2) sensor-frame points in a
    square grid of ``size`` x ``size`` cells of ``cell`` m from -``radius`` (row = y,
    column = x); outside points get the nearest border cell."""
    index = np.floor((np.asarray(xy, np.float64)[:, :2] + radius) / cell).astype(np.int64)
    inside = ((index >= 0) & (index < size)).all(axis=1)
    index = np.clip(index, 0, size - 1)
    return index[:, 1], index[:, 0], inside


def pixel_centres(radius: float = RADIUS, resolution: float = RESOLUTION) -> tuple:
    """(size,) x and y of the pixel centres of a raster (the module docstring's grid)."""
    size = int(round(2 * radius / resolution))
    centres = -radius + (np.arange(size) + 0.5) * resolution
    return centres, centres


def class_layers(class_name: str, table: dict | None = None) -> tuple:
    """The layers ``class_name`` may stand on: ``table`` (class -> layers) over CLASS_LAYERS,
    names compared in lower case; () for a class neither knows."""
    merged = {**CLASS_LAYERS, **{name.lower(): tuple(layers) for name, layers in (table or {}).items()}}
    return tuple(merged.get(class_name.lower(), ()))


def checked_legend(legend, channels: int, source) -> dict:
    """{layer: (channels,) int64 key} of a map legend {layer: label or [r, g, b]} for an
    8-bit image of ``channels`` (1 or 3); InputError naming ``source`` otherwise."""
    if not isinstance(legend, dict) or not legend:
        raise InputError(source, "expected a JSON object {layer: label or [r, g, b]}")
    keys = {}
    for layer, value in legend.items():
        key = value if isinstance(value, list) else [value]
        if len(key) != channels or not all(type(part) is int and 0 <= part <= 255 for part in key):
            raise InputError(source, f"legend entry {layer!r} is {value!r}: expected " +
                             ("a label 0-255 for a one-channel image" if channels == 1 else
                              "[r, g, b] of 0-255 for a colour image"))
        keys[layer] = np.array(key, np.int64)
    return keys


def checked_class_layers(table, source) -> dict:
    """{class: (layer, ...)} of a JSON {class: [layer, ...]}; InputError naming ``source``
    otherwise (a bare string would be read as its letters)."""
    if not isinstance(table, dict):
        raise InputError(source, "expected a JSON object {class: [layer, ...]}")
    for name, layers in table.items():
        if not isinstance(layers, list) or not all(isinstance(layer, str) for layer in layers):
            raise InputError(source, f"class {name!r} has {layers!r}: expected a list of layer names")
    return {name: tuple(layers) for name, layers in table.items()}


def _mapping(value) -> dict:
    """``value`` when it is a JSON object, else an empty one (a GeoJSON member of another type)."""
    return value if isinstance(value, dict) else {}


def read_polygons(path) -> list:
    """[(layer, [ring (K, 2) float64, ...]), ...] of a GeoJSON FeatureCollection or a JSON
    list of {"layer", "polygon"} (the module docstring); InputError naming ``path``."""
    path = regular_file(path, TEXT_LIMIT)
    try:
        data = json.loads(path.read_text())
    except OSError as error:
        raise InputError(path, f"cannot read the file ({error.strerror or error})") from None
    except (ValueError, RecursionError) as error:
        raise InputError(path, f"not JSON ({error})") from None
    if isinstance(data, dict) and data.get("type") == "FeatureCollection":
        shapes = []
        if not isinstance(data.get("features", []), list):
            raise InputError(path, "features must be a list")
        for index, feature in enumerate(data.get("features", [])):
            feature = _mapping(feature)
            geometry = _mapping(feature.get("geometry"))
            layer = _mapping(feature.get("properties")).get("layer")
            if not isinstance(layer, str):
                raise InputError(path, f"feature {index} has no 'layer' property naming its map layer")
            if geometry.get("type") == "Polygon":
                polygons = [geometry.get("coordinates")]
            elif geometry.get("type") == "MultiPolygon":
                polygons = geometry.get("coordinates")
            else:
                raise InputError(path, f"feature {index} is a {geometry.get('type')!r}, not a Polygon or MultiPolygon")
            shapes += [(layer, _rings(path, f"feature {index}", polygon)) for polygon in polygons or []]
        return shapes
    if isinstance(data, list):
        shapes = []
        for index, item in enumerate(data):
            if not (isinstance(item, dict) and isinstance(item.get("layer"), str) and "polygon" in item):
                raise InputError(path, f"item {index} is not {{\"layer\": name, \"polygon\": [[x, y], ...]}}")
            shapes.append((item["layer"], _rings(path, f"item {index}", [item["polygon"]])))
        return shapes
    raise InputError(path, "not a GeoJSON FeatureCollection or a list of {\"layer\", \"polygon\"}")


def _rings(path, where: str, rings) -> list:
    checked = []
    for ring in rings or []:
        try:
            ring = np.asarray(ring, np.float64)
        except (TypeError, ValueError):
            raise InputError(path, f"{where}: a ring is not a list of [x, y] numbers") from None
        if ring.ndim != 2 or ring.shape[1] < 2 or len(ring) < 3 or not np.isfinite(ring).all():
            raise InputError(path, f"{where}: a ring needs 3 or more finite [x, y] points")
        checked.append(ring[:, :2])
    if not checked:
        raise InputError(path, f"{where}: a polygon without rings")
    return checked


def map_from_polygons(shapes: list, lidar_to_world: np.ndarray, radius: float = RADIUS,
                      resolution: float = RESOLUTION) -> MapRaster:
    """The MapRaster of ``shapes`` [(layer, [ring (K, 2) world x, y])] seen from a sensor at
    ``lidar_to_world`` (4, 4): each polygon filled by the even-odd rule over its rings."""
    world_to_lidar = np.linalg.inv(np.asarray(lidar_to_world, np.float64))
    layers = tuple(sorted({layer for layer, _ in shapes}))
    size = int(round(2 * radius / resolution))
    masks = np.zeros((len(layers), size, size), bool)
    for layer, rings in shapes:
        local = [(np.column_stack([ring, np.zeros(len(ring)), np.ones(len(ring))]) @ world_to_lidar.T)[:, :2]
                 for ring in rings]
        masks[layers.index(layer)] |= _fill(local, radius, resolution, size)
    return MapRaster(layers, masks, resolution, radius)


def _fill(rings: list, radius: float, resolution: float, size: int) -> np.ndarray:
    """(size, size) bool: pixel centres inside the rings (sensor-frame (K, 2) each) by the
    even-odd rule, scanline by scanline (vectorised over rows and edges)."""
    starts = np.concatenate([ring for ring in rings])
    ends = np.concatenate([np.roll(ring, -1, axis=0) for ring in rings])
    y = -radius + (np.arange(size) + 0.5) * resolution
    low, high = np.minimum(starts[:, 1], ends[:, 1]), np.maximum(starts[:, 1], ends[:, 1])
    crosses = (y[:, None] >= low) & (y[:, None] < high)  # (rows, edges), half-open: vertices count once
    rows, edges = np.nonzero(crosses)
    t = (y[rows] - starts[edges, 1]) / (ends[edges, 1] - starts[edges, 1])
    x = starts[edges, 0] + t * (ends[edges, 0] - starts[edges, 0])
    # the number of crossings left of each pixel centre, per row: odd is inside
    column = np.clip(np.ceil((x + radius) / resolution - 0.5), 0, size).astype(np.int64)
    toggles = np.zeros((size, size + 1), np.int64)
    np.add.at(toggles, (rows, column), 1)
    return (np.cumsum(toggles, axis=1)[:, :size] % 2).astype(bool)


@dataclass(frozen=True)
class ImagePose:
    """Where a map image lies in the world: ``x0``, ``y0`` world metres of its top-left
    corner, ``resolution`` metres per pixel, ``yaw_deg`` of its columns' axis from world +x."""

    x0: float
    y0: float
    resolution: float
    yaw_deg: float = 0.0


def map_from_image(image: np.ndarray, legend: dict, pose: ImagePose, lidar_to_world: np.ndarray,
                   radius: float = RADIUS, resolution: float = RESOLUTION, source="map",
                   legend_source="legend") -> MapRaster:
    """The MapRaster of a semantic ``image`` (H, W) 8-bit labels or (H, W, >= 3) 8-bit
    colours, its ``legend`` {layer: label or [r, g, b]} and ``pose``, seen from a sensor at
    ``lidar_to_world``: each raster pixel takes the image pixel under its centre. InputError
    naming ``source`` when the image does not cover the raster's circle of ``radius``, or
    ``legend_source`` when the legend does not fit the image (checked_legend)."""
    image = np.asarray(image)
    if pose.resolution <= 0:
        raise InputError(source, f"the map's resolution must be > 0 m per pixel, got {pose.resolution}")
    xs, ys = pixel_centres(radius, resolution)
    grid_x, grid_y = np.meshgrid(xs, ys)
    local = np.column_stack([grid_x.ravel(), grid_y.ravel(), np.zeros(grid_x.size), np.ones(grid_x.size)])
    world = local @ np.asarray(lidar_to_world, np.float64).T
    yaw = np.radians(pose.yaw_deg)
    dx, dy = world[:, 0] - pose.x0, world[:, 1] - pose.y0
    # In floats first: a pose far off (or a tiny resolution) gives indexes beyond int64, or inf.
    with np.errstate(over="ignore", invalid="ignore"):
        columns = np.floor((dx * np.cos(yaw) + dy * np.sin(yaw)) / pose.resolution)
        rows = np.floor(-(-dx * np.sin(yaw) + dy * np.cos(yaw)) / pose.resolution)
    inside = (rows >= 0) & (rows < image.shape[0]) & (columns >= 0) & (columns < image.shape[1])
    rows, columns = np.where(inside, rows, 0).astype(np.int64), np.where(inside, columns, 0).astype(np.int64)
    within = np.hypot(grid_x.ravel(), grid_y.ravel()) <= radius
    if not inside[within].all():
        raise InputError(source, f"the map image does not cover the scene: {int((within & ~inside).sum())} map "
                                 f"pixels within {radius:g} m of the sensor fall outside it (check --map-pose)")
    values = image[rows, columns]
    size = len(xs)
    keys = checked_legend(legend, 1 if image.ndim == 2 else 3, legend_source)
    layers = tuple(sorted(keys))
    masks = np.zeros((len(layers), size, size), bool)
    for index, layer in enumerate(layers):
        key = keys[layer]
        hit = values == key[0] if image.ndim == 2 else (values[:, :3] == key).all(axis=1)
        masks[index] = (hit & inside).reshape(size, size)
    return MapRaster(layers, masks, resolution, radius)
