"""Pipeline step 1: bring a reconstruction in.

``load_reconstruction(path)`` picks the importer from the path:

| input                                   | kind             | importer            |
|-----------------------------------------|------------------|---------------------|
| folder with cameras/images/points3D     | ``colmap``       | pycolmap            |
| 3DGS output folder (point_cloud/iteration_N) | ``gaussian_splat`` | splat_run.py + numpy PLY reader |
| .ply with opacity, scale_*, rot_* and f_dc_* (or red/green/blue: splatfacto) | ``gaussian_splat`` | numpy PLY reader |
| .npz Plenoxels (svox2) checkpoint       | ``plenoxels``    | plenoxels.py        |
| .ply with faces                         | ``mesh``         | trimesh             |
| other .ply                              | ``point_ply``    | numpy PLY reader    |
| .obj .glb .gltf .stl                    | ``mesh``         | trimesh             |
"""

from pathlib import Path

from ..errors import InputError
from ..files import no_dead_link, regular_file
from ..reconstruction import Reconstruction
from .cameras import load_cameras
from .colmap import load_colmap
from .mesh import MESH_SUFFIXES, load_mesh
from .nerfstudio import DATAPARSER_TRANSFORMS, to_model_frame
from .plenoxels import load_plenoxels
from .ply import read_header
from .points import is_gaussian_splat, load_gaussian_splat, load_point_ply
from .splat_run import run_cameras, run_of, run_ply

SUPPORTED = ("a COLMAP model folder, a 3D Gaussian Splatting output folder, .ply (points, Gaussian splats, "
             "meshes), .npz (Plenoxels), .obj, .glb, .gltf, .stl")


KIND_NAMES = {"colmap": "a COLMAP model folder", "gaussian_splat": "Gaussian splats", "point_ply": "a point cloud",
              "mesh": "a mesh", "plenoxels": "a Plenoxels grid"}  # as the importers' menu names them


def detect_kind(path) -> str:
    """The source kind of ``path`` (see the table above), or InputError."""
    path = Path(path)
    if path.is_dir():
        return "gaussian_splat" if run_ply(path) else "colmap"
    if not path.exists():
        raise InputError(path, "no such file or folder")
    regular_file(path)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        header = read_header(path)
        face = header.element("face")
        if face is not None and face.count > 0:
            return "mesh"
        return "gaussian_splat" if is_gaussian_splat(path, header) else "point_ply"
    if suffix in MESH_SUFFIXES:
        return "mesh"
    if suffix == ".npz":
        return "plenoxels"
    raise InputError(path, f"unsupported format '{suffix or path.name}' (supported: {SUPPORTED})")


def load_reconstruction(path, kind: str = "auto", with_cameras: bool = True, cameras=None,
                        capture=None) -> Reconstruction:
    """Read ``path`` into a Reconstruction. ``kind`` forces an importer (an operator for
    Gaussian splats refuses a plain point PLY); ``"auto"`` detects it.

    ``cameras`` (a 3DGS cameras.json or a COLMAP model folder, in the same frame as the
    elements) gives the training views; a COLMAP model given to a splat file with a
    nerfstudio ``dataparser_transforms.json`` beside it is moved into the splats' frame
    (``nerfstudio.py``). Without it a splat or Plenoxels input takes its run's cameras
    (``splat_run.py``) or a ``cameras.json`` beside the file. ``capture``
    (``core.capture.CaptureOptions``) runs view-agnostic color and foreground extraction
    on what was read. ``with_cameras`` False leaves the cameras out of the result (they
    are still read when ``capture`` needs them)."""
    path = Path(path)
    detected = detect_kind(path)
    if kind not in ("auto", detected):
        found = "a folder" if detected == "colmap" else KIND_NAMES[detected]  # colmap: any folder
        raise InputError(path, f"expected {KIND_NAMES.get(kind, kind)} but this is {found}")
    needs_cameras = with_cameras or (capture is not None and capture.needs_cameras)
    recon = _read(path, detected, needs_cameras and cameras is None)
    if cameras is not None:
        recon.cameras = load_cameras(cameras)
        transform = path.parent / DATAPARSER_TRANSFORMS
        if Path(cameras).is_dir() and detected == "gaussian_splat" and path.is_file() and transform.is_file():
            recon.cameras = to_model_frame(recon.cameras, transform)
    if capture is not None:
        from ..capture import apply_capture  # the capture steps import this package's readers

        recon = apply_capture(recon, capture)
    if not with_cameras:
        recon.cameras = []
    return recon


def _read(path: Path, kind: str, with_cameras: bool) -> Reconstruction:
    if kind == "colmap":
        return load_colmap(path, with_cameras=with_cameras)
    if kind == "mesh":
        return load_mesh(path)
    if kind == "point_ply":
        return load_point_ply(path, read_header(path))
    ply = run_ply(path) if path.is_dir() else path
    recon = load_plenoxels(path) if kind == "plenoxels" else load_gaussian_splat(ply, read_header(ply))
    if with_cameras:
        run = path if path.is_dir() else run_of(path)
        if run is not None:
            recon.cameras = run_cameras(run)
        elif (path.parent / "cameras.json").is_file():
            recon.cameras = load_cameras(path.parent / "cameras.json")
    return recon


def find_reconstructions(directory) -> list:
    """The reconstructions directly in ``directory``, sorted by name: files of the
    suffixes above, 3DGS output folders and COLMAP model folders (a folder with
    points3D, or its sparse/0).
    InputError when ``directory`` is not a folder."""
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(directory, "not a folder")
    found = []
    for entry in sorted(directory.iterdir()):
        if entry.name.startswith("."):
            continue
        if entry.suffix.lower() in {".ply", ".npz", *MESH_SUFFIXES} and no_dead_link(entry).is_file():
            found.append(entry)
        elif entry.is_dir() and run_ply(entry):
            found.append(entry)
        elif entry.is_dir():
            model = entry / "sparse" / "0" if (entry / "sparse" / "0").is_dir() else entry
            if any((model / f"points3D{ext}").exists() for ext in (".bin", ".txt")):
                found.append(model)
    return found
