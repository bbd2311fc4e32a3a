"""Mesh files (OBJ, PLY with faces, GLB/GLTF, STL) -> Reconstruction, through trimesh."""

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..reconstruction import Reconstruction
from .ply import read_header
from .source import checked_positions, sha256_of_files

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl")


def load_mesh(path: Path) -> Reconstruction:
    """Triangles in the file's frame and units. A multi-part scene (GLB, OBJ groups) is
    flattened with its node transforms applied; per-vertex colours are kept when the
    file has them. Vertices are not merged or reordered (``process=False``)."""
    import trimesh

    path = Path(path)
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as error:  # trimesh raises many types for corrupt files
        raise InputError(path, f"could not be read as a mesh: {error}") from None
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64).reshape(-1, 3)
    if len(faces) == 0:
        raise InputError(path, "mesh has no faces")
    positions = checked_positions(path, mesh.vertices, "vertices")
    if path.suffix.lower() == ".ply":
        _require_declared_counts(path, len(positions), len(faces))
    if faces.min() < 0 or faces.max() >= len(positions):
        raise InputError(path, f"face indices out of range for {len(positions)} vertices")
    colors = None
    if mesh.visual.kind == "vertex":
        colors = np.asarray(mesh.visual.vertex_colors, np.float32)[:, :4] / 255.0
    return Reconstruction(
        positions=positions, faces=faces.astype(np.int32), kind="mesh",
        source=path, sha256=sha256_of_files([path]), colors=colors,
    )


def _require_declared_counts(path: Path, vertices: int, triangles: int) -> None:
    """InputError when trimesh read fewer vertices or faces than the PLY header declares
    (it accepts a short ASCII body without a word). A polygon of n corners gives n - 2
    triangles, so whole faces give at least as many triangles as declared faces."""
    header = read_header(path)
    declared = {element.name: element.count for element in header.elements}
    if declared.get("vertex", vertices) != vertices or declared.get("face", 0) > triangles:
        raise InputError(path, f"the header declares {declared.get('vertex')} vertices and {declared.get('face')} "
                               f"faces but the body holds {vertices} vertices and {triangles} triangles")
