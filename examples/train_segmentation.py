"""Per-vertex segmentation from multiscale features, against raw xyz and heat kernel signatures.

Task: label every vertex with the tertile (within its mesh) of its *average geodesic distance*
to 32 random source vertices (graph distances along the edges): 0 = central, 1 = middle,
2 = extremities (limbs, ears, tails). The labels are intrinsic and global; no input below
holds them by construction. Each mesh is randomly rotated (the training meshes four times),
and the split is by mesh: the test meshes are shapes the network never saw.

The same per-vertex MLP (two hidden layers of 64) is trained on three inputs:

* ``stochastic``: :class:`~stochlap_torch.features.MultiscaleFeatures` (rotation invariant:
  normal / tangential coefficients, norms, difference maps and saliency), via
  :class:`~stochlap_torch.data.MeshFeatureDataset` and its on-disk cache;
* ``xyz``: positions centred on the centroid and divided by the bounding-box diagonal;
* ``hks``: log heat kernel signature, 16 times, 64 eigenpairs
  (:func:`stochlap_torch.baselines.heat_kernel_signature`).

Run (a few minutes on 2 CPU cores; the features are cached in ``--cache``)::

    python examples/train_segmentation.py
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import torch
from torch import nn

import stochlap_torch as sl
from stochlap_torch.baselines import heat_kernel_signature
from stochlap_torch.learning import MeshFeatureDataset

REPO = Path(__file__).resolve().parent.parent
MESHES = REPO.parent / "shared" / "meshes"
TRAIN = [
    "cow.obj",
    "spot.obj",
    "dinosaur.obj",
    "horse_10k.obj",
    "horse.off",
    "maxplanck.obj",
    "fandisk.off",
    "foot.off",
    "polygirl.off",
    "rocker_arm.off",
    "squirrel.off",
]
TEST = ["camel.off", "teddy.off", "octopus.off", "gargoyle.off", "fertility.off"]
NUM_CLASSES = 3


def average_geodesic_distance(mesh: sl.Mesh, num_sources: int, rng) -> np.ndarray:
    """``(V,)`` mean edge-graph distance to random sources (NaN for unreachable-only rows)."""
    edges = sl.unique_edges(mesh.faces, mesh.num_vertices).numpy()
    vertices = mesh.vertices.numpy()
    lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    graph = scipy.sparse.coo_matrix(
        (lengths, (edges[:, 0], edges[:, 1])), shape=(mesh.num_vertices,) * 2
    ).tocsr()
    referenced = np.unique(mesh.faces.numpy())
    sources = rng.choice(referenced, size=min(num_sources, referenced.size), replace=False)
    distances = scipy.sparse.csgraph.dijkstra(graph, directed=False, indices=sources)
    finite = np.isfinite(distances)
    total = np.where(finite, distances, 0.0).sum(axis=0)
    count = finite.sum(axis=0)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def tertile_labels(values: np.ndarray) -> torch.Tensor:
    """``(V,)`` int64 class 0/1/2 by tertile of ``values``; -1 where undefined."""
    labels = np.full(values.shape, -1, dtype=np.int64)
    defined = np.isfinite(values)
    low, high = np.quantile(values[defined], [1 / 3, 2 / 3])
    labels[defined] = np.digitize(values[defined], [low, high])
    return torch.from_numpy(labels)


def random_rotation(generator: torch.Generator) -> torch.Tensor:
    """A uniformly random ``(3, 3)`` rotation."""
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=generator, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def xyz_features(vertices: torch.Tensor) -> torch.Tensor:
    """``(V, 3)`` positions centred and divided by the bounding-box diagonal."""
    centred = vertices - vertices.mean(dim=0)
    return centred / (vertices.max(dim=0).values - vertices.min(dim=0).values).norm()


def hks_features(mesh: sl.Mesh) -> torch.Tensor:
    """``(V, 16)`` log heat kernel signature (zero rows of unreferenced vertices stay finite)."""
    hks = heat_kernel_signature(mesh.vertices, mesh.faces, num_eigenpairs=64, num_times=16)
    return torch.log(hks.clamp_min(1e-12))


def make_mlp(channels: int) -> nn.Module:
    return nn.Sequential(
        nn.Linear(channels, 64),
        nn.ReLU(),
        nn.Linear(64, 64),
        nn.ReLU(),
        nn.Linear(64, NUM_CLASSES),
    )


def train_and_test(train_x, train_y, test_x, test_y, steps: int, seed: int) -> tuple[float, float]:
    """Train the MLP on standardised inputs; return (train accuracy, test accuracy)."""
    torch.manual_seed(seed)
    mean, std = train_x.mean(dim=0), train_x.std(dim=0).clamp_min(1e-8)
    train_x, test_x = (train_x - mean) / std, (test_x - mean) / std
    model = make_mlp(train_x.shape[1])
    optimiser = torch.optim.Adam(model.parameters(), lr=3e-3)
    generator = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        pick = torch.randint(0, train_x.shape[0], (4096,), generator=generator)
        loss = nn.functional.cross_entropy(model(train_x[pick]), train_y[pick])
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        train_acc = (model(train_x).argmax(1) == train_y).float().mean().item()
        test_acc = (model(test_x).argmax(1) == test_y).float().mean().item()
    return train_acc, test_acc


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", type=Path, default=MESHES)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/stochlap_feature_cache"))
    parser.add_argument("--num-scales", type=int, default=10)
    parser.add_argument(
        "--normalisation",
        choices=["mean_edge", "bbox_diagonal", "none"],
        default="mean_edge",
        help="per-mesh length of the stochastic coefficients (bbox: of the unrotated file)",
    )
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--rotations", type=int, default=4, help="copies per training mesh")
    parser.add_argument("--seeds", type=int, default=2, help="training runs per input")
    args = parser.parse_args()
    torch.set_num_threads(2)
    start = time.time()

    paths = [args.meshes / name for name in TRAIN + TEST]
    dataset = MeshFeatureDataset(
        paths,
        num_scales=args.num_scales,
        rotation_invariant=True,
        cache_dir=args.cache,
        normalisation=args.normalisation,
        merge_seams=True,
        dtype=torch.float32,
    )
    print(
        f"stochastic features: {len(dataset.channel_names())} channels, {time.time() - start:.0f} s"
    )

    rng = np.random.default_rng(0)
    generator = torch.Generator().manual_seed(0)
    inputs = {"stochastic": {}, "xyz": {}, "hks": {}}
    labels = {}
    for sample in dataset:
        name = Path(sample.path).name
        mesh = sl.load_mesh(sample.path, merge_seams=True)
        labels[name] = tertile_labels(average_geodesic_distance(mesh, 32, rng))
        copies = args.rotations if name in TRAIN else 1
        rotations = [random_rotation(generator) for _ in range(copies)]
        inputs["stochastic"][name] = [sample.features] * copies  # rotation invariant
        inputs["xyz"][name] = [xyz_features(mesh.vertices @ r.T).float() for r in rotations]
        inputs["hks"][name] = [hks_features(mesh).float()] * copies  # intrinsic
    inputs["stochastic+hks"] = {
        name: [
            torch.cat([a, b], dim=1)
            for a, b in zip(inputs["stochastic"][name], inputs["hks"][name], strict=True)
        ]
        for name in labels
    }
    print(f"labels and baselines ready, {time.time() - start:.0f} s")

    def stack(kind, names):
        xs, ys = [], []
        for name in names:
            for copy in inputs[kind][name]:
                keep = labels[name] >= 0
                xs.append(copy[keep])
                ys.append(labels[name][keep])
        return torch.cat(xs), torch.cat(ys)

    print(f"\ntrain meshes: {', '.join(TRAIN)}\ntest meshes:  {', '.join(TEST)}")
    print(f"task: 3-way tertile of average geodesic distance (chance 0.333), {args.seeds} seeds")
    print(f"{'input':<16}{'channels':>9}{'train acc':>12}{'test acc':>12}{'test std':>10}")
    for kind in inputs:
        train_x, train_y = stack(kind, TRAIN)
        test_x, test_y = stack(kind, TEST)
        runs = [
            train_and_test(train_x, train_y, test_x, test_y, args.steps, seed)
            for seed in range(args.seeds)
        ]
        train_acc = np.mean([r[0] for r in runs])
        test_accs = [r[1] for r in runs]
        print(
            f"{kind:<16}{train_x.shape[1]:>9}{train_acc:>12.3f}{np.mean(test_accs):>12.3f}"
            f"{np.std(test_accs):>10.3f}"
        )
    print(f"\ntotal {time.time() - start:.0f} s")


if __name__ == "__main__":
    main()
