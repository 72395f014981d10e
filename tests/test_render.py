"""Pictures: PNG files of the expected size that show the mesh, and robust vertex colours."""

from __future__ import annotations

import struct
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from reference import icosphere, noisy_sphere, open_grid

matplotlib = pytest.importorskip("matplotlib")

from stochlap_torch import viz  # noqa: E402
from stochlap_torch.viz import colors, framing, shading  # noqa: E402
from stochlap_torch.viz.render import default_scales  # noqa: E402

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def _pixels(path: Path) -> np.ndarray:
    from PIL import Image  # a dependency of matplotlib

    with Image.open(path) as image:
        return np.asarray(image.convert("RGB"), dtype=np.int64)


def _non_white_fraction(pixels: np.ndarray) -> float:
    return float((pixels.sum(axis=2) < 3 * 245).mean())


# --------------------------------------------------------------------------------------------
# scalar_colors


def test_scalar_colors_shape_and_range():
    values = np.linspace(0.0, 1.0, 101)
    colours = viz.scalar_colors(values)
    assert colours.shape == (101, 4) and colours.dtype == np.uint8
    assert np.all(colours[:, 3] == 255)
    brightness = colours[:, :3].astype(int).sum(axis=1)
    assert brightness[-1] > brightness[0]  # inferno runs from dark to light


@pytest.mark.parametrize("value", [0.0, 3.5, -1e9])
def test_scalar_colors_constant_input(value):
    colours = viz.scalar_colors(np.full(10, value))
    assert colours.shape == (10, 4)
    assert np.all(colours == colours[0])  # one colour, no NaN turned into garbage
    expected = viz.scalar_colors(np.array([0.0, 0.5, 1.0]))[1]
    assert np.abs(colours[0].astype(int) - expected.astype(int)).max() <= 1  # middle colour


def test_scalar_colors_robust_to_outliers_and_nan():
    values = np.concatenate([np.linspace(0.0, 1.0, 200), [1e6, np.nan]])
    colours = viz.scalar_colors(values)
    # The outlier does not squash the others into the bottom colour.
    assert len({tuple(c) for c in colours[:200]}) > 50
    assert tuple(colours[-1]) == (128, 128, 128, 255)  # NaN is grey


def test_robust_range_ignores_unreferenced_vertices():
    mesh = icosphere(1)
    values = np.concatenate([np.linspace(0.0, 1.0, 42), np.full(10, -100.0)])
    lo, hi = viz.robust_range(values)
    assert lo == -100.0  # 10 of 52 vertices are far below: they set the 1st percentile
    lo, hi = viz.robust_range(values, mesh.faces)  # only the 42 vertices the faces use
    assert 0.0 <= lo < 0.05 and 0.95 < hi <= 1.0
    assert viz.robust_range(values, vmin=-1.0, vmax=2.0) == (-1.0, 2.0)
    lo, hi = viz.robust_range(np.full(5, 7.0))
    assert lo < 7.0 < hi


def test_scalar_colors_explicit_range_and_tensor_input():
    values = torch.tensor([0.0, 5.0, 10.0])
    colours = viz.scalar_colors(values, vmin=0.0, vmax=5.0)
    assert np.array_equal(colours[1], colours[2])  # clipped at vmax


def test_scalar_colors_without_matplotlib_matches(monkeypatch):
    values = np.linspace(-2.0, 3.0, 57)
    with_mpl = viz.scalar_colors(values).astype(int)

    def missing(_cmap):
        raise ImportError("no matplotlib")

    monkeypatch.setattr(colors, "colormap", missing)
    fallback = viz.scalar_colors(values).astype(int)
    assert np.abs(fallback - with_mpl).max() <= 12


def test_missing_matplotlib_message(monkeypatch):
    for name in list(sys.modules):
        if name == "matplotlib" or name.startswith(("matplotlib.", "mpl_toolkits")):
            monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(ImportError, match=r"stochlap_torch\[viz\]"):
        viz.render_scalar(*icosphere(1).tensors(), np.zeros(42), "unused.png")


# --------------------------------------------------------------------------------------------
# render_scalar


def test_render_scalar_size_and_content(tmp_path):
    mesh = noisy_sphere()
    values = mesh.vertices[:, 2]
    path = viz.render_scalar(
        mesh.vertices, mesh.faces, values, tmp_path / "s.png", figsize=(6, 3), dpi=50
    )
    assert path == tmp_path / "s.png"
    assert _png_size(path) == (300, 150)
    pixels = _pixels(path)
    assert 0.05 < _non_white_fraction(pixels) < 0.9
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 50  # shaded and coloured


def test_render_scalar_default_size_tensors_and_title(tmp_path):
    vertices, faces = icosphere(2).tensors(torch.float32)
    values = torch.rand(vertices.shape[0], generator=torch.Generator().manual_seed(0))
    path = viz.render_scalar(vertices, faces, values, tmp_path / "a" / "b.png")
    assert _png_size(path) == (1200, 480)
    path = viz.render_scalar(vertices, faces, values, tmp_path / "t.png", title="t", views=2)
    assert _png_size(path) == (800, 520)


