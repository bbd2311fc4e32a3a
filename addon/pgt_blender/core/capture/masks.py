"""Foreground from per-image masks (any segmenter's): keep the elements whose projection
falls inside the mask in at least ``share`` of the views that see them.

A mask belongs to the image of the same name: ``IMG_1.png`` or ``IMG_1.jpg.png`` for
``IMG_1.jpg`` (3DGS camera names carry no extension; the stem matches). Mask files are
PNG, JPEG, BMP, TIFF (Pillow: alpha > 127 where the image has an alpha channel, else
luminance > 127) or ``.npy`` (non-zero). A mask has its image's size or a uniform scale
of it (a segmenter run on smaller frames).

"The views that see an element" are the views whose rays hit it (``visibility.py``): a
background element hidden behind the object in a view is not judged by that view's mask.
An element no view hits (inside the object, or always hidden) is judged by every view
that frames it instead, the visual-hull rule; an element no view frames is dropped.
"""

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import regular_file

MASK_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".npy")


def match_masks(folder, cameras: list) -> list:
    """The mask file of each camera (by image name, see above); InputError naming the
    folder when some image has none or two."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "masks: not a folder")
    by_name = {}
    for path in sorted(folder.iterdir()):
        if path.suffix.lower() in MASK_SUFFIXES and not path.name.startswith("."):
            by_name.setdefault(path.stem, []).append(path)
    found, missing = [], []
    for view in cameras:
        name = Path(view.name).name
        candidates = by_name.get(name, []) + (by_name.get(Path(name).stem, []) if Path(name).suffix else [])
        if len(candidates) > 1:
            raise InputError(folder, f"image {name} has {len(candidates)} masks: "
                                     f"{', '.join(p.name for p in candidates)}")
        if not candidates:
            missing.append(name)
        found += candidates
    if missing:
        raise InputError(folder, f"no mask for {len(missing)} of {len(cameras)} images ({', '.join(missing[:3])}"
                                 f"{', ...' if len(missing) > 3 else ''}); a mask is named after its image "
                                 f"(IMG_1.png for IMG_1.jpg)")
    return found


def read_mask(path: Path, view) -> np.ndarray:
    """(h, w) bool foreground of the mask file ``path`` for ``view``; InputError naming
    the file when it cannot be read or its size does not fit the image's."""
    path = regular_file(path)
    try:
        if path.suffix.lower() == ".npy":
            mask = np.load(path, allow_pickle=False)
            mask = mask != 0 if mask.ndim == 2 else None
        else:
            from PIL import Image

            with Image.open(path) as image:
                mask = (np.asarray(image.getchannel("A")) if "A" in image.getbands()
                        else np.asarray(image.convert("L"))) > 127
    except (OSError, ValueError) as error:
        raise InputError(path, f"not a readable mask ({type(error).__name__}: {error})") from None
    if mask is None:
        raise InputError(path, "a .npy mask must be a 2-D array")
    height, width = mask.shape
    if abs(width / view.width - height / view.height) > 1.5 / min(view.width, view.height):
        raise InputError(path, f"is {width}x{height} pixels but its image {view.name} is "
                               f"{view.width}x{view.height} (a mask has the image's size or aspect ratio)")
    return mask


class MaskVotes:
    """Per element: in how many of the views that hit (or frame) it it projects inside the mask."""

    def __init__(self, size: int, mask_files: list):
        self.mask_files = mask_files
        self.seen = np.zeros(size, np.int32)
        self.seen_inside = np.zeros(size, np.int32)
        self.framed = np.zeros(size, np.int32)
        self.framed_inside = np.zeros(size, np.int32)

    def add(self, hits, view) -> None:
        mask = read_mask(self.mask_files[hits.view], view)
        scale = np.array([mask.shape[1] / view.width, mask.shape[0] / view.height], np.float32)
        cells = np.minimum((hits.pixels * scale).astype(np.int64), np.array(mask.shape[::-1]) - 1)
        inside = mask[cells[:, 1], cells[:, 0]]
        self.framed[hits.framed] += 1
        self.framed_inside[hits.framed] += inside
        self.seen[hits.framed[hits.hit]] += 1
        self.seen_inside[hits.framed[hits.hit]] += inside[hits.hit]

    def shares(self) -> np.ndarray:
        """(N,) float share of the judging views (hits, else framing views) that put the
        element inside the mask; 0 for an element no view frames."""
        seen = self.seen > 0
        judged = np.where(seen, self.seen, self.framed)
        inside = np.where(seen, self.seen_inside, self.framed_inside)
        return np.divide(inside, judged, out=np.zeros(len(judged)), where=judged > 0)
