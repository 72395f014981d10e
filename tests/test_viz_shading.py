"""Smooth and flat shading in pictures, checked on the pixels: a field linear in x is a
smooth ramp when drawn smooth and steps when drawn flat; nearer faces cover farther ones
whatever the face order; hidden markers stay hidden; the 2D projection is mplot3d's."""

from __future__ import annotations

import numpy as np
import pytest
from reference import icosphere

matplotlib = pytest.importorskip("matplotlib")

from stochlap_torch import viz  # noqa: E402
from stochlap_torch._common.errors import ParameterError  # noqa: E402
from stochlap_torch.viz import framing  # noqa: E402

#: The top of the drawing frame seen from above, with ``up="z"``: the picture's x is the mesh's x.
TOP = [(90.0, -90.0)]


def _pixels(path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as image:
        return np.asarray(image.convert("RGB"), dtype=np.int64)


def grid(cols: int = 9, rows: int = 5, z: float = 0.0, x0: float = 0.0, y0: float = 0.0):
    """A flat, regular, consistently wound grid of unit squares in the plane ``z``."""
    xs, ys = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64))
    vertices = np.stack([xs.ravel() + x0, ys.ravel() + y0, np.full(rows * cols, z)], axis=1)
    faces = []
    for r in range(rows - 1):
        for c in range(cols - 1):
            a = r * cols + c
            faces += [(a, a + 1, a + cols + 1), (a, a + cols + 1, a + cols)]
    return vertices, np.asarray(faces, dtype=np.int64)


def _middle_row(path) -> np.ndarray:
    """Grey levels along the middle row of the mesh, a few pixels in from its ends."""
    grey = _pixels(path)[..., 0]
    panel = grey[: int(grey.shape[0] * 0.7)]  # above the colour bar
    rows, cols = np.nonzero(panel < 250)
    row = (rows.min() + rows.max()) // 2
    return panel[row, cols.min() + 4 : cols.max() - 4]


def _ramp(tmp_path, shading: str) -> np.ndarray:
    vertices, faces = grid()
    path = viz.render_scalar(
        vertices,
        faces,
        vertices[:, 0],  # linear in x
        tmp_path / f"{shading}.png",
        views=TOP,
        up="z",
        cmap="gray",
        vmin=-2.0,
        vmax=10.0,  # no clipping, no white
        figsize=(8.0, 4.0),
        dpi=50,
        shading=shading,
    )
    return _middle_row(path)


def test_a_linear_field_drawn_smooth_is_a_ramp(tmp_path):
    ramp = _ramp(tmp_path, "smooth")
    steps = np.diff(ramp)
    assert ramp.size > 250
    assert steps.min() >= -1  # monotone, up to rounding
    assert steps.max() <= 2  # no face-constant steps
    assert len(np.unique(ramp)) > 80
    assert ramp[-1] - ramp[0] > 100


def test_a_linear_field_drawn_flat_has_steps(tmp_path):
    ramp = _ramp(tmp_path, "flat")
    assert np.diff(ramp).min() >= -1  # still monotone
    assert np.diff(ramp).max() >= 4  # a jump at each face edge
    assert len(np.unique(ramp)) < 60  # one colour per face (and the edges between)


def test_smooth_and_flat_differ_only_in_shading(tmp_path):
    smooth, flat = _ramp(tmp_path, "smooth"), _ramp(tmp_path, "flat")
    assert smooth.shape == flat.shape
    assert np.abs(smooth.astype(int) - flat).max() < 12  # a third of a face apart at most


def _two_sheets():
    """A 4 x 4 sheet at z=0 (values 0) under a 2 x 2 sheet at z=1 (values 1), centred."""
    lower, lower_faces = grid(5, 5, z=0.0)
    upper, upper_faces = grid(3, 3, z=1.0, x0=1.0, y0=1.0)
    vertices = np.vstack([lower, upper])
    faces = np.vstack([lower_faces, upper_faces + len(lower)])
    values = np.r_[np.zeros(len(lower)), np.ones(len(upper))]
    return vertices, faces, values


