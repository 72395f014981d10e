"""The compiled core of a diffusion step: a block of rows of ``F^(k)`` from ``F^(k-1)``
(Gustavson's algorithm with a dense accumulator per thread), with ``D^(k)``, ``F^(k) P`` and
each row's cost in the next step in the same pass.

Rows go in blocks of :data:`LANES` consecutive rows: in a locality order they share most of
their columns, so each row of ``Lhat`` a block needs is read once and its products for the
four rows are one vector operation. A row's block is fixed by its index, so results never
depend on the number of threads.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .threads import numba_available

if numba_available():
    from llvmlite import ir
    from numba import njit, types
    from numba.extending import intrinsic

#: Rows computed together (one vector operation per product); the kernel is written for four.
LANES = 4


class SplitLhat(NamedTuple):
    """``Lhat = diag(diagonal) + W`` as the kernel reads it (numpy arrays): ``(V,)`` float
    ``diagonal``, ``W`` (``Lhat`` without its diagonal) in CSR form and ``(V,)`` ``row_sums``
    of ``Lhat``."""

    diagonal: np.ndarray
    w_crow: np.ndarray
    w_col: np.ndarray
    w_val: np.ndarray
    row_sums: np.ndarray

    @property
    def num_cols(self) -> int:
        return int(self.diagonal.shape[0])


def row_width(num_cols: int, longest: int, threshold: float) -> int:
    """Entries a row of any ``F^(k)`` holds at most: those of the longest row of ``F^(1)``, or
    those kept, each at least ``threshold`` of a row summing to one (or the row's largest);
    ``1 / threshold`` is bounded first, so that a tiny threshold cannot overflow the integer."""
    return min(num_cols, max(longest, math.floor(min(1.0 / threshold, num_cols)) + 1))


class RowArrays(NamedTuple):
    """Rows of ``F^(k-1)``: row ``i`` is ``col[start[i] : start[i] + count[i]]`` (and ``val``)."""

    start: np.ndarray
    count: np.ndarray
    col: np.ndarray
    val: np.ndarray


class StepInputs(NamedTuple):
    """A step's inputs besides ``F^(k-1)`` and ``Lhat``: ``(V,)`` ``alpha`` (Eq. 9), ``lambda``,
    ``(V, C)`` positions ``P`` (``C`` may be 0), whether to sort each output row's columns,
    and whether to count each row's products in the next step (whole steps size with them)."""

    alpha: np.ndarray
    threshold: float
    points: np.ndarray
    sort_columns: bool
    count_costs: bool


class BlockScratch(NamedTuple):
    """One thread's scratch for a block: dense ``(V * LANES,)`` accumulator and input rows
    (``acc``, ``weights``), ``(V,)`` column marks (``in_mark``, ``out_mark``), column lists
    (``inputs``, ``touched``) and ``LANES`` staging rows of ``width + 1`` entries
    (``stage_col``, ``stage_val``). All zero on entry and on exit of a block."""

    acc: np.ndarray
    weights: np.ndarray
    in_mark: np.ndarray
    out_mark: np.ndarray
    inputs: np.ndarray
    touched: np.ndarray
    stage_col: np.ndarray
    stage_val: np.ndarray
    width: int


class BlockResults(NamedTuple):
    """A block's results, one entry per row: entries kept, ``D^(k)``, next-step cost (zero
    unless ``StepInputs.count_costs``), and ``(LANES, C)`` moved points."""

    kept: np.ndarray
    differences: np.ndarray
    costs: np.ndarray
    moved: np.ndarray


if numba_available():
    # Array indices of type uint64 compile to plain loads: numba adds a negative-index fix-up
    # to every signed index.
    _U = np.uint64

    # numba leaves LLVM's SLP vectoriser off, so four adjacent scalar updates stay four; this
    # writes the vector operation out.
    @intrinsic
    def _add_scaled_lanes(typingctx, acc, p, weights, q, scale):
        """``acc[p : p + LANES] += weights[q : q + LANES] * scale`` as one vector operation
        (a multiply, then an add, in each lane: the rounding of the scalar code)."""

        if weights.dtype != acc.dtype:  # one vector type for both (numba reports no match)
            return None

        def codegen(context, builder, signature, args):
            acc_value, p_value, weights_value, q_value, scale_value = args
            acc_type, _, weights_type, _, scale_type = signature.args
            scale_value = context.cast(builder, scale_value, scale_type, acc_type.dtype)
            vector = ir.VectorType(context.get_data_type(acc_type.dtype), LANES)
            target = context.make_array(acc_type)(context, builder, acc_value).data
            source = context.make_array(weights_type)(context, builder, weights_value).data
            target = builder.bitcast(builder.gep(target, [p_value]), vector.as_pointer())
            source = builder.bitcast(builder.gep(source, [q_value]), vector.as_pointer())
            splat = builder.insert_element(
                ir.Constant(vector, ir.Undefined), scale_value, ir.Constant(ir.IntType(32), 0)
            )
            splat = builder.shuffle_vector(
                splat,
                ir.Constant(vector, ir.Undefined),
                ir.Constant(ir.VectorType(ir.IntType(32), LANES), [0] * LANES),
            )
            product = builder.fmul(builder.load(source, align=1), splat)
            total = builder.fadd(builder.load(target, align=1), product)
            builder.store(total, target, align=1)
            return context.get_dummy_value()

        return types.void(acc, p, weights, q, scale), codegen

    @njit(nogil=True, inline="always")
    def _lane(acc, q, inverse, largest, threshold, scale, stage_col, slot, column, kept, total):
        """Normalise, threshold and scale the entry ``acc[q]`` of one row in place and stage
        its ``column`` at ``stage_col[slot + kept]``; return the row's count of kept entries
        and its sum, updated."""
        raw = acc[q]
        value = raw * inverse
        keep = (value >= threshold) | (raw == largest)
        scaled = value * scale if keep else 0.0
        acc[q] = scaled
        stage_col[slot + _U(kept)] = column
        return kept + keep, total + scaled

    # Inlined into its caller: a call counts references to each of its ~25 arrays.
    @njit(nogil=True, inline="always")
    def _block(first_row, lanes, rows, lhat, step, scratch, out):
        """Rows ``first_row .. first_row + lanes - 1`` (``lanes <= LANES``) of ``F^(k)``; row
        ``b`` goes to ``scratch.stage_*[b * (scratch.width + 1):]`` and entry ``b`` of each
        array of ``out``. ``weights`` holds the input rows and ``acc`` the product rows as flat
        ``(V, LANES)`` arrays (see :class:`BlockScratch`)."""
        f_start, f_count, f_col, f_val = rows.start, rows.count, rows.col, rows.val
        diagonal, w_crow, w_col, w_val = lhat.diagonal, lhat.w_crow, lhat.w_col, lhat.w_val
        row_sums = lhat.row_sums
        alpha, threshold, points = step.alpha, step.threshold, step.points
        acc, weights = scratch.acc, scratch.weights
        in_mark, out_mark = scratch.in_mark, scratch.out_mark
        inputs, touched, width = scratch.inputs, scratch.touched, scratch.width
        stage_col, stage_val = scratch.stage_col, scratch.stage_val
        kept, differences, costs, moved = out.kept, out.differences, out.costs, out.moved
        # The input rows, side by side, and the list of their columns.
        m = 0
        for b in range(lanes):
            i = first_row + b
            for e in range(f_start[i], f_start[i] + f_count[i]):
                j = _U(f_col[_U(e)])
                inputs[_U(m)] = j
                m += 1 - in_mark[j]
                in_mark[j] = 1
                weights[j * _U(LANES) + _U(b)] = f_val[_U(e)]
        # [F^(k-1) Lhat] rows: the diagonal first (its columns are all new), then W. The
        # row sums come from those of Lhat, so the product loop carries no running sum.
        n = 0
        t0 = t1 = t2 = t3 = 0.0
        for r in range(m):
            j = _U(inputs[_U(r)])
            q = j * _U(LANES)
            f0, f1, f2, f3 = weights[q], weights[q + _U(1)], weights[q + _U(2)], weights[q + _U(3)]
            d, s = diagonal[j], row_sums[j]
            acc[q], acc[q + _U(1)], acc[q + _U(2)], acc[q + _U(3)] = f0 * d, f1 * d, f2 * d, f3 * d
            t0, t1, t2, t3 = t0 + f0 * s, t1 + f1 * s, t2 + f2 * s, t3 + f3 * s
            touched[_U(n)] = j
            n += 1
            out_mark[j] = 1
        for r in range(m):
            j = _U(inputs[_U(r)])
            q = j * _U(LANES)
            for slot in range(_U(w_crow[j]), _U(w_crow[j + _U(1)])):
                c = _U(w_col[slot])
                touched[_U(n)] = c
                n += 1 - out_mark[c]
                out_mark[c] = 1
                _add_scaled_lanes(acc, c * _U(LANES), weights, q, w_val[slot])
        # Normalise, threshold, multiply by alpha, one output column for all rows at a time.
        # Lanes past ``lanes`` hold zeros and keep nothing.
        inv0, inv1 = 1.0 / t0, 1.0 / t1 if lanes > 1 else 0.0
        inv2, inv3 = 1.0 / t2 if lanes > 2 else 0.0, 1.0 / t3 if lanes > 3 else 0.0
        # A row's maximum always survives the threshold. It can only fall below it when the
        # row holds more than 1 / threshold entries, so it is looked up only then.
        g0 = g1 = g2 = g3 = np.inf
        if n * threshold > 0.5:
            g0 = g1 = g2 = g3 = 0.0
            for t in range(n):
                p = _U(touched[_U(t)]) * _U(LANES)
                g0, g1 = max(g0, acc[p]), max(g1, acc[p + _U(1)])
                g2, g3 = max(g2, acc[p + _U(2)]), max(g3, acc[p + _U(3)])
            # Lanes past ``lanes`` are all zero: no maximum to keep there.
            g1 = g1 if lanes > 1 else np.inf
            g2 = g2 if lanes > 2 else np.inf
            g3 = g3 if lanes > 3 else np.inf
        k0 = k1 = k2 = k3 = 0
        s0 = s1 = s2 = s3 = 0.0
        o1, o2, o3 = _U(width + 1), _U(2 * (width + 1)), _U(3 * (width + 1))
        for t in range(n):
            c = touched[_U(t)]
            p = _U(c) * _U(LANES)
            scale = alpha[_U(c)]
            k0, s0 = _lane(acc, p, inv0, g0, threshold, scale, stage_col, _U(0), c, k0, s0)
            k1, s1 = _lane(acc, p + _U(1), inv1, g1, threshold, scale, stage_col, o1, c, k1, s1)
            k2, s2 = _lane(acc, p + _U(2), inv2, g2, threshold, scale, stage_col, o2, c, k2, s2)
            k3, s3 = _lane(acc, p + _U(3), inv3, g3, threshold, scale, stage_col, o3, c, k3, s3)
        kept[0], kept[1], kept[2], kept[3] = k0, k1, k2, k3
        scaled_totals = (s0, s1, s2, s3)
        # Per row: normalise again, P^(k)(i), the next step's products and D^(k)(i).
        for b in range(lanes):
            i = first_row + b
            o = b * (width + 1)
            size = kept[b]
            if step.sort_columns:
                stage_col[o : o + size].sort()
            inverse = 1.0 / scaled_totals[b]
            new_sum = 0.0
            cost = 0
            # Positions (three channels) are summed in registers in the same pass; any other
            # number of channels one at a time after it.
            xyz = points.shape[1] == 3
            moved_x = moved_y = moved_z = 0.0
            for t in range(size):
                c = _U(stage_col[_U(o + t)])
                q = c * _U(LANES) + _U(b)
                value = acc[q] * inverse
                acc[q] = value
                stage_val[_U(o + t)] = value
                new_sum += value
                if step.count_costs:
                    cost += w_crow[c + _U(1)] - w_crow[c] + 1
                if xyz:
                    moved_x += value * points[c, 0]
                    moved_y += value * points[c, 1]
                    moved_z += value * points[c, 2]
            if xyz:
                moved[b, 0], moved[b, 1], moved[b, 2] = moved_x, moved_y, moved_z
            else:
                for d in range(points.shape[1]):
                    total = 0.0
                    for t in range(size):
                        total += stage_val[_U(o + t)] * points[_U(stage_col[_U(o + t)]), d]
                    moved[b, d] = total
            # D^(k)(i) = sum_j |F^(k) - F^(k-1)|(i, j): the new row's sum, corrected on the
            # columns of the old row by |new - old| - new (new = 0 where a column was dropped).
            difference = new_sum
            for e in range(f_start[i], f_start[i] + f_count[i]):
                now = acc[_U(f_col[_U(e)]) * _U(LANES) + _U(b)]
                difference += abs(now - f_val[_U(e)]) - now
            differences[b] = difference
            costs[b] = cost
        # Leave the scratch arrays zero.
        for t in range(n):
            c = _U(touched[_U(t)])
            p = c * _U(LANES)
            acc[p] = acc[p + _U(1)] = acc[p + _U(2)] = acc[p + _U(3)] = 0.0
            out_mark[c] = 0
        for r in range(m):
            j = _U(inputs[_U(r)])
            q = j * _U(LANES)
            weights[q] = weights[q + _U(1)] = weights[q + _U(2)] = weights[q + _U(3)] = 0.0
            in_mark[j] = 0

    @njit(nogil=True, inline="always")
    def _first_row(row, lhat, out_col, out_val):
        """Row ``row`` of ``F^(1)`` into ``out_col``/``out_val`` from the split ``Lhat``, the
        diagonal in its place among the ascending columns; returns the entry count."""
        diagonal, w_crow, w_col, w_val = lhat.diagonal, lhat.w_crow, lhat.w_col, lhat.w_val
        scale = lhat.row_sums[row]
        count, placed = 0, False
        for s in range(w_crow[row], w_crow[row + 1]):
            if not placed and w_col[s] > row:
                out_col[count], out_val[count] = row, diagonal[row] / scale
                count, placed = count + 1, True
            out_col[count], out_val[count] = w_col[s], w_val[s] / scale
            count += 1
        if not placed:
            out_col[count], out_val[count] = row, diagonal[row] / scale
            count += 1
        return count
