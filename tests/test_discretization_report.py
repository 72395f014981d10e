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


def _method(**changes) -> dict:
    """One method's results on one mesh, as ``discretization.json`` holds them."""
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
    return {**method, **changes}


def _results(rows: list[dict]) -> dict:
    bodies = sorted({row["body"] for row in rows})
    return {
        "run": {"command": "x", "commit": "c", "date": "d", "cpu": "p", "cores": 2},
        "rows": rows,
        "load": [0.0, 0.0],
        "elapsed_s": 1.0,
        "bodies": bodies,
        "samples": 300,
        "channels": ["dn0"],
    }


@pytest.mark.parametrize("handles", [0, 2])
def test_the_report_lists_the_bodies_with_handles(handles):
    rows = [
        {
            "body": "080",
            "policy": policy,
            "V": 100,
            "handles": handles if policy == "mc" else 0,
            "methods": {"robust": _method(), "hks": _method()},
        }
        for policy in discretization.POLICIES
    ]
    report = discretization.render(_results(rows))
    section = report.split("## Where the remeshing joined touching parts")[1].split("## ")[0]
    assert ("| 080 | mc | 2 | 0.970 | 0.970 | 0.90 | 0.90 |" in section) == bool(handles)
    assert "| 080 | qes |" not in section


def test_the_report_times_the_structure_apart():
    """The speed verdict also gives HKS's time over the features' on a structure built
    ahead: the robust pipeline's time less its build."""
    rows = [
        {
            "body": body,
            "policy": policy,
            "V": 100,
            "handles": 0,
            "methods": {
                "robust": _method(seconds=0.4, build_seconds=0.3),
                "hks": _method(seconds=hks),
            },
        }
        for policy in discretization.POLICIES
        for body, hks in (("080", 1.0), ("081", 1.2), ("082", 0.8))
    ]
    report = discretization.render(_results(rows))
    # medians per mesh: HKS / 0.4 = 2.5x, HKS / (0.4 - 0.3) = 10x
    assert "**FAIL** (2.5x; 10.0x with the structure built ahead)" in report
    assert "| of which building the structure, s (median) | 0.30 / 0.30 / 0.30 | n/a" in report


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
