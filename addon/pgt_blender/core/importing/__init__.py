"""Pipeline step 1: bring a reconstruction in.

``load_reconstruction(path)`` picks the importer from the path:

| input                                   | kind             | importer            |
|-----------------------------------------|------------------|---------------------|
| folder with cameras/images/points3D     | ``colmap``       | pycolmap            |
| .ply with f_dc_*, opacity, scale_*, rot_* | ``gaussian_splat`` | numpy PLY reader  |
| .ply with faces                         | ``mesh``         | trimesh             |
| other .ply                              | ``point_ply``    | numpy PLY reader    |
| .obj .glb .gltf .stl                    | ``mesh``         | trimesh             |
"""

from pathlib import Path

from ..errors import InputError
from ..reconstruction import Reconstruction
from .colmap import load_colmap
from .mesh import MESH_SUFFIXES, load_mesh
from .ply import read_header
from .points import is_gaussian_splat, load_gaussian_splat, load_point_ply

SUPPORTED = "a COLMAP model folder, .ply (points, Gaussian splats, meshes), .obj, .glb, .gltf, .stl"


def detect_kind(path) -> str:
    """The source kind of ``path`` (see the table above), or InputError."""
    path = Path(path)
    if path.is_dir():
        return "colmap"
    if not path.exists():
        raise InputError(path, "no such file or folder")
    suffix = path.suffix.lower()
    if suffix == ".ply":
        header = read_header(path)
        face = header.element("face")
        if face is not None and face.count > 0:
            return "mesh"
        return "gaussian_splat" if is_gaussian_splat(path, header) else "point_ply"
    if suffix in MESH_SUFFIXES:
        return "mesh"
    raise InputError(path, f"unsupported format '{suffix or path.name}' (supported: {SUPPORTED})")


def load_reconstruction(path, kind: str = "auto", with_cameras: bool = True) -> Reconstruction:
    """Read ``path`` into a Reconstruction. ``kind`` forces an importer (an operator for
    Gaussian splats refuses a plain point PLY); ``"auto"`` detects it."""
    path = Path(path)
    detected = detect_kind(path)
    if kind not in ("auto", detected):
        raise InputError(path, f"expected a {kind.replace('_', ' ')} input but this is a {detected.replace('_', ' ')}")
    if detected == "colmap":
        return load_colmap(path, with_cameras=with_cameras)
    if detected == "mesh":
        return load_mesh(path)
    header = read_header(path)
    return load_gaussian_splat(path, header) if detected == "gaussian_splat" else load_point_ply(path, header)


def find_reconstructions(directory) -> list:
    """The reconstructions directly in ``directory``, sorted by name: files of the
    suffixes above and COLMAP model folders (a folder with points3D, or its sparse/0).
    InputError when ``directory`` is not a folder."""
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(directory, "not a folder")
    found = []
    for entry in sorted(directory.iterdir()):
        if entry.name.startswith("."):
            continue
        if entry.is_file() and entry.suffix.lower() in {".ply", *MESH_SUFFIXES}:
            found.append(entry)
        elif entry.is_dir():
            model = entry / "sparse" / "0" if (entry / "sparse" / "0").is_dir() else entry
            if any((model / f"points3D{ext}").exists() for ext in (".bin", ".txt")):
                found.append(model)
    return found
