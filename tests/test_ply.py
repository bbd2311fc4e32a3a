"""The strict PLY reader and writer (no bpy)."""

import numpy as np
import pytest

from pgt_blender.core.errors import InputError
from pgt_blender.core.importing.ply import read_header, read_vertices, write_ply

HEADER = "ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"


def columns(count=5, seed=0):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(count, 3)).astype(np.float32)
    return {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
            "red": rng.integers(0, 256, count).astype(np.uint8),
            "weight": rng.random(count).astype(np.float64)}


@pytest.mark.parametrize("binary", [True, False])
def test_write_read_round_trip(tmp_path, binary):
    data = columns()
    path = tmp_path / "points.ply"
    write_ply(path, data, binary=binary)
    header = read_header(path)
    assert header.format == ("binary_little_endian" if binary else "ascii")
    table = read_vertices(path)
    assert tuple(table) == tuple(data)
    for name, values in data.items():
        assert table[name].dtype == values.dtype and table[name].flags.c_contiguous
        np.testing.assert_allclose(table[name], values, rtol=1e-7)


def test_big_endian_binary(tmp_path):
    path = tmp_path / "be.ply"
    xyz = np.arange(6, dtype=">f4")
    path.write_bytes(HEADER.format(fmt="binary_big_endian", n=2).encode() + xyz.tobytes())
    np.testing.assert_array_equal(read_vertices(path)["y"], [1.0, 4.0])


def test_write_leaves_no_partial_file_on_error(tmp_path):
    path = tmp_path / "bad.ply"
    with pytest.raises(KeyError):  # complex numbers have no PLY type
        write_ply(path, {"x": np.zeros(3, np.complex64)})
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("content, problem", [
    (b"hello\n", "not a PLY file"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", "no 'end_header'"),
    (b"ply\nelement vertex 1\nproperty float x\nend_header\n", "no 'format' line"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty floot x\nend_header\n", "unknown property type 'floot'"),
    (b"ply\nformat ascii 1.0\nelement vertex many\nproperty float x\nend_header\n", "bad PLY header line 3"),
    (b"ply\nformat binary_middle_endian 1.0\nend_header\n", "unknown format"),
])
def test_bad_headers(tmp_path, content, problem):
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(InputError, match=problem) as error:
        read_vertices(path)
    assert str(error.value).startswith(str(path)) and "\n" not in str(error.value)


def test_binary_truncated(tmp_path):
    path = tmp_path / "t.ply"
    path.write_bytes(HEADER.format(fmt="binary_little_endian", n=4).encode() + bytes(12 * 3 + 5))
    with pytest.raises(InputError, match=r"truncated: the header declares 4 vertex \(\d+ bytes\)"):
        read_vertices(path)


def test_binary_more_data_than_declared(tmp_path):
    path = tmp_path / "m.ply"
    path.write_bytes(HEADER.format(fmt="binary_little_endian", n=2).encode() + bytes(12 * 3))
    with pytest.raises(InputError, match="12 bytes follow the declared 2 vertex"):
        read_vertices(path)


@pytest.mark.parametrize("declared, rows", [(3, 2), (2, 3)])
def test_ascii_row_count_mismatch(tmp_path, declared, rows):
    path = tmp_path / "a.ply"
    path.write_text(HEADER.format(fmt="ascii", n=declared) + "0 0 0\n" * rows)
    with pytest.raises(InputError, match=f"declares {declared} data rows .* but the body has {rows}"):
        read_vertices(path)


def test_ascii_ragged_and_non_numeric_rows(tmp_path):
    path = tmp_path / "r.ply"
    path.write_text(HEADER.format(fmt="ascii", n=2) + "0 0 0\n1 1\n")
    with pytest.raises(InputError, match="3 values each"):
        read_vertices(path)
    path.write_text(HEADER.format(fmt="ascii", n=2) + "0 0 0\n1 x 1\n")
    with pytest.raises(InputError, match="non-numeric"):
        read_vertices(path)


def test_list_properties_refused_in_point_ply(tmp_path):
    path = tmp_path / "l.ply"
    path.write_text(HEADER.format(fmt="ascii", n=1).replace(
        "end_header", "element edge 1\nproperty list uchar int vertex_indices\nend_header") + "0 0 0\n1 0\n")
    with pytest.raises(InputError, match="element 'edge' has list properties"):
        read_vertices(path)
