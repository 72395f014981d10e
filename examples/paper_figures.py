"""Reproduce the paper's figures as PNGs in docs/figures (one command, a few minutes).

    python examples/paper_figures.py [--only fig01 fig05 ...] [--out docs/figures]

Meshes come from ``../shared/meshes`` (see its SOURCES.md). The paper's exact meshes are not
all available; the closest ones are used and named in every figure:

* ``fig01_sparsity.png`` (Fig. 1): entries per row of ``F^(k)`` and the sparsity pattern of
  ``F^(1), F^(4), F^(8), F^(12)`` on the 9926-vertex horse, with the paper's threshold
  ``lambda = 1e-3`` and "without thresholding", which here means ``lambda = 1e-12`` (exact
  zero would keep entries down to the float64 underflow; 1e-12 drops nothing that matters for
  K = 12 on this mesh).
* ``fig03_sphere_multiscale.png`` (Fig. 3): an icosphere (642 vertices, 12 of valence 5) at
  k = 1, 5, 10, 20; ``fig04_sphere_displacement.png`` (Fig. 4a): the displacement
  ``|P^(11) - P^(10)|`` drawn on ``S^(10)``, the valence-5 vertices marked.
* ``fig05_spectral_vs_stochastic.png`` (Fig. 5): the horse projected on its first k cotangent
  Laplacian eigenvectors against ``P^(k)`` of the stochastic Laplacian.
* ``fig10_saliency_gallery.png`` (Fig. 10): paper-mode saliency (K = 8) on several meshes.
* ``fig11_laplacians.png`` (Fig. 11): Algorithm 2 with the uniform, cotangent and stochastic
  Laplacians on the cow, and the ``normal_displacement`` variant.
* ``fig12_gargoyle_interest.png``, ``fig13_camel_interest.png``, ``fig14_cow_interest.png``
  (Figs. 12-14): interest points (non-maximum suppression, radius 0.1, the 20 most salient)
  of the paper-mode saliency and of the ``normal_displacement`` variant.

The README's and the CLI guide's pictures come from the very commands those pages quote
(run as ``python -m stochlap_torch``), so that a picture cannot drift from what the
command gives:

* ``../spot_saliency.png``: ``stochlap saliency --png spot_saliency.png`` (README);
* ``readme_multiscale_bunny.png``: ``stochlap multiscale bunny.obj -K 16 --scales 1 4 8 12 16``;
* ``readme_interest_armadillo.png``: ``stochlap interest armadillo.obj --top-k 20``.
"""

# The gallery shows a committed figure: the build does not run this script.
# sphinx_gallery_thumbnail_path = "figures/fig10_saliency_gallery.png"

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

import stochlap_torch as sl
from stochlap_torch.baselines import laplacian_saliency, spectral_reconstruction
from stochlap_torch.mesh import vertex_valence
from stochlap_torch.viz.render import render_interest_points, render_multiscale, render_scalar

ROOT = Path(__file__).resolve().parents[1]
MESH_DIR = ROOT.parent / "shared" / "meshes"

#: Vertical axis of each mesh file and a good (elevation, azimuth) view.
UP = {
    "horse_10k.obj": "y",
    "gargoyle.off": "y",
    "camel.off": "y",
    "cow.obj": "y",
    "foot.off": "z",
    "maxplanck.obj": "y",
    "polygirl.off": "z",
    "dinosaur.obj": "y",
    "squirrel.off": "y",
    "armadillo.obj": "y",
}


def load(name: str) -> sl.Mesh:
    mesh = sl.load_mesh(MESH_DIR / name)
    return sl.Mesh(mesh.vertices.double(), mesh.faces)


