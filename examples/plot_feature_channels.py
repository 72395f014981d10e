"""
The feature channels, each at a fine and a coarse scale
=======================================================

:func:`stochlap_torch.multiscale_features` returns one row of channels per vertex. This draws
every kind of channel on the bundled ``spot`` cow (2930 vertices) at two scales: first the
robust variant's (the default), then the paper's. Runs in seconds; the documentation build
executes it.
"""

# %%
# The features of both variants, and the channel names that say which column is which.
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import torch

import stochlap_torch as sl
from stochlap_torch.viz import render_scalar

mesh = sl.load_mesh(sl.bundled_mesh_path(), dtype=torch.float64)
robust = sl.multiscale_features(mesh.vertices, mesh.faces)  # (V, 33)
paper = sl.multiscale_features(mesh.vertices, mesh.faces, variant="paper")  # (V, 21)
robust_names = sl.feature_channel_names()
paper_names = sl.feature_channel_names(variant="paper")
print(robust.shape, robust_names[:3], "...", robust_names[-2:])
print(paper.shape, paper_names[:3], "...", paper_names[-2:])


def draw(features, names, rows, title):
    """A grid of the named channels: one row per kind of channel, one column per scale."""
    fig, axes = plt.subplots(len(rows), 2, figsize=(6.4, 2.6 * len(rows)))
    with tempfile.TemporaryDirectory() as folder:
        for row, (kind, pair) in enumerate(rows.items()):
            for column, name in enumerate(pair):
                png = Path(folder) / f"{name}.png"
                values = features[:, names.index(name)]
                render_scalar(
                    mesh.vertices,
                    mesh.faces,
                    values,
                    png,
                    views=[(10.0, -60.0)],
                    label=name,
                    figsize=(3.2, 2.6),
                    dpi=90,
                    cmap="coolwarm",
                )
                axes[row, column].imshow(plt.imread(png))
                axes[row, column].set_axis_off()
            axes[row, 0].set_title(kind, loc="left", fontsize=9)
    fig.suptitle(title)
    fig.tight_layout()


# %%
# Robust channels (``variant="robust"``): scales are diffusion times ``t_k = 1e-3 2^k A``
# (``A`` the area). ``dn`` is the normal displacement over ``sqrt(t)`` (positive on bulges,
# negative in creases); ``spread_1..3`` are where heat from a vertex spreads to (the
# eigenvalues of the diffused positions' covariance over ``2 t``: 1, 1, 0 on a plane, the
# third grows where the surface curves within the scale); ``heat`` is the log heat kernel
# diagonal, taken at the two coarsest scales only.
draw(
    robust,
    robust_names,
    {
        "dn (normal displacement)": ("dn1", "dn5"),
        "spread_1 (largest)": ("spread1_1", "spread5_1"),
        "spread_2": ("spread1_2", "spread5_2"),
        "spread_3 (smallest)": ("spread1_3", "spread5_3"),
        "heat (heat kernel diagonal)": ("heat5", "heat6"),
    },
    "robust channels: fine scale (left), coarse scale (right)",
)

# %%
# Paper channels (``variant="paper"``): scale ``k`` is ``k`` applications of the stochastic
# mesh Laplacian, so a scale covers a number of edge lengths. ``coef`` is the coefficient
# ``C^(k) = P^(k-1) - P^(k)`` split into its component along the vertex normal, its length
# across it, and its norm, in units of the mean edge length; ``diff`` is the difference map
# ``D^(k)`` of Algorithm 2, whose sum over the scales is the paper's saliency.
draw(
    paper,
    paper_names,
    {
        "coef, normal": ("coef2_normal", "coef6_normal"),
        "coef, tangent": ("coef2_tangent", "coef6_tangent"),
        "coef, norm": ("coef2_norm", "coef6_norm"),
        "diff (D^(k))": ("diff2", "diff6"),
    },
    "paper channels: scale 2 (left), scale 6 (right)",
)
plt.show()
