"""GPU benchmark: the CUDA kernel of the streamed steps against the torch
ops on the same GPU and the CPU kernel, and a ~10M-vertex torus within the targets.

    python benchmarks/gpu.py [--runs 10] [--torus-vertices 10240000] [--out benchmarks/GPU.md]

Without a CUDA GPU (or without numba's CUDA target) it prints why and exits 0. On a GPU it
names the card, times the paper method (K=8, lambda=1e-3, positions included) on
gargoyle_50k with ``backend="cuda"``, ``"torch"`` (both on the GPU, float32 and float64) and
``"numba"`` (CPU, float64), as medians of ``--runs`` runs after a warm-up, each run ended by
``torch.cuda.synchronize()``, with the peak GPU memory (``torch.cuda.max_memory_allocated``),
checks that the kernel's results equal the CPU kernel's, then runs a procedural float32 torus
of ``--torus-vertices`` vertices, and writes a markdown report.

Targets: gargoyle_50k K=8 <= 5 ms; the 10.2M-vertex torus in float32 <= 1 s and <= 8 GiB.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import stochlap_torch as sl  # noqa: E402
from stochlap_torch import _kernels  # noqa: E402

MESH = ROOT.parent / "shared" / "meshes" / "gargoyle_50k.off"
NUM_SCALES, THRESHOLD = 8, 1e-3
GARGOYLE_TARGET_S = 5e-3
TORUS_TARGET_S, TORUS_TARGET_BYTES = 1.0, 8 * 2**30


def why_skipped() -> str | None:
    """Why this section cannot run here, or ``None``."""
    if not torch.cuda.is_available():
        return "no CUDA GPU (torch.cuda.is_available() is False)"
    if not _kernels.cuda_available():
        return "numba's CUDA target is unavailable (numba.cuda.is_available() is False)"
    return None


def torus(num_vertices: int, device, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """A closed torus of about ``num_vertices`` vertices (an ``n x m`` grid, ``n = 2.5 m``
    around the big circle), built on ``device``: ``(V, 3)`` and ``(2 V, 3)`` int64."""
    minor = max(3, round(math.sqrt(num_vertices / 2.5)))
    major = max(3, round(num_vertices / minor))
    u = torch.arange(major, device=device, dtype=torch.float64) * (2 * math.pi / major)
    v = torch.arange(minor, device=device, dtype=torch.float64) * (2 * math.pi / minor)
    uu, vv = torch.meshgrid(u, v, indexing="ij")
    ring = 3.0 + torch.cos(vv)
    vertices = torch.stack([ring * torch.cos(uu), ring * torch.sin(uu), torch.sin(vv)], -1)
    i, j = torch.meshgrid(
        torch.arange(major, device=device), torch.arange(minor, device=device), indexing="ij"
    )
    a = i * minor + j
    b = ((i + 1) % major) * minor + j
    c = ((i + 1) % major) * minor + (j + 1) % minor
    d = i * minor + (j + 1) % minor
    faces = torch.cat([torch.stack([a, b, c], -1), torch.stack([a, c, d], -1)]).reshape(-1, 3)
    return vertices.reshape(-1, 3).to(dtype), faces


def timed(function, runs: int, device) -> tuple[float, int, object]:
    """``(median seconds, peak bytes on the GPU, last result)`` of ``function()`` after a
    warm-up call (compiles the kernels)."""
    synchronize = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    result = function()
    synchronize()
    torch.cuda.reset_peak_memory_stats()
    times = []
    for _ in range(runs):
        result = None  # the last result's memory is not part of the next run's peak
        synchronize()
        start = time.perf_counter()
        result = function()
        synchronize()
        times.append(time.perf_counter() - start)
    return statistics.median(times), torch.cuda.max_memory_allocated(), result


def run_paper(vertices, faces, backend: str):
    return lambda: sl.multiscale_representation(
        vertices, faces, NUM_SCALES, THRESHOLD, backend=backend
    )


def gargoyle_rows(runs: int) -> tuple[list[str], list[str]]:
    """Table rows for gargoyle_50k, and notes."""
    if not MESH.is_file():
        return [], [f"gargoyle_50k skipped: {MESH} not found"]
    mesh = sl.load_mesh(MESH)
    cpu_vertices, cpu_faces = mesh.vertices, mesh.faces
    reference = sl.multiscale_representation(
        cpu_vertices, cpu_faces, NUM_SCALES, THRESHOLD, backend="numba"
    )
    rows, notes = [], []
    seconds, _, _ = timed(run_paper(cpu_vertices, cpu_faces, "numba"), runs, torch.device("cpu"))
    rows.append(f"| CPU kernel (numba) | float64 | {seconds * 1e3:.2f} | - | - |")
    device = torch.device("cuda")
    for dtype in (torch.float32, torch.float64):
        vertices, faces = cpu_vertices.to(device, dtype), cpu_faces.to(device)
        for backend in ("cuda", "torch"):
            seconds, peak, result = timed(run_paper(vertices, faces, backend), runs, device)
            error = max(
                float((got.double().cpu() - want).abs().max())
                for got, want in (
                    (result.differences, reference.differences),
                    (result.positions, reference.positions),
                )
            )
            # The kernel is checked before it is timed: float64 equals the CPU kernel's.
            if backend == "cuda" and dtype == torch.float64 and error > 1e-10:
                raise SystemExit(f"the CUDA kernel differs from the CPU kernel by {error:.2e}")
            verdict = ""
            if backend == "cuda":
                verdict = "meets" if seconds <= GARGOYLE_TARGET_S else "misses"
                verdict = f" ({verdict} the 5 ms target)"
            rows.append(
                f"| {backend} | {str(dtype)[6:]} | {seconds * 1e3:.2f}{verdict} | "
                f"{peak / 2**20:.0f} | {error:.1e} |"
            )
    return rows, notes


def torus_rows(num_vertices: int, runs: int) -> list[str]:
    """Table rows for the torus, float32, CUDA kernel."""
    device = torch.device("cuda")
    vertices, faces = torus(num_vertices, device, torch.float32)
    # backend="cuda" by name: "auto" keeps the torch ops until this benchmark has checked it.
    seconds, peak, result = timed(run_paper(vertices, faces, "cuda"), runs, device)
    finite = bool(torch.isfinite(result.differences).all())
    ok = seconds <= TORUS_TARGET_S and peak <= TORUS_TARGET_BYTES
    return [
        f"| torus | {vertices.shape[0]:,} | {seconds:.3f} | {peak / 2**30:.2f} | "
        f"{'yes' if finite else 'NO'} | {'meets' if ok else 'misses'} (<= 1 s, <= 8 GiB) |"
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--torus-vertices", type=int, default=10_240_000)
    parser.add_argument("--torus-runs", type=int, default=3)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "GPU.md")
    args = parser.parse_args(argv)
    reason = why_skipped()
    if reason is not None:
        print(f"GPU benchmark skipped: {reason}")
        return 0
    card = torch.cuda.get_device_name()
    print(f"GPU: {card}")
    rows, notes = gargoyle_rows(args.runs)
    lines = [
        "# GPU benchmark: the paper method's CUDA kernel",
        "",
        f"Card: **{card}**; torch {torch.__version__}; paper method, K={NUM_SCALES}, "
        f"lambda={THRESHOLD:g}, positions included; medians of {args.runs} runs after a "
        "warm-up, `torch.cuda.synchronize()` after each.",
        "",
        "## gargoyle_50k",
        "",
        "| backend | dtype | ms | peak GPU MiB | max abs difference of D, P^(k) vs CPU kernel |",
        "|---|---|---|---|---|",
        *rows,
        "",
        *notes,
        "## Torus (float32, CUDA kernel)",
        "",
        "| mesh | vertices | s | peak GPU GiB | finite | target |",
        "|---|---|---|---|---|---|",
        *torus_rows(args.torus_vertices, args.torus_runs),
        "",
    ]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    sys.exit(main())
