"""A pyramid level's heat operator and its semigroup ``exp(-t M^-1 L)``: ``L`` the intrinsic
Delaunay cotangent Laplacian, ``M`` the vertex areas (:func:`heat_operator`), expanded in
Chebyshev polynomials: one recurrence serves every time at once, at about ``sqrt(t bound)``
sparse products (:func:`chebyshev_apply`). :func:`heat_diagonal` takes eigenpairs, on a coarse
level."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from .._common.errors import MeshError
from .._kernels import intrinsic_delaunay_weights
from ..params import RobustParams
from ..sparse.csr import CSR

#: More Chebyshev steps than this means a level far finer than its scales (an outlying vertex).
MAX_CHEBYSHEV_TERMS = 1e7
#: Chebyshev terms summed by one matrix product: at most this many, and at most
#: :data:`_TERMS_PER_TIME` per time (the terms held at once cost memory). Both at least 2.
_MAX_TERMS_PER_PRODUCT = 16
_TERMS_PER_TIME = 4
#: The heat diagonal leaves out the eigenpairs that decay below this at its smallest time.
HEAT_TRUNCATION = 1e-6
#: Levels up to this size get a full (dense) eigendecomposition for the heat diagonal.
_DENSE_LEVEL = 400


@dataclass(frozen=True)
class HeatOperator:
    """``M^-1 L`` of one mesh.

    Attributes:
        laplacian: ``(n, n)`` scipy CSR ``L = D - W``, symmetric positive semi-definite (``W``
            the :func:`clamped_weights`).
        mass: ``(n,)`` lumped vertex areas of the intrinsic triangulation (at least
            ``1e-12`` of their mean).
        capped_mass: ``(n,)`` the masses the semigroup uses (:func:`capped_mass`).
        bound: an upper bound of the spectrum of ``capped_mass^-1 L`` (Gershgorin).
    """

    laplacian: object
    mass: np.ndarray
    capped_mass: np.ndarray
    bound: float

    @property
    def num_vertices(self) -> int:
        return int(self.mass.shape[0])

    @cached_property
    def order(self) -> np.ndarray:
        """``(n,)`` a bandwidth-reducing order of the vertices (reverse Cuthill-McKee): the
        products of :attr:`recurrence` read the fields in cache-friendly runs."""
        from scipy.sparse.csgraph import reverse_cuthill_mckee

        return np.asarray(
            reverse_cuthill_mckee(self.laplacian, symmetric_mode=True), dtype=np.int64
        )

    @cached_property
    def recurrence(self):
        """``(n, n)`` scipy CSR ``R = 2 ((2 / bound) m^-1 L - I)`` in :attr:`order` (``m`` the
        capped masses), sorted indices: the Chebyshev recurrence ``T_(k+1) = R T_k - T_(k-1)``."""
        from scipy import sparse

        order = self.order
        scale = (4.0 / self.bound) / self.capped_mass[order]
        ordered = self.laplacian[order][:, order]
        matrix = (sparse.diags(scale) @ ordered - 2.0 * sparse.identity(order.size)).tocsr()
        matrix.sort_indices()
        return matrix


def chebyshev_terms(scaled_time: float, tol: float) -> int:
    """The Chebyshev terms of ``exp(-t x)`` on ``[0, bound]`` kept at truncation ``tol``
    (``scaled_time = t bound / 2 = a``): one more than the last ``k`` whose ``|c_k| = (2 - [k =
    0]) e^-a I_k(a)`` exceeds ``tol``, at least 1; by bisection (``I_k(a)`` decreases in ``k``)
    up to ``a + 12 sqrt(a) + 30``, where the coefficients are below ``1e-30``."""
    from scipy.special import ive

    def above(k: int) -> bool:
        return 2.0 * float(ive(k, scaled_time)) > tol

    if not above(1):
        return 1
    low, high = 1, int(scaled_time + 12.0 * math.sqrt(scaled_time) + 30)
    while high - low > 1:  # above(low), and not above(high)
        middle = (low + high) // 2
        low, high = (middle, high) if above(middle) else (low, middle)
    return low + 1


def _median_ratio(numerator: np.ndarray, denominator: np.ndarray) -> float:
    """The median of ``numerator / denominator`` where both are positive (1 if nowhere)."""
    usable = (numerator > 0.0) & (denominator > 0.0)
    return float(np.median(numerator[usable] / denominator[usable])) if usable.any() else 1.0


def _floored(mass: np.ndarray) -> np.ndarray:
    """``mass`` raised to at least ``1e-12`` of its mean (no vertex without mass)."""
    return np.maximum(mass, 1e-12 * max(float(mass.mean()) if mass.size else 1.0, 1e-300))


def clamped_weights(
    edges: np.ndarray, weights: np.ndarray, mass: np.ndarray, clamp: float = RobustParams.clamp
) -> np.ndarray:
    """``(E,)`` the edge weights with every edge's rate ``W_ij / min(M_i, M_j)`` clamped to
    ``clamp`` times the median rate: two vertices much closer together than their neighbours
    make the semigroup stiff; raising their masses instead would make them heat reservoirs.

    Args:
        edges: ``(E, 2)`` int64 vertex pairs; weights: ``(E,)`` float64 ``W_ij >= 0``;
        mass: ``(n,)`` float64 vertex areas; clamp: the largest rate, in median rates.
    """
    smaller = np.minimum(mass[edges[:, 0]], mass[edges[:, 1]])
    return np.minimum(weights, clamp * _median_ratio(weights, smaller) * smaller)


def capped_mass(
    laplacian, mass: np.ndarray, cap: float = RobustParams.cap
) -> tuple[np.ndarray, float]:
    """``(m, bound)``: ``m = max(M, D / (cap median(D / M)))`` and ``2 max(D / m)``, a bound of
    the spectrum of ``m^-1 L`` (Gershgorin)."""
    diagonal = laplacian.diagonal()
    capped = np.maximum(_floored(mass), diagonal / (cap * _median_ratio(diagonal, mass)))
    with np.errstate(divide="ignore", invalid="ignore"):  # heat_operator checks the result
        bound = 2.0 * float(np.max(diagonal / capped)) if diagonal.size else 1.0
    return capped, max(bound, 1e-300)


def _not_finite(what: str) -> MeshError:
    return MeshError(
        f"{what}: the mesh's triangles differ in size by many orders of magnitude (vertices "
        "far out from the rest?); remove the outlying vertices, or use variant='paper'"
    )


def heat_operator(
    vertices: np.ndarray,
    faces: np.ndarray,
    cap: float = RobustParams.cap,
    clamp: float = RobustParams.clamp,
) -> HeatOperator:
    """The :class:`HeatOperator` of a mesh (``(n, 3)`` float64, ``(m, 3)`` int64, every vertex
    referenced); ``clamp`` for :func:`clamped_weights`, then ``cap`` for :func:`capped_mass`."""
    from scipy import sparse

    edges, weights, lumped = intrinsic_delaunay_weights(vertices, faces)
    lumped = _floored(lumped)
    weights = clamped_weights(edges, weights, lumped, clamp)
    # Rebuild L = D - W from the clamped weights so that L 1 = 0 exactly.
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    n = vertices.shape[0]
    w = sparse.csr_matrix((np.concatenate([weights, weights]), (rows, cols)), shape=(n, n))
    lap = (sparse.diags(np.asarray(w.sum(axis=1)).ravel()) - w).tocsr()
    capped, bound = capped_mass(lap, lumped, cap)
    if not (np.isfinite(bound) and np.isfinite(capped).all() and capped.min() > 0.0):
        raise _not_finite("the robust variant's heat operator is not finite on this mesh")
    return HeatOperator(lap, lumped, capped, bound)


def chebyshev_coefficients(times: np.ndarray, bound: float, tol: float) -> np.ndarray:
    """``(T, K)`` coefficients of ``exp(-t x)`` on ``[0, bound]`` in the Chebyshev basis of
    ``y = 2 x / bound - 1``: ``c_k = (2 - [k = 0]) (-1)^k e^-a I_k(a)``, ``a = t bound / 2``,
    up to the last term any time keeps at truncation ``tol`` (:func:`chebyshev_terms`)."""
    from scipy.special import ive

    a = np.asarray(times, dtype=np.float64) * bound / 2.0
    if not np.max(a) <= MAX_CHEBYSHEV_TERMS:
        raise _not_finite(
            f"diffusing to the robust variant's scales would take {np.max(a):.3g} steps"
        )
    terms = max(chebyshev_terms(float(value), tol) for value in a)
    k = np.arange(terms)
    signs = np.where(k % 2 == 0, 1.0, -1.0) * np.where(k == 0, 1.0, 2.0)
    return ive(k[None, :], a[:, None]) * signs


class LevelSemigroup:
    """``exp(-t m^-1 L)`` of one level on one device (``m`` the capped masses).

    Attributes:
        recurrence: ``(n, n)`` float64 ``torch.sparse_csr`` :attr:`HeatOperator.recurrence`.
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

    def to(self, device) -> LevelSemigroup:
        """This semigroup with its tensors on ``device`` (itself if already there)."""
        if torch.device(device) == self.device:
            return self
        tensors = (self.recurrence, self.order, self.capped_mass)
        return LevelSemigroup(*(tensor.to(device) for tensor in tensors), self.bound)

    def state_dict(self, prefix: str) -> dict[str, Tensor]:
        """The semigroup as tensors named ``prefix`` + entry (read by :meth:`from_state`)."""
        state = {
            "crow": self.recurrence.crow_indices().to(torch.int64),
            "col": self.recurrence.col_indices().to(torch.int64),
            "val": self.recurrence.values(),
            "order": self.order,
            "capped_mass": self.capped_mass,
            "bound": torch.tensor(self.bound, dtype=torch.float64),
        }
        return {prefix + name: value for name, value in state.items()}

    @classmethod
    def from_state(cls, reader, prefix: str, n: int) -> LevelSemigroup | None:
        """The semigroup of a level of ``n`` vertices from its :meth:`state_dict` entries in a
        :class:`~stochlap_torch.robust.pyramid.StateReader` (``None`` if it has none), checked:
        ``R`` of a Laplacian has its diagonal in ``[-2, 0]``, no positive off-diagonal entry and
        rows summing to ``-2``, so its spectrum in ``[-2, 2]`` (Gershgorin), as the recurrence
        needs. ``ValueError`` names the entry that is not so."""
        if prefix + "crow" not in reader:
            return None
        col = reader.get(prefix + "col", torch.int64, (None,), 0, n)
        crow = reader.get(prefix + "crow", torch.int64, (n + 1,))
        val = reader.get(prefix + "val", torch.float64, (col.numel(),))
        order = reader.get(prefix + "order", torch.int64, (n,), 0, n)
        mass = reader.get(prefix + "capped_mass", torch.float64, (n,), 0.0)
        bound = float(reader.get(prefix + "bound", torch.float64, (), 0.0))
        slack = 1e-9
        if int(crow[0]) != 0 or int(crow[-1]) != col.numel() or bool((crow.diff() < 0).any()):
            raise ValueError(f"{prefix}crow: not the row pointers of {col.numel()} entries")
        rows = torch.repeat_interleave(torch.arange(n), crow.diff())
        if bool(((col.diff() <= 0) & (rows.diff() == 0)).any()):
            raise ValueError(f"{prefix}col: not strictly ascending within a row")
        diagonal = rows == col
        if bool((val[~diagonal] > 0.0).any()) or bool(
            ((val[diagonal] < -2.0 - slack) | (val[diagonal] > slack)).any()
        ):
            raise ValueError(f"{prefix}val: values outside the operator's spectral bound")
        sums = torch.zeros(n, dtype=torch.float64).index_add_(0, rows, val)
        if n and float((sums + 2.0).abs().max()) > slack:
            raise ValueError(f"{prefix}val: rows not those of a Laplacian")
        if not torch.equal(torch.sort(order).values, torch.arange(n)):
            raise ValueError(f"{prefix}order: not a permutation")
        return cls(CSR(crow, col, val, n).to_sparse_csr(compact=True), order, mass, bound)

    def matrix(self, dtype: torch.dtype) -> Tensor:
        """:attr:`recurrence` in ``dtype`` (converted once per dtype)."""
        key = ("matrix", dtype)
        if key not in self._cache:
            self._cache[key] = self.recurrence.to(dtype)
        return self._cache[key]

    def coefficients(
        self, times: tuple, tol: float, dtype: torch.dtype, constant: bool = False
    ) -> Tensor:
        """``(T, K)`` :func:`chebyshev_coefficients` in ``dtype`` on the device (computed once);
        with ``constant``, ``(T,)`` ``sum_k c_k (-1)^k - 1``, summed in float64."""
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
    """``(T, n, C)`` the increments ``exp(-t m^-1 L) fields - fields`` for every ``t`` of
    ``times``, by one Chebyshev recurrence of sparse products on the device of ``fields`` ``(n,
    C)``, in ``dtype`` (default: theirs) after the first term, computed in theirs.

    The recurrence runs on ``y_k = T_k x - (-1)^k x``: ``y_0 = 0``, ``y_1 = (R x) / 2 + x``,
    ``y_(k+1) = R y_k - y_(k-1) + (-1)^k 2 y_1``, and ``exp(-t A) x - x = sum_k c_k y_k +
    (sum_k c_k (-1)^k - 1) x``: terms as small as what the diffusion changes, so the increments
    keep digits that ``F x - x`` would cancel. Only ``y_1`` rounds relative to the fields: far
    from zero (the spread's squared positions) they need it in float64.
    """
    dtype = fields.dtype if dtype is None else dtype
    return chebyshev_apply_groups(semigroup, [(fields, tuple(times), None)], tol, dtype)[0]


