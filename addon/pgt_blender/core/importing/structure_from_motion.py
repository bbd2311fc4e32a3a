"""Images -> a COLMAP sparse model, on the CPU with pycolmap: the model the COLMAP
importer (colmap.py) reads, as if COLMAP itself had made it.

1. **Features**: SIFT (``extract_features`` on the CPU), at most ``max_features`` per
   image at most ``max_image_size`` px on a side, into ``OUT/database.db`` (made anew).
   One camera for every image (a video's frames: one lens) or one per image. Focal
   lengths from EXIF are dropped: a cropped or resized photo keeps its original
   sensor's EXIF focal, and a wrong prior spoils the calibrated two-view geometry (the
   shipped statue photos claim focals up to 9x the true one, and no initial pair
   is found); the mapper starts from 1.2 x the larger image side and refines it.
2. **Matching** of chosen image pairs (``match_image_pairs``, in blocks so the progress
   bar moves), in the images' order: "orbit" pairs each image with the next
   ``overlap`` ones and with those 2^j ahead, cyclically, so the end of an orbit video
   meets its start and the loop closes without a vocabulary tree; "exhaustive" pairs
   all; "auto" is exhaustive up to EXHAUSTIVE_UP_TO images (unordered photos), else orbit.
3. **Mapping**: ``incremental_mapping`` seeded with ``seed``; the model with the most
   registered images is written to ``OUT/sparse/0`` (cameras.bin, images.bin,
   points3D.bin), complete or not at all.

Frames: the model's own world frame (arbitrary origin, orientation and scale), as for
any COLMAP model. ``camera_centre_errors`` compares two models' camera centres after
the similarity transform that best maps one onto the other (Umeyama 1991).
"""

import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import folders_made
from ..progress import progress_bar
from .frames import checked_image_size

MATCHINGS = ("auto", "orbit", "exhaustive")
EXHAUSTIVE_UP_TO = 60  # images: "auto" matches every pair up to this many
PAIRS_PER_BLOCK = 64  # image pairs per match_image_pairs call (one progress step)
DATABASE = "database.db"
MODEL_FOLDER = Path("sparse") / "0"


@dataclass(frozen=True)
class SfmOptions:
    """matching: one of MATCHINGS; overlap: the orbit pairing's run of neighbours;
    single_camera: one camera (intrinsics) for all images, else one per image;
    max_features, max_image_size (px): SIFT's limits; threads: CPU threads (0: all);
    seed: RANSAC's and the mapper's random seed."""

    matching: str = "auto"
    overlap: int = 10
    single_camera: bool = True
    max_features: int = 8192
    max_image_size: int = 1600
    threads: int = 0
    seed: int = 0

    def __post_init__(self):
        if self.matching not in MATCHINGS:
            raise ValueError(f"matching must be one of {', '.join(MATCHINGS)}, got {self.matching!r}")
        if self.overlap < 1 or self.max_features < 1 or self.max_image_size < 1 or self.threads < 0:
            raise ValueError("overlap, max_features and max_image_size must be positive, threads >= 0")


@dataclass
class SfmResult:
    """What a reconstruction made: ``model`` the folder (OUT/sparse/0), images given,
    registered (in the model written), 3-D points, mean reprojection error (px), the
    models the mapper made, the camera(s) (COLMAP model name and parameters) and the
    wall time of each step (s)."""

    model: Path
    images: int
    registered: int
    points: int
    reprojection_error: float
    models: int
    cameras: list
    seconds: dict = field(default_factory=dict)


def image_pairs(count: int, matching: str = "auto", overlap: int = 10) -> np.ndarray:
    """(P, 2) int64 pairs (i < j) of image indices to match among ``count`` images in
    their order (see the module docstring), sorted and unique."""
    if matching == "auto":
        matching = "exhaustive" if count <= EXHAUSTIVE_UP_TO else "orbit"
    if matching == "exhaustive":
        first, second = np.triu_indices(count, k=1)
        return np.column_stack([first, second]).astype(np.int64)
    steps = np.unique(np.concatenate([np.arange(1, overlap + 1), 2 ** np.arange(int(np.log2(max(count, 2))) + 1)]))
    steps = steps[steps < count]
    first = np.repeat(np.arange(count), len(steps))
    second = (first + np.tile(steps, count)) % count
    pairs = np.unique(np.sort(np.column_stack([first, second]), axis=1), axis=0)
    return pairs[pairs[:, 0] != pairs[:, 1]].astype(np.int64)


