"""The heat semigroup ``exp(-t M^-1 L)`` applied to per-vertex fields, for several times.

No eigendecomposition: the exponential is expanded in Chebyshev polynomials of ``M^-1 L``
scaled to ``[-1, 1]`` (its coefficients are scaled Bessel functions), and one three-term
recurrence serves every time at once; it costs about ``sqrt(t * bound)`` sparse products
with the fields. :func:`heat_apply` works on numpy arrays; :class:`HeatSemigroup` wraps it as
a torch function of the fields, with the operator held constant: ``exp(-t M^-1 L)`` is
self-adjoint in the ``M`` inner product, so its transpose is ``M exp(-t M^-1 L) M^-1`` and the
backward pass is one more application. :func:`heat_diagonal` is the one place that takes
eigenpairs: the diagonal of the heat kernel (the robust variant's ``heat`` channel) on a
coarse level, from the few low ones it needs.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from .._common.errors import MeshError
from ..operators.heat_operator import HeatOperator, chebyshev_terms
from ..sparse.csr import CSR

__all__ = [
    "DEFAULT_TOLERANCE",
    "HEAT_TRUNCATION",
    "HeatSemigroup",
    "LevelSemigroup",
    "chebyshev_apply",
    "chebyshev_coefficients",
    "heat_apply",
    "heat_diagonal",
]

#: More Chebyshev steps than this means a level far finer than its scales (a vertex far out
#: from the rest of the mesh): well above what real meshes need, even after graded remeshing.
MAX_CHEBYSHEV_TERMS = 1e7
#: Chebyshev terms are dropped once every time's coefficient is below this.
DEFAULT_TOLERANCE = 1e-6


def chebyshev_coefficients(times: np.ndarray, bound: float, tol: float) -> np.ndarray:
    """``(T, K)`` coefficients of ``exp(-t x)`` on ``[0, bound]`` in the Chebyshev basis of
    ``y = 2 x / bound - 1``: ``c_k = (2 - [k = 0]) (-1)^k e^-a I_k(a)``, ``a = t bound / 2``,
    up to the last term any time keeps at truncation ``tol`` (:func:`~stochlap_torch.
    operators.heat_operator.chebyshev_terms`)."""
    from scipy.special import ive

    a = np.asarray(times, dtype=np.float64) * bound / 2.0
    if not np.max(a) <= MAX_CHEBYSHEV_TERMS:
        raise MeshError(
            f"diffusing to the robust variant's scales would take {np.max(a):.3g} steps: the "
            "mesh's triangles differ in size by many orders of magnitude (vertices far out "
            "from the rest?); remove the outlying vertices, or use variant='paper'"
        )
    terms = max(chebyshev_terms(float(value), tol) for value in a)
    k = np.arange(terms)
    signs = np.where(k % 2 == 0, 1.0, -1.0) * np.where(k == 0, 1.0, 2.0)
    return ive(k[None, :], a[:, None]) * signs


#: Chebyshev terms summed by one matrix product: at most this many, and at most
#: :data:`_TERMS_PER_TIME` per time asked for (the terms held at once cost memory). Both at
#: least 2: the first two terms are written before any block is added.
_MAX_TERMS_PER_PRODUCT = 16
_TERMS_PER_TIME = 4


def heat_apply(
    operator: HeatOperator, fields: np.ndarray, times, tol: float = DEFAULT_TOLERANCE
) -> np.ndarray:
    """``(T, n, C)``: ``exp(-t m^-1 L) fields`` for every ``t`` of ``times`` (``m`` the capped
    masses), by one shared Chebyshev recurrence (in the operator's bandwidth-reducing
    :attr:`~stochlap_torch.operators.heat_operator.HeatOperator.order`).

    The terms ``T_k(y) fields`` are kept a block at a time and added to every time's sum by
    one matrix product (torch's, on the calling thread's thread count): a term costs one
    sparse product and one subtraction into its slot, not five passes over the fields.

    Args:
        operator: the level's :class:`~stochlap_torch.operators.heat_operator.HeatOperator`.
        fields: ``(n, C)`` float64.
        times: ``(T,)`` diffusion times (in the units of the mesh's area).
        tol: Chebyshev truncation (:data:`DEFAULT_TOLERANCE`).
    """
    return _recurrence(operator.recurrence, operator.order, operator.bound, fields, times, tol)


def _recurrence(
    recurrence, order: np.ndarray, bound: float, fields: np.ndarray, times, tol: float
) -> np.ndarray:
    """:func:`heat_apply` of the scipy CSR ``recurrence`` in ``order``."""
    coefficients = chebyshev_coefficients(np.asarray(times), bound, tol)
    count, terms = coefficients.shape
    n, channels = fields.shape
    size = min(terms, _MAX_TERMS_PER_PRODUCT, _TERMS_PER_TIME * count)  # >= 2 (the constants)
    block = np.empty((size, n, channels))  # T_k fields in slot k % size
    flat = torch.from_numpy(block.reshape(size, n * channels))
    sums = torch.zeros(count, n * channels, dtype=torch.float64)

    def add(first: int, used: int) -> None:  # the terms first..first+used-1, slots 0..used-1
        weights = np.ascontiguousarray(coefficients[:, first : first + used])
        sums.addmm_(torch.from_numpy(weights), flat[:used])

    block[0] = fields[order]
    if terms > 1:
        np.multiply(recurrence @ block[0], 0.5, out=block[1])
    for k in range(2, terms):
        slot = k % size
        if slot == 0:
            add(k - size, size)
        np.subtract(recurrence @ block[(k - 1) % size], block[(k - 2) % size], out=block[slot])
    done = (terms - 1) // size * size
    add(done, terms - done)
    out = np.empty((count, n, channels))
    out[:, order] = sums.numpy().reshape(count, n, channels)
    return out


class LevelSemigroup:
    """``exp(-t m^-1 L)`` of one level as torch tensors on one device (``m`` the capped masses):
    what the diffusion needs at call time, built once from a
    :class:`~stochlap_torch.operators.heat_operator.HeatOperator` and moved with :meth:`to`.

    Attributes:
        recurrence: ``(n, n)`` float64 ``torch.sparse_csr`` ``R`` in :attr:`order`, int32
            indices where they fit
            (:attr:`~stochlap_torch.operators.heat_operator.HeatOperator.recurrence`).
        order: ``(n,)`` int64 the bandwidth-reducing order of the vertices.
        inverse: ``(n,)`` int64 its inverse permutation.
        capped_mass: ``(n,)`` float64 ``m`` (the backward pass's inner product).
        bound: the spectral bound the recurrence is scaled by.
    """

    def __init__(self, recurrence: Tensor, order: Tensor, capped_mass: Tensor, bound: float):
        self.recurrence = recurrence
        self.order = order
        self.inverse = torch.empty_like(order)
        self.inverse[order] = torch.arange(order.numel(), device=order.device)
        self.capped_mass = capped_mass
        self.bound = float(bound)
        self._cache: dict = {}

    @classmethod
    def of(cls, operator: HeatOperator) -> LevelSemigroup:
        matrix = operator.recurrence
        csr = CSR(
            torch.from_numpy(matrix.indptr.astype(np.int64)),
            torch.from_numpy(matrix.indices.astype(np.int64)),
            torch.from_numpy(np.asarray(matrix.data, dtype=np.float64)),
            matrix.shape[1],
        )
        order = torch.from_numpy(operator.order)
        mass = torch.from_numpy(np.asarray(operator.capped_mass, dtype=np.float64))
        return cls(csr.to_sparse_csr(compact=True), order, mass, operator.bound)

    @property
    def device(self) -> torch.device:
        return self.order.device

    @property
    def num_vertices(self) -> int:
        return int(self.order.shape[0])

    def to(self, device) -> LevelSemigroup:
        """This semigroup with its tensors on ``device`` (itself if already there)."""
        device = torch.device(device)
        if device == self.device:
            return self
        return LevelSemigroup(
            self.recurrence.to(device),
            self.order.to(device),
            self.capped_mass.to(device),
            self.bound,
        )

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_cache"] = {}  # derived: rebuilt on first use
        return state

    def matrix(self, dtype: torch.dtype) -> Tensor:
        """:attr:`recurrence` in ``dtype`` (converted once per dtype)."""
        key = ("matrix", dtype)
        if key not in self._cache:
            self._cache[key] = self.recurrence.to(dtype)
        return self._cache[key]

    def coefficients(
        self, times: tuple, tol: float, dtype: torch.dtype, constant: bool = False
    ) -> Tensor:
        """``(T, K)`` :func:`chebyshev_coefficients` of ``times`` in ``dtype`` on the device
        (computed on the host once per ``times``, ``tol`` and ``dtype``); with ``constant``,
        ``(T,)`` what the truncated series does to a constant, less one (``sum_k c_k (-1)^k -
        1``, summed in float64)."""
        key = ("coefficients", tuple(times), tol, dtype, constant)
        if key not in self._cache:
            table = chebyshev_coefficients(np.asarray(times, dtype=np.float64), self.bound, tol)
            if constant:
                signs = np.where(np.arange(table.shape[1]) % 2 == 0, 1.0, -1.0)
                table = table @ signs - 1.0
            self._cache[key] = torch.from_numpy(table).to(dtype=dtype, device=self.device)
        return self._cache[key]


def chebyshev_apply(
    semigroup: LevelSemigroup, fields: Tensor, times, tol: float, dtype: torch.dtype | None = None
) -> Tensor:
    """``(T, n, C)``: the increments ``exp(-t m^-1 L) fields - fields`` for every ``t`` of
    ``times``, by the shared Chebyshev recurrence of :func:`heat_apply` written in torch:
    sparse CSR products (cuSPARSE on CUDA) on the device of ``fields`` (``(n, C)`` float;
    ``semigroup`` on that device), in ``dtype`` (default: that of ``fields``) after the
    first term, which is computed in the dtype of ``fields``.

    The recurrence runs on ``y_k = T_k x - (-1)^k x`` (``T_k x -> (-1)^k x`` for a constant
    ``x``): ``y_0 = 0``, ``y_1 = (R x) / 2 + x``, ``y_(k+1) = R y_k - y_(k-1) + (-1)^k 2 y_1``,
    and ``exp(-t A) x - x = sum_k c_k y_k + (sum_k c_k (-1)^k - 1) x`` (the last term is the
    truncation's, as :func:`heat_apply` has it: ``sum_k c_k (-1)^k = 1`` for the whole
    series). The terms are as small as what the diffusion changes, not as the fields, so
    ``F x - x``, a difference of nearly equal numbers when computed from ``F x``, keeps the
    digits it needs. Only ``y_1`` is computed from the fields themselves, and the rounding of
    ``R x`` is relative to ``x``: fields far from zero (the squared positions of the spread)
    need it in float64, after which the rest of the recurrence runs in float32 (``dtype``).
    """
    dtype = fields.dtype if dtype is None else dtype
    coefficients = semigroup.coefficients(tuple(times), tol, dtype)
    count, terms = coefficients.shape
    n, channels = fields.shape
    ordered = fields[semigroup.order]
    truncation = semigroup.coefficients(tuple(times), tol, fields.dtype, constant=True)
    sums = (truncation[:, None] * ordered.reshape(1, n * channels)).to(dtype)
    if terms == 1:
        return sums.reshape(count, n, channels)[:, semigroup.inverse]
    size = min(terms, _MAX_TERMS_PER_PRODUCT, _TERMS_PER_TIME * count)  # >= 2
    block = ordered.new_zeros(size, n, channels, dtype=dtype)  # y_k in slot k % size (y_0 = 0)
    flat = block.reshape(size, n * channels)
    first = torch.add(semigroup.matrix(fields.dtype) @ ordered, ordered, alpha=2.0).mul_(0.5)
    first = first.to(dtype)  # y_1
    block[1] = first
    matrix = semigroup.matrix(dtype)
    slots = block.unbind(0)  # the views, made once: hundreds of terms reuse them
    for k in range(2, terms):
        slot = k % size
        if slot == 0:
            sums.addmm_(coefficients[:, k - size : k], flat)
        # R y_(k-1) - y_(k-2) in one sparse product into the slot (size >= 3 here, so the
        # slot is not y_(k-2)'s), then the (-1)^(k-1) 2 y_1 of the increment form.
        out = slots[slot]
        torch.addmm(slots[(k - 2) % size], matrix, slots[(k - 1) % size], beta=-1.0, out=out)
        out.add_(first, alpha=-2.0 if k % 2 == 0 else 2.0)
    done = (terms - 1) // size * size
    sums.addmm_(coefficients[:, done:terms], flat[: terms - done])
    return sums.reshape(count, n, channels)[:, semigroup.inverse]


#: Times whose gradients one recurrence of the backward pass carries side by side (its memory
#: grows with their square).
_TIMES_PER_BACKWARD = 3


class HeatSemigroup(torch.autograd.Function):
    """``(T, n, C)`` the increments ``exp(-t m^-1 L) x - x`` of ``(n, C)`` fields ``x`` (in
    ``dtype``, by default theirs, as :func:`chebyshev_apply` computes them; on their device:
    the :class:`LevelSemigroup`'s), differentiable w.r.t. ``x``
    with the operator held constant (O(n C) memory: nothing but the operator is saved; the
    backward pass holds ``O(n C)`` more while it runs, for up to :data:`_TIMES_PER_BACKWARD`
    times at once).

    ``exp(-t m^-1 L)`` is self-adjoint in the ``m`` inner product: the transpose of ``F - I``
    is ``m (F - I) m^-1``, so the backward pass is one more application.
    """

    @staticmethod
    def forward(
        ctx,
        fields: Tensor,
        semigroup: LevelSemigroup,
        times: tuple,
        tol: float,
        dtype: torch.dtype | None = None,
    ):
        ctx.semigroup, ctx.times, ctx.tol, ctx.dtype = semigroup, times, tol, fields.dtype
        return chebyshev_apply(semigroup, fields.detach(), times, tol, dtype)

    @staticmethod
    @once_differentiable  # the recurrence writes into its slots: no graph of the backward
    def backward(ctx, grad: Tensor):
        mass = ctx.semigroup.capped_mass.to(grad.dtype)
        upstream = grad / mass[None, :, None]  # m^-1 g
        count, n, channels = upstream.shape
        total = grad.new_zeros(n, channels)
        # sum_t (F_t - I) g_t, by one recurrence on up to _TIMES_PER_BACKWARD g_t side by side
        # (fewer, wider sparse products, each reading the matrix once for several times), of
        # which block t of time t is kept.
        for first in range(0, count, _TIMES_PER_BACKWARD):
            times = ctx.times[first : first + _TIMES_PER_BACKWARD]
            group = upstream[first : first + len(times)]
            stacked = group.transpose(0, 1).reshape(n, -1)
            # In the gradient's dtype after a first term in the fields' (as the forward).
            diffused = chebyshev_apply(
                ctx.semigroup, stacked.to(ctx.dtype), times, ctx.tol, grad.dtype
            )
            for index in range(len(times)):
                total += diffused[index][:, index * channels : (index + 1) * channels]
        return (total * mass[:, None]).to(ctx.dtype), None, None, None, None


#: The heat diagonal leaves out the eigenpairs that decay below this at its smallest time
#: (they change ``h_t(i, i)`` by less, relatively).
HEAT_TRUNCATION = 1e-6
#: Levels up to this size get a full (dense) eigendecomposition for the heat diagonal.
_DENSE_LEVEL = 400


def _low_eigenpairs(laplacian, mass: np.ndarray, limit: float) -> tuple[Tensor, Tensor]:
    """``(values (k,), basis (n, k))`` of ``M^-1/2 L M^-1/2`` (``M`` the vertex areas, not the
    capped masses the semigroup needs to bound its cost: the eigensolver does not, and raised
    masses bias ``h_t(i, i)``) of a connected level: every eigenpair with eigenvalue below
    ``limit``, and possibly a few above.

    Dense (torch's LAPACK, which follows the calling thread's one-thread setting inside a
    library call) on small levels; otherwise shift-invert Lanczos for the ``k`` lowest, ``k``
    from Weyl's law (``k ~ area limit / 4 pi``, with margin), doubled until the ``k``-th
    eigenvalue passes ``limit``: the heat channel needs a few tens of pairs, far fewer than a
    full ``eigh`` computes. (Connected: every component adds a zero eigenvalue, which Weyl's
    law does not count.)
    """
    from scipy import sparse
    from scipy.sparse.linalg import eigsh

    count = mass.shape[0]
    scale = 1.0 / np.sqrt(mass)
    symmetric = sparse.diags(scale) @ laplacian @ sparse.diags(scale)
    wanted = int(1.25 * float(mass.sum()) * limit / (4.0 * math.pi)) + 10
    # A fixed start vector: ARPACK's own is random, and the features would differ in their
    # last bits from call to call.
    start = np.random.default_rng(0).standard_normal(count)
    shift = -1e-6 * float(np.median(laplacian.diagonal() / mass))
    while count > _DENSE_LEVEL and wanted < count // 2:
        values, basis = eigsh(symmetric.tocsc(), k=wanted, sigma=shift, which="LM", v0=start)
        if values.max() >= limit:
            return torch.from_numpy(values), torch.from_numpy(basis)
        wanted *= 2
    dense = symmetric.toarray()
    return torch.linalg.eigh(torch.from_numpy(0.5 * (dense + dense.T)))


def _diagonal(values: Tensor, basis: Tensor, mass: np.ndarray, times: np.ndarray) -> np.ndarray:
    """``(..., n, H)`` ``h_t(i, i)`` from eigenpairs ``(..., k)``, ``(..., n, k)``."""
    decay = torch.exp(-values.clamp_min(0.0)[..., :, None] * torch.from_numpy(times))
    return (basis.square() @ decay).numpy() / mass[..., :, None]


def _components(laplacian) -> np.ndarray:
    """``(n,)`` the connected component of every vertex under the nonzero couplings of
    ``laplacian`` (on which ``exp(-t M^-1 L)`` is block diagonal)."""
    from scipy.sparse.csgraph import connected_components

    coupled = laplacian.copy()
    coupled.eliminate_zeros()
    return connected_components(coupled, directed=False)[1]


def _blocks_of_size(laplacian, mass, labels, members: np.ndarray, limit: float, times):
    """``(B s, H)`` the heat diagonal of ``B`` components of ``s <= _DENSE_LEVEL`` vertices
    each (``members (B, s)``, each row ascending), by one batched dense eigendecomposition."""
    batch, size = members.shape
    slot = np.full(labels.max() + 1, -1, dtype=np.int64)
    slot[labels[members[:, 0]]] = np.arange(batch)
    position = np.empty(labels.size, dtype=np.int64)
    position[members] = np.arange(size)[None, :]
    block = laplacian[members.reshape(-1)].tocoo()  # rows in member order
    dense = np.zeros((batch, size, size))
    rows = members.reshape(-1)[block.row]
    # Stored zeros may couple a row to another component (the components come from the
    # nonzeros): such an entry would land on a real one of this block.
    inside = labels[block.col] == labels[rows]
    rows, cols, data = rows[inside], block.col[inside], block.data[inside]
    dense[slot[labels[rows]], position[rows], position[cols]] = data
    scale = 1.0 / np.sqrt(mass[members])
    dense *= scale[:, :, None] * scale[:, None, :]
    values, basis = torch.linalg.eigh(torch.from_numpy(0.5 * (dense + dense.transpose(0, 2, 1))))
    return _diagonal(values, basis, mass[members], times).reshape(batch * size, -1)


def heat_diagonal(operator: HeatOperator, times: np.ndarray) -> np.ndarray:
    """``(n, H)`` ``log(4 pi t h_t(i, i))`` on a coarse level (``h_t`` the kernel of ``exp(-t
    M^-1 L)`` with respect to the vertex areas ``M``), from its low eigenpairs
    (:func:`_low_eigenpairs`, truncated at :data:`HEAT_TRUNCATION`), component by component.

    The kernel is block diagonal over the connected components, and each adds a zero
    eigenvalue: solved whole, a level of thousands of components (a triangle soup) asked
    Lanczos for ever more eigenpairs. Components of equal size up to :data:`_DENSE_LEVEL`
    share one batched dense eigendecomposition; larger ones get their own eigenpairs.
    """
    limit = math.log(1.0 / HEAT_TRUNCATION) / float(np.min(times))
    labels = _components(operator.laplacian)
    sizes = np.bincount(labels)
    if sizes.size == 1:
        values, basis = _low_eigenpairs(operator.laplacian, operator.mass, limit)
        diagonal = _diagonal(values, basis, operator.mass, times)
    else:
        diagonal = np.empty((labels.size, len(times)))
        order = np.argsort(labels, kind="stable")  # every component's vertices, ascending
        starts = np.concatenate([[0], np.cumsum(sizes)])
        for size in np.unique(sizes[sizes <= _DENSE_LEVEL]):
            chosen = np.flatnonzero(sizes == size)
            members = order[starts[chosen][:, None] + np.arange(size)[None, :]]
            diagonal[members.reshape(-1)] = _blocks_of_size(
                operator.laplacian, operator.mass, labels, members, limit, times
            )
        for label in np.flatnonzero(sizes > _DENSE_LEVEL):
            members = order[starts[label] : starts[label + 1]]
            laplacian = operator.laplacian[members][:, members]
            values, basis = _low_eigenpairs(laplacian, operator.mass[members], limit)
            diagonal[members] = _diagonal(values, basis, operator.mass[members], times)
    return np.log(np.maximum(4.0 * math.pi * times[None, :] * diagonal, 1e-300))