def _first_term(semigroup: LevelSemigroup, ordered: Tensor) -> Tensor:
    """``y_1 = (R x) / 2 + x`` of ``ordered`` fields, in their dtype."""
    return torch.add(semigroup.matrix(ordered.dtype) @ ordered, ordered, alpha=2.0).mul_(0.5)


def _union_table(semigroup: LevelSemigroup, tables: list, tol: float, dtype: torch.dtype):
    """``(table (R, K), rows)``: the rows of every group's :meth:`LevelSemigroup.coefficients`
    (each time up to that group's own last term, zeros after, so that sharing a recurrence
    changes no group's truncation), a row shared by equal (time, terms); ``rows[g]``: group
    ``g``'s rows, in its times' order. Built once per set of groups."""
    key = ("union", tuple(tables), tol, dtype)
    if key not in semigroup._cache:
        found: dict = {}
        rows, chunks = [], []
        for times in tables:
            table = semigroup.coefficients(times, tol, dtype)
            indices = []
            for index, time in enumerate(times):
                row_key = (time, table.shape[1])
                if row_key not in found:
                    found[row_key] = len(chunks)
                    chunks.append(table[index])
                indices.append(found[row_key])
            rows.append(indices)
        terms = max(chunk.shape[0] for chunk in chunks)
        union = chunks[0].new_zeros(len(chunks), terms)
        for index, chunk in enumerate(chunks):
            union[index, : chunk.shape[0]] = chunk
        semigroup._cache[key] = (union, rows)
    return semigroup._cache[key]