def reconstruct(image_folder, names: list, out_folder, options: SfmOptions = SfmOptions(),
                progress: bool = False) -> SfmResult:
    """A COLMAP model of the images ``names`` (in match order) of ``image_folder``,
    written under ``out_folder`` (its database.db and sparse/0). InputError when fewer
    than two images are given, COLMAP's reader skips one, or no model comes out; a
    failed run leaves ``out_folder`` as it was (the database is built beside the
    earlier one and renamed onto it with the model)."""
    image_folder, out_folder = Path(image_folder), Path(out_folder)
    if len(names) < 2:
        raise InputError(image_folder, f"{len(names)} image(s): structure from motion needs at least 2")
    if options.single_camera:
        _require_one_size(image_folder, names)
    with folders_made(out_folder):
        database = out_folder / f".{DATABASE}.partial"
        database.unlink(missing_ok=True)
        try:
            result = _reconstruct(image_folder, names, out_folder, database, options, progress)
        except BaseException:
            database.unlink(missing_ok=True)
            raise
        os.replace(database, out_folder / DATABASE)
    return result


def _reconstruct(image_folder: Path, names: list, out_folder: Path, database: Path, options: SfmOptions,
                 progress: bool) -> SfmResult:
    """reconstruct's steps, building ``database``."""
    import pycolmap

    threads = options.threads or -1
    seconds = {}

    start = time.perf_counter()
    extraction = pycolmap.FeatureExtractionOptions(num_threads=threads, max_image_size=options.max_image_size)
    extraction.sift.max_num_features = options.max_features
    mode = pycolmap.CameraMode.SINGLE if options.single_camera else pycolmap.CameraMode.PER_IMAGE
    reader = pycolmap.ImageReaderOptions()
    with progress_bar(progress, len(names), "image") as bar:
        for block in range(0, len(names), 8):  # blocks of 8 images: the bar moves
            pycolmap.extract_features(database, image_folder, image_names=names[block:block + 8], camera_mode=mode,
                                      reader_options=reader, extraction_options=extraction,
                                      device=pycolmap.Device.cpu)
            if options.single_camera:  # later blocks share the first block's camera
                reader.existing_camera_id = 1
            if bar is not None:
                bar.update(len(names[block:block + 8]))
    _require_all_read(database, image_folder, names)
    _drop_focal_priors(database)
    seconds["features"] = time.perf_counter() - start

    start = time.perf_counter()
    pairs = image_pairs(len(names), options.matching, options.overlap)
    matching = pycolmap.FeatureMatchingOptions(num_threads=threads)
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = options.seed
    pairs_file = out_folder / ".pairs.txt"
    try:
        with progress_bar(progress, len(pairs), "pair") as bar:
            for block in range(0, len(pairs), PAIRS_PER_BLOCK):
                chosen = pairs[block:block + PAIRS_PER_BLOCK]
                pairs_file.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in chosen))
                pycolmap.match_image_pairs(database, matching, pycolmap.ImportedPairingOptions(
                    match_list_path=str(pairs_file)), verification, device=pycolmap.Device.cpu)
                if bar is not None:
                    bar.update(len(chosen))
    finally:
        pairs_file.unlink(missing_ok=True)
    seconds["matching"] = time.perf_counter() - start

    start = time.perf_counter()
    mapping = pycolmap.IncrementalPipelineOptions(num_threads=threads, random_seed=options.seed)
    mapping.mapper.random_seed = options.seed
    mapping.triangulation.random_seed = options.seed
    scratch = out_folder / ".mapping.partial"
    shutil.rmtree(scratch, ignore_errors=True)
    try:
        with progress_bar(progress, len(names), "registered") as bar:
            models = pycolmap.incremental_mapping(database, image_folder, scratch, mapping,
                                                  next_image_callback=None if bar is None else lambda: bar.update())
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    seconds["mapping"] = time.perf_counter() - start
    if not models:
        raise InputError(image_folder, f"no model: the mapper found no initial pair among {len(names)} images "
                                       f"(too little overlap or texture)")
    model = max(models.values(), key=lambda m: m.num_reg_images())
    path = _write_model(model, out_folder / MODEL_FOLDER)
    cameras = [{"model": camera.model.name, "params": [float(p) for p in camera.params]}
               for camera in model.cameras.values()]
    return SfmResult(path, len(names), model.num_reg_images(), model.num_points3D(),
                     float(model.compute_mean_reprojection_error()), len(models), cameras, seconds)


