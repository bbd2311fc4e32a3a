"""Frames -> a COLMAP model (core/importing/frames.py, structure_from_motion.py,
reconstruct_frames.py): frame choice, pairing, the similarity fit, and real
reconstructions of statue photos compared with the shipped model's cameras."""

import struct
import zlib

import numpy as np
import pycolmap
import pytest

from pgt_blender.core.errors import InputError
from pgt_blender.core.importing import find_reconstructions, load_reconstruction
from pgt_blender.core.importing.frames import FRAME_NAME, chosen_indices, decode_video, sharpness
from pgt_blender.core.importing.structure_from_motion import (SfmOptions, camera_centre_errors, camera_centres,
                                                              image_pairs, reconstruct, similarity_transform)

from .conftest import run_script

# 12 statue photos seen together in the shipped model (its most co-visible set): the
# subset a test can reconstruct in about 10 s on 2 cores.
SUBSET = ["28694662092_ef147bd65c_o.jpg", "45194583384_53c1aef0f9_o.jpg", "42308389510_313e27d74f_o.jpg",
          "49569326278_5592a1f0f9_o.jpg", "49569826016_639cc2b75e_o.jpg", "29561140525_9e8b4a29fc_o.jpg",
          "7574644852_9c9f081a67_o.jpg", "8151983731_066084233f_o.jpg", "2558473737_26550c7634_o.jpg",
          "5090398104_47d3e1112a_o.jpg", "90772798_17c2fd261e_o.jpg", "8524740662_f35c08a99f_o.jpg"]
SHIPPED_FOCAL = 2395.65  # px, the shipped model's SIMPLE_RADIAL camera
FAST = SfmOptions(max_features=4096, threads=2)


def box_blur(image: np.ndarray, radius: int) -> np.ndarray:
    """(H, W, C) uint8 blurred by a (2 radius + 1)^2 box, edges clamped."""
    padded = np.pad(image.astype(np.float64), ((radius, radius), (radius, radius), (0, 0)), mode="edge")
    for axis in (0, 1):
        summed = np.cumsum(np.insert(padded, 0, 0.0, axis=axis), axis=axis)
        size = 2 * radius + 1
        padded = (np.take(summed, range(size, summed.shape[axis]), axis=axis)
                  - np.take(summed, range(0, summed.shape[axis] - size), axis=axis)) / size
    return np.round(padded).astype(np.uint8)


def test_sharpness_ranks_blur_and_is_zero_when_flat():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (60, 80, 1), dtype=np.uint8)
    assert sharpness(np.full((10, 10), 7)) == 0.0
    scores = [sharpness(box_blur(image, radius)[..., 0]) for radius in (0, 1, 2, 4)]
    assert scores == sorted(scores, reverse=True) and scores[-1] < 0.05 * scores[0]
    with pytest.raises(ValueError):
        sharpness(np.zeros((2, 10)))


def test_chosen_indices_every_and_sharpest():
    assert chosen_indices(10, 3, "every").tolist() == [0, 3, 6, 9]
    scores = np.array([1, 5, 2, 9, 9, 0, 3, 1, 8, 7], float)
    # runs [0, 3) [3, 6) [6, 9) [9]: the highest of each, the earlier on a tie
    assert chosen_indices(10, 3, "sharpest", scores).tolist() == [1, 3, 8, 9]
    assert chosen_indices(4, 1, "sharpest", scores[:4]).tolist() == [0, 1, 2, 3]
    with pytest.raises(ValueError):
        chosen_indices(4, 2, "sharpest", scores)


def test_image_pairs_close_the_orbit():
    exhaustive = image_pairs(12, "auto")
    assert len(exhaustive) == 66 and (exhaustive[:, 0] < exhaustive[:, 1]).all()
    orbit = image_pairs(100, "auto", overlap=3)  # more than EXHAUSTIVE_UP_TO: orbit pairs
    pairs = {tuple(pair) for pair in orbit.tolist()}
    assert {(0, 1), (0, 3), (0, 8), (0, 64), (0, 99), (97, 99), (2, 99)} <= pairs  # 99 meets 0, 1, 2: wrapped
    assert (0, 5) not in pairs and len(pairs) == len(orbit)
    differences = np.minimum((orbit[:, 1] - orbit[:, 0]) % 100, (orbit[:, 0] - orbit[:, 1]) % 100)
    assert set(differences.tolist()) == {1, 2, 3, 4, 8, 16, 32, 36}  # 64 ahead is 36 behind


