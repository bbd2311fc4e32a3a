"""The pictures structure from motion starts from: the images of a folder, or frames
decoded from a video, every k-th or the sharpest of each run of k.

Sharpness is the variance of the 4-neighbour Laplacian of the grey image (grey levels
0..255 squared): motion blur and defocus flatten edges and lower it, so the sharpest
frame of a run is the one SIFT finds most features in. Images are read with pycolmap's
own reader (what feature extraction reads); videos are decoded with PyAV (FFmpeg's
libraries, the optional ``video`` extra), frame by frame, holding one run at a time.
"""

import warnings
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import folders_made
from ..progress import progress_bar
from .source import MAX_IMAGE_SIDE

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
PICKS = ("every", "sharpest")
FRAME_NAME = "frame_{:06d}.jpg"  # a decoded video frame, by its index in the video
FRAME_JPEG_QUALITY = 95
MIN_IMAGE_SIDE = 3  # px: the sharpness Laplacian's support; SIFT finds nothing in less


def sharpness(grey: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of ``grey`` (H, W) (any numeric type,
    computed in float64 on the interior pixels); 0 for a flat image."""
    image = np.asarray(grey, np.float64)
    if image.ndim != 2 or min(image.shape) < 3:
        raise ValueError(f"sharpness needs a 2-D image of at least 3 x 3 pixels, got shape {image.shape}")
    laplacian = (image[:-2, 1:-1] + image[2:, 1:-1] + image[1:-1, :-2] + image[1:-1, 2:]
                 - 4.0 * image[1:-1, 1:-1])
    return float(laplacian.var())


def chosen_indices(count: int, every: int, pick: str, scores=None) -> np.ndarray:
    """(K,) int64 indices of the frames kept among ``count``: ``pick`` "every" keeps
    0, k, 2k, ...; "sharpest" keeps the highest of ``scores`` (count,) in each run
    [0, k), [k, 2k), ... (the last run may be shorter; ties go to the earlier frame)."""
    if every < 1:
        raise ValueError(f"every must be at least 1, got {every}")
    if pick not in PICKS:
        raise ValueError(f"pick must be one of {', '.join(PICKS)}, got {pick!r}")
    if pick == "every":
        return np.arange(0, count, every)
    scores = np.asarray(scores, np.float64)
    if scores.shape != (count,):
        raise ValueError(f"sharpest needs {count} scores, got shape {scores.shape}")
    padded = np.full(-(-count // every) * every, -np.inf)
    padded[:count] = scores
    return np.arange(0, len(padded), every) + np.argmax(padded.reshape(-1, every), axis=1)


def folder_images(folder) -> list:
    """The image names (IMAGE_SUFFIXES, any case) directly in ``folder``, sorted; their
    order is the order frames are matched in. InputError when there are none, or for
    the first whose name is not UTF-8 (COLMAP's database and model hold UTF-8 names) or
    whose header is not a usable image (checked_image_size)."""
    folder = Path(folder)
    names = sorted(entry.name for entry in folder.iterdir()
                   if entry.is_file() and entry.suffix.lower() in IMAGE_SUFFIXES and not entry.name.startswith("."))
    if not names:
        raise InputError(folder, f"no images ({', '.join(IMAGE_SUFFIXES)}) in the folder")
    for name in names:
        try:
            name.encode()  # a name that is not UTF-8 holds surrogate escapes, which do not encode
        except UnicodeEncodeError:
            raise InputError(folder / name, "the file name is not UTF-8 text, which COLMAP stores; "
                                            "rename the image") from None
        checked_image_size(folder / name)
    return names


def checked_image_size(path) -> tuple:
    """(width, height) px from the image's header (Pillow decodes no pixels; a PNG's
    chunks are walked, so a cut one is caught); InputError for a file that is not an
    image, or a size outside MIN_IMAGE_SIDE .. MAX_IMAGE_SIDE (a header claiming
    100,000 px a side had COLMAP's reader allocate tens of GB, or crash)."""
    from PIL import Image

    try:
        with warnings.catch_warnings():  # the size is checked below
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as image:
                width, height = image.size
                image.verify()
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as error:
        raise InputError(path, f"not a readable image ({type(error).__name__}: {error})") from None
    if not (MIN_IMAGE_SIDE <= min(width, height) and max(width, height) <= MAX_IMAGE_SIDE):
        raise InputError(path, f"image of {width} x {height} px: each side must be {MIN_IMAGE_SIDE} .. "
                               f"{MAX_IMAGE_SIDE} px")
    return width, height


def read_grey(path) -> np.ndarray:
    """(H, W) uint8 grey image of ``path`` through pycolmap (the reader feature
    extraction uses); InputError when it cannot be read."""
    import pycolmap

    bitmap = pycolmap.Bitmap.read(str(path), as_rgb=False)
    if bitmap is None:
        raise InputError(path, "not a readable image")
    return bitmap.to_array().reshape(bitmap.height, bitmap.width)


def choose_images(folder, every: int = 1, pick: str = "every", progress: bool = False) -> list:
    """The names of ``folder``'s images kept by ``chosen_indices`` (sharpness read from
    each image when ``pick`` is "sharpest")."""
    names = folder_images(folder)
    scores = None
    if pick == "sharpest" and every > 1:
        scores = []
        with progress_bar(progress, len(names), "image") as bar:
            for name in names:
                scores.append(sharpness(read_grey(Path(folder) / name)))
                if bar is not None:
                    bar.update()
    return [names[index] for index in chosen_indices(len(names), every, "every" if scores is None else pick, scores)]


def decode_video(path, out_folder, every: int = 10, pick: str = "sharpest", progress: bool = False) -> list:
    """Decode the first video stream of ``path`` and write the frames kept (as
    ``chosen_indices`` picks them, scoring each frame as it arrives) to ``out_folder``
    as FRAME_NAME JPEGs; returns their names in video order. InputError when PyAV is
    missing, the file is not a decodable video, or it has no frame."""
    import pycolmap

    try:
        import av
    except ImportError:
        raise InputError(path, "reading a video needs PyAV: pip install 'pgt_blender[video]' (or av)") from None
    if every < 1 or pick not in PICKS:
        raise ValueError(f"every must be >= 1 and pick one of {', '.join(PICKS)}")
    out_folder = Path(out_folder)
    written = []

    def write(kept_index: int, rgb: np.ndarray) -> None:
        bitmap = pycolmap.Bitmap.from_array(np.ascontiguousarray(rgb))
        bitmap.set_jpeg_quality(FRAME_JPEG_QUALITY)
        name = FRAME_NAME.format(kept_index)
        if not bitmap.write(str(out_folder / name)):
            raise OSError(0, "could not write the frame", str(out_folder / name))
        written.append(name)

    with folders_made(out_folder):  # nothing left behind: the frames written and the folders made
        try:
            index = _decode(av, path, every, pick, progress, write)
            if index < 0:
                raise InputError(path, "the video has no frames")
        except BaseException:
            for name in written:
                (out_folder / name).unlink(missing_ok=True)
            raise
    return written


def _decode(av, path, every: int, pick: str, progress: bool, write) -> int:
    """Decode ``path``, calling ``write(frame index, (H, W, 3) uint8 RGB)`` for each frame
    kept; returns the last frame's index (-1: none)."""
    best, index = None, -1
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise InputError(path, "has no video stream")
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            with progress_bar(progress, stream.frames or None, "frame") as bar:
                for index, frame in enumerate(container.decode(stream)):
                    if min(frame.width, frame.height) < MIN_IMAGE_SIDE:
                        raise InputError(path, f"frames of {frame.width} x {frame.height} px: each side must be at "
                                               f"least {MIN_IMAGE_SIDE} px")
                    if bar is not None:
                        bar.update()
                    if pick == "every" or every == 1:
                        if index % every == 0:
                            write(index, frame.to_ndarray(format="rgb24"))
                        continue
                    score = sharpness(frame.to_ndarray(format="gray"))
                    if best is None or score > best[1]:
                        best = (index, score, frame.to_ndarray(format="rgb24"))
                    if index % every == every - 1:
                        write(best[0], best[2])
                        best = None
    except av.FFmpegError as error:
        raise InputError(path, f"not a decodable video ({error.__class__.__name__}: {error})") from None
    if best is not None:  # the last, shorter run
        write(best[0], best[2])
    return index
