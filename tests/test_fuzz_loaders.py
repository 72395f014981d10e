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

import stochlap_torch as sl
from stochlap_torch._common.errors import StochlapError

SEED = 20261123
MUTATIONS_PER_FILE = 100
#: Huge and tiny finite values: where float64 squared edge lengths overflow (1e155) or
#: vanish (1e-155), and where float32's squares overflow (1e20).
_HUGE_AND_TINY = ["1e100", "1e155", "-1e155", "1e-155", "1e20", "-1e-20"]
_REPLACEMENTS = [
    "nan", "inf", "-inf", "1e308", "-1e308", "1e-320", "0", "-1", "99999999999999999999999",
    "abc", "1.2.3", "", "\t", "3/4/5", "//", "0x10", "1e", "-", "4294967296", "2147483648",
    *_HUGE_AND_TINY,
]  # fmt: skip


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
    kind = rng.choice(["flip", "truncate", "delete_line", "duplicate_line", "swap_lines",
                       "replace_token", "insert_garbage"])  # fmt: skip
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
    dtypes and both saliency variants (issue 16 item 11: NaN, or a bare ValueError from the
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