@pytest.mark.parametrize("reverse", [False, True])
@pytest.mark.parametrize("elev, shown", [(90.0, 1.0), (-90.0, 0.0)])
def test_nearer_faces_cover_farther_ones(tmp_path, reverse, elev, shown):
    vertices, faces, values = _two_sheets()
    if reverse:
        faces = faces[::-1]
    options = {"up": "z", "cmap": "gray", "vmin": -0.5, "vmax": 1.5, "dpi": 40}
    path = viz.render_scalar(
        vertices, faces, values, tmp_path / "s.png", views=[(elev, -90.0)], **options
    )
    grey = _pixels(path)[..., 0]
    panel = grey[: int(grey.shape[0] * 0.75)]
    rows, cols = np.nonzero(panel < 250)
    centre = panel[(rows.min() + rows.max()) // 2, (cols.min() + cols.max()) // 2]
    expected = (shown + 0.5) / 2.0 * 255  # before shading, which only darkens
    other = (1.5 - shown) / 2.0 * 255
    assert abs(centre - expected) < abs(centre - other)
    assert centre <= expected + 2


def _cyan_pixels(path) -> int:
    pixels = _pixels(path)
    return int((np.abs(pixels - np.array([0x19, 0xE6, 0xFF])).max(axis=2) < 40).sum())


def test_hidden_markers_stay_hidden(tmp_path):
    mesh = icosphere(3)
    view = (10.0, -60.0)
    frame, _ = framing.canonical_frame(mesh.vertices, "z", mesh.faces)
    facing = frame @ framing.direction(*view)
    front, back = int(np.argmax(facing)), int(np.argmin(facing))
    options = {"views": [view], "up": "z", "dpi": 80, "cmap": "Greys"}
    values = np.zeros(len(mesh.vertices))
    shown = viz.render_scalar(
        mesh.vertices, mesh.faces, values, tmp_path / "f.png", points=[front], **options
    )
    hidden = viz.render_scalar(
        mesh.vertices, mesh.faces, values, tmp_path / "b.png", points=[back], **options
    )
    assert _cyan_pixels(shown) > 20
    assert _cyan_pixels(hidden) == 0


@pytest.mark.parametrize(
    "elev, azim", [(20, -130), (0, -90), (90, -90), (-90, -90), (-60, 40), (45, 33)]
)
def test_the_projection_is_mplot3d_s(elev, azim):
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d import proj3d

    points = np.random.default_rng(0).normal(size=(40, 3))
    ax = Figure(figsize=(3.0, 3.0)).add_axes([0.0, 0.0, 1.0, 1.0], projection="3d")
    ax.set_proj_type("ortho")
    ax.view_init(elev, azim)
    for setter in (ax.set_xlim, ax.set_ylim, ax.set_zlim):
        setter(-3.0, 3.0)  # a cube, drawn as one (the old pictures' axes)
    ax.set_box_aspect((1.0, 1.0, 1.0))
    xs, ys, zs = proj3d.proj_transform(*points.T, ax.get_proj())
    xs, ys = ax.transData.transform(np.column_stack([xs, ys])).T  # pixels
    mine = points @ framing.screen_axes(elev, azim).T
    assert np.corrcoef(xs, mine[:, 0])[0, 1] > 0.999999
    assert np.corrcoef(ys, mine[:, 1])[0, 1] > 0.999999
    assert np.corrcoef(zs, mine[:, 2])[0, 1] < -0.999999  # mplot3d's depth grows away
    assert np.allclose(
        framing.screen_axes(elev, azim) @ framing.screen_axes(elev, azim).T, np.eye(3)
    )


def test_bad_shading_is_a_parameter_error(tmp_path):
    mesh = icosphere(1)
    with pytest.raises(ParameterError, match="shading must be one of smooth, flat"):
        viz.render_scalar(
            mesh.vertices, mesh.faces, np.ones(42), tmp_path / "x.png", shading="phong"
        )
    scales = np.stack([mesh.vertices, mesh.vertices])
    with pytest.raises(ParameterError, match="shading"):
        viz.render_multiscale(scales, mesh.faces, tmp_path / "x.png", shading=None)
    assert not (tmp_path / "x.png").exists()


def test_multiscale_flat_and_smooth(tmp_path):
    mesh = icosphere(2)
    scales = np.stack([mesh.vertices * (1.0 - 0.1 * k) for k in range(3)])
    pictures = {
        shading: _pixels(
            viz.render_multiscale(
                scales, mesh.faces, tmp_path / f"{shading}.png", dpi=30, shading=shading
            )
        )
        for shading in ("smooth", "flat")
    }
    # Same silhouettes, different shading inside.
    inked = {name: pixels.sum(axis=2) < 3 * 245 for name, pixels in pictures.items()}
    assert (inked["smooth"] != inked["flat"]).mean() < 0.01
    assert np.abs(pictures["smooth"] - pictures["flat"]).max() > 10
