"""Per-vertex features from the multiscale representation, for learning pipelines.

:class:`MultiscaleFeatures` turns the representation of a mesh (or of a packed batch) into a
``(V, C)`` feature matrix. The channels come in groups, always in this order (scales
``k = 2..K``; scale 1 is the input, whose coefficient is zero and is left out):

=================  ======================  ===============================================
group              channels                names
=================  ======================  ===============================================
``coefficients``   ``3 (K-1)``             ``coef{k}_x``, ``coef{k}_y``, ``coef{k}_z``
  (rotation inv.)  ``2 (K-1)``             ``coef{k}_normal``, ``coef{k}_tangent``
``norms``          ``K-1``                 ``coef{k}_norm``
``differences``    ``K-1``                 ``diff{k}``
``saliency``       ``1``                   ``saliency``
=================  ======================  ===============================================

Within the coefficient group the channels are ordered scale-major (all channels of scale 2,
then scale 3, ...). :meth:`MultiscaleFeatures.channel_names` lists them.

Invariances: the operators are invariant to translations, rotations and uniform scaling of the
mesh, so the coefficients ``C^(k) = P^(k-1) - P^(k)`` are translation invariant and scale with
the mesh. They are divided per mesh by a length (the mean edge length by default), which makes
every channel scale invariant. With ``rotation_invariant=True`` each coefficient is expressed
in the local frame of its vertex: the component along the vertex normal (area-weighted face
normals, following the face orientation) and the norm of the tangential part.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .batch import check_batch
from .diffusion import MultiscaleRepresentation, check_parameters, multiscale_representation
from .mesh import as_mesh_tensors
from .operators import unique_edges

__all__ = [
    "FEATURE_GROUPS",
    "NORMALISATIONS",
    "MultiscaleFeatures",
    "feature_channel_names",
    "features_from_representation",
    "mesh_lengths",
    "multiscale_features",
    "vertex_normals",
]

#: Feature groups, in channel order.
FEATURE_GROUPS = ("coefficients", "norms", "differences", "saliency")
#: Per-mesh lengths the coefficients are divided by (``"none"``: left in mesh units).
NORMALISATIONS = ("mean_edge", "bbox_diagonal", "none")


def _safe_norm(values: Tensor, dim: int) -> Tensor:
    """Euclidean norm along ``dim`` with a zero (not NaN) gradient at the zero vector."""
    squared = values.square().sum(dim=dim)
    tiny = torch.finfo(values.dtype).tiny
    return torch.where(squared > tiny, squared.clamp_min(tiny).sqrt(), torch.zeros_like(squared))


def vertex_normals(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(V, 3)`` unit vertex normals: the area-weighted sum of the incident face normals.

    Args:
        vertices: ``(V, 3)`` float.
        faces: ``(F, 3)`` int64; the normal follows their orientation.

    Returns:
        ``(V, 3)`` float; zero at a vertex no face uses (or whose face normals cancel).
    """
    corners = vertices[faces]
    # |cross| is twice the face area: summing the raw cross products weights by area.
    cross = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    summed = vertices.new_zeros(vertices.shape).index_add(
        0, faces.reshape(-1), cross.repeat_interleave(3, dim=0)
    )
    length = _safe_norm(summed, dim=1).unsqueeze(1)
    return torch.where(
        length > 0,
        summed / length.clamp_min(torch.finfo(length.dtype).tiny),
        torch.zeros_like(summed),
    )


def mesh_lengths(
    vertices: Tensor, faces: Tensor, batch: Tensor | None = None, kind: str = "mean_edge"
) -> Tensor:
    """``(B,)`` one length per mesh of a packed batch (``B = 1`` without ``batch``).

    Args:
        vertices: ``(V, 3)`` float.
        faces: ``(F, 3)`` int64.
        batch: optional ``(V,)`` int64 mesh index of every vertex.
        kind: ``"mean_edge"`` (mean length of the unique edges), ``"bbox_diagonal"`` (diagonal
            of the axis-aligned bounding box of the vertices) or ``"none"`` (ones).
    """
    if kind not in NORMALISATIONS:
        raise ValueError(f"normalisation must be one of {NORMALISATIONS}, got {kind!r}")
    if batch is None:
        batch = torch.zeros(vertices.shape[0], dtype=torch.int64, device=vertices.device)
    num_meshes = int(batch.max()) + 1 if batch.numel() else 1
    if kind == "none":
        return vertices.new_ones(num_meshes)
    if kind == "bbox_diagonal":
        index = batch.unsqueeze(1).expand(-1, 3)
        high = vertices.new_full((num_meshes, 3), -torch.inf).scatter_reduce(
            0, index, vertices, reduce="amax"
        )
        low = vertices.new_full((num_meshes, 3), torch.inf).scatter_reduce(
            0, index, vertices, reduce="amin"
        )
        lengths = _safe_norm(high - low, dim=1)
    else:
        edges = unique_edges(faces, vertices.shape[0])
        edge_lengths = _safe_norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], dim=1)
        mesh = batch[edges[:, 0]]
        sums = vertices.new_zeros(num_meshes).index_add(0, mesh, edge_lengths)
        counts = vertices.new_zeros(num_meshes).index_add(0, mesh, torch.ones_like(edge_lengths))
        lengths = sums / counts.clamp_min(1)
    # A mesh without edges or extent (a single point) keeps its units.
    return torch.where(torch.isfinite(lengths) & (lengths > 0), lengths, torch.ones_like(lengths))