def _figure(width: float, height: float, dpi: float = 100):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def tile(
    paths: list[Path],
    titles: list[str],
    out: Path,
    columns: int,
    suptitle: str,
    panel_width: float = 4.2,
) -> None:
    """Lay out already rendered PNGs in a grid with a title over each."""
    import matplotlib.image as mpimg

    images = [mpimg.imread(p) for p in paths]
    rows = (len(images) + columns - 1) // columns
    aspect = images[0].shape[0] / images[0].shape[1]
    width = panel_width * columns
    fig = _figure(width, rows * panel_width * aspect + 0.9)
    for i, (image, title) in enumerate(zip(images, titles, strict=True)):
        ax = fig.add_subplot(rows, columns, i + 1)
        ax.imshow(image)
        ax.set_title(title, fontsize=10)
        ax.axis("off")
    fig.suptitle(suptitle, fontsize=12)
    fig.subplots_adjust(
        left=0.01,
        right=0.99,
        bottom=0.01,
        top=1 - 0.8 / fig.get_figheight(),
        wspace=0.02,
        hspace=0.08,
    )
    fig.savefig(out)


def fig01(out: Path, tmp: Path) -> None:
    mesh = load("horse_10k.obj")
    num = mesh.vertices.shape[0]
    runs = {}
    for label, threshold in (
        ("lambda = 1e-3 (paper)", 1e-3),
        ("lambda = 1e-12 (no threshold)", 1e-12),
    ):
        start = time.perf_counter()
        rep = sl.multiscale_representation(
            mesh.vertices, mesh.faces, 12, threshold, return_operators=True
        )
        runs[label] = (rep, time.perf_counter() - start)
    scales = (1, 4, 8, 12)
    fig = _figure(15.0, 8.2)
    grid = fig.add_gridspec(2, 5, width_ratios=[1.35, 1, 1, 1, 1])
    ax = fig.add_subplot(grid[:, 0])
    for label, (rep, seconds) in runs.items():
        per_row = (rep.entries.double() / num).numpy()
        ax.plot(np.arange(1, 13), per_row, marker="o", label=f"{label}, {seconds:.1f} s")
    ax.set_xlabel("scale k")
    ax.set_ylabel("stored entries per row of F^(k)")
    ax.set_title("sparsity growth (horse, 9926 vertices)", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    bins = 300
    for row, (label, (rep, _)) in enumerate(runs.items()):
        for col, k in enumerate(scales):
            operator = rep.operators[k - 1]
            crow = operator.crow_indices().numpy()
            rows = np.repeat(np.arange(num), np.diff(crow))
            cols = operator.col_indices().numpy()
            density, _, _ = np.histogram2d(rows, cols, bins=bins, range=[[0, num], [0, num]])
            axk = fig.add_subplot(grid[row, col + 1])
            axk.imshow(np.log1p(density), cmap="Greys", interpolation="nearest")
            axk.set_xticks([])
            axk.set_yticks([])
            nnz = int(rep.entries[k - 1])
            axk.set_title(f"k={k}: {nnz / num:.0f}/row, {100 * nnz / num**2:.2f}% full", fontsize=9)
            if col == 0:
                axk.set_ylabel(label, fontsize=9)
    fig.suptitle("Fig. 1: non-zero pattern of F^(k) (log density, file vertex order)", fontsize=12)
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.07, top=0.9, wspace=0.15, hspace=0.2)
    fig.savefig(out / "fig01_sparsity.png")


def fig03_04(out: Path, tmp: Path) -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3)
    vertices = torch.tensor(np.asarray(sphere.vertices), dtype=torch.float64)
    faces = torch.tensor(np.asarray(sphere.faces), dtype=torch.int64)
    rep = sl.multiscale_representation(vertices, faces, 20, 1e-3)
    render_multiscale(
        rep.positions,
        faces,
        out / "fig03_sphere_multiscale.png",
        scales=[0, 4, 9, 19],
        up="z",
        view=(25.0, -60.0),
        title="Fig. 3: icosphere (642 vertices) at k = 1, 5, 10, 20",
    )
    displacement = (rep.positions[10] - rep.positions[9]).norm(dim=1)
    five = (vertex_valence(faces, vertices.shape[0]) == 5).nonzero().flatten()
    render_interest_points(
        rep.positions[9],
        faces,
        displacement,
        five,
        out / "fig04_sphere_displacement.png",
        views=[(25.0, -60.0), (-30.0, 120.0)],
        up="z",
        cmap="viridis",
        label="|P^(11) - P^(10)|",
        title="Fig. 4a: displacement from S^(10) to S^(11); markers: the valence-5 vertices",
    )


