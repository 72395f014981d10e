"""Paper-mode outputs of every path, saved and compared bit for bit across library versions.

The promise of a restructure or a speed-up is that the paper's method gives the *same bits*.
``dump`` runs the paper-mode paths (eager, with operators, torch ops, gradients, partitioned,
differentiable, batched, the memory estimate, interest points) on the shared meshes in float64
and float32 and saves every output; ``compare`` lists the arrays that differ. Run ``dump`` in a
checkout of each version (``git worktree add ../old REV``), then ``compare``::

    python benchmarks/paper_outputs.py dump /tmp/new.npz
    (cd ../old && python /path/to/benchmarks/paper_outputs.py dump /tmp/old.npz)
    python benchmarks/paper_outputs.py compare /tmp/old.npz /tmp/new.npz

About two minutes per dump on 2 cores. Meshes missing from ``../shared/meshes`` are skipped.
Only calls whose defaults are the paper's method in every version are used. The float32
gradient of ``differentiable_multiscale`` (``spot_float32_ad_grad``) differs from run to run
in its last bits (a parallel reduction in torch's backward), in any version.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

MESH_DIR = Path(__file__).resolve().parents[2] / "shared" / "meshes"
MESHES = {
    "spot": None,
    "gargoyle_50k": "gargoyle_50k.off",
    "bunny": "bunny.obj",
    "octopus": "octopus.off",
    "squirrel": "squirrel.off",
}
#: Meshes that also run the slower paths (operators, torch ops, gradients, partitions).
FULL_PATHS = ("spot", "squirrel", "bunny")


def _array(value) -> np.ndarray:
    import torch

    return value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else np.asarray(value)


def _operator_paths(out: dict, tag: str, v, f) -> None:
    """Kept operators, torch ops, gradients through P^(k), partitioned rows, memory estimate."""
    import stochlap_torch as sl

    rep = sl.multiscale_representation(v, f, 6, 1e-3, return_operators=True)
    out[f"{tag}_ops_pos"], out[f"{tag}_ops_diff"] = _array(rep.positions), _array(rep.differences)
    for k, op in enumerate(rep.operators):
        out[f"{tag}_op{k}_crow"] = _array(op.crow_indices())
        out[f"{tag}_op{k}_col"] = _array(op.col_indices())
        out[f"{tag}_op{k}_val"] = _array(op.values())
    rep = sl.multiscale_representation(v, f, 6, 1e-3, backend="torch")
    out[f"{tag}_torch_pos"] = _array(rep.positions)
    out[f"{tag}_torch_diff"] = _array(rep.differences)
    moving = v.clone().requires_grad_(True)
    rep = sl.multiscale_representation(moving, f, 6, 1e-3)
    rep.positions[-1].square().sum().backward()
    out[f"{tag}_grad"] = _array(moving.grad)
    rep = sl.partitioned_multiscale(v, f, 6, 1e-3)
    out[f"{tag}_dist_pos"], out[f"{tag}_dist_diff"] = _array(rep.positions), _array(rep.differences)
    estimate = sl.estimate_memory(sl.mesh_operators(v, f), 8, 1e-3)
    out[f"{tag}_est"] = np.array(estimate.entries_per_row)


def dump(path: str) -> None:
    """Save the paper-mode outputs of every path to ``path`` (``.npz``)."""
    import torch

    import stochlap_torch as sl

    out: dict[str, np.ndarray] = {}
    for name, file in MESHES.items():
        if file is not None and not (MESH_DIR / file).is_file():
            print(f"skipped {name}: {MESH_DIR / file} is missing", file=sys.stderr)
            continue
        mesh = sl.load_mesh(MESH_DIR / file if file else sl.bundled_mesh_path())
        for dtype in (torch.float64, torch.float32):
            v, f = mesh.vertices.to(dtype), mesh.faces
            tag = f"{name}_{str(dtype)[6:]}"
            rep = sl.multiscale_representation(v, f, 8, 1e-3)
            out[f"{tag}_pos"], out[f"{tag}_diff"] = _array(rep.positions), _array(rep.differences)
            out[f"{tag}_ent"], out[f"{tag}_sal"] = _array(rep.entries), _array(rep.saliency())
            if name in FULL_PATHS:
                _operator_paths(out, tag, v, f)
            if name == "spot":
                moving = v.clone().requires_grad_(True)
                rep6 = sl.differentiable_multiscale(moving, f, 4, 1e-3)
                rep6.differences.sum().backward()
                out[f"{tag}_ad_pos"], out[f"{tag}_ad_grad"] = (
                    _array(rep6.positions),
                    _array(moving.grad),
                )
                out[f"{tag}_pts"] = _array(sl.interest_points(rep.saliency(), v, f, top_k=20))
        print(name, flush=True)
    np.savez(path, **out)
    print(f"{len(out)} arrays -> {path}")


def compare(old: str, new: str) -> int:
    """Print the arrays that differ; return their count."""
    a, b = np.load(old), np.load(new)
    differ = 0
    for key in a.files:
        if key not in b.files:
            print("missing in new:", key)
            differ += 1
            continue
        x, y = a[key], b[key]
        if x.shape != y.shape or x.dtype != y.dtype or not np.array_equal(x, y):
            gap = np.abs(x.astype(float) - y.astype(float)).max() if x.shape == y.shape else "shape"
            print(f"DIFFERS {key}: {x.shape} {x.dtype} vs {y.shape} {y.dtype}, max gap {gap}")
            differ += 1
    print(f"{len(a.files)} arrays compared, {differ} differ")
    return differ


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("dump").add_argument("path")
    both = commands.add_parser("compare")
    both.add_argument("old")
    both.add_argument("new")
    args = parser.parse_args()
    if args.command == "dump":
        dump(args.path)
        return 0
    return 1 if compare(args.old, args.new) else 0


if __name__ == "__main__":
    sys.exit(main())