def test_similarity_transform_recovers_a_known_one():
    rng = np.random.default_rng(1)
    source = rng.normal(size=(20, 3))
    rotation, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rotation *= np.sign(np.linalg.det(rotation))
    target = 2.5 * source @ rotation.T + [1.0, -2.0, 3.0]
    scale, found, translation = similarity_transform(source, target)
    assert scale == pytest.approx(2.5) and np.allclose(found, rotation) and np.allclose(translation, [1, -2, 3])
    errors = camera_centre_errors(dict(zip("abcdefghijklmnopqrst", source)), dict(zip("abcdefghijklmnopqrst", target)))
    assert errors["common"] == 20 and errors["relative"].max() < 1e-9


def agreement(found: dict, reference: dict) -> dict:
    errors = camera_centre_errors(found, reference)
    print(f"camera centres after a similarity transform: median {np.median(errors['relative']):.2%}, "
          f"max {errors['relative'].max():.2%} of the orbit size")
    return errors


def test_reconstruct_statue_subset_from_the_command(shared_data, tmp_path):
    images = tmp_path / "frames"
    images.mkdir()
    for name in SUBSET:
        (images / name).symlink_to(shared_data / "colmap_statue" / "images" / name)
    out = tmp_path / "out"
    result = run_script("reconstruct_frames.py", images, "--out", out, "--max-features", 4096, "--threads", 2,
                        "--quiet")
    assert result.returncode == 0, result.stderr
    assert f"wrote {out / 'sparse' / '0'}" in result.stdout
    model = out / "sparse" / "0"
    assert find_reconstructions(tmp_path) == [model]  # importable as any COLMAP model
    recon = load_reconstruction(model)
    assert len(recon.cameras) == 12 and len(recon.positions) > 1000
    assert {camera.fx for camera in recon.cameras} == {recon.cameras[0].fx}  # one camera
    assert recon.cameras[0].fx == pytest.approx(SHIPPED_FOCAL, rel=0.05)
    errors = agreement(camera_centres(model), camera_centres(shared_data / "colmap_statue" / "sparse" / "0"))
    assert errors["common"] == 12
    assert np.median(errors["relative"]) < 0.03 and errors["relative"].max() < 0.08


