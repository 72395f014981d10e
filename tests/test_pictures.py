"""Pictures for a paper: --dpi, --cmap, --views, --no-title; a colour bar
that says where it clips; a mesh lying on its side stood upright; large meshes drawn from a
decimated copy."""

from __future__ import annotations

import argparse
import struct
from pathlib import Path

import numpy as np
import pytest
import trimesh
from reference import icosphere, noisy_sphere

matplotlib = pytest.importorskip("matplotlib")

from stochlap_torch import viz  # noqa: E402
from stochlap_torch._common.errors import ParameterError  # noqa: E402
from stochlap_torch.cli import common, main  # noqa: E402
from stochlap_torch.viz import backend, colors, decimate, drawing, framing, render  # noqa: E402
from stochlap_torch.viz.shading import Geometry  # noqa: E402


def _png_size(path: Path) -> tuple[int, int]:
    data = Path(path).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


# --------------------------------------------------------------------------------------------
# Views


def test_views_by_name_pair_and_count():
    names = framing.VIEW_NAMES
    assert framing.resolve_views("front,side,top") == [names["front"], names["side"], names["top"]]
    assert framing.resolve_views(" Front , 20:-130") == [names["front"], (20.0, -130.0)]
    assert framing.resolve_views("3") == framing.default_views(3)
    assert framing.resolve_views(["back", (10, 5)]) == [names["back"], (10.0, 5.0)]
    # "front" looks straight at the broad side (azimuth -90 of the drawing frame).
    assert np.allclose(framing.direction(*names["front"]), [0.0, -1.0, 0.0], atol=1e-12)
    assert np.allclose(framing.direction(*names["top"]), [0.0, 0.0, 1.0], atol=1e-12)


@pytest.mark.parametrize(
    "views, message",
    [
        ("front,nope", "unknown view 'nope'"),
        ("100:0", "unknown view"),  # elevation beyond 90
        ("", "at least one"),
        (",", "at least one"),
        ("0", "at least 1"),
        (13, "at most 12"),
        ([(0.0, float("nan"))], "finite"),
        ([(1.0, 2.0, 3.0)], "pair"),
    ],
)
def test_bad_views_are_parameter_errors(views, message):
    with pytest.raises(ParameterError, match=message):
        framing.resolve_views(views)


def test_named_views_make_one_panel_each(tmp_path):
    mesh = icosphere(1)
    path = viz.render_scalar(
        mesh.vertices,
        mesh.faces,
        mesh.vertices[:, 0],
        tmp_path / "v.png",
        views="front,top",
        dpi=20,
    )
    assert _png_size(path) == (2 * 4 * 20, round(4.8 * 20))


def test_multiscale_views_are_rows(tmp_path):
    mesh = icosphere(1)
    scales = np.stack([mesh.vertices * (1.0 - 0.1 * k) for k in range(3)])
    path = viz.render_multiscale(scales, mesh.faces, tmp_path / "m.png", views="front,top", dpi=20)
    assert _png_size(path) == (round(3.2 * 3 * 20), round(2 * 3.6 * 20))


# --------------------------------------------------------------------------------------------
# Library-level checks of dpi and cmap


@pytest.mark.parametrize("dpi", [0, -5, 1, 5000, float("nan"), float("inf"), "many", True])
def test_bad_dpi_is_a_parameter_error(tmp_path, dpi):
    mesh = icosphere(1)
    with pytest.raises(ParameterError, match=r"dpi must be a number in \[10, 600\]"):
        viz.render_scalar(mesh.vertices, mesh.faces, np.ones(42), tmp_path / "x.png", dpi=dpi)
    with pytest.raises(ParameterError, match="dpi"):
        viz.plot_error_curves([0.1], {"m": {"fne": [0], "fpe": [0], "wme": [0]}}, "x.png", dpi=dpi)
    assert not (tmp_path / "x.png").exists()


def test_unknown_cmap_names_valid_ones(tmp_path):
    mesh = icosphere(1)
    with pytest.raises(ParameterError, match=r"unknown colormap 'viridiss'.*viridis"):
        viz.render_scalar(
            mesh.vertices, mesh.faces, np.ones(42), tmp_path / "x.png", cmap="viridiss"
        )
    assert colors.check_cmap("viridis") == "viridis"


