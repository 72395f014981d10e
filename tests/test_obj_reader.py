"""The OBJ reader: the bulk (numpy) parse of regular files equals the line-by-line reader and
hand-written expectations, and every irregular file still gets the line reader's answer."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import stochlap_torch as sl
from stochlap_torch.mesh import io

SQUARE = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]

#: name -> (file text, expected vertices, expected faces, read in bulk?)
CASES = {
    "triangles": (
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n",
        SQUARE,
        [[0, 1, 2], [0, 2, 3]],
        True,
    ),
    "quad fanned": (
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n",
        SQUARE,
        [[0, 1, 2], [0, 2, 3]],
        True,
    ),
    "slashes, CRLF, tabs, indent": (
        "v 0 0 0\r\nv\t1 0 0\r\n  v 1 1 0\r\nv 0 1 0\r\nvt 0 0\r\nvn 0 0 1\r\n"
        "f 1/1/1 2//1 3/1\r\n\tf 1 3 4\r\n",
        SQUARE,
        [[0, 1, 2], [0, 2, 3]],
        True,
    ),
    "weights and colours ignored": (
        "v 0 0 0 1 0.5 0.5\nv 1 0 0 1 0.5 0.5\nv 1 1 0 1 0 0\nv 0 1 0 1 0 0\nf 1 2 3\nf 1 3 4\n",
        SQUARE,
        [[0, 1, 2], [0, 2, 3]],
        True,
    ),
    "comments, groups, unreferenced last vertex": (
        "# a square\no sq\nv 0 0 0\nv 1 0 0\nv 1 1 0\ng top\nv 0 1 0\nusemtl m\nf 1 2 3\nv 9 9 9\n",
        [*SQUARE, [9, 9, 9]],
        [[0, 1, 2]],
        True,
    ),
    "negative indices": (
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nf -3 -2 -1\nv 0 1 0\nf 1 3 4\n",
        SQUARE,
        [[0, 1, 2], [0, 2, 3]],
        False,
    ),
    "mixed polygons": (
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\nf 1 2 4\n",
        SQUARE,
        [[0, 1, 2], [0, 2, 3], [0, 1, 3]],
        False,
    ),
    "mixed vertex widths": (
        "v 0 0 0\nv 1 0 0 1\nv 1 1 0\nv 0 1 0\nf 1 2 3\n",
        SQUARE,
        [[0, 1, 2]],
        False,
    ),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_obj_records_are_read_as_written(tmp_path: Path, name: str) -> None:
    text, vertices, faces, bulk = CASES[name]
    path = tmp_path / "mesh.obj"
    path.write_bytes(text.encode())
    assert (io._read_regular_obj(path.read_bytes()) is not None) == bulk
    got_vertices, got_faces = io.read_obj(path)
    assert got_vertices.dtype == np.float64 and got_faces.dtype == np.int64
    assert got_vertices.flags.c_contiguous and got_faces.flags.c_contiguous
    np.testing.assert_array_equal(got_vertices, np.array(vertices, dtype=np.float64))
    np.testing.assert_array_equal(got_faces, np.array(faces, dtype=np.int64))


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("v 0 0 0\nv 1 0 0\nv 1 x 0\nf 1 2 3\n", ":3: vertex coordinates are not numbers"),
        ("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 q\n", ":4: face vertex 'q' is not an index"),
        ("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 0\n", ":4: face vertex index 0 is out of range"),
        ("v 0 0\nv 1 0\nv 1 1\nf 1 2 3\n", ":1: a vertex needs three coordinates"),
        ("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2\n", ":4: a face needs at least 3 vertices"),
        ("v 0 0 0\nv 1 0 0\nv 1 1 0\n", "no faces found"),
        ("v 0 0 0\nv\nv 1 0 0\nv 1 1 0\nf 1 2 3\n", ":2: a vertex needs three coordinates"),
        ("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3\nf\n", ":5: a face needs at least 3 vertices"),
        ("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 99999999999999999999999\n", "out of range"),
    ],
)
def test_a_bad_record_is_named_with_its_line(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.obj"
    path.write_text(text)
    with pytest.raises(sl.MeshError, match=message):
        io.read_obj(path)


@pytest.mark.parametrize(
    "name", ["spot.obj", "bunny.obj", "armadillo.obj", "cow.obj", "maxplanck.obj", "nefertiti.obj"]
)
def test_real_obj_files_read_in_bulk_as_line_by_line(meshes_dir: Path, name: str) -> None:
    """The shared OBJ files (texture coordinates, unreferenced vertices) take the bulk path and
    give exactly the line reader's arrays."""
    path = meshes_dir / name
    if not path.exists():
        pytest.skip(f"real mesh {path} not found")
    bulk = io._read_regular_obj(path.read_bytes())
    assert bulk is not None
    lines = io._read_obj_lines(path)
    for got, expected in zip(bulk, lines, strict=True):
        np.testing.assert_array_equal(got, expected)
