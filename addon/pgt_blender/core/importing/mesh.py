"""Mesh files (OBJ, PLY with faces, GLB/GLTF, STL) -> Reconstruction, through trimesh."""

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import TEXT_LIMIT, listed, regular_file
from ..reconstruction import Reconstruction
from .ply import read_header
from .source import checked_positions, sha256_of_files

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl")


def load_mesh(path: Path) -> Reconstruction:
    """Triangles in the file's frame and units. A multi-part scene (GLB, OBJ groups) is
    flattened with its node transforms applied; per-vertex colors are kept when the
    file has them. Vertices are not merged or reordered (``process=False``)."""
    path = Path(path)
    mesh = _trimesh_load(path, "mesh")
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


def _trimesh_load(path: Path, force: str):
    """trimesh.load of ``path`` as a "mesh" or a "scene" (``force``), unprocessed;
    InputError naming the file when it cannot be read."""
    import trimesh

    if path.suffix.lower() == ".obj":
        _require_readable_obj(path)
    try:
        return trimesh.load(str(path), force=force, process=False)
    except IndexError:  # trimesh indexes the vertices with the faces as read
        raise InputError(path, "could not be read as a mesh: a face refers to a vertex the file does not have") \
            from None
    except Exception as error:  # trimesh raises many types for corrupt files
        raise InputError(path, f"could not be read as a mesh: {error}") from None


# a face line's index (vertex, texture or normal) that is zero: OBJ counts from 1 (or back from -1)
_ZERO_INDEX = re.compile(rb"^[ \t]*f[ \t][^\n#]*?(?<=[ \t/])[+-]?0+(?=[ \t/\r\n#]|$)", re.M)
_MATERIAL_LIBRARY = re.compile(rb"^[ \t]*mtllib[ \t]+([^\r\n#]+?)[ \t]*(?:#[^\r\n]*)?\r?$", re.M)


def _require_readable_obj(path: Path) -> None:
    """InputError naming the OBJ ``path`` and the line of a face with an index 0, which
    trimesh reads as the last vertex (a silently wrong triangle; about 15 ms per MB), or
    a material library it names that trimesh would wait on or read whole (a pipe, a
    huge file: files.regular_file). A library that is not there trimesh goes without."""
    try:
        data = path.read_bytes()
    except OSError as error:
        raise InputError(path, f"cannot read the file ({error.strerror or error})") from None
    zero = _ZERO_INDEX.search(data)
    if zero:
        line = data.count(b"\n", 0, zero.start()) + 1
        raise InputError(path, f"line {line}: a face index is 0; OBJ indices count from 1 (or back from -1)")
    for names in _MATERIAL_LIBRARY.findall(data):  # one name with spaces, or several
        for name in dict.fromkeys([names, *names.split()]):
            library = path.parent / os.fsdecode(name)
            if os.path.lexists(library):
                regular_file(library, TEXT_LIMIT)


def _require_declared_counts(path: Path, vertices: int, triangles: int) -> None:
    """InputError when trimesh read fewer vertices or faces than the PLY header declares
    (it accepts a short ASCII body without a word). A polygon of n corners gives n - 2
    triangles, so whole faces give at least as many triangles as declared faces."""
    header = read_header(path)
    declared = {element.name: element.count for element in header.elements}
    if declared.get("vertex", vertices) != vertices or declared.get("face", 0) > triangles:
        raise InputError(path, f"the header declares {declared.get('vertex')} vertices and {declared.get('face')} "
                               f"faces but the body holds {vertices} vertices and {triangles} triangles")


@dataclass(frozen=True)
class MaterialMesh:
    """A mesh with its per-face appearance, in the file's frame and units.

    vertices (V, 3) float64; faces (F, 3) int64; face_srgb (F, 3) float32 sRGB in [0, 1]
    (the material's diffuse color ``Kd``, else the mean of the face's vertex colors;
    NaN where the file gives no color); see_through (F,) bool (glass: the material's
    name, or an .mtl dissolve ``d`` < 1, which trimesh does not keep; see
    scan/targets.see_through_materials)."""

    vertices: np.ndarray
    faces: np.ndarray
    face_srgb: np.ndarray
    see_through: np.ndarray


def read_material_mesh(path) -> MaterialMesh:
    """``path`` (OBJ + MTL, GLB/GLTF, PLY, STL) with its parts' transforms applied,
    through trimesh; InputError naming the file when it has no faces or cannot be read."""
    from ..scan.targets import see_through_materials

    path = Path(path)
    scene = _trimesh_load(path, "scene")
    parts = [geometry for geometry in scene.dump() if len(getattr(geometry, "faces", ()))]
    if not parts:
        raise InputError(path, "mesh has no faces")
    alphas = _mtl_dissolves(path) if path.suffix.lower() == ".obj" else {}
    vertices, faces, colors, names, offset = [], [], [], [], 0
    for part in parts:
        material = getattr(part.visual, "material", None)
        if material is not None:
            color = np.tile(np.asarray(material.main_color[:3], np.float32) / 255, (len(part.faces), 1))
        elif part.visual.kind is not None:
            color = np.asarray(part.visual.face_colors[:, :3], np.float32) / 255
        else:
            color = np.full((len(part.faces), 3), np.nan, np.float32)
        vertices.append(np.asarray(part.vertices, np.float64))
        faces.append(np.asarray(part.faces, np.int64) + offset)
        colors.append(color)
        names.append(getattr(material, "name", "") or "")
        offset += len(part.vertices)
    flags = see_through_materials(names, [alphas.get(name, 1.0) for name in names])
    return MaterialMesh(checked_positions(path, np.concatenate(vertices), "vertices"), np.concatenate(faces),
                        np.concatenate(colors), np.repeat(flags, [len(part.faces) for part in parts]))


def _mtl_dissolves(path: Path) -> dict:
    """Material name -> dissolve ``d`` of the .mtl libraries beside an OBJ."""
    alphas = {}
    for library in listed(path.parent, "*.mtl"):
        name = None
        for line in regular_file(library, TEXT_LIMIT).read_text(errors="replace").splitlines():
            words = line.split()
            if words[:1] == ["newmtl"] and len(words) > 1:
                name = words[1]
            elif words[:1] == ["d"] and name and len(words) > 1:
                try:
                    alphas[name] = float(words[1])
                except ValueError:
                    raise InputError(library, f"material {name}: dissolve 'd' must be a number, got "
                                              f"{words[1]!r}") from None
    return alphas
