"""Seeded fuzzing of the mesh loaders: hundreds of mutated OBJ, OFF and PLY files.

Every mutated file must either load into a mesh the library then processes to a finite
saliency, or raise one of the library's named errors (a ``StochlapError``: ``MeshError`` for
an unreadable or invalid mesh). Any other exception, a NaN, or a hang is a defect. The
mutations are byte flips, truncations, deleted, duplicated and swapped lines, and numbers
replaced by garbage, huge and tiny finite values, ``nan``/``inf`` and out-of-range indices.
"""

from __future__ import annotations

import itertools
import random
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from scipy.stats import spearmanr

import stochlap_torch as sl
from stochlap_torch._common.errors import StochlapError

SEED = 20261123
MUTATIONS_PER_FILE = 100
#: Huge and tiny finite values: where float64 squared edge lengths overflow (1e155) or
#: vanish (1e-155), and where float32's squares overflow (1e20).
_HUGE_AND_TINY = ["1e100", "1e155", "-1e155", "1e-155", "1e20", "-1e-20"]
_REPLACEMENTS = [
    "nan",
    "inf",
    "-inf",
    "1e308",
    "-1e308",
    "1e-320",
    "0",
    "-1",
    "99999999999999999999999",
    "abc",
    "1.2.3",
    "",
    "\t",
    "3/4/5",
    "//",
    "0x10",
    "1e",
    "-",
    "4294967296",
    "2147483648",
    *_HUGE_AND_TINY,
]


def _base_files(folder: Path) -> list[Path]:
    """A small sphere as OBJ (with a polygon, texture indices and a comment), OFF, and
    PLY in ASCII and binary."""
    sphere = trimesh.creation.icosphere(1)
    lines = ["# a small sphere", "o sphere"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in sphere.vertices]
    lines += ["vt 0.5 0.5"]
    lines += [f"f {a + 1}/1 {b + 1}/1 {c + 1}/1" for a, b, c in sphere.faces[:-2]]
    a, b, c = sphere.faces[-2]
    lines += [f"f {a + 1} {b + 1} {c + 1} {sphere.faces[-1][2] + 1}"]
    obj = folder / "sphere.obj"
    obj.write_text("\n".join(lines) + "\n")
    off = folder / "sphere.off"
    off.write_bytes(trimesh.exchange.off.export_off(sphere).encode())
    ascii_ply = folder / "sphere_ascii.ply"
    ascii_ply.write_bytes(trimesh.exchange.ply.export_ply(sphere, encoding="ascii"))
    binary_ply = folder / "sphere_binary.ply"
    binary_ply.write_bytes(trimesh.exchange.ply.export_ply(sphere, encoding="binary"))
    return [obj, off, ascii_ply, binary_ply]


def _mutate(data: bytes, rng: random.Random) -> bytes:
    """One random mutation of a file's bytes."""
    kind = rng.choice(
        [
            "flip",
            "truncate",
            "delete_line",
            "duplicate_line",
            "swap_lines",
            "replace_token",
            "insert_garbage",
        ]
    )
    if kind == "flip" and data:
        position = rng.randrange(len(data))
        return (
            data[:position] + bytes([data[position] ^ rng.randrange(1, 256)]) + data[position + 1 :]
        )
    if kind == "truncate":
        return data[: rng.randrange(len(data) + 1)]
    if kind == "insert_garbage":
        position = rng.randrange(len(data) + 1)
        garbage = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 16)))
        return data[:position] + garbage + data[position:]
    lines = data.split(b"\n")
    if not lines:
        return data
    i, j = rng.randrange(len(lines)), rng.randrange(len(lines))
    if kind == "delete_line":
        del lines[i]
    elif kind == "duplicate_line":
        lines.insert(j, lines[i])
    elif kind == "swap_lines":
        lines[i], lines[j] = lines[j], lines[i]
    else:  # replace_token
        tokens = lines[i].split(b" ")
        tokens[rng.randrange(len(tokens))] = rng.choice(_REPLACEMENTS).encode()
        lines[i] = b" ".join(tokens)
    return b"\n".join(lines)


def test_mutated_mesh_files_load_or_raise_a_named_error(tmp_path: Path) -> None:
    rng = random.Random(SEED)
    outcomes = {"loaded": 0, "refused": 0}
    for base in _base_files(tmp_path):
        original = base.read_bytes()
        for number in range(MUTATIONS_PER_FILE):
            data = original
            for _ in range(rng.randrange(1, 4)):
                data = _mutate(data, rng)
            path = tmp_path / f"mutant_{number}{base.suffix}"
            path.write_bytes(data)
            try:
                mesh = sl.load_mesh(path)
                values = sl.saliency(mesh.vertices, mesh.faces, num_scales=3)
            except StochlapError:
                outcomes["refused"] += 1
                continue
            except Exception as error:
                pytest.fail(f"{base.name} mutant {number}: {type(error).__name__}: {error}")
            assert torch.isfinite(values).all(), f"{base.name} mutant {number}: NaN saliency"
            assert np.isfinite(mesh.vertices.numpy()).all()
            outcomes["loaded"] += 1
    # Both outcomes occur: the mutations are neither all harmless nor all fatal.
    assert outcomes["loaded"] > 40 and outcomes["refused"] > 40, outcomes