def test_cmap_and_dpi_are_used(tmp_path):
    mesh = noisy_sphere()
    values = mesh.vertices[:, 2]
    args = (mesh.vertices, mesh.faces, values)
    greys = viz.render_scalar(*args, tmp_path / "g.png", cmap="Greys", dpi=30, views=1)
    assert _png_size(greys) == (120, 144)
    from PIL import Image

    with Image.open(greys) as image:
        pixels = np.asarray(image.convert("RGB"), dtype=np.int64)
    # A grey colormap with grey shading leaves no colour at all.
    assert np.abs(pixels - pixels.mean(axis=2, keepdims=True)).max() <= 3


# --------------------------------------------------------------------------------------------
# The colour bar says where it clips


@pytest.mark.parametrize(
    "span, extend",
    [((0.0, 1.0), "neither"), ((0.0, 2.86), "max"), ((-1.0, 1.0), "min"), ((-1.0, 3.0), "both")],
)
def test_clipped_ends(span, extend):
    assert colors.clipped_ends(span, 0.0, 1.0) == extend


def test_clipped_ends_of_nothing_finite():
    assert colors.clipped_ends(None, 0.0, 1.0) == "neither"
    assert colors.value_span(np.array([np.nan, np.inf])) is None


def test_value_span_counts_only_drawn_vertices():
    values = np.array([5.0, 1.0, 2.0, 3.0, -9.0])
    assert colors.value_span(values, np.array([[1, 2, 3]])) == (1.0, 3.0)
    assert colors.value_span(values) == (-9.0, 5.0)


def _bar(span):
    fig = backend.new_figure((6.0, 2.0), 50)
    return drawing.add_colorbar(fig, [0.2, 0.4, 0.6, 0.1], "inferno", 0.0, 1.9, "s", span)


def _notes(bar) -> list[str]:
    return [text.get_text() for text in bar.ax.texts]


def test_colour_bar_notes_the_true_maximum_when_clipped():
    bar = _bar((0.0, 2.86))
    assert bar.extend == "max"
    assert _notes(bar) == ["max 2.86"]
    bar = _bar((-0.5, 2.86))
    assert bar.extend == "both"
    assert sorted(_notes(bar)) == ["max 2.86", "min -0.5"]


def test_colour_bar_has_no_arrow_when_nothing_is_clipped():
    bar = _bar((0.0, 1.9))
    assert bar.extend == "neither"
    assert _notes(bar) == []


def _drawn_bar(monkeypatch, tmp_path, values, **options):
    """The colour bar render_scalar draws for ``values`` on icosphere(1)."""
    bars = []
    original = drawing.add_colorbar

    def spy(*args, **kwargs):
        bars.append(original(*args, **kwargs))
        return bars[-1]

    monkeypatch.setattr(drawing, "add_colorbar", spy)
    mesh = icosphere(1)
    viz.render_scalar(mesh.vertices, mesh.faces, values, tmp_path / "c.png", dpi=20, **options)
    (bar,) = bars
    return bar


def test_render_marks_a_clipped_outlier(monkeypatch, tmp_path):
    values = np.linspace(0.0, 1.0, 42)
    values[:5] = 0.0  # the 1st percentile is the minimum: nothing clipped below
    values[7] = 2.86  # beyond the 99th percentile: clipped
    bar = _drawn_bar(monkeypatch, tmp_path, values)
    assert bar.extend == "max"
    assert _notes(bar) == ["max 2.86"]


def test_render_without_clipping_has_no_arrow(monkeypatch, tmp_path):
    values = np.linspace(0.0, 1.0, 42)
    bar = _drawn_bar(monkeypatch, tmp_path, values, vmin=0.0, vmax=1.0)
    assert bar.extend == "neither" and _notes(bar) == []
    bar = _drawn_bar(monkeypatch, tmp_path, values, vmin=0.2, vmax=1.0)
    assert bar.extend == "min" and _notes(bar) == ["min 0"]


# --------------------------------------------------------------------------------------------
# Upright


def _box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """A closed axis-aligned box, outward-oriented."""
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])],
        float,
    )
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return corners, np.array([tri for a, b, c, d in quads for tri in ((a, c, b), (a, d, c))])


