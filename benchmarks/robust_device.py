"""The robust variant with a reused structure, in float32 and float64, on the CPU and (when
present) a CUDA device; writes ``benchmarks/ROBUST_DEVICE.md``.

Run: ``OMP_NUM_THREADS=1 python benchmarks/robust_device.py [MESH]`` (default
``../shared/meshes/gargoyle_50k.off``). The script pins its own process to one thread; the
library's thread settings are not touched. Every time is the median of :data:`RUNS` runs.
"""

from __future__ import annotations

import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch
from scipy.stats import spearmanr

import stochlap_torch as sl

RUNS = 5
HERE = Path(__file__).resolve().parent
DEFAULT_MESH = HERE.parent.parent / "shared" / "meshes" / "gargoyle_50k.off"


def median_time(call, runs: int = RUNS) -> float:
    """Median wall time of ``call()`` over ``runs`` runs, after one untimed run."""
    call()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        call()
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def measure(vertices: torch.Tensor, faces: torch.Tensor) -> dict[str, float]:
    """Timings and agreement on the device of ``vertices`` (float64)."""
    structure = sl.robust_structure(vertices, faces)
    single = vertices.float()
    out = {
        "cold float64": median_time(lambda: sl.multiscale_features(vertices, faces)),
        "cold float32": median_time(lambda: sl.multiscale_features(single, faces)),
        "reused float64": median_time(
            lambda: sl.multiscale_features(vertices, faces, structure=structure)
        ),
        "reused float32": median_time(
            lambda: sl.multiscale_features(single, faces, structure=structure)
        ),
        "saliency reused float64": median_time(
            lambda: sl.saliency(vertices, faces, structure=structure)
        ),
        "saliency reused float32": median_time(
            lambda: sl.saliency(single, faces, structure=structure)
        ),
    }

    def forward_backward(points):
        moved = points.clone().requires_grad_(True)
        sl.multiscale_features(moved, faces, structure=structure).square().sum().backward()

    out["forward+backward reused float64"] = median_time(lambda: forward_backward(vertices))
    out["forward+backward reused float32"] = median_time(lambda: forward_backward(single))
    error, rho = float32_agreement(vertices, faces, structure)
    out["max abs(f32 - f64) / std (reused)"] = float(error.max())
    out["saliency Spearman f32/f64 (reused)"] = rho
    a = sl.saliency(vertices, faces, structure=structure).cpu().numpy()
    c = sl.saliency(single, faces).double().cpu().numpy()
    out["saliency Spearman f32/f64 (cold)"] = float(spearmanr(a, c)[0])
    return out


def float32_agreement(vertices: torch.Tensor, faces: torch.Tensor, structure):
    """``((C,) max abs(f32 - f64) / std per channel, saliency Spearman)`` of float64
    ``vertices`` and their float32 copy, both through ``structure``."""
    double = sl.multiscale_features(vertices, faces, structure=structure).double()
    single = sl.multiscale_features(vertices.float(), faces, structure=structure).double()
    error = (single - double).abs().max(0).values / double.std(0).clamp_min(1e-300)
    a = sl.saliency(vertices, faces, structure=structure).cpu().numpy()
    b = sl.saliency(vertices.float(), faces, structure=structure).double().cpu().numpy()
    return error.cpu(), float(spearmanr(a, b)[0])


#: Other shared meshes the float32 features are compared on (accuracy only).
ACCURACY_MESHES = ("bunny.obj", "fandisk.off", "horse.off", "camel.off", "octopus.off")


def float32_accuracy(folder: Path) -> list[tuple[str, float, str, float]]:
    """Per mesh of :data:`ACCURACY_MESHES` found in ``folder``: ``(name, worst channel's max
    abs(f32 - f64) / std, that channel, saliency Spearman)``, with one structure for both."""
    rows = []
    for name in ACCURACY_MESHES:
        if not (folder / name).exists():
            continue
        loaded = sl.load_mesh(folder / name)
        vertices, faces = loaded.vertices.double(), loaded.faces
        error, rho = float32_agreement(vertices, faces, sl.robust_structure(vertices, faces))
        worst = int(error.argmax())
        channel = sl.MultiscaleFeatures().channel_names()[worst]
        rows.append((name, float(error[worst]), channel, rho))
    return rows


def report(
    path: Path,
    mesh: Path,
    results: dict[str, dict[str, float]],
    accuracy: list[tuple[str, float, str, float]],
) -> str:
    lines = [
        "# Robust variant: reused structure, float32, device",
        "",
        f"Mesh `{mesh.name}`; command `OMP_NUM_THREADS=1 python benchmarks/robust_device.py`;",
        f"medians of {RUNS} runs, one thread (torch {torch.__version__}).",
        "",
    ]
    for device, values in results.items():
        lines += [f"## {device}", "", "| measure | value |", "|---|---|"]
        for name, value in values.items():
            unit = " s" if not any(key in name for key in ("Spearman", "/ std")) else ""
            lines.append(f"| {name} | {value:.4g}{unit} |")
        reuse = values["cold float64"] / values["reused float64"]
        dtype = values["reused float64"] / values["reused float32"]
        salient = values["saliency reused float64"] / values["saliency reused float32"]
        lines += [
            f"| cold / reused (float64) | {reuse:.2f}x (target >= 4x) |",
            f"| float64 / float32, features reused | {dtype:.2f}x (target >= 1.5x) |",
            f"| float64 / float32, saliency reused | {salient:.2f}x |",
            "",
        ]
    if accuracy:
        lines += [
            "## float32 against float64 on other meshes",
            "",
            "The same structure for both; the worst channel's largest difference over its",
            "standard deviation (target: below 1e-3), and the saliency's rank agreement.",
            "",
            "| mesh | max abs(f32 - f64) / std | channel | saliency Spearman |",
            "|---|---|---|---|",
        ]
        for name, error, channel, rho in accuracy:
            lines.append(f"| {name} | {error:.3g} | {channel} | {rho:.6f} |")
        lines.append("")
    if "cuda" not in results:
        lines += ["No CUDA device here: the GPU section was skipped.", ""]
    text = "\n".join(lines)
    path.write_text(text)
    return text


def main() -> None:
    torch.set_num_threads(1)
    mesh = Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_MESH
    loaded = sl.load_mesh(mesh)
    vertices, faces = loaded.vertices.double(), loaded.faces
    results = {"cpu": measure(vertices, faces)}
    if torch.cuda.is_available():
        results["cuda"] = measure(vertices.cuda(), faces.cuda())
    accuracy = float32_accuracy(mesh.parent)
    print(report(HERE / "ROBUST_DEVICE.md", mesh, results, accuracy))


if __name__ == "__main__":
    main()
