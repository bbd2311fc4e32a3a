"""Foreground from per-image masks (any segmenter's): keep the elements whose projection
falls inside the mask in at least ``share`` of the views that see them.

A mask belongs to the image of the same name: ``IMG_1.png`` or ``IMG_1.jpg.png`` for
``IMG_1.jpg`` (3DGS camera names carry no extension; the stem matches). Mask files are
PNG, JPEG, BMP, TIFF (Pillow: alpha > 127 where the image has an alpha channel, else
luminance > 127) or ``.npy`` (2-D numbers, non-zero). A mask has its image's size or a
uniform scale of it, 1/16 to 16 times (a segmenter run on smaller or larger frames).

"The views that see an element" are the views whose rays hit it (``visibility.py``): a
background element hidden behind the object in a view is not judged by that view's mask.
An element no view hits (inside the object, or always hidden) is judged by every view
that frames it instead, the visual-hull rule; an element no view frames is dropped.
"""

import warnings
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import npy_header, regular_file

MASK_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".npy")
# A mask's size over its image's: a segmenter run on frames scaled down, or on the full
# photos a 3DGS run scaled down (to 1.6k px); beyond these, not this image's mask.
MASK_SCALES = (1 / 16, 16)


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
    from PIL import Image

    path = regular_file(path)
    try:
        if path.suffix.lower() == ".npy":
            with open(path, "rb") as stream:
                shape, dtype = npy_header(stream, path)
            if len(shape) != 2 or dtype.kind not in "biuf":
                raise InputError(path, f"a .npy mask must be a 2-D array of numbers, not {dtype} {shape}")
            _check_mask_size(path, shape, view)  # before numpy allocates what the header declares
            mask = np.load(path, allow_pickle=False) != 0
        else:
            with warnings.catch_warnings():  # the size is checked before any pixel is read
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)
                image = Image.open(path)  # refuses a header claiming more pixels than memory holds
            with image:
                _check_mask_size(path, image.size[::-1], view)
                mask = (np.asarray(image.getchannel("A")) if "A" in image.getbands()
                        else np.asarray(image.convert("L"))) > 127
    except (OSError, ValueError, EOFError, Image.DecompressionBombError) as error:
        if isinstance(error, InputError):
            raise
        raise InputError(path, f"not a readable mask ({type(error).__name__}: {error})") from None
    return mask


def _check_mask_size(path: Path, shape: tuple, view) -> None:
    """InputError unless a mask of ``shape`` (height, width) px fits ``view``'s image:
    its size or a uniform scale of it (a pixel of rounding either way) by
    MASK_SCALES."""
    height, width = shape
    scale = width / view.width
    if not (MASK_SCALES[0] <= scale <= MASK_SCALES[1] and abs(width - height * view.width / view.height) <= 1.5):
        raise InputError(path, f"is {width}x{height} pixels but its image {view.name} is "
                               f"{view.width}x{view.height} (a mask has the image's size or its aspect ratio, "
                               f"at 1/{1 / MASK_SCALES[0]:g} to {MASK_SCALES[1]:g} times its size)")


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
