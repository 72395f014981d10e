"""The discretization benchmark's own helpers (``benchmarks/discretization.py``): the genus it
reports for every remeshed body, and the report's section on the bodies that have handles."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from reference import icosphere

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import discretization


def _torus() -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces, dtype=np.int64)


def test_the_genus_is_that_of_the_largest_component():
    sphere = icosphere(2)
    assert discretization.genus(sphere.vertices, sphere.faces) == 0
    v, f = _torus()
    assert discretization.genus(v, f) == 1
    # Largest component only: a small sphere beside the torus changes nothing, a torus beside
    # a larger sphere is not counted.
    small = icosphere(1)  # listed first: the largest component is not the first
    both_v = np.vstack([small.vertices * 0.1 + 5.0, v])
    both_f = np.vstack([small.faces, f + len(small.vertices)])
    assert discretization.genus(both_v, both_f) == 1
    big = icosphere(4)
    torus_beside = np.vstack([big.vertices * 10.0, v])
    faces_beside = np.vstack([big.faces, f + len(big.vertices)])
    assert discretization.genus(torus_beside, faces_beside) == 0


@pytest.mark.parametrize("handles", [0, 2])
def test_the_report_lists_the_bodies_with_handles(handles):
    method = {
        "seconds": 1.0,
        "error": None,
        "note": None,
        "matches": 0.9,
        "mean_error": 0.02,
        "saliency_rho": 0.97,
        "repeatability": 0.9,
        "flips": 0.0,
        "mean_error_lr": 0.01,
        "channel_rho": [0.99],
    }
    rows = [
        {
            "body": "080",
            "policy": policy,
            "V": 100,
            "handles": handles if policy == "mc" else 0,
            "methods": {"robust": dict(method), "hks": dict(method)},
        }
        for policy in discretization.POLICIES
    ]
    results = {
        "run": {"command": "x", "commit": "c", "date": "d", "cpu": "p", "cores": 2},
        "rows": rows,
        "load": [0.0, 0.0],
        "elapsed_s": 1.0,
        "bodies": ["080"],
        "samples": 300,
        "channels": ["dn0"],
    }
    report = discretization.render(results)
    section = report.split("## Where the remeshing joined touching parts")[1].split("## ")[0]
    assert ("| 080 | mc | 2 | 0.970 | 0.970 | 0.90 | 0.90 |" in section) == bool(handles)
    assert "| 080 | qes |" not in section


@pytest.mark.parametrize("time_", [1e-3, 0.05])
def test_the_exact_channels_heat_is_the_matrix_exponential(time_):
    """``discretization_exact.exact_heat`` against scipy's dense ``expm`` of ``-t M^-1 S``."""
    import discretization_exact
    import robust_laplacian
    from scipy.linalg import expm

    sphere = icosphere(2)
    rng = np.random.default_rng(0)
    v = sphere.vertices * (1.0 + 0.1 * rng.random((len(sphere.vertices), 1)))
    stiffness, mass = robust_laplacian.mesh_laplacian(v, sphere.faces)
    mass = mass.diagonal()
    fields = rng.standard_normal((len(v), 3))
    expected = expm(-time_ * stiffness.toarray() / mass[:, None]) @ fields
    got = discretization_exact.exact_heat(stiffness, mass, time_, fields)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-10)