def fig05(out: Path, tmp: Path) -> None:
    mesh = load("horse_10k.obj")
    ks = [10, 30, 100, 300]
    spectral = spectral_reconstruction(mesh.vertices, mesh.faces, ks)
    positions = torch.cat([mesh.vertices.unsqueeze(0), spectral])
    view = (10.0, -90.0)
    import matplotlib.image as mpimg

    strips = []
    for i, k in enumerate(ks):
        # Frame from the input (scale index 0), panel labelled with the number of eigenvectors.
        path = tmp / f"spectral_{k}.png"
        render_multiscale(
            positions[[0, i + 1]],
            mesh.faces,
            path,
            scales=[1],
            up=UP["horse_10k.obj"],
            view=view,
            first_scale=k - 1,
        )
        strips.append(mpimg.imread(path))
    top = np.concatenate(strips, axis=1)
    rep = sl.multiscale_representation(mesh.vertices, mesh.faces, 12, 1e-3)
    render_multiscale(
        rep.positions,
        mesh.faces,
        tmp / "stochastic.png",
        scales=[0, 2, 5, 8, 11],
        up=UP["horse_10k.obj"],
        view=view,
    )
    bottom = mpimg.imread(tmp / "stochastic.png")
    fig = _figure(
        16.0, 16.0 * top.shape[0] / top.shape[1] + 16.0 * bottom.shape[0] / bottom.shape[1] + 0.9
    )
    for i, (image, text) in enumerate(
        [
            (
                top,
                "(a) spectral mesh processing: projection on the first k = 10, 30, 100, 300 "
                "cotangent-Laplacian eigenvectors",
            ),
            (bottom, "(b) stochastic mesh Laplacian: P^(k), k = 1, 3, 6, 9, 12"),
        ]
    ):
        ax = fig.add_subplot(2, 1, i + 1)
        ax.imshow(image)
        ax.set_title(text, fontsize=10)
        ax.axis("off")
    fig.suptitle("Fig. 5: horse (9926 vertices), spectral vs stochastic multiscale", fontsize=12)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.93, hspace=0.12)
    fig.savefig(out / "fig05_spectral_vs_stochastic.png")


GALLERY = ("cow.obj", "foot.off", "maxplanck.obj", "camel.off", "gargoyle.off", "polygirl.off")
VIEWS = {
    "cow.obj": (15.0, -90.0),
    "foot.off": (15.0, -90.0),
    "maxplanck.obj": (10.0, 170.0),
    "camel.off": (10.0, -90.0),
    "gargoyle.off": (10.0, -10.0),
    "polygirl.off": (10.0, -10.0),
    "horse_10k.obj": (10.0, -90.0),
}


def fig10(out: Path, tmp: Path) -> None:
    paths, titles = [], []
    for name in GALLERY:
        mesh = load(name)
        saliency = sl.mesh_saliency(mesh.vertices, mesh.faces)
        path = tmp / f"gallery_{name}.png"
        render_scalar(
            mesh.vertices,
            mesh.faces,
            saliency,
            path,
            views=[VIEWS[name]],
            up=UP[name],
            figsize=(4.0, 4.8),
        )
        paths.append(path)
        titles.append(f"{name} ({mesh.vertices.shape[0]} V)")
    tile(
        paths,
        titles,
        out / "fig10_saliency_gallery.png",
        3,
        "Fig. 10: saliency (Algorithm 2, K = 8, lambda = 1e-3); warm = salient",
    )