def _table_z_up() -> tuple[np.ndarray, np.ndarray]:
    """A thin table top (1.8 x 4 along x, y) on four legs standing along +z: a file stored
    z-up, longest along y, so that y-up would stand it on a thin edge."""
    parts = [_box((0.0, 0.0, 1.95), (1.8, 4.0, 2.0))]
    for x in (0.2, 1.5):
        for y in (0.5, 3.4):
            parts.append(_box((x, y, 0.0), (x + 0.1, y + 0.1, 1.95)))
    vertices, faces, offset = [], [], 0
    for v, f in parts:
        vertices.append(v)
        faces.append(f + offset)
        offset += v.shape[0]
    return np.vstack(vertices), np.vstack(faces)


def test_support_of_a_table():
    vertices, faces = _table_z_up()
    standing, centred = framing.support(vertices, faces, "z")
    # The feet span (1.6 - 0.2 + 0.1) x (3.5 - 0.5) of the 1.8 x 4 cross-section.
    assert standing == pytest.approx(1.4 * 3.0 / (1.8 * 4.0))
    assert centred
    edge, _ = framing.support(vertices, faces, "y")
    assert edge == pytest.approx(1.8 * 0.05 / (1.8 * 2.0))  # the edge of the top
    assert framing.support(vertices, faces, "-z")[0] == pytest.approx(1.0)  # the top itself


def test_a_mesh_lying_on_its_side_is_stood_upright():
    vertices, faces = _table_z_up()
    assert framing.guess_up(vertices, faces) == "z"
    # Stored with its legs along -z it also stands well on its top: the file's + is kept.
    assert framing.guess_up(vertices * np.array([1.0, -1.0, -1.0]), faces) == "z"
    # Legs along -z on a top too narrow to stand on: -z.
    narrow = vertices.copy()
    top = narrow[:, 2] > 1.9
    narrow[top, 0] = np.clip(narrow[top, 0], 0.85, 0.95)
    narrow[top, 1] = np.clip(narrow[top, 1], 1.95, 2.05)
    assert framing.guess_up(narrow * np.array([1.0, -1.0, -1.0]), faces) == "-z"
    # Stored y-up (z -> y, y -> -z; a rotation), it stays y. (The narrow top: a broad flat
    # top would turn it over, by the flat-base rule.)
    turned = np.stack([narrow[:, 0], narrow[:, 2], -narrow[:, 1]], axis=1)
    assert framing.guess_up(turned, faces) == "y"
    # An explicit up is kept.
    rotation, _, _ = framing.frame_axes(vertices, "y", faces)
    assert np.allclose(rotation[2], [0.0, 1.0, 0.0])


def test_lying_mesh_renders_legs_down(tmp_path):
    vertices, faces = _table_z_up()
    path = viz.render_scalar(
        vertices, faces, np.zeros(len(vertices)), tmp_path / "t.png", views="front", dpi=40
    )
    from PIL import Image

    with Image.open(path) as image:
        dark = np.asarray(image.convert("L"), dtype=np.int64)[: 4 * 40] < 200
    ink = dark.sum(axis=1)
    rows = np.flatnonzero(ink)
    # Seen from the front the top is a wide line above two narrow legs.
    assert ink[rows[0] : rows[0] + 3].max() > 3 * ink[rows[-1] - 3 : rows[-1]].max()


def test_shared_z_up_meshes_stand_upright(meshes_dir):
    from stochlap_torch import load_mesh

    for name in ("horse_48k.ply", "polygirl.off"):
        mesh = load_mesh(meshes_dir / name)
        assert framing.guess_up(mesh.vertices.numpy(), mesh.faces.numpy()) == "z", name


# --------------------------------------------------------------------------------------------
# Large meshes are drawn from a decimated copy


def test_within_the_budget_every_face_is_drawn():
    mesh = icosphere(2)
    assert decimate.drawing_faces(mesh.vertices, mesh.faces, 320) is mesh.faces
    assert decimate.drawing_faces(mesh.vertices, mesh.faces, None) is mesh.faces


