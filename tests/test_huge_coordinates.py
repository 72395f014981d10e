"""Large and tiny finite coordinates: a finite result equal to the one at unit size, or a named
error; never NaN, never a bare exception, never an ``inf`` file."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from reference import noisy_sphere

import stochlap_torch as sl
from stochlap_torch._common.errors import FileFormatError, MeshError

SCALES = {torch.float64: (1e155, 1e-155, 1e300), torch.float32: (1e20, 1e-20, 1e35)}
CALLS = {
    "saliency robust": lambda v, f: sl.saliency(v, f),
    "saliency paper": lambda v, f: sl.saliency(v, f, variant="paper"),
    "saliency normal_displacement": lambda v, f: sl.saliency(v, f, variant="normal_displacement"),
    "features robust": lambda v, f: sl.multiscale_features(v, f),
    "features paper": lambda v, f: sl.multiscale_features(v, f, variant="paper"),
}


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("name", sorted(CALLS))
def test_scaled_meshes_give_the_unit_size_result(name, dtype):
    vertices, faces = noisy_sphere().tensors(dtype)
    expected = CALLS[name](vertices, faces)
    tolerance = 1e-9 if dtype == torch.float64 else 1e-3
    for scale in SCALES[dtype]:
        result = CALLS[name](vertices * scale, faces)
        assert bool(torch.isfinite(result).all()), scale
        torch.testing.assert_close(result, expected, atol=tolerance, rtol=tolerance)


def test_positions_come_back_at_the_input_scale():
    vertices, faces = noisy_sphere().tensors()
    rep = sl.multiscale_representation(vertices * 1e155, faces, 4)
    expected = sl.multiscale_representation(vertices, faces, 4)
    assert bool(torch.isfinite(rep.positions).all())
    torch.testing.assert_close(rep.positions / 1e155, expected.positions, rtol=1e-12, atol=0)


@pytest.mark.parametrize("far", [1e100, 1e30, 1e12, 1e6])
@pytest.mark.parametrize("mesh", ["sphere", "spot"])
def test_a_vertex_far_out_gives_a_finite_saliency_or_a_named_error(mesh, far):
    if mesh == "spot":
        loaded = sl.load_mesh(sl.bundled_mesh_path())
        vertices, faces = loaded.vertices.clone(), loaded.faces
    else:
        vertices, faces = noisy_sphere().tensors()
    vertices[0] = torch.tensor([far, 0.0, 0.0], dtype=torch.float64)
    try:
        result = sl.saliency(vertices, faces)
    except MeshError as error:  # the robust variant may refuse such a mesh, naming a way out
        assert "variant='paper'" in str(error)
    else:
        assert bool(torch.isfinite(result).all())
    assert bool(torch.isfinite(sl.saliency(vertices, faces, variant="paper")).all())


@pytest.mark.parametrize("scale", [1e155, 1e-155])
def test_ply_output_refuses_coordinates_float32_cannot_hold(tmp_path, scale):
    vertices, faces = noisy_sphere().tensors()
    with pytest.raises(FileFormatError, match="float32"):
        sl.save_ply(tmp_path / "out.ply", vertices * scale, faces)
    assert not (tmp_path / "out.ply").exists()
    sl.save_ply(tmp_path / "ok.ply", vertices * 1e20, faces)  # within float32: written
    assert np.isfinite(sl.load_mesh(tmp_path / "ok.ply").vertices.numpy()).all()


@pytest.mark.parametrize("variant", ["robust", "paper"])
def test_cli_on_a_huge_mesh_exits_2_with_one_line_or_writes_finite_files(tmp_path, capsys, variant):
    from stochlap_torch.cli import main

    vertices, faces = noisy_sphere().tensors()
    mesh_path = tmp_path / "huge.obj"
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in (vertices * 1e155).tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces.tolist()]
    mesh_path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "huge_saliency.ply"
    status = main(["saliency", str(mesh_path), "-o", str(out), "--no-png", "--variant", variant])
    # refused before any computing: no progress line, only the error
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and "float32" in err[0]
    assert not out.exists()
