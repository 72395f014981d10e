"""Which way is up in pictures: signed ``up`` axes, the guess (flat base at the bottom), and
reproducible renders."""

from __future__ import annotations

import numpy as np
import pytest
from reference import icosphere

from stochlap_torch._common.errors import ParameterError
from stochlap_torch.viz import framing

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def cone(segments: int = 48, height: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """A closed cone along +y: a flat disc of radius 1 at y=0 (the base), apex at y=height;
    outward-oriented faces."""
    angles = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    rim = np.stack([np.cos(angles), np.zeros(segments), np.sin(angles)], axis=1)
    vertices = np.vstack([rim, [[0.0, height, 0.0]], [[0.0, 0.0, 0.0]]])
    apex, centre = segments, segments + 1
    faces = []
    for i in range(segments):
        j = (i + 1) % segments
        faces += [(i, apex, j), (i, j, centre)]
    return vertices, np.array(faces, dtype=np.int64)


def upside_down(vertices: np.ndarray) -> np.ndarray:
    """Turned over about the z axis (a rotation: orientation is kept)."""
    return vertices * np.array([-1.0, -1.0, 1.0])


def test_the_cone_is_oriented_outward():
    vertices, faces = cone()
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    assert np.einsum("ij,ij->i", a, np.cross(b, c)).sum() > 0


def test_guess_keeps_a_mesh_standing_on_its_base():
    vertices, faces = cone()
    assert framing.guess_up(vertices, faces) == "y"
    assert framing.guess_up(upside_down(vertices), faces) == "-y"
    # No faces, or no flat region at either end: the file's +y.
    assert framing.guess_up(upside_down(vertices)) == "y"
    sphere = icosphere(2)
    assert framing.guess_up(sphere.vertices, sphere.faces) == "y"


def test_flat_at_both_ends_is_not_turned_over():
    # A closed box (flat at the top and the bottom): no reason to turn it over.
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 2) for z in (0, 1)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))])
    assert framing.guess_up(corners, faces) == "y"
    assert framing.guess_up(upside_down(corners), faces) == "y"


def test_flat_mesh_lies_flat():
    # y is the smallest extent: the middle extent (z here) is up.
    vertices = np.array([[0, 0, 0], [4, 0.1, 0], [0, 0, 2], [4, 0.1, 2]], float)
    assert framing.guess_up(vertices, np.array([[0, 1, 2], [1, 3, 2]])) == "z"


@pytest.mark.parametrize("up", ["x", "y", "z", "-x", "-y", "-z", "+y"])
def test_frame_puts_the_signed_axis_up(up):
    vertices, faces = cone()
    rotation, _, _ = framing.frame_axes(vertices, up, faces)
    assert np.allclose(rotation @ rotation.T, np.eye(3))
    assert np.linalg.det(rotation) == pytest.approx(1.0)  # a rotation: no mirror image
    axis = np.zeros(3)
    axis["xyz".index(up[-1])] = -1.0 if up.startswith("-") else 1.0
    assert np.allclose(rotation[2], axis)


def test_explicit_up_is_never_turned_over():
    vertices, faces = cone()
    frame, _ = framing.canonical_frame(upside_down(vertices), "y", faces)
    assert frame[-2, 2] < 0  # the apex stays at the bottom: the user said +y
    frame, _ = framing.canonical_frame(upside_down(vertices), None, faces)
    assert frame[-2, 2] > 0  # the guess turns it over


@pytest.mark.parametrize("up", ["w", "yy", "", 1])
def test_bad_up_is_a_parameter_error(up):
    with pytest.raises(ParameterError, match="up must be one of"):
        framing.parse_up(up)


def test_shared_meshes_are_upright(meshes_dir):
    from stochlap_torch import load_mesh

    expected = {"gargoyle_50k.off": "-y", "gargoyle.off": "y", "spot.obj": "y", "bunny.obj": "y"}
    for name, up in expected.items():
        mesh = load_mesh(meshes_dir / name)
        assert framing.guess_up(mesh.vertices.numpy(), mesh.faces.numpy()) == up, name


# --------------------------------------------------------------------------------------------
# Pictures


@pytest.fixture
def viz():
    pytest.importorskip("matplotlib")
    from stochlap_torch import viz

    return viz


def _ink_rows(path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as image:
        pixels = np.asarray(image.convert("L"), dtype=np.int64)
    return (pixels < 200).sum(axis=1)  # dark pixels per row, top to bottom


def test_upside_down_file_renders_base_down(viz, tmp_path):
    vertices, faces = cone()
    flipped = upside_down(vertices)
    path = viz.render_scalar(
        flipped, faces, np.zeros(len(vertices)), tmp_path / "c.png", views=[(0.0, -90.0)], dpi=40
    )
    rows = np.flatnonzero(_ink_rows(path)[: 4 * 40] > 0)  # the mesh panel, above the bar
    top, bottom = rows[0], rows[-1]
    widths = _ink_rows(path)
    # The cone's wide base is at the bottom of the picture, its apex at the top.
    assert widths[bottom - 2] > 3 * widths[top + 2]


def test_renders_are_reproducible(viz, tmp_path):
    vertices, faces = cone()
    values = vertices[:, 1]
    first = viz.render_scalar(vertices, faces, values, tmp_path / "a.png", dpi=30, title="t")
    second = viz.render_scalar(vertices, faces, values, tmp_path / "b.png", dpi=30, title="t")
    assert first.read_bytes() == second.read_bytes()
    assert first.read_bytes()[:8] == PNG_SIGNATURE