def test_decimated_faces_index_the_original_vertices():
    mesh = icosphere(3)  # 1280 faces
    drawn = decimate.drawing_faces(mesh.vertices, mesh.faces, 200)
    assert 100 <= drawn.shape[0] <= 200
    assert drawn.dtype == np.int64 and drawn.min() >= 0 and drawn.max() < len(mesh.vertices)
    assert (np.sort(drawn, axis=1)[:, :-1] != np.sort(drawn, axis=1)[:, 1:]).all()
    # Still a closed, outward sphere: back faces are culled and shading stays smooth.
    geometry = Geometry(mesh.vertices, drawn)
    assert geometry.outward == 1.0 and geometry.vertex_normals is not None
    area = trimesh.Trimesh(mesh.vertices, drawn, process=False).area
    assert area == pytest.approx(4.0 * np.pi, rel=0.1)


def test_decimation_skips_unreferenced_vertices():
    mesh = icosphere(3)
    # Stray vertices all over the same sphere, nearer to many decimated points than any
    # vertex of the mesh.
    strays = icosphere(4).vertices
    vertices = np.vstack([strays, mesh.vertices])
    drawn = decimate.drawing_faces(vertices, mesh.faces + len(strays), 200)
    assert drawn.min() >= len(strays)  # never snapped to a stray vertex


def test_snapping_drops_degenerate_and_stacked_triangles():
    triangles = np.array(
        [[0, 1, 2], [3, 3, 4], [5, 6, 7], [7, 6, 5], [2, 1, 8], [4, 5, 5], [9, 8, 9]]
    )
    kept = decimate._without_repeats(triangles)
    # A repeated corner has no area; two triangles on the same three vertices are a fold.
    assert kept.tolist() == [[0, 1, 2], [2, 1, 8]]


def test_markers_move_to_drawn_vertices():
    mesh = icosphere(3)
    drawn = decimate.drawing_faces(mesh.vertices, mesh.faces, 200)
    dropped = np.setdiff1d(np.arange(len(mesh.vertices)), np.unique(drawn))[:5]
    moved = decimate.nearest_drawn(mesh.vertices, drawn, dropped)
    assert np.isin(moved, drawn).all()
    used = np.unique(drawn)
    for point, target in zip(dropped, moved, strict=True):
        distances = np.linalg.norm(mesh.vertices[used] - mesh.vertices[point], axis=1)
        assert np.linalg.norm(mesh.vertices[target] - mesh.vertices[point]) == distances.min()


def _drawn_face_counts(monkeypatch, tmp_path, **options) -> list[int]:
    counts = []
    original = render.draw_mesh

    def spy(ax, frame, faces, *args):
        counts.append(faces.shape[0])
        return original(ax, frame, faces, *args)

    monkeypatch.setattr(render, "draw_mesh", spy)
    mesh = noisy_sphere()
    points = np.arange(0, 162, 20)
    viz.render_scalar(
        mesh.vertices,
        mesh.faces,
        mesh.vertices[:, 0],
        tmp_path / "d.png",
        dpi=20,
        views=2,
        points=points,
        **options,
    )
    return counts


def test_render_draws_a_decimated_copy_above_the_budget(monkeypatch, tmp_path):
    assert _drawn_face_counts(monkeypatch, tmp_path, max_faces=None) == [320, 320]
    assert _drawn_face_counts(monkeypatch, tmp_path) == [320, 320]  # within the default budget
    counts = _drawn_face_counts(monkeypatch, tmp_path, max_faces=100)
    assert len(counts) == 2 and all(50 <= count <= 100 for count in counts)


@pytest.mark.parametrize("max_faces", [0, 3, 2.5, "many", True])
def test_bad_face_budget_is_a_parameter_error(tmp_path, max_faces):
    mesh = icosphere(1)
    with pytest.raises(ParameterError, match="max_faces"):
        viz.render_scalar(
            mesh.vertices, mesh.faces, np.ones(42), tmp_path / "x.png", max_faces=max_faces
        )


# --------------------------------------------------------------------------------------------
# The command line