def _require_one_size(image_folder: Path, names: list) -> None:
    """InputError naming the first image whose size differs from the first's: one
    camera has one image size (COLMAP's reader would skip the others)."""
    first = checked_image_size(image_folder / names[0])
    for name in names[1:]:
        size = checked_image_size(image_folder / name)
        if size != first:
            raise InputError(image_folder / name, f"is {size[0]} x {size[1]} px but {names[0]} is {first[0]} x "
                                                  f"{first[1]}: one camera takes one image size (--camera "
                                                  f"per-image for photos from several cameras)")


def _require_all_read(database: Path, image_folder: Path, names: list) -> None:
    """InputError naming the first of ``names`` COLMAP's reader skipped (it logs an
    unreadable image and goes on; a damaged JPEG passes the header check)."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        read = {image.name for image in db.read_all_images()}
    finally:
        db.close()
    skipped = [name for name in names if name not in read]
    if skipped:
        raise InputError(image_folder / skipped[0], f"not a readable image (COLMAP's reader skipped it; "
                                                    f"{len(skipped)} of {len(names)} skipped)")


def _drop_focal_priors(database: Path) -> None:
    """Every camera of ``database`` back to the uninformed start: focal 1.2 x the larger
    side, principal point at the centre, no distortion, no focal prior."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        for camera in db.read_all_cameras():
            if camera.has_prior_focal_length:
                camera.params = pycolmap.Camera.create_from_model_name(
                    camera.camera_id, camera.model.name, 1.2 * max(camera.width, camera.height),
                    camera.width, camera.height).params
                camera.has_prior_focal_length = False
                db.update_camera(camera)
    finally:
        db.close()


def _write_model(model, folder: Path) -> Path:
    """``model`` written to ``folder`` (binary files) so that it appears complete or not
    at all: written beside it, then renamed over any earlier one."""
    partial = folder.with_name(f".{folder.name}.partial")
    old = folder.with_name(f".{folder.name}.old")
    for stale in (partial, old):
        shutil.rmtree(stale, ignore_errors=True)
    partial.mkdir(parents=True)
    model.write(str(partial))
    if folder.exists():
        os.replace(folder, old)
    os.replace(partial, folder)
    shutil.rmtree(old, ignore_errors=True)
    return folder


def similarity_transform(source: np.ndarray, target: np.ndarray) -> tuple:
    """(scale, (3, 3) rotation, (3,) translation) minimising the squared distances
    ||target - (scale R source + t)|| of matching rows of ``source`` and ``target``
    (N, 3), N >= 3 not collinear (Umeyama 1991)."""
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    mean_source, mean_target = source.mean(axis=0), target.mean(axis=0)
    centred_source, centred_target = source - mean_source, target - mean_target
    covariance = centred_target.T @ centred_source / len(source)
    u, singular, vt = np.linalg.svd(covariance)
    sign = np.eye(3)
    sign[2, 2] = np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0
    rotation = u @ sign @ vt
    scale = np.trace(np.diag(singular) @ sign) / (centred_source ** 2).sum(axis=1).mean()
    return float(scale), rotation, mean_target - scale * rotation @ mean_source


def camera_centres(model_folder) -> dict:
    """Image name -> (3,) float64 camera centre (model frame) of a COLMAP model folder's
    registered images."""
    import pycolmap

    model = pycolmap.Reconstruction(str(model_folder))
    return {image.name: np.asarray(image.projection_center(), np.float64)
            for image in model.images.values() if image.has_pose}


def camera_centre_errors(found: dict, reference: dict) -> dict:
    """How well camera centres ``found`` (image name -> (3,), camera_centres) agree with
    a reference model's, after the similarity transform mapping the centres of the
    images both registered onto the reference's (at least 3). ``errors`` (K,) are the
    distances in the reference's units, ``relative`` the same over the orbit's size (the
    RMS distance of the reference's centres from their mean); ``scale`` the transform's."""
    names = sorted(set(found) & set(reference))
    if len(names) < 3:
        raise ValueError(f"{len(names)} image(s) registered in both models; need 3 to compare")
    source = np.array([found[name] for name in names])
    target = np.array([reference[name] for name in names])
    scale, rotation, translation = similarity_transform(source, target)
    errors = np.linalg.norm(source @ (scale * rotation).T + translation - target, axis=1)
    orbit = float(np.sqrt(((target - target.mean(axis=0)) ** 2).sum(axis=1).mean()))
    return {"names": names, "common": len(names), "errors": errors, "relative": errors / orbit,
            "orbit_size": orbit, "scale": scale}