def _scale_channel_names(group: str, num_scales: int, rotation_invariant: bool) -> list[str]:
    scales = range(2, num_scales + 1)
    if group == "coefficients":
        parts = ("normal", "tangent") if rotation_invariant else ("x", "y", "z")
        return [f"coef{k}_{part}" for k in scales for part in parts]
    if group == "norms":
        return [f"coef{k}_norm" for k in scales]
    if group == "differences":
        return [f"diff{k}" for k in scales]
    return ["saliency"]


def feature_channel_names(
    num_scales: int, include: tuple[str, ...] = FEATURE_GROUPS, rotation_invariant: bool = False
) -> list[str]:
    """Names of the channels :func:`multiscale_features` returns, in order."""
    return [
        name
        for group in FEATURE_GROUPS
        if group in include
        for name in _scale_channel_names(group, num_scales, rotation_invariant)
    ]


def _check_include(include) -> tuple[str, ...]:
    include = tuple(include)
    unknown = sorted(set(include) - set(FEATURE_GROUPS))
    if unknown or not include:
        raise ValueError(f"include must be a non-empty subset of {FEATURE_GROUPS}, got {include!r}")
    return include


def features_from_representation(
    rep: MultiscaleRepresentation,
    faces: Tensor,
    include: tuple[str, ...] = FEATURE_GROUPS,
    rotation_invariant: bool = False,
    normalisation: str = "mean_edge",
) -> Tensor:
    """``(V, C)`` features from a representation; channel order of :func:`feature_channel_names`.

    Args:
        rep: the representation (its ``batch`` is used for the per-mesh lengths).
        faces: ``(F, 3)`` int64 faces of the mesh it was computed on (normals, edge lengths).
        include: groups of :data:`FEATURE_GROUPS` to return.
        rotation_invariant: coefficients as (normal component, tangential norm).
        normalisation: one of :data:`NORMALISATIONS`.
    """
    include = _check_include(include)
    vertices = rep.positions[0]
    batch = rep.batch
    lengths = mesh_lengths(vertices, faces, batch, normalisation)
    per_vertex = lengths[batch] if batch is not None else lengths.expand(vertices.shape[0])
    coefficients = rep.coefficients[1:] / per_vertex.reshape(1, -1, 1)  # (K-1, V, 3)
    channels = []
    if "coefficients" in include:
        if rotation_invariant:
            normals = vertex_normals(vertices, faces)
            normal = (coefficients * normals).sum(dim=2)
            tangent = _safe_norm(coefficients - normal.unsqueeze(2) * normals, dim=2)
            local = torch.stack([normal, tangent], dim=2)  # (K-1, V, 2)
            channels.append(local.permute(1, 0, 2).reshape(vertices.shape[0], -1))
        else:
            channels.append(coefficients.permute(1, 0, 2).reshape(vertices.shape[0], -1))
    if "norms" in include:
        channels.append(_safe_norm(coefficients, dim=2).T)
    if "differences" in include:
        channels.append(rep.differences[1:].T)
    if "saliency" in include:
        channels.append(rep.saliency().unsqueeze(1))
    return torch.cat(channels, dim=1)