def test_picture_options_pass_through():
    seen = {}

    def scalar(path, *, title=None, cmap="inferno", dpi=100, views=3):
        seen.update(title=title, cmap=cmap, dpi=dpi, views=views)

    args = argparse.Namespace(dpi=300, cmap="viridis", views=[(0.0, -90.0)], no_title=True)
    args.quiet = True
    common.draw_picture(args, "p.png", scalar, title="a title")
    assert seen == {"title": None, "cmap": "viridis", "dpi": 300, "views": [(0.0, -90.0)]}
    # Options not given leave the picture's own defaults.
    args = argparse.Namespace(dpi=None, cmap=None, views=None, no_title=False, quiet=True)
    common.draw_picture(args, "p.png", scalar, title="a title")
    assert seen == {"title": "a title", "cmap": "inferno", "dpi": 100, "views": 3}


def test_an_option_a_picture_cannot_use_is_refused():
    def grey(path, *, title=None, dpi=100):
        raise AssertionError("not drawn")

    args = argparse.Namespace(dpi=None, cmap="viridis", views=None, no_title=False, quiet=True)
    with pytest.raises(common.CommandError, match="--cmap does not apply"):
        common.draw_picture(args, "p.png", grey)


@pytest.mark.parametrize(
    "option, message",
    [
        (["--cmap", "nope"], "unknown colormap 'nope'"),
        (["--views", "front,nope"], "unknown view 'nope'"),
        (["--dpi", "0"], "--dpi: must lie in [10, 600], got '0'"),
        # Issue 32: a FreeType traceback, minutes and gigabytes, a bad_alloc traceback, each
        # after the PLY was written; and every view built before the count was checked.
        (["--dpi", "1"], "--dpi: must lie in [10, 600], got '1'"),
        (["--dpi", "5000"], "--dpi: must lie in [10, 600]"),
        (["--dpi", "100000"], "--dpi: must lie in [10, 600]"),
        (["--views", "99999999999999999999"], "at most 12 views fit a picture"),
        (["--views", "13"], "at most 12 views fit a picture, got 13"),
    ],
)
def test_bad_picture_options_are_usage_errors(workdir_tmp, capsys, option, message):
    assert main(["saliency", *option]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.splitlines()) == 1
    assert not list(workdir_tmp.iterdir())  # refused before any work


def test_a_huge_view_count_is_refused_without_building_the_views():
    """Issue 32: ``--views 99999999999999999999`` built every view (16 GB) before the check;
    here in a process of at most 1 GiB."""
    import resource
    import subprocess
    import sys

    def limit_memory():
        resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))

    code = "from stochlap_torch.viz.framing import resolve_views; resolve_views(10**20)"
    result = subprocess.run(
        [sys.executable, "-c", code],
        preexec_fn=limit_memory,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert "ParameterError: at most 12 views fit a picture" in result.stderr


@pytest.fixture
def workdir_tmp(tmp_path, monkeypatch) -> Path:
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_saliency_picture_with_every_option(workdir_tmp):
    mesh = icosphere(2)
    trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(workdir_tmp / "ball.obj")
    argv = ["saliency", "ball.obj", "-K", "3", "-q", "--threads", "1", "--png", "b.png"]
    argv += ["--dpi", "30", "--views", "front,top", "--no-title", "--cmap", "viridis"]
    assert main(argv) == 0
    assert _png_size(workdir_tmp / "b.png") == (2 * 4 * 30, round(4.8 * 30))  # no title room


def test_the_cli_bounds_dpi_as_the_pictures_do():
    from stochlap_torch.cli import options
    from stochlap_torch.viz import _arrays

    assert (options.DPI_MIN, options.DPI_MAX) == _arrays.DPI_RANGE


def test_the_cli_shading_reaches_the_picture(tmp_path):
    """``--shading flat`` changes the picture from the smooth default; another name is a usage
    error."""
    from stochlap_torch.cli import main

    common_args = ["saliency", "-K", "3", "--variant", "paper", "--views", "1", "--dpi", "30"]
    outputs = {}
    for shading in ("flat", "smooth"):
        png = tmp_path / f"{shading}.png"
        ply = str(tmp_path / f"{shading}.ply")
        assert main([*common_args, "-o", ply, "--png", str(png), "--shading", shading, "-q"]) == 0
        outputs[shading] = png.read_bytes()
    assert outputs["flat"] != outputs["smooth"]
    with pytest.raises(SystemExit):
        options_parser = argparse.ArgumentParser()
        from stochlap_torch.cli import options

        options.add_picture_options(options_parser)
        options_parser.parse_args(["--shading", "gouraud"])