def chebyshev_apply_groups(
    semigroup: LevelSemigroup, groups, tol: float, dtype: torch.dtype
) -> list[Tensor]:
    """:func:`chebyshev_apply` of several groups of fields by one recurrence: their columns
    side by side in every sparse product (a product costs little more for more columns).

    Args:
        groups: ``(fields (n, C_g), times, keep)`` each: the group's increments at its
            ``times`` (a tuple; its coefficients and truncation are those of
            :func:`chebyshev_apply` at these times), all of them (``keep`` ``None``) or the
            one at index ``keep``. Each group's first term is computed in its fields' dtype.
        dtype: the dtype of the recurrence and of the results.

    Returns:
        ``(T_g, n, C_g)`` per group (``(n, C_g)`` with ``keep``), in ``dtype``.
    """
    table, table_rows = _union_table(semigroup, [times for _, times, _ in groups], tol, dtype)
    count, terms = table.shape
    n = semigroup.order.numel()
    widths = [fields.shape[1] for fields, _, _ in groups]
    channels = sum(widths)
    starts = [sum(widths[:index]) for index in range(len(groups))]
    ordered = [fields.index_select(0, semigroup.order) for fields, _, _ in groups]
    # Each group's increments start from its truncation term, in the rows it reads.
    sums = ordered[0].new_zeros(count, n, channels, dtype=dtype)
    picks = []
    for (fields, times, keep), rows, start, here in zip(
        groups, table_rows, starts, ordered, strict=True
    ):
        chosen = range(len(times)) if keep is None else [keep]
        picks.append([rows[index] for index in chosen])
        truncation = semigroup.coefficients(times, tol, fields.dtype, constant=True)
        for index in chosen:
            sums[rows[index], :, start : start + here.shape[1]] = truncation[index] * here
    if terms > 1:
        flat_sums = sums.view(count, n * channels)
        first = torch.cat([_first_term(semigroup, here).to(dtype) for here in ordered], dim=1)
        _recurrence(semigroup.matrix(dtype), first, table, flat_sums)
    results = []
    for (_, _, keep), pick, start, width in zip(groups, picks, starts, widths, strict=True):
        columns = slice(start, start + width)
        if keep is not None:  # (n, C_g) gathered from a view of its row
            results.append(sums[pick[0], :, columns].index_select(0, semigroup.inverse))
            continue
        part = sums if pick == list(range(count)) else sums[pick]
        results.append(part[:, :, columns].index_select(1, semigroup.inverse))
    return results