def _scaled_sphere_files(folder: Path, factor: float, whole: bool) -> list[Path]:
    """The small sphere as OBJ and OFF (text, every digit kept) with every vertex, or only
    vertex 5, multiplied by ``factor``."""
    sphere = trimesh.creation.icosphere(1)
    vertices = np.array(sphere.vertices, dtype=np.float64)
    if whole:
        vertices *= factor
    else:
        vertices[5] *= factor
    points = [f"{x!r} {y!r} {z!r}\n" for x, y, z in vertices.tolist()]
    obj = folder / "scaled.obj"
    obj_faces = [f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in sphere.faces]
    obj.write_text("".join("v " + point for point in points) + "".join(obj_faces))
    off = folder / "scaled.off"
    off_faces = [f"3 {a} {b} {c}\n" for a, b, c in sphere.faces]
    off.write_text(f"OFF\n{len(points)} {len(off_faces)} 0\n" + "".join(points + off_faces))
    return [obj, off]


def test_huge_and_tiny_coordinates_load_or_raise_a_named_error(tmp_path: Path) -> None:
    """The random mutations above rarely leave a huge value in a coordinate of a file that
    still loads: every such file here, whole mesh or one vertex scaled, in both loaders, both
    dtypes and both saliency variants (once: NaN, or a bare ValueError from the
    robust variant, at 1e155 in float64 and 1e20 in float32)."""
    failures = []
    for token, whole in itertools.product(_HUGE_AND_TINY, (True, False)):
        files = _scaled_sphere_files(tmp_path, float(token), whole)
        for path, dtype, variant in itertools.product(
            files, (torch.float64, torch.float32), ("robust", "paper")
        ):
            case = f"{token} {'all' if whole else 'one'} {path.suffix} {dtype} {variant}"
            try:
                mesh = sl.load_mesh(path, dtype=dtype)
                values = sl.saliency(mesh.vertices, mesh.faces, num_scales=3, variant=variant)
            except StochlapError:
                continue
            except Exception as error:
                failures.append(f"{case}: {type(error).__name__}: {error}")
                continue
            if not bool(torch.isfinite(values).all()):
                failures.append(f"{case}: non-finite saliency")
    assert failures == [], "\n".join(failures)


def _stl_files(folder: Path) -> list[Path]:
    """The small sphere as ASCII and binary STL (every facet with its own three corners)."""
    sphere = trimesh.creation.icosphere(1)
    files = []
    for name, data in [
        ("sphere_ascii.stl", trimesh.exchange.stl.export_stl_ascii(sphere).encode()),
        ("sphere_binary.stl", trimesh.exchange.stl.export_stl(sphere)),
    ]:
        files.append(folder / name)
        files[-1].write_bytes(data)
    return files


def test_mutated_stl_files_load_or_raise_a_named_error(tmp_path: Path) -> None:
    """STL files load merged into the connected sphere (as soups, the robust
    saliency followed the facets); mutants load or raise a named error, never hang."""
    rng = random.Random(SEED + 1)
    sphere = trimesh.creation.icosphere(1)
    outcomes = {"loaded": 0, "refused": 0}
    for base in _stl_files(tmp_path):
        mesh = sl.load_mesh(base)
        assert (mesh.num_vertices, mesh.num_faces) == (len(sphere.vertices), len(sphere.faces))
        original = base.read_bytes()
        for number in range(MUTATIONS_PER_FILE // 2):
            path = tmp_path / f"mutant_{number}{base.suffix}"
            path.write_bytes(_mutate(original, rng))
            try:
                mesh = sl.load_mesh(path)
                values = sl.saliency(mesh.vertices, mesh.faces, num_scales=3)
            except StochlapError:
                outcomes["refused"] += 1
                continue
            except Exception as error:
                pytest.fail(f"{base.name} mutant {number}: {type(error).__name__}: {error}")
            assert torch.isfinite(values).all(), f"{base.name} mutant {number}: NaN saliency"
            outcomes["loaded"] += 1
    assert outcomes["loaded"] > 10, outcomes


def test_mixed_winding_files_give_the_same_robust_saliency(tmp_path: Path) -> None:
    """The sphere written with random faces reversed gives the robust saliency of the same
    file's vertices with the faces consistently wound: to the bit where the file keeps the
    vertex order (OBJ, OFF, PLY), and by rank where STL's merge orders the vertices by facet
    and corner (once: 0.33-0.44 with half the faces flipped)."""
    rng = np.random.default_rng(SEED)
    sphere = trimesh.creation.icosphere(3)
    sphere.export(tmp_path / "wound.stl")
    wound = sl.load_mesh(tmp_path / "wound.stl")
    wound_saliency = sl.saliency(wound.vertices, wound.faces).numpy()
    for number in range(3):
        faces = sphere.faces.copy()
        chosen = rng.random(len(faces)) < rng.uniform(0.1, 0.9)
        faces[chosen] = faces[chosen, ::-1]
        mixed = trimesh.Trimesh(sphere.vertices, faces, process=False)
        for suffix in ("obj", "off", "ply"):
            path = tmp_path / f"mixed_{number}.{suffix}"
            mixed.export(path)
            mesh = sl.load_mesh(path)
            expected = sl.saliency(mesh.vertices, torch.from_numpy(sphere.faces))
            values = sl.saliency(mesh.vertices, mesh.faces)
            assert torch.equal(values, expected), (number, suffix)
        mixed.export(tmp_path / f"mixed_{number}.stl")
        mesh = sl.load_mesh(tmp_path / f"mixed_{number}.stl")
        order = {tuple(point): i for i, point in enumerate(wound.vertices.tolist())}
        match = [order[tuple(point)] for point in mesh.vertices.tolist()]
        values = sl.saliency(mesh.vertices, mesh.faces).numpy()
        assert spearmanr(values, wound_saliency[match])[0] > 0.99, number