def test_video_sharpest_frames_reconstruct(shared_data, tmp_path):
    """A video of the subset, each photo for 3 frames of which only the middle one is
    sharp: the command's sharpest pick keeps exactly those, and they reconstruct as the
    photos do."""
    av = pytest.importorskip("av")

    video = tmp_path / "orbit.mp4"
    with av.open(str(video), "w") as container:
        stream = container.add_stream("libx264", rate=10, options={"crf": "12"})
        stream.width, stream.height, stream.pix_fmt = 800, 1200, "yuv420p"
        for name in SUBSET:
            rgb = pycolmap.Bitmap.read(str(shared_data / "colmap_statue" / "images" / name), as_rgb=True).to_array()
            for frame in (box_blur(rgb, 3), rgb, box_blur(rgb, 2)):
                container.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
        container.mux(stream.encode())
    assert decode_video(video, tmp_path / "every", every=5, pick="every") == [FRAME_NAME.format(i) for i in
                                                                              range(0, 36, 5)]
    out = tmp_path / "out"
    result = run_script("reconstruct_frames.py", video, "--out", out, "--every", 3, "--pick", "sharpest",
                        "--max-features", 4096, "--threads", 2, "--quiet")
    assert result.returncode == 0, result.stderr
    names = sorted(path.name for path in (out / "images").iterdir())
    assert names == [FRAME_NAME.format(3 * k + 1) for k in range(12)]  # the sharp middle frames
    found = {SUBSET[(int(name[6:12]) - 1) // 3]: centre  # frame 3k + 1 is photo k
             for name, centre in camera_centres(out / "sparse" / "0").items()}
    assert len(found) == 12
    errors = agreement(found, camera_centres(shared_data / "colmap_statue" / "sparse" / "0"))
    assert np.median(errors["relative"]) < 0.03 and errors["relative"].max() < 0.08


def test_too_few_images_and_no_model(shared_data, tmp_path):
    images = shared_data / "colmap_statue" / "images"
    with pytest.raises(InputError, match="structure from motion needs at least 2"):
        reconstruct(images, SUBSET[:1], tmp_path / "one", FAST)
    assert not (tmp_path / "one").exists()
    flat = tmp_path / "flat"
    flat.mkdir()
    for index in range(3):  # textureless: no features, no pair
        pycolmap.Bitmap.from_array(np.full((64, 64), 100 + index, np.uint8)).write(str(flat / f"{index}.png"))
    with pytest.raises(InputError, match="no model"):
        reconstruct(flat, ["0.png", "1.png", "2.png"], tmp_path / "none", FAST)
    assert not (tmp_path / "none").exists()  # nothing left behind
    earlier = tmp_path / "earlier"
    (earlier / "sparse").mkdir(parents=True)
    (earlier / "database.db").write_bytes(b"an earlier run's")
    with pytest.raises(InputError, match="no model"):
        reconstruct(flat, ["0.png", "1.png", "2.png"], earlier, FAST)
    assert sorted(path.name for path in earlier.iterdir()) == ["database.db", "sparse"]
    assert (earlier / "database.db").read_bytes() == b"an earlier run's"


def test_one_camera_needs_one_image_size(tmp_path):
    """COLMAP's reader would skip the odd image; it is named before anything is read."""
    for name, shape in (("a.png", (48, 64)), ("b.png", (64, 48))):
        pycolmap.Bitmap.from_array(np.full(shape, 90, np.uint8)).write(str(tmp_path / name))
    with pytest.raises(InputError, match=r"b.png: is 48 x 64 px but a.png is 64 x 48: one camera takes one image "
                                         r"size \(--camera per-image"):
        reconstruct(tmp_path, ["a.png", "b.png"], tmp_path / "out", FAST)
    assert not (tmp_path / "out").exists()


def test_a_failed_video_run_leaves_the_output_as_it_was(tmp_path):
    """A textureless video: no model. The error names the video; frames already in
    OUT/images stay as they were and no decoded frame is left."""
    av = pytest.importorskip("av")

    video = tmp_path / "flat.mp4"
    with av.open(str(video), "w") as container:
        stream = container.add_stream("libx264", rate=10)
        stream.width, stream.height, stream.pix_fmt = 64, 64, "yuv420p"
        for level in range(4):
            frame = np.full((64, 64, 3), 60 + 40 * level, np.uint8)
            container.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
        container.mux(stream.encode())
    out = tmp_path / "out"
    (out / "images").mkdir(parents=True)
    (out / "images" / FRAME_NAME.format(0)).write_bytes(b"an earlier frame")
    result = run_script("reconstruct_frames.py", video, "--out", out, "--every", 1, "--quiet")
    assert result.returncode == 1 and result.stderr.startswith(f"error: {video}: no model"), result.stderr
    assert [path.name for path in out.iterdir()] == ["images"]
    assert [path.read_bytes() for path in (out / "images").iterdir()] == [b"an earlier frame"]


def png_claiming(width: int, height: int) -> bytes:
    """A grey PNG whose header claims ``width`` x ``height`` px, with almost no pixel data."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


@pytest.mark.parametrize("name, content, problem", [
    ("huge.png", png_claiming(100_000, 100_000), "not a readable image (DecompressionBombError"),  # COLMAP crashed
    ("wide.png", png_claiming(70_000, 10), "image of 70000 x 10 px: each side must be 3 .. 65536 px"),
    ("dot.png", None, "image of 1 x 1 px: each side must be 3 .. 65536 px"),
    ("empty.jpg", b"", "not a readable image (UnidentifiedImageError"),
    ("notes.jpg", b"not a picture", "not a readable image (UnidentifiedImageError"),
], ids=["100000 px a side", "70000 px wide", "1 x 1", "empty", "text"])
def test_unusable_images_are_named_before_colmap_reads_them(shared_data, tmp_path, name, content, problem):
    images = tmp_path / "frames"
    images.mkdir()
    for photo in SUBSET[:2]:
        (images / photo).symlink_to(shared_data / "colmap_statue" / "images" / photo)
    if content is None:
        pycolmap.Bitmap.from_array(np.zeros((1, 1), np.uint8)).write(str(images / name))
    else:
        (images / name).write_bytes(content)
    result = run_script("reconstruct_frames.py", images, "--out", tmp_path / "out", "--quiet")
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 1 and len(lines) == 1 and lines[0].startswith(f"error: {images / name}: {problem}")
    assert not (tmp_path / "out").exists()