def multiscale_features(
    vertices,
    faces,
    num_scales: int = 6,
    threshold: float = 1e-3,
    batch: Tensor | None = None,
    include: tuple[str, ...] = FEATURE_GROUPS,
    rotation_invariant: bool = False,
    normalisation: str = "mean_edge",
    differentiable_operator: bool = False,
    max_memory: int | None = None,
) -> Tensor:
    """``(V, C)`` per-vertex multiscale features of a mesh or packed batch.

    Args:
        vertices: ``(V, 3)`` float tensor.
        faces: ``(F, 3)`` integer tensor.
        num_scales: ``K >= 2``.
        threshold: ``lambda`` in ``(0, 1)``.
        batch: optional ``(V,)`` int64 mesh index of every vertex of a packed batch.
        include: groups of :data:`FEATURE_GROUPS` to return (all by default).
        rotation_invariant: coefficients as (normal component, tangential norm).
        normalisation: per-mesh length of :data:`NORMALISATIONS` the coefficients are divided by.
        differentiable_operator: gradients also through the operators
            (:func:`~stochlap_torch.autodiff.differentiable_multiscale`).
        max_memory: byte budget for the operators (constant-operator path).

    Returns:
        ``(V, C)`` float in the dtype of ``vertices``; ``C = len(feature_channel_names(...))``.
    """
    check_parameters(num_scales, threshold)
    include = _check_include(include)
    if normalisation not in NORMALISATIONS:
        raise ValueError(f"normalisation must be one of {NORMALISATIONS}, got {normalisation!r}")
    points, faces = as_mesh_tensors(vertices, faces)
    if batch is not None:
        batch = check_batch(batch.to(points.device), points.shape[0], faces)
    if differentiable_operator:
        from .autodiff import differentiable_multiscale

        rep = differentiable_multiscale(points, faces, num_scales, threshold, batch=batch)
    else:
        rep = multiscale_representation(
            points, faces, num_scales, threshold, max_memory=max_memory, batch=batch
        )
    return features_from_representation(rep, faces, include, rotation_invariant, normalisation)


class MultiscaleFeatures(nn.Module):
    """Per-vertex features from the multiscale representation: ``(V, 3)``, ``(F, 3)`` -> ``(V, C)``.

    Args:
        num_scales: ``K >= 2``.
        threshold: ``lambda`` in ``(0, 1)``.
        include: groups of :data:`FEATURE_GROUPS`, returned in that order.
        rotation_invariant: coefficients as (normal component, tangential norm) instead of xyz.
        normalisation: per-mesh length the coefficients are divided by (:data:`NORMALISATIONS`).
        differentiable_operator: gradients also through the operators into the vertices.
        max_memory: byte budget for the operators.

    Shapes:
        vertices ``(V, 3)`` float, faces ``(F, 3)`` int64, optional batch ``(V,)`` int64 ->
        ``(V, C)`` with ``C = self.num_channels``; :meth:`channel_names` names the channels.
    """

    def __init__(
        self,
        num_scales: int = 6,
        threshold: float = 1e-3,
        include: tuple[str, ...] = FEATURE_GROUPS,
        rotation_invariant: bool = False,
        normalisation: str = "mean_edge",
        differentiable_operator: bool = False,
        max_memory: int | None = None,
    ):
        super().__init__()
        check_parameters(num_scales, threshold)
        if normalisation not in NORMALISATIONS:
            raise ValueError(
                f"normalisation must be one of {NORMALISATIONS}, got {normalisation!r}"
            )
        self.num_scales = num_scales
        self.threshold = threshold
        self.include = _check_include(include)
        self.rotation_invariant = rotation_invariant
        self.normalisation = normalisation
        self.differentiable_operator = differentiable_operator
        self.max_memory = max_memory

    def channel_names(self) -> list[str]:
        """The ``C`` channel names, in the order of the feature columns."""
        return feature_channel_names(self.num_scales, self.include, self.rotation_invariant)

    @property
    def num_channels(self) -> int:
        return len(self.channel_names())

    def forward(self, vertices: Tensor, faces: Tensor, batch: Tensor | None = None) -> Tensor:
        return multiscale_features(
            vertices,
            faces,
            self.num_scales,
            self.threshold,
            batch=batch,
            include=self.include,
            rotation_invariant=self.rotation_invariant,
            normalisation=self.normalisation,
            differentiable_operator=self.differentiable_operator,
            max_memory=self.max_memory,
        )

    def extra_repr(self) -> str:
        return (
            f"num_scales={self.num_scales}, threshold={self.threshold:g}, "
            f"include={self.include}, rotation_invariant={self.rotation_invariant}, "
            f"normalisation={self.normalisation!r}, "
            f"differentiable_operator={self.differentiable_operator}"
        )
