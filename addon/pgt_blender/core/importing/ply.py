"""Strict PLY reading and writing for point clouds (numpy, no per-point Python).

Why not trimesh's PLY reader: it silently accepts an ASCII body with fewer or more
rows than the header declares. Here every mismatch between header and body is an
InputError. Meshes (PLY with faces) still go through trimesh (see ``mesh.py``).
"""

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import atomic_output, regular_file

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_TYPE_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort",
               "i4": "int", "u4": "uint", "f4": "float", "f8": "double"}
_BYTE_ORDER = {"ascii": "<", "binary_little_endian": "<", "binary_big_endian": ">"}
_MAX_HEADER_BYTES = 1 << 16


@dataclass
class PlyElement:
    name: str
    count: int
    properties: list = field(default_factory=list)  # [(name, numpy type code)]
    list_properties: list = field(default_factory=list)  # names of list properties

    def dtype(self, byte_order: str) -> np.dtype:
        return np.dtype([(name, byte_order + code) for name, code in self.properties])


@dataclass
class PlyHeader:
    format: str
    elements: list
    size: int  # bytes up to and including the end_header line

    def element(self, name: str) -> PlyElement | None:
        return next((e for e in self.elements if e.name == name), None)


def read_header(path: Path) -> PlyHeader:
    """Parse the header of ``path``; InputError when it is not a valid PLY header."""
    path = regular_file(path)
    try:
        with open(path, "rb") as stream:
            head = stream.read(_MAX_HEADER_BYTES)
    except OSError as error:
        raise InputError(path, f"cannot be read ({error.strerror})") from None
    if not head.startswith(b"ply"):
        raise InputError(path, "not a PLY file (it does not start with 'ply')")
    end = head.find(b"end_header")
    if end < 0:
        raise InputError(path, "PLY header has no 'end_header' line (truncated or corrupt)")
    size = head.index(b"\n", end) + 1 if b"\n" in head[end:] else len(head)
    fmt, elements = None, []
    for number, raw in enumerate(head[:end].decode("ascii", "replace").splitlines()[1:], 2):
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
                if fmt not in _BYTE_ORDER:
                    raise ValueError(f"unknown format '{fmt}'")
            elif words[0] == "element":
                elements.append(PlyElement(words[1], int(words[2])))
                if elements[-1].count < 0:
                    raise ValueError("negative element count")
            elif words[0] == "property":
                name = words[4] if words[1] == "list" else words[2]
                element = elements[-1]
                if name in element.list_properties or name in (known for known, _ in element.properties):
                    raise ValueError(f"property '{name}' appears twice in element '{element.name}'")
                if words[1] == "list":
                    element.list_properties.append(name)
                elif words[1] not in PLY_TYPES:
                    raise ValueError(f"unknown property type '{words[1]}'")
                else:
                    element.properties.append((name, PLY_TYPES[words[1]]))
            else:
                raise ValueError(f"unexpected keyword '{words[0]}'")
        except (IndexError, ValueError) as error:
            raise InputError(path, f"bad PLY header line {number} '{raw.strip()}': {error}") from None
    if fmt is None:
        raise InputError(path, "PLY header has no 'format' line")
    for element in elements:
        if element.count and not (element.properties or element.list_properties):
            raise InputError(path, f"PLY element '{element.name}' declares {element.count} rows but no properties")
    return PlyHeader(fmt, elements, size)


def read_vertices(path: Path, header: PlyHeader | None = None) -> dict:
    """The ``vertex`` element of a point PLY as {property name: (N,) contiguous array},
    in header order and native byte order.

    Every element must have fixed-size rows (no list properties with rows), and the
    body must hold exactly the rows the header declares, else InputError.
    """
    path = Path(path)
    header = header or read_header(path)
    vertex = header.element("vertex")
    if vertex is None:
        raise InputError(path, "PLY has no 'vertex' element")
    for element in header.elements:
        if element.list_properties and element.count:
            raise InputError(
                path, f"element '{element.name}' has list properties; a point PLY cannot hold them"
            )
    if header.format == "ascii":
        return _read_ascii_vertices(path, header, vertex)
    return _columns(_read_binary_vertices(path, header, vertex))


_TRANSPOSE_ROWS = 4096  # rows per transposed block: fits the CPU cache


