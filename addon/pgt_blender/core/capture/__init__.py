"""From a capture to a clean colored object (the paper's section 3.1 and Algorithm 1):
view-agnostic color and foreground extraction on an imported splat, Plenoxels or point
reconstruction with its training cameras.

- ``visibility.py``: which elements each view's pixel rays hit (a z-buffer per view);
- ``view_color.py``: the mean SH color over the views that hit each element;
- ``masks.py``: foreground from per-image masks, voted over the views that see each element;
- ``support.py``: foreground without masks (support plane, the object at the orbit centre).

Both color and mask votes come from one pass over the views. Results land on the
Reconstruction: ``colors`` (view color where hit), attributes ``view_hit`` (bool) and
``view_count`` (int32, views that hit it), only the foreground elements, and a JSON-ready
``capture`` report.
"""

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..importing.sh import coefficients_from_attributes
from ..reconstruction import PROJECTED_MODELS, Reconstruction
from .masks import MaskVotes, match_masks
from .support import plane_foreground
from .view_color import ViewColorSums
from .visibility import VisibilitySettings, element_spacing, view_hits

VIEW_COLOR_ATTRIBUTES = ("view_hit", "view_count")  # what the view color adds per element

FOREGROUND_MODES = ("none", "masks", "plane")


@dataclass(frozen=True)
class CaptureOptions:
    """``view_color``: Algorithm 1; ``foreground``: "none", "masks" (``masks``: the
    folder, ``mask_share``: the share of seeing views an element must be inside the mask
    in) or "plane" (``plane_tolerance``: the most the support plane's half thickness can
    be, in element spacings); ``seed`` for every random draw (spacing sample, RANSAC)."""

    view_color: bool = False
    foreground: str = "none"
    masks: Path | None = None
    mask_share: float = 0.5
    plane_tolerance: float = 4.0
    seed: int = 0
    visibility: VisibilitySettings = field(default_factory=VisibilitySettings)

    def __post_init__(self):
        if self.foreground not in FOREGROUND_MODES:
            raise ValueError(f"foreground must be one of {FOREGROUND_MODES}, not {self.foreground!r}")
        if self.foreground == "masks" and not self.masks:
            raise ValueError("foreground 'masks' needs a masks folder")
        if not 0.0 <= self.mask_share <= 1.0:
            raise ValueError(f"mask_share must be within [0, 1], not {self.mask_share}")

    @property
    def needs_cameras(self) -> bool:
        """Whether the steps asked for use the cameras (the plane mode uses them when present)."""
        return self.view_color or self.foreground != "none"


def apply_capture(recon: Reconstruction, options: CaptureOptions) -> Reconstruction:
    """``recon`` after view color (its colors and attributes changed in place) and
    foreground extraction (a subset of it), see the module docstring; InputError naming
    its source when it is a mesh, or has no usable cameras for what was asked."""
    if not options.needs_cameras:
        return recon
    if len(recon.faces):
        raise InputError(recon.source, "view color and foreground work on points, splats and voxels, not on a mesh")
    taken = [name for name in VIEW_COLOR_ATTRIBUTES if name in recon.attributes] if options.view_color else []
    if taken:  # the file's own values would be lost without a word
        raise InputError(recon.source, f"has its own '{taken[0]}' property, which the view color makes; rename it")
    rng = np.random.default_rng(options.seed)
    spacing = element_spacing(recon.positions, rng)
    report = {"spacing": round(spacing, 9), "cameras": len(recon.cameras)}
    keep = np.ones(len(recon.positions), bool)
    if options.view_color or options.foreground == "masks":
        cameras = _projectable(recon)
        mask_files = match_masks(options.masks, cameras) if options.foreground == "masks" else None
        color, votes = _view_pass(recon, cameras, options, spacing, mask_files)
        if color is not None:
            report["view_color"] = _apply_view_color(recon, color)
        if votes is not None:
            shares = votes.shares()
            keep = shares >= options.mask_share
            report["foreground"] = {"mode": "masks", "share": options.mask_share, "kept": int(keep.sum()),
                                    "judged_by_hits": int((votes.seen > 0).sum()),
                                    "judged_by_framing": int(((votes.seen == 0) & (votes.framed > 0)).sum()),
                                    "never_framed": int((votes.framed == 0).sum())}
    if options.foreground == "plane":
        keep, details = plane_foreground(recon.positions, recon.cameras, spacing, rng, options.plane_tolerance)
        report["foreground"] = {"mode": "plane", **details}
    if "foreground" in report:
        report["foreground"]["elements"] = len(keep)
        recon = recon.subset(keep)
    recon.capture = report
    return recon


def _projectable(recon: Reconstruction) -> list:
    """The cameras, or InputError when there are none or one cannot be projected."""
    if not recon.cameras:
        raise InputError(recon.source, "has no cameras: view color and mask foreground need the training views "
                                       "(a 3DGS run's cameras.json, a COLMAP model, or cameras given with the input)")
    odd = sorted({view.model for view in recon.cameras} - set(PROJECTED_MODELS))
    if odd:
        raise InputError(recon.source, f"camera model {odd[0]} is not supported for projection "
                                       f"(supported: {', '.join(PROJECTED_MODELS)})")
    return recon.cameras


def _view_pass(recon: Reconstruction, cameras: list, options: CaptureOptions, spacing: float, mask_files):
    """One pass over ``cameras`` feeding the color sums and the mask votes."""
    color = votes = None
    if options.view_color:
        try:
            coefficients = coefficients_from_attributes(recon.attributes)
        except ValueError as error:
            raise InputError(recon.source, str(error)) from None
        color = ViewColorSums(recon.positions, coefficients)
    if mask_files is not None:
        votes = MaskVotes(len(recon.positions), mask_files)
    accumulators = [a for a in (color, votes) if a is not None]
    for hits in view_hits(recon.positions, cameras, spacing, recon.attributes.get("opacity"), options.visibility):
        for accumulator in accumulators:
            accumulator.add(hits, cameras[hits.view])
    return color, votes


def _apply_view_color(recon: Reconstruction, color: ViewColorSums) -> dict:
    if recon.colors is None:
        recon.colors = np.ones((len(recon.positions), 4), np.float32)
    recon.colors[:, :3] = color.colors(recon.colors[:, :3])
    hit = color.counts > 0
    recon.attributes.update(zip(VIEW_COLOR_ATTRIBUTES, (hit, color.counts)))
    return {"sh_degree": color.degree, "hit": int(hit.sum()), "never_hit": int((~hit).sum()),
            "hit_share": round(float(hit.mean()), 6),
            "mean_views_per_hit_element": round(float(color.counts[hit].mean()), 3) if hit.any() else 0.0}
