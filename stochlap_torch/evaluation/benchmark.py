"""Interest-point detectors against human-marked ground truth, mesh by mesh (Fig. 15):
:func:`evaluate_detectors` turns every detector's saliency (:func:`detector_saliency`) into
points with the same :func:`~stochlap_torch.interest.interest_points` and measures them
against the ground truth; :func:`mean_error_curves` averages the curves over meshes.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from torch import Tensor

from .._common.checks import check_choice
from .._common.errors import ParameterError
from ..baselines import heat_kernel_signature, laplacian_saliency, lee_saliency
from ..mesh import as_mesh_tensors
from ..params import PaperParams, resolve_params
from ..saliency_maps import mesh_saliency
from .constants import DEFAULT_RADII, EVALUATE_METHODS, GEODESIC_METHODS, SCALED_METHODS
from .geodesics import choose_geodesic_method, mesh_diameter
from .interest_metrics import ErrorCurves, build_ground_truth, evaluate_interest_points

_CURVES = ("fne", "fpe", "wme")


@dataclass(frozen=True)
class DetectorResult:
    """One detector on one mesh.

    Attributes:
        num_points: number of interest points it detected.
        curves: :class:`~.interest_metrics.ErrorCurves` over the radii.
        seconds: time to compute its saliency and points and measure them.
    """

    num_points: int
    curves: ErrorCurves
    seconds: float

    def as_dict(self) -> dict:
        """JSON-serialisable: ``num_points`` and the ``(R,)`` lists ``fne``, ``fpe``, ``wme``,
        ``num_correct``."""
        curves = {key: getattr(self.curves, key).tolist() for key in (*_CURVES, "num_correct")}
        return {"num_points": self.num_points, **curves}


@dataclass(frozen=True)
class MeshEvaluation:
    """Every detector on one mesh.

    Attributes:
        num_truth: number of ground-truth points.
        num_subjects: number of subjects whose marks formed them.
        geodesics: ``"heat"`` or ``"dijkstra"``, the distances used.
        diameter: the mesh's geodesic diameter (radii and sigma are fractions of it).
        results: ``{method: DetectorResult}`` in the order the methods were given.
    """

    num_truth: int
    num_subjects: int
    geodesics: str
    diameter: float
    results: dict[str, DetectorResult]

    def as_dict(self) -> dict:
        """JSON-serialisable summary (``methods``: each :meth:`DetectorResult.as_dict`)."""
        fields = ("num_truth", "num_subjects", "geodesics", "diameter")
        methods = {method: result.as_dict() for method, result in self.results.items()}
        return {**{name: getattr(self, name) for name in fields}, "methods": methods}


@dataclass(frozen=True)
class EvaluationSettings:
    """The checked parameters of :func:`evaluate_detectors` besides mesh, marks and methods.

    Attributes:
        radii: localisation radii, fractions of the mesh diameter.
        sigma, min_subjects: ground-truth region radius (fraction of the diameter) and the
            subjects that must agree (:func:`~.interest_metrics.build_ground_truth`).
        num_scales, threshold: ``K`` and ``lambda`` of the Algorithm-2 detectors
            (``evaluation.constants.SCALED_METHODS``; ``None``: the paper's, 8 and ``1e-3``).
        mode, radius, top_k: of :func:`~stochlap_torch.interest.interest_points` (``None``:
            radius 0.1 for ``"nms"``, no cap on the points).
        geodesics: ``"auto"``, ``"heat"`` or ``"dijkstra"``.

    Raises:
        ParameterError: the first parameter out of range, named.
    """

    radii: Sequence[float] = DEFAULT_RADII
    sigma: float = 0.03
    min_subjects: int = 2
    num_scales: int | None = None
    threshold: float | None = None
    mode: str = "nms"
    radius: float | None = None
    top_k: int | None = None
    geodesics: str = "auto"

    def __post_init__(self) -> None:
        from ..interest import check_interest_parameters

        sigma, min_subjects, radii = self.sigma, self.min_subjects, self.radii
        if not 0.0 < sigma < 1.0:
            raise ParameterError(f"sigma must lie in (0, 1), got {sigma!r}")
        if isinstance(min_subjects, bool) or not isinstance(min_subjects, int) or min_subjects < 1:
            raise ParameterError(f"min_subjects must be an integer >= 1, got {min_subjects!r}")
        if len(radii) == 0 or not all(math.isfinite(r) and r >= 0.0 for r in radii):
            raise ParameterError(f"radii must be finite and >= 0 (at least one), got {list(radii)}")
        given = {"num_scales": self.num_scales, "threshold": self.threshold}
        paper = resolve_params(PaperParams, "paper", given)
        object.__setattr__(self, "num_scales", paper.num_scales)
        object.__setattr__(self, "threshold", paper.threshold)
        # The detector's own checks: "nms" gets its default radius, "paper" refuses one.
        _, radius, _, _ = check_interest_parameters(self.mode, self.radius, self.top_k, 0.0)
        object.__setattr__(self, "radius", radius)
        check_choice("geodesics", self.geodesics, GEODESIC_METHODS)


def _checked(methods: Sequence[str], settings: dict):
    """``(methods each once in the order given, EvaluationSettings)``, checked."""
    unique = tuple(dict.fromkeys(methods))
    unknown = [m for m in unique if m not in EVALUATE_METHODS]
    if unknown or not unique:
        raise ParameterError(
            f"unknown method {', '.join(unknown) or '(none given)'}; "
            f"choose from {', '.join(EVALUATE_METHODS)}"
        )
    given = {name: settings.get(name) for name in ("num_scales", "threshold")}
    unused = [f"{name}={value!r}" for name, value in given.items() if value is not None]
    if unused and not set(unique) & set(SCALED_METHODS):
        verb, pronoun = ("does", "it") if len(unused) == 1 else ("do", "them")
        raise ParameterError(
            f"{', '.join(unused)} {verb} not apply to methods={unique!r}: leave {pronoun} "
            f"unset, or add a method that uses {pronoun} ({', '.join(SCALED_METHODS)})"
        )
    return unique, EvaluationSettings(**settings)


def check_evaluation_parameters(methods: Sequence[str], **settings) -> tuple[str, ...]:
    """Check the parameters of :func:`evaluate_detectors` before any work.

    Args:
        methods: detector names from :data:`~.constants.EVALUATE_METHODS`.
        **settings: the fields of :class:`EvaluationSettings`.

    Returns:
        The methods, each once, in the order given.

    Raises:
        ParameterError: the first parameter out of range, named; ``num_scales`` or
            ``threshold`` given when no method uses them.
        TypeError: a keyword that is no field of :class:`EvaluationSettings`.
    """
    return _checked(methods, settings)[0]


def detector_saliency(
    method: str,
    vertices: Tensor,
    faces: Tensor,
    num_scales: int = PaperParams.num_scales,
    threshold: float = PaperParams.threshold,
) -> Tensor:
    """The ``(V,)`` float saliency a detector takes its interest points from.

    Args:
        method: one of :data:`~.constants.EVALUATE_METHODS`.
        vertices, faces: the mesh, ``(V, 3)`` float and ``(F, 3)`` int64 tensors.
        num_scales, threshold: ``K`` and ``lambda`` of the Algorithm-2 methods (the robust
            one keeps its own scales).
    """
    check_choice("method", method, EVALUATE_METHODS)
    if method == "lee":
        return lee_saliency(vertices, faces)
    if method == "hks":  # at the middle of 16 log-spaced times, from 100 eigenpairs
        return heat_kernel_signature(vertices, faces, num_eigenpairs=100, num_times=16)[:, 8]
    if method in ("uniform", "cotangent"):
        return laplacian_saliency(vertices, faces, method, num_scales, threshold)
    if method == "robust":
        return mesh_saliency(vertices, faces, variant="robust")
    variant = "paper" if method == "stochastic" else method
    return mesh_saliency(
        vertices, faces, variant=variant, num_scales=num_scales, threshold=threshold
    )


def evaluate_detectors(
    vertices,
    faces,
    marks: Sequence[Sequence[int]],
    methods: Sequence[str],
    *,
    progress: Callable[[str, DetectorResult], None] | None = None,
    **settings,
) -> MeshEvaluation:
    """Ground truth of one mesh from its marks, and every detector's errors against it.

    Args:
        vertices, faces: the mesh, ``(V, 3)`` float (computed in float64) and ``(F, 3)``
            integer tensors.
        marks: one sequence of marked vertex indices per subject
            (:func:`~.truth.read_marks`).
        methods: detector names from :data:`~.constants.EVALUATE_METHODS`.
        progress: called as ``progress(method, result)`` after each detector (``None``: no
            reports).
        **settings: the fields of :class:`EvaluationSettings`.

    Raises:
        ParameterError: as :func:`check_evaluation_parameters`, or no ground-truth point with
            these ``sigma`` and ``min_subjects``.
    """
    from ..interest import interest_points

    methods, params = _checked(methods, settings)
    vertices, faces = as_mesh_tensors(vertices, faces)
    vertices = vertices.double()
    used = choose_geodesic_method(faces, params.geodesics)
    diameter = mesh_diameter(vertices, faces, used)
    truth = build_ground_truth(
        vertices, faces, marks, params.sigma, params.min_subjects, diameter, used
    )
    if truth.num_points == 0:
        raise ParameterError(
            f"no ground-truth point has {params.min_subjects} subjects agreeing within sigma="
            f"{params.sigma:g}; lower min_subjects or raise sigma"
        )
    results: dict[str, DetectorResult] = {}
    for method in methods:
        start = time.perf_counter()
        values = detector_saliency(method, vertices, faces, params.num_scales, params.threshold)
        points = interest_points(
            values, vertices, faces, mode=params.mode, radius=params.radius, top_k=params.top_k
        )
        curves = evaluate_interest_points(
            vertices, faces, truth, points, params.radii, diameter, used
        )
        results[method] = DetectorResult(int(points.numel()), curves, time.perf_counter() - start)
        if progress is not None:
            progress(method, results[method])
    return MeshEvaluation(truth.num_points, truth.num_subjects, used, float(diameter), results)


def mean_error_curves(evaluations: Sequence[MeshEvaluation]) -> dict[str, dict[str, list[float]]]:
    """``{method: {"fne": (R,), "fpe": (R,), "wme": (R,)}}`` averaged over the meshes, for the
    methods every evaluation has (all evaluated at the same radii)."""
    if not evaluations:
        raise ParameterError("no evaluations to average")
    methods = [m for m in evaluations[0].results if all(m in e.results for e in evaluations)]

    def mean(method: str, key: str) -> list[float]:
        curves = [getattr(e.results[method].curves, key).numpy() for e in evaluations]
        return np.mean(curves, axis=0).tolist()

    return {method: {key: mean(method, key) for key in _CURVES} for method in methods}