def _columns(table: np.ndarray) -> dict:
    """Split a structured array into contiguous columns. Copying field by field out of
    rows of 60+ floats, or one big transpose, is cache-hostile; transposing blocks of
    rows is ~5x faster on a 1M-splat file."""
    names = table.dtype.names
    types = {table.dtype[name] for name in names}
    if len(types) > 1:
        return {name: np.ascontiguousarray(table[name]) for name in names}
    rows = table.view(types.pop()).reshape(len(table), len(names))
    columns = np.empty(rows.shape[::-1], rows.dtype)
    for start in range(0, len(rows), _TRANSPOSE_ROWS):
        columns[:, start:start + _TRANSPOSE_ROWS] = rows[start:start + _TRANSPOSE_ROWS].T
    return dict(zip(names, columns))


def _read_binary_vertices(path, header, vertex):
    byte_order = _BYTE_ORDER[header.format]
    offset = header.size
    for element in header.elements:
        if element is vertex:
            break
        offset += element.count * element.dtype(byte_order).itemsize
    expected = header.size + sum(e.count * e.dtype(byte_order).itemsize for e in header.elements)
    actual = os.path.getsize(path)
    declared = ", ".join(f"{e.count} {e.name}" for e in header.elements)
    if actual < expected:
        raise InputError(
            path, f"truncated: the header declares {declared} ({expected} bytes) "
            f"but the file has {actual} bytes"
        )
    if actual > expected:
        raise InputError(
            path, f"{actual - expected} bytes follow the declared {declared}: "
            "element counts do not match the data"
        )
    if vertex.count == 0:
        return np.empty(0, vertex.dtype("="))
    # Mapped, not read: the columns are copied out once, straight from the page cache.
    data = np.memmap(path, dtype=vertex.dtype(byte_order), mode="r", offset=offset, shape=(vertex.count,))
    return data.astype(vertex.dtype("="), copy=False)


def _read_ascii_vertices(path, header, vertex):
    with open(path, "rb") as stream:
        stream.seek(header.size)
        rows = [row for row in stream.read().splitlines() if row.strip()]
    declared = sum(e.count for e in header.elements)
    if len(rows) != declared:
        raise InputError(
            path, f"the header declares {declared} data rows "
            f"({', '.join(f'{e.count} {e.name}' for e in header.elements)}) but the body has {len(rows)}"
        )
    start = sum(e.count for e in header.elements[: header.elements.index(vertex)])
    columns = len(vertex.properties)
    try:
        values = np.array(b" ".join(rows[start:start + vertex.count]).split(), dtype=np.float64)
    except ValueError as error:
        raise InputError(path, f"non-numeric value in the vertex rows ({error})") from None
    if values.size != vertex.count * columns:
        raise InputError(path, f"vertex rows must hold {columns} values each; some rows differ")
    table = values.reshape(vertex.count, columns)
    for index, (name, code) in enumerate(vertex.properties):
        kind = np.dtype(code)
        if kind.kind in "iu":  # an integer property must hold whole numbers its type can store
            column = table[:, index]
            info = np.iinfo(kind)
            bad = (column != np.round(column)) | (column < info.min) | (column > info.max)
            if bad.any():
                raise InputError(path, f"property {name} ({kind.name}) holds {column[bad][0]:g} in row "
                                       f"{int(np.argmax(bad)) + 1}: not a {kind.name} value "
                                       f"({info.min}..{info.max})")
    return {name: np.ascontiguousarray(table[:, index], dtype=code)
            for index, (name, code) in enumerate(vertex.properties)}


def write_ply(path: Path, columns: dict, binary: bool = True) -> None:
    """Write a point PLY with one scalar property per entry of ``columns``
    (name -> (N,) array; its dtype picks the PLY type, bool is written as uchar 0/1).
    Written to a temporary file and renamed, so a failed write leaves no partial file."""
    path = Path(path)
    arrays = {name: np.asarray(values) for name, values in columns.items()}
    arrays = {name: a.astype(np.uint8) if a.dtype == bool else a for name, a in arrays.items()}
    count = len(next(iter(arrays.values())))
    dtype = np.dtype([(name, "<" + a.dtype.str[1:]) for name, a in arrays.items()])
    lines = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
             f"element vertex {count}"]
    lines += [f"property {_TYPE_NAMES[dtype[name].str[1:]]} {name}" for name in dtype.names]
    lines.append("end_header")
    table = np.empty(count, dtype)
    for name, values in arrays.items():
        table[name] = values
    with atomic_output(path) as stream:
        stream.write(("\n".join(lines) + "\n").encode("ascii"))
        if binary:
            table.tofile(stream)
        else:
            formats = ["%d" if dtype[n].kind in "iu" else "%.9g" for n in dtype.names]
            np.savetxt(stream, np.column_stack([table[n] for n in dtype.names]), fmt=formats)