def _recurrence(matrix: Tensor, first: Tensor, table: Tensor, sums: Tensor) -> None:
    """Add ``sum_k table[:, k] y_k`` (``k >= 1``) to ``sums`` ``(R, n C)``: the recurrence of
    :func:`chebyshev_apply` from ``y_1 = first`` ``(n, C)``, ``terms`` products."""
    count, terms = table.shape
    n, channels = first.shape
    size = min(terms, _MAX_TERMS_PER_PRODUCT, _TERMS_PER_TIME * count)  # >= 2
    block = first.new_empty(size, n, channels)  # y_k in slot k % size
    flat = block.view(size, n * channels)
    block[0] = 0.0  # y_0; every other slot is written before it is read
    block[1] = first
    slots = block.unbind(0)  # the views, made once: hundreds of terms reuse them
    for k in range(2, terms):
        slot = k % size
        if slot == 0:
            sums.addmm_(table[:, k - size : k], flat)
        # R y_(k-1) - y_(k-2) in one sparse product into the slot (size >= 3 here, so the
        # slot is not y_(k-2)'s), then the (-1)^(k-1) 2 y_1 of the increment form.
        out = slots[slot]
        torch.addmm(slots[(k - 2) % size], matrix, slots[(k - 1) % size], beta=-1.0, out=out)
        out.add_(first, alpha=-2.0 if k % 2 == 0 else 2.0)
    done = (terms - 1) // size * size
    sums.addmm_(table[:, done:terms], flat[: terms - done])


