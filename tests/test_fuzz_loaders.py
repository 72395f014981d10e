"""Seeded fuzzing of the mesh loaders: hundreds of mutated OBJ, OFF and PLY files.

Every mutated file must either load into a mesh the library then processes to a finite
saliency, or raise one of the library's named errors (a ``StochlapError``: ``MeshError`` for
an unreadable or invalid mesh). Any other exception, a NaN, or a hang is a defect. The
mutations are byte flips, truncations, deleted, duplicated and swapped lines, and numbers
replaced by garbage, huge values, ``nan``/``inf`` and out-of-range indices.
"""

from __future__ import annotations

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
_REPLACEMENTS = [
    "nan", "inf", "-inf", "1e308", "-1e308", "1e-320", "0", "-1", "99999999999999999999999",
    "abc", "1.2.3", "", "\t", "3/4/5", "//", "0x10", "1e", "-", "4294967296", "2147483648",
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
