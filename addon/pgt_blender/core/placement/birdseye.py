"""The placement's bird's-eye picture (``birdseye.png``), sensor frame seen from above
(x to the right, y up, the sensor at the centre): map layers (faint colours), the
area where the classes asked may stand (green), the scene's returns coloured by
height over the estimated ground (ground returns grey), the scene points removed in
the inserted objects' shadows (magenta), the scene's boxes (black) and the inserted
ones (red, with their class). matplotlib is imported only here."""

import io

import numpy as np

from .collision import footprint_corners
from .ground import GROUND_TOLERANCE

DPI = 110
GRID = 0.25  # m: the feasible-area raster of the picture


def birdseye_png(scene_points: np.ndarray, placement, title: str, extent: float = 54.0) -> bytes:
    """PNG bytes of the picture for a Placement of the (N, >= 3) ``scene_points``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import ListedColormap
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch, Polygon

    figure = Figure(figsize=(9.5, 9), layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.subplots()
    bounds = (-extent, extent, -extent, extent)
    legend = []
    feasibility = placement.feasibility
    if feasibility.map is not None:
        layer_map = feasibility.map
        labels = np.where(layer_map.masks.any(axis=0), layer_map.masks.argmax(axis=0), -1).astype(float)
        labels[labels < 0] = np.nan
        colors = [f"C{index % 10}" for index in range(len(layer_map.layers))]
        radius = layer_map.radius
        axes.imshow(labels, origin="lower", extent=(-radius, radius, -radius, radius), alpha=0.25,
                    cmap=ListedColormap(colors), vmin=-0.5, vmax=len(colors) - 0.5, interpolation="nearest")
        legend += [Patch(color=color, alpha=0.25, label=f"map: {name}") for name, color in zip(layer_map.layers, colors)]
    # every class asked, placed or not: where one could stand says most when none did
    classes = sorted(set(placement.names[placement.inserted]) | set(placement.missing))
    if classes:
        centres = -extent + (np.arange(int(2 * extent / GRID)) + 0.5) * GRID
        grid_x, grid_y = np.meshgrid(centres, centres)
        spots = np.column_stack([grid_x.ravel(), grid_y.ravel()])
        allowed = np.zeros(len(spots), bool)
        for name in classes:
            allowed |= feasibility.allows(name, spots)
        axes.imshow(np.where(allowed, 1.0, np.nan).reshape(grid_x.shape), origin="lower", extent=bounds,
                    cmap=ListedColormap(["#3a3"]), alpha=0.3, interpolation="nearest")
        legend.append(Patch(color="#3a3", alpha=0.3, label=f"may stand: {', '.join(classes)}"))
    xyz = np.asarray(scene_points, np.float64)[:, :3]
    height = placement.ground.height_above(xyz)
    removed = placement.scene_in_boxes | placement.scene_shadowed
    ground = (np.abs(height) <= GROUND_TOLERANCE) & ~removed
    axes.scatter(*xyz[ground, :2].T, s=0.3, c="0.6", linewidths=0, label="ground returns")
    other = ~ground & ~removed
    dots = axes.scatter(*xyz[other, :2].T, s=0.4, c=np.clip(height[other], 0.0, 4.0), cmap="viridis",
                        linewidths=0)
    figure.colorbar(dots, ax=axes, shrink=0.6, label="height over the ground (m)")
    axes.scatter(*xyz[placement.scene_shadowed, :2].T, s=1.5, c="m", linewidths=0, label="removed: in a shadow")
    inserted_points = placement.points[:placement.rows[-1, 1]] if len(placement.rows) else placement.points[:0]
    axes.scatter(*np.asarray(inserted_points[:, :2], np.float64).T, s=1.0, c="r", linewidths=0,
                 label="inserted returns")
    for box, name, inserted in zip(placement.boxes, placement.names, placement.inserted):
        color = "r" if inserted else "k"
        axes.add_patch(Polygon(footprint_corners(box[None])[0], closed=True, fill=False, edgecolor=color,
                               linewidth=1.2 if inserted else 0.8))
        if inserted:
            axes.annotate(str(name), box[:2], fontsize=7, color=color, ha="center", va="center")
    handles, _ = axes.get_legend_handles_labels()
    axes.legend(handles=handles + legend, loc="upper right", fontsize="small", markerscale=8)
    axes.set(xlim=bounds[:2], ylim=bounds[2:], aspect="equal", xlabel="x (m)", ylabel="y (m)", title=title)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI, metadata={"Software": None})
    return buffer.getvalue()