def _semigroup_backward(semigroup, times: list, tol: float, dtypes: list, grads) -> list:
    """The gradients of fields ``(n, C_g)`` in ``dtypes`` whose increments at ``times[g]`` got
    the gradients ``grads[g]`` ``(T_g, n, C_g)``, by one recurrence for every time of every
    group (:func:`_adjoint_recurrence`): the transpose of ``F - I`` is ``m (F - I) m^-1``."""
    dtype = grads[0].dtype
    mass = semigroup.capped_mass.to(dtype)
    table, table_rows = _union_table(semigroup, [tuple(group) for group in times], tol, dtype)
    n, order, widths = semigroup.order.numel(), semigroup.order, [g.shape[2] for g in grads]
    starts = [sum(widths[:index]) for index in range(len(grads))]
    # One row per (group, time): m^-1 g in the recurrence's vertex order, its group's columns.
    upstream = [(grad / mass[None, :, None]).index_select(1, order) for grad in grads]
    firsts = upstream[0].new_zeros(sum(len(group) for group in times), n, sum(widths))
    rows = []
    for here, group_rows, start, kind in zip(upstream, table_rows, starts, dtypes, strict=True):
        # The first term in the fields' dtype, as in the forward pass.
        first = _first_term(semigroup, here.to(kind).transpose(0, 1).reshape(n, -1)).to(dtype)
        first = first.reshape(n, here.shape[0], -1).transpose(0, 1)
        firsts[len(rows) : len(rows) + here.shape[0], :, start : start + here.shape[2]] = first
        rows += group_rows
    totals = _adjoint_recurrence(semigroup.matrix(dtype), table[rows], firsts)
    results = []
    for here, group, start, kind in zip(upstream, times, starts, dtypes, strict=True):
        truncation = semigroup.coefficients(tuple(group), tol, dtype, constant=True)
        total = totals[:, start : start + here.shape[2]] + torch.einsum(
            "t,tnc->nc", truncation, here
        )
        total = total.index_select(0, semigroup.inverse) * mass[:, None]
        results.append(total.to(kind))
    return results