def fig11(out: Path, tmp: Path) -> None:
    mesh = load("cow.obj")
    maps = {
        "uniform Laplacian": laplacian_saliency(mesh.vertices, mesh.faces, "uniform"),
        "cotangent Laplacian": laplacian_saliency(mesh.vertices, mesh.faces, "cotangent"),
        "stochastic Laplacian (paper)": sl.mesh_saliency(
            mesh.vertices, mesh.faces, variant="paper"
        ),
        "variant: normal_displacement": sl.saliency(
            mesh.vertices, mesh.faces, variant="normal_displacement"
        ),
    }
    paths = []
    for i, values in enumerate(maps.values()):
        path = tmp / f"lap_{i}.png"
        render_scalar(
            mesh.vertices,
            mesh.faces,
            values,
            path,
            views=[(20.0, -120.0)],
            up=UP["cow.obj"],
            figsize=(4.0, 4.8),
        )
        paths.append(path)
    tile(
        paths,
        list(maps),
        out / "fig11_laplacians.png",
        4,
        "Fig. 11: Algorithm 2 on the cow (2903 V), three Laplacians and a variant",
    )


#: Interest points drawn per saliency (people mark about 10-25 on these models).
TOP_K = 20


def interest_figure(name: str, number: int, out: Path, tmp: Path) -> None:
    mesh = load(name)
    paths, titles = [], []
    for variant in ("paper", "normal_displacement"):
        saliency = sl.saliency(mesh.vertices, mesh.faces, variant=variant)
        points = sl.interest_points(saliency, mesh.vertices, mesh.faces, top_k=TOP_K)
        path = tmp / f"interest_{name}_{variant}.png"
        render_interest_points(
            mesh.vertices,
            mesh.faces,
            saliency,
            points,
            path,
            views=[VIEWS[name], (15.0, VIEWS[name][1] + 180.0)],
            up=UP[name],
            figsize=(8.0, 4.8),
        )
        paths.append(path)
        titles.append(f"{variant}: {points.numel()} points")
    stem = Path(name).stem
    tile(
        paths,
        titles,
        out / f"fig{number}_{stem}_interest.png",
        2,
        f"Fig. {number}: interest points on {name} ({mesh.vertices.shape[0]} V), "
        f"non-maximum suppression radius 0.1, at most {TOP_K}",
        panel_width=8.0,
    )


def cli_figure(command: str, written: str, picture: str, out: Path, tmp: Path) -> None:
    """Run the quoted ``stochlap`` command in ``tmp`` (a word naming a file of
    :data:`MESH_DIR` is that file) and keep the picture it writes, ``written``, as
    ``out / picture``."""
    words = [str(MESH_DIR / w) if (MESH_DIR / w).is_file() else w for w in command.split()]
    subprocess.run([sys.executable, "-m", "stochlap_torch", *words], cwd=tmp, check=True)
    (out / picture).parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(tmp / written, out / picture)


FIGURES = {
    "fig01": fig01,
    "fig03": fig03_04,
    "fig05": fig05,
    "fig10": fig10,
    "fig11": fig11,
    "fig12": lambda out, tmp: interest_figure("gargoyle.off", 12, out, tmp),
    "fig13": lambda out, tmp: interest_figure("camel.off", 13, out, tmp),
    "fig14": lambda out, tmp: interest_figure("cow.obj", 14, out, tmp),
    "readme_spot": lambda out, tmp: cli_figure(
        "saliency --png spot_saliency.png", "spot_saliency.png", "../spot_saliency.png", out, tmp
    ),
    "readme_multiscale": lambda out, tmp: cli_figure(
        "multiscale bunny.obj -K 16 --scales 1 4 8 12 16",
        "bunny_multiscale/bunny_multiscale.png",
        "readme_multiscale_bunny.png",
        out,
        tmp,
    ),
    "readme_interest": lambda out, tmp: cli_figure(
        "interest armadillo.obj --top-k 20",
        "armadillo_interest.png",
        "readme_interest_armadillo.png",
        out,
        tmp,
    ),
}


def main() -> None:
    parser = argparse.ArgumentParser(description="Write the paper's figures as PNGs.")
    parser.add_argument("--only", nargs="+", choices=sorted(FIGURES), help="a subset")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "figures")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    total = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for key in args.only or list(FIGURES):
            start = time.perf_counter()
            FIGURES[key](args.out, Path(tmp))
            print(f"{key}: {time.perf_counter() - start:.1f} s")
    print(f"all in {time.perf_counter() - total:.1f} s -> {args.out}")


if __name__ == "__main__":
    main()