@pytest.mark.parametrize("views", [1, 4, 5, [(10.0, 20.0)], [(0.0, 0.0), (90.0, 0.0)]])
def test_render_scalar_views(tmp_path, views):
    mesh = icosphere(1)
    path = viz.render_scalar(
        mesh.vertices, mesh.faces, mesh.vertices[:, 0], tmp_path / "v.png", views=views, dpi=30
    )
    count = views if isinstance(views, int) else len(views)
    assert _png_size(path) == (round(4 * count * 30), round(4.8 * 30))


def test_render_scalar_open_and_inconsistent_meshes(tmp_path):
    grid = open_grid()
    faces = grid.faces.copy()
    faces[::3] = faces[::3, ::-1]  # flip some triangles: inconsistent orientation
    for name, tris in (("open", grid.faces), ("flipped", faces)):
        path = viz.render_scalar(
            grid.vertices, tris, grid.vertices[:, 0], tmp_path / f"{name}.png", dpi=40
        )
        assert _non_white_fraction(_pixels(path)) > 0.02


def test_render_scalar_constant_values(tmp_path):
    mesh = icosphere(1)
    path = viz.render_scalar(mesh.vertices, mesh.faces, np.ones(42), tmp_path / "c.png", dpi=30)
    assert _png_size(path) == (360, 144)


def test_render_scalar_rejects_bad_input(tmp_path):
    mesh = icosphere(1)
    with pytest.raises(ValueError, match="one entry per vertex"):
        viz.render_scalar(mesh.vertices, mesh.faces, np.ones(5), tmp_path / "x.png")
    with pytest.raises(ValueError, match="face indices"):
        viz.render_scalar(mesh.vertices, mesh.faces + 100, np.ones(42), tmp_path / "x.png")
    with pytest.raises(ValueError, match="views"):
        viz.render_scalar(mesh.vertices, mesh.faces, np.ones(42), tmp_path / "x.png", views=0)
    with pytest.raises(ValueError, match="up"):
        viz.render_scalar(mesh.vertices, mesh.faces, np.ones(42), tmp_path / "x.png", up="w")


def test_rendering_leaves_the_backend_alone(tmp_path):
    before = matplotlib.get_backend()
    mesh = icosphere(1)
    viz.render_scalar(mesh.vertices, mesh.faces, np.ones(42), tmp_path / "b.png", dpi=20)
    assert matplotlib.get_backend() == before


# --------------------------------------------------------------------------------------------
# render_multiscale and render_interest_points


def test_render_multiscale_strip(tmp_path):
    mesh = noisy_sphere()
    scales = np.stack([mesh.vertices * (1.0 - 0.1 * k) for k in range(6)])
    path = viz.render_multiscale(scales, mesh.faces, tmp_path / "m.png")
    assert _png_size(path) == (round(3.2 * 5 * 100), 360)  # 5 panels by default
    path = viz.render_multiscale(
        torch.from_numpy(scales), mesh.faces, tmp_path / "m2.png", scales=[0, -1], dpi=50
    )
    assert _png_size(path) == (320, 180)
    pixels = _pixels(path)
    grey = np.abs(pixels - pixels.mean(axis=2, keepdims=True)).max(axis=2) < 4
    assert grey.all()  # grey shading only
    with pytest.raises(ValueError, match="scales"):
        viz.render_multiscale(scales, mesh.faces, tmp_path / "x.png", scales=[6])


def test_default_scales_evenly_spaced():
    assert default_scales(8) == [0, 2, 4, 5, 7]
    assert default_scales(3) == [0, 1, 2]
    assert default_scales(12)[0] == 0 and default_scales(12)[-1] == 11


def test_render_interest_points(tmp_path):
    mesh = noisy_sphere()
    saliency = mesh.vertices[:, 1]
    points = np.argsort(saliency)[-5:][::-1]
    path = viz.render_interest_points(
        mesh.vertices, mesh.faces, saliency, torch.from_numpy(points.copy()), tmp_path / "i.png"
    )
    assert _png_size(path) == (1200, 480)
    # No points at all is fine too.
    path = viz.render_interest_points(
        mesh.vertices, mesh.faces, saliency, np.zeros(0, dtype=np.int64), tmp_path / "e.png"
    )
    assert _png_size(path) == (1200, 480)
    with pytest.raises(ValueError, match="points"):
        viz.render_interest_points(
            mesh.vertices, mesh.faces, saliency, [10_000], tmp_path / "x.png"
        )


def test_visibility_of_points_on_a_sphere():
    mesh = icosphere(3)
    direction = framing.direction(20.0, -40.0)
    facing = mesh.vertices @ direction
    visible = shading.visible_points(mesh.vertices, mesh.faces, mesh.vertices, direction)
    assert visible[facing > 0.2].all()
    assert not visible[facing < -0.2].any()