def _adjoint_recurrence(matrix: Tensor, table: Tensor, firsts: Tensor) -> Tensor:
    """``(n, C)`` ``sum_t sum_k table[t, k] P_k(R) f_t`` (``k >= 1``) for the first terms
    ``f_t = (R h_t) / 2 + h_t`` ``firsts`` ``(P, n, C)``, where ``P_k(R) f = y_k`` is the forward
    recurrence's term (:func:`chebyshev_apply`): the forward recurrence run backwards (its
    adjoint, ``R`` standing for its own transpose under the mass inner product), one sparse
    product per term on ``C`` columns, where a forward recurrence per time carries ``P C``.

    With ``u_k = sum_t table[t, k] f_t``, ``b_k = u_k + R b_(k+1) - b_(k+2)`` down to ``k = 1``
    (Clenshaw's recurrence) and the sum is ``b_1 + sum_(k>=2) s_k b_k``, ``s_k = 2 (-1)^(k-1)``
    the weight of ``y_1`` in the forward step to ``y_k``. Every term is as small as the first
    terms, as in the forward recurrence.
    """
    count, terms = table.shape
    _, n, channels = firsts.shape
    flat = firsts.reshape(count, n * channels)
    later = torch.zeros_like(firsts[0])  # b_(k+1)
    latest = torch.zeros_like(firsts[0])  # b_(k+2), then b_k in its place
    total = torch.zeros_like(firsts[0])  # sum_(j>k) s_j b_j
    size = min(_MAX_TERMS_PER_PRODUCT, max(terms - 1, 1))
    for top in range(terms - 1, 0, -size):
        bottom = max(top - size, 0)
        block = (table[:, bottom + 1 : top + 1].T @ flat).view(-1, n, channels)  # u_k, k > bottom
        for k in range(top, bottom, -1):
            latest.addmm_(matrix, later, beta=-1.0).add_(block[k - bottom - 1])
            later, latest = latest, later
            if k >= 2:
                total.add_(later, alpha=2.0 if k % 2 == 1 else -2.0)
    return total.add_(later)


class HeatSemigroups(torch.autograd.Function):
    """:func:`chebyshev_apply` of several groups of fields (each its own times) by one
    recurrence (:func:`chebyshev_apply_groups`), differentiable w.r.t. every group's fields
    (the operator constant; the backward pass is :func:`_semigroup_backward`):
    ``apply(semigroup, times, tol, dtype, *fields)``, ``times[g]`` those of ``fields[g]``;
    returns their increments ``(T_g, n, C_g)`` in ``dtype``."""

    @staticmethod
    def forward(ctx, semigroup: LevelSemigroup, times: tuple, tol: float, dtype, *fields):
        ctx.semigroup, ctx.times, ctx.tol = semigroup, [tuple(group) for group in times], tol
        ctx.dtypes = [field.dtype for field in fields]
        groups = [(f.detach(), t, None) for f, t in zip(fields, ctx.times, strict=True)]
        return tuple(chebyshev_apply_groups(semigroup, groups, tol, dtype))

    @staticmethod
    @once_differentiable
    def backward(ctx, *grads):
        gradients = _semigroup_backward(ctx.semigroup, ctx.times, ctx.tol, ctx.dtypes, grads)
        return None, None, None, None, *gradients


def _low_eigenpairs(laplacian, mass: np.ndarray, limit: float) -> tuple[Tensor, Tensor]:
    """``(values (k,), basis (n, k))`` of ``M^-1/2 L M^-1/2`` (``M`` the vertex areas: capped
    masses bias ``h_t(i, i)``) of a connected level, every eigenpair below ``limit`` and maybe
    a few above: dense on small levels, else shift-invert Lanczos for the ``k`` lowest, ``k``
    from Weyl's law (``area limit / 4 pi``, with margin) doubled until past ``limit``."""
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
    M^-1 L)`` w.r.t. the vertex areas ``M``) from its eigenpairs above :data:`HEAT_TRUNCATION`,
    component by component (each adds a zero eigenvalue); those of equal size up to
    :data:`_DENSE_LEVEL` by one batched dense eigendecomposition."""
    from scipy.sparse.csgraph import connected_components

    limit = math.log(1.0 / HEAT_TRUNCATION) / float(np.min(times))
    coupled = operator.laplacian.copy()  # components of the nonzero couplings
    coupled.eliminate_zeros()
    labels = connected_components(coupled, directed=False)[1]
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
