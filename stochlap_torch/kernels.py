"""Fused CPU kernel for one diffusion step, compiled with numba.

Row ``i`` of ``F^(k)`` depends only on row ``i`` of ``F^(k-1)``, ``Lhat`` and ``alpha``, so each
step is computed row by row in one pass, in parallel over row ranges, with a dense accumulator
per thread (Gustavson's algorithm)::

    row of F^(k-1) @ Lhat  ->  normalise  ->  threshold  ->  * alpha  ->  normalise

and, in the same pass, the difference map ``D^(k)(i) = sum_j |F^(k) - F^(k-1)|(i, j)``, the
row ``P^(k)(i) = F^(k)(i, :) P`` and the cost of the row in the next step.

Rows are computed in blocks of :data:`LANES` consecutive rows. Meshes from a few thousand
vertices are put in a locality order first, so the rows of a block share most of their
columns (four rows of a 50k-vertex mesh touch about 1.75 times the columns of one): each row
of ``Lhat`` that the block needs is read once, and its products for the four rows are one
vector operation, on an accumulator that holds the four rows side by side. A row's block is
fixed by its index, so results never depend on the number of threads or on how rows are
split between them.

Two drivers run the blocks:

* :func:`stream_steps` takes each block from ``F^(1)`` to ``F^(K)`` before the next, with its
  rows in two small staging buffers: no operator is stored, and a run needs only its outputs
  and a few rows per thread. This is the path of every run that does not ask for the
  operators.
* :func:`fused_step` computes one whole step, for runs that keep the operators or go op by
  op. Each row range writes its rows back to back into a region of the output sized from an
  estimate of the row lengths (``growth`` times the input row lengths). A block that does not
  fit stops its range; the rest of the range is redone in a later round with larger regions,
  the last round with regions that cannot overflow. The result is :class:`Rows`, a CSR whose
  rows may be separated by gaps, so no step copies its output; :meth:`Rows.to_csr` packs it
  when a canonical CSR is needed.

Compiled functions are cached on disk (``cache=True``): only the first call on a machine pays
the compile time.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from .kernel_buffers import Workspace, grown

try:
    import numba
    from llvmlite import ir
    from numba import njit, prange, types
    from numba.extending import intrinsic
except ImportError:  # pragma: no cover - numba is a dependency; kept for exotic platforms
    numba = None

__all__ = [
    "DEFAULT_GROWTH",
    "SERIAL_ENTRIES",
    "Rows",
    "SplitLhat",
    "available",
    "first_rows",
    "fused_step",
    "index_dtype",
    "stream_steps",
]

logger = logging.getLogger(__name__)

#: Rows computed together (one vector operation per product for all of them); the kernel
#: is written out for four.
LANES = 4
#: Row ranges per thread, handed out dynamically.
PARTS_PER_THREAD = 32
#: Below this many entries of ``F^(k-1)`` a step runs on one thread.
SERIAL_ENTRIES = 1 << 18
#: Below this many rows of ``F`` a streamed run (:func:`stream_steps`) uses one thread.
SERIAL_ROWS = 1 << 13
#: Output room per input entry when nothing better is known (a first step grows ~3x).
DEFAULT_GROWTH = 3.0
#: Rounds with estimated regions before the last, overflow-free one.
_ESTIMATED_ROUNDS = 3


def available() -> bool:
    """Whether the compiled kernel can run here (numba importable)."""
    return numba is not None


if numba is not None:
    # Array indices of type uint64 compile to plain loads: numba adds a negative-index fix-up
    # to every signed index, which costs about a sixth of the hot loop below.
    _U = np.uint64

    @njit(cache=True, parallel=True, nogil=True)
    def _split_diagonal(l_crow, l_col, l_val, index_like):
        """``Lhat = diag(d) + W``: ``(d, w_crow, w_col, w_val, row_sums)``, ``W`` without the
        diagonal (columns in the dtype of ``index_like``) and ``row_sums`` those of ``Lhat``
        (summed in row order)."""
        num_rows = l_crow.shape[0] - 1
        diagonal = np.zeros(num_rows, dtype=l_val.dtype)
        row_sums = np.zeros(num_rows, dtype=l_val.dtype)
        w_crow = np.zeros(num_rows + 1, dtype=np.int64)
        for i in prange(num_rows):
            off_diagonal = 0
            for slot in range(l_crow[i], l_crow[i + 1]):
                off_diagonal += l_col[slot] != i
            w_crow[i + 1] = off_diagonal
        for i in range(num_rows):
            w_crow[i + 1] += w_crow[i]
        w_col = np.empty(w_crow[-1], dtype=index_like.dtype)
        w_val = np.empty(w_crow[-1], dtype=l_val.dtype)
        for i in prange(num_rows):
            count = w_crow[i]
            for slot in range(l_crow[i], l_crow[i + 1]):
                row_sums[i] += l_val[slot]
                if l_col[slot] == i:
                    diagonal[i] += l_val[slot]
                else:
                    w_col[count] = l_col[slot]
                    w_val[count] = l_val[slot]
                    count += 1
        return diagonal, w_crow, w_col, w_val, row_sums

    @njit(cache=True, parallel=True, nogil=True)
    def _packed_first_rows(diagonal, w_crow, w_col, w_val, row_sums, rows, out_col):
        """Rows ``rows`` of ``F^(1)`` (each as :func:`_first_row` gives it), packed:
        ``(out_crow, out_val)``, the columns written to ``out_col`` (in their index dtype)."""
        out_crow = np.zeros(rows.shape[0] + 1, dtype=np.int64)
        for r in range(rows.shape[0]):
            out_crow[r + 1] = out_crow[r] + w_crow[rows[r] + 1] - w_crow[rows[r]] + 1
        out_val = np.empty(out_crow[-1], dtype=w_val.dtype)
        for r in prange(rows.shape[0]):
            start = out_crow[r]
            _first_row(rows[r], diagonal, w_crow, w_col, w_val, row_sums, out_col[start:],
                       out_val[start:])  # fmt: skip
        return out_crow, out_val


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
            splat = builder.insert_element(ir.Constant(vector, ir.Undefined), scale_value,
                                           ir.Constant(ir.IntType(32), 0))  # fmt: skip
            splat = builder.shuffle_vector(splat, ir.Constant(vector, ir.Undefined),
                                           ir.Constant(ir.VectorType(ir.IntType(32), LANES),
                                                       [0] * LANES))  # fmt: skip
            product = builder.fmul(builder.load(source, align=1), splat)
            total = builder.fadd(builder.load(target, align=1), product)
            builder.store(total, target, align=1)
            return context.get_dummy_value()

        return types.void(acc, p, weights, q, scale), codegen

    @njit(cache=True, nogil=True, inline="always")
    def _lane(acc, q, inverse, largest, threshold, scale):
        """Normalise, threshold and scale the entry ``acc[q]`` of one row in place; return
        (kept, the scaled value)."""
        raw = acc[q]
        value = raw * inverse
        keep = (value >= threshold) | (raw == largest)
        scaled = value * scale if keep else 0.0
        acc[q] = scaled
        return keep, scaled

    # Inlined into its caller: a call passes ~25 arrays, and numba counts a reference to each
    # one on the way in and out, which costs as much as a row's arithmetic.
    @njit(cache=True, nogil=True, inline="always")
    def _block(
        first_row, lanes, f_start, f_count, f_col, f_val, diagonal, w_crow, w_col, w_val,
        row_sums, alpha, threshold, points, sort_columns, acc, weights, in_mark, out_mark,
        inputs, touched, stage_col, stage_val, width, kept, differences, costs, moved,
    ):  # fmt: skip
        """Rows ``first_row .. first_row + lanes - 1`` (``lanes <= LANES``) of ``F^(k)``,
        computed together; row ``b`` goes to ``stage_*[b * (width + 1):]``, ``kept[b]``,
        ``differences[b]``, ``costs[b]`` and ``moved[b]``.

        The rows of a block are usually neighbours (large meshes are put in a locality order),
        so their columns overlap: every row of ``W`` that one of them needs is read once for
        all of them, and its products for the ``LANES`` rows are one vector operation. ``weights``
        holds the input rows and ``acc`` the product rows as ``(V, LANES)`` dense arrays
        (flat), all zero on entry and on exit, as are the marks of the columns listed in
        ``inputs`` (input columns) and ``touched`` (output columns).
        """
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
            keep, x = _lane(acc, p, inv0, g0, threshold, scale)
            stage_col[_U(k0)] = c
            k0 += keep
            s0 += x
            keep, x = _lane(acc, p + _U(1), inv1, g1, threshold, scale)
            stage_col[o1 + _U(k1)] = c
            k1 += keep
            s1 += x
            keep, x = _lane(acc, p + _U(2), inv2, g2, threshold, scale)
            stage_col[o2 + _U(k2)] = c
            k2 += keep
            s2 += x
            keep, x = _lane(acc, p + _U(3), inv3, g3, threshold, scale)
            stage_col[o3 + _U(k3)] = c
            k3 += keep
            s3 += x
        kept[0], kept[1], kept[2], kept[3] = k0, k1, k2, k3
        scaled_totals = (s0, s1, s2, s3)
        # Per row: normalise again, P^(k)(i), the next step's products and D^(k)(i).
        for b in range(lanes):
            i = first_row + b
            o = b * (width + 1)
            size = kept[b]
            if sort_columns:  # canonical CSR; the steps themselves do not need it
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

    @njit(cache=True, parallel=True, nogil=True)
    def _parts(
        part_first, part_last, region_start, region_end, products, f_start, f_count, f_col,
        f_val, diagonal, w_crow, w_col, w_val, row_sums, alpha, threshold, points, sort_columns,
        acc, weights, marks, out_col, out_val, out_start, out_count, differences, new_points,
        row_target, costs, stopped,
    ):  # fmt: skip
        """Rows ``[part_first[p], part_last[p])`` into ``out_*[region_start[p]:region_end[p]]``,
        in blocks of ``LANES`` rows (see :func:`_block`; parts start at multiples of it).

        The difference and moved point of row ``i`` go to row ``row_target[i]`` of
        ``differences`` and ``new_points``.

        ``acc`` and ``weights`` hold ``(threads, V * LANES)`` zeroed scratch rows and
        ``marks`` ``(threads, 2 V)`` zeroed bytes, one row per thread. A block whose rows do
        not fit the rest of its region stops its part: ``stopped[p]`` is the block's first
        row (``part_last[p]`` when the part completed).
        """
        num_cols = diagonal.shape[0]
        channels = points.shape[1]
        for part in prange(part_first.shape[0]):
            thread = numba.get_thread_id()
            thread_acc, thread_weights = acc[thread], weights[thread]
            in_mark, out_mark = marks[thread, :num_cols], marks[thread, num_cols:]
            width, block_width, block_inputs = 0, 0, 0
            for start in range(part_first[part], part_last[part], LANES):
                block_products, inputs = 0, 0
                for i in range(start, min(start + LANES, part_last[part])):
                    width = max(width, min(products[i], num_cols))
                    block_products += products[i]
                    inputs += f_count[i]
                block_width = max(block_width, min(block_products, num_cols))
                block_inputs = max(block_inputs, inputs)
            inputs = np.empty(block_inputs + 1, dtype=np.int64)
            touched = np.empty(block_width + 1, dtype=np.int64)
            stage_col = np.empty(LANES * (width + 1), dtype=out_col.dtype)
            stage_val = np.empty(LANES * (width + 1), dtype=out_val.dtype)
            kept = np.zeros(LANES, dtype=np.int64)
            block_differences = np.zeros(LANES, dtype=out_val.dtype)
            block_costs = np.zeros(LANES, dtype=np.int64)
            moved = np.zeros((LANES, channels), dtype=out_val.dtype)
            cursor, end = region_start[part], region_end[part]
            stopped[part] = part_last[part]
            for first_row in range(part_first[part], part_last[part], LANES):
                lanes = min(LANES, part_last[part] - first_row)
                _block(
                    first_row, lanes, f_start, f_count, f_col, f_val, diagonal, w_crow, w_col,
                    w_val, row_sums, alpha, threshold, points, sort_columns, thread_acc,
                    thread_weights, in_mark, out_mark, inputs, touched, stage_col, stage_val,
                    width, kept, block_differences, block_costs, moved,
                )  # fmt: skip
                size = 0
                for b in range(lanes):
                    size += kept[b]
                if cursor + size > end:
                    stopped[part] = first_row
                    break
                for b in range(lanes):
                    i = first_row + b
                    size = kept[b]
                    o = b * (width + 1)
                    out_col[cursor : cursor + size] = stage_col[o : o + size]
                    out_val[cursor : cursor + size] = stage_val[o : o + size]
                    out_start[i] = cursor
                    out_count[i] = size
                    differences[row_target[i]] = block_differences[b]
                    costs[i] = block_costs[b]
                    for d in range(channels):
                        new_points[row_target[i], d] = moved[b, d]
                    cursor += size

    @njit(cache=True, parallel=True, nogil=True)
    def _stream_parts(
        part_first, part_last, diagonal, w_crow, w_col, w_val, row_sums, alpha, threshold,
        points, width, acc, weights, marks, row_target, differences, positions, entries,
    ):  # fmt: skip
        """Rows ``[part_first[p], part_last[p])`` through every step, a block of ``LANES``
        rows at a time (see :func:`_block`; parts start at multiples of it).

        A block goes from its rows of ``F^(1)`` (``Lhat``'s rows over their sums, written
        straight from the split ``Lhat`` by :func:`_first_row`, as in :func:`first_rows`) to
        ``F^(K)`` before the next block starts, with its rows of ``F^(k-1)`` and ``F^(k)`` in
        two small staging buffers: no operator is ever stored, ``F^(1)`` included. ``D^(k)`` and
        ``P^(k)`` of row ``i`` go to row ``row_target[i]`` of ``differences[k - 1]``
        (``(K, m)``) and ``positions[k - 1]`` (``(K, m, C)``); ``entries[p, k - 1]`` counts
        the entries of ``F^(k)`` (k >= 2) in part ``p``.
        ``width`` bounds the entries of a row of any ``F^(k)``. Scratch rows as in
        :func:`_parts`.
        """
        num_cols = diagonal.shape[0]
        num_scales = differences.shape[0]
        channels = points.shape[1]
        stride = width + 1
        for part in prange(part_first.shape[0]):
            thread = numba.get_thread_id()
            thread_acc, thread_weights = acc[thread], weights[thread]
            in_mark, out_mark = marks[thread, :num_cols], marks[thread, num_cols:]
            inputs = np.empty(min(num_cols, LANES * width) + 1, dtype=np.int64)
            touched = np.empty(num_cols + 1, dtype=np.int64)
            old_col = np.empty(LANES * stride, dtype=w_col.dtype)
            old_val = np.empty(LANES * stride, dtype=w_val.dtype)
            new_col, new_val = np.empty_like(old_col), np.empty_like(old_val)
            offsets = np.arange(LANES) * stride
            old_count = np.zeros(LANES, dtype=np.int64)
            new_count = np.zeros(LANES, dtype=np.int64)
            block_differences = np.zeros(LANES, dtype=w_val.dtype)
            block_costs = np.zeros(LANES, dtype=np.int64)
            moved = np.zeros((LANES, channels), dtype=w_val.dtype)
            for first_row in range(part_first[part], part_last[part], LANES):
                lanes = min(LANES, part_last[part] - first_row)
                old_count[:] = 0
                for b in range(lanes):
                    old_count[b] = _first_row(
                        first_row + b, diagonal, w_crow, w_col, w_val, row_sums,
                        old_col[offsets[b] :], old_val[offsets[b] :],
                    )  # fmt: skip
                for k in range(1, num_scales):
                    _block(
                        0, lanes, offsets, old_count, old_col, old_val, diagonal, w_crow,
                        w_col, w_val, row_sums, alpha, threshold, points, False, thread_acc,
                        thread_weights, in_mark, out_mark, inputs, touched, new_col, new_val,
                        width, new_count, block_differences, block_costs, moved,
                    )  # fmt: skip
                    for b in range(lanes):
                        target = row_target[first_row + b]
                        differences[k, target] = block_differences[b]
                        for d in range(channels):
                            positions[k, target, d] = moved[b, d]
                        entries[part, k] += new_count[b]
                    old_col, new_col = new_col, old_col
                    old_val, new_val = new_val, old_val
                    old_count, new_count = new_count, old_count

    @njit(cache=True, nogil=True, inline="always")
    def _first_row(row, diagonal, w_crow, w_col, w_val, row_sums, out_col, out_val):
        """Row ``row`` of ``F^(1)`` into ``out_col``/``out_val`` from the split ``Lhat``: its
        entries over the row sum, the diagonal in its place among the ascending columns;
        returns the entry count. The one definition of ``F^(1)``'s rows for the kernels."""
        scale = row_sums[row]
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

    @njit(cache=True, nogil=True)
    def _regions(part_first, part_last, counts, products, num_cols, factor, used):
        """Back-to-back ``[start, end)`` output regions of the parts, from ``used`` on.

        Row ``i`` gets room for ``ceil(factor * counts[i]) + 2`` entries, at most its bound
        ``min(products[i], V)``; with ``factor < 0``, the bound itself (a round that cannot
        overflow).
        """
        start = np.empty(part_first.shape[0], dtype=np.int64)
        end = np.empty(part_first.shape[0], dtype=np.int64)
        cursor = used
        for part in range(part_first.shape[0]):
            start[part] = cursor
            for i in range(part_first[part], part_last[part]):
                room = min(products[i], num_cols)
                if factor >= 0:
                    room = min(room, math.ceil(factor * counts[i]) + 2)
                cursor += room
            end[part] = cursor
        return start, end

    @njit(cache=True, parallel=True, nogil=True)
    def _gather_rows(starts, counts, col, val, crow, out_col, out_val):
        """Copy the rows of a gapped CSR back to back at ``crow`` (a packed CSR)."""
        for i in prange(starts.shape[0]):
            source, size = starts[i], counts[i]
            out_col[crow[i] : crow[i] + size] = col[source : source + size]
            out_val[crow[i] : crow[i] + size] = val[source : source + size]

    @njit(cache=True, nogil=True)
    def _balanced_parts(work, parts):
        """Split rows ``[0, n)`` into at most ``parts`` ranges ``[first, last)`` of about
        equal ``work``: a range ends before the row whose running total first exceeds the
        next ``p / parts`` of the total."""
        num_rows = work.shape[0]
        total = 0
        for i in range(num_rows):
            total += work[i]
        first = np.empty(max(parts, 1), dtype=np.int64)
        last = np.empty(max(parts, 1), dtype=np.int64)
        count, start, running, p = 0, 0, 0, 1
        for i in range(num_rows):
            running += work[i]
            while p < parts and running > total * p / parts:
                if start < i:  # a boundary before row i (empty ranges are skipped)
                    first[count], last[count] = start, i
                    count += 1
                    start = i
                p += 1
        if start < num_rows:
            first[count], last[count] = start, num_rows
            count += 1
        return first[:count], last[:count]

    @njit(cache=True, parallel=True, nogil=True)
    def _products(f_start, f_count, f_col, w_crow):
        """``(n,)`` scalar products each row of ``F @ Lhat`` costs (``W`` plus the diagonal)."""
        products = np.zeros(f_start.shape[0], dtype=np.int64)
        for i in prange(f_start.shape[0]):
            total = 0
            for e in range(f_start[i], f_start[i] + f_count[i]):
                total += w_crow[f_col[e] + 1] - w_crow[f_col[e]] + 1
            products[i] = total
        return products


@dataclass(frozen=True)
class SplitLhat:
    """``Lhat = diag(diagonal) + W`` in the form the kernel reads.

    Attributes:
        diagonal: ``(V,)`` float.
        w_crow, w_col, w_val: ``W`` (``Lhat`` without its diagonal) in CSR form.
        row_sums: ``(V,)`` row sums of ``Lhat``.
    """

    diagonal: np.ndarray
    w_crow: np.ndarray
    w_col: np.ndarray
    w_val: np.ndarray
    row_sums: np.ndarray

    @classmethod
    def from_csr(cls, crow: np.ndarray, col: np.ndarray, val: np.ndarray, index=None
                 ) -> SplitLhat:  # fmt: skip
        """Split ``Lhat`` given in CSR form (every row holds its diagonal entry); ``W``'s
        columns in the dtype ``index`` (default: that of ``col``)."""
        index_like = np.empty(0, dtype=col.dtype if index is None else index)
        return cls(*_split_diagonal(crow, col, val, index_like))

    @property
    def num_cols(self) -> int:
        return int(self.diagonal.shape[0])


def first_rows(lhat: SplitLhat, rows: np.ndarray | None = None, index=np.int64) -> Rows:
    """Rows of ``F^(1)``, ``Lhat`` normalised by rows, packed with ``index`` column indices:
    the rows a streamed run builds block by block (:func:`stream_steps`), for the runs that
    step whole matrices.

    Args:
        lhat: the split ``Lhat``.
        rows: ``(R,)`` int64 rows to take, in that order (default: all).
        index: column index dtype of the result.
    """
    if rows is None:
        rows = np.arange(lhat.num_cols, dtype=np.int64)
    size = int((lhat.w_crow[rows + 1] - lhat.w_crow[rows]).sum()) + rows.shape[0]
    out_col = np.empty(size, dtype=index)
    out_crow, out_val = _packed_first_rows(lhat.diagonal, lhat.w_crow, lhat.w_col, lhat.w_val,
                                           lhat.row_sums, rows, out_col)  # fmt: skip
    return Rows.from_csr(out_crow, out_col, out_val)


@dataclass
class Rows:
    """A CSR matrix whose rows may be separated by unused entries.

    Row ``i`` is ``col[starts[i] : starts[i] + counts[i]]`` (and the same slice of ``val``).

    Attributes:
        starts, counts: ``(n,)`` int64.
        col: ``(capacity,)`` int32 or int64 column indices.
        val: ``(capacity,)`` float values.
        costs: ``(n,)`` int64 scalar products each row costs in the next step, or ``None``.
    """

    starts: np.ndarray
    counts: np.ndarray
    col: np.ndarray
    val: np.ndarray
    costs: np.ndarray | None = None

    @classmethod
    def from_csr(cls, crow: np.ndarray, col: np.ndarray, val: np.ndarray) -> Rows:
        """View a packed CSR ``(crow, col, val)``."""
        return cls(crow[:-1], np.diff(crow), col, val)

    @property
    def num_rows(self) -> int:
        return int(self.starts.shape[0])

    @property
    def nnz(self) -> int:
        return int(self.counts.sum())

    def to_csr(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(crow, col, val)``: the rows packed into fresh arrays."""
        crow = np.zeros(self.num_rows + 1, dtype=np.int64)
        np.cumsum(self.counts, out=crow[1:])
        col = np.empty(crow[-1], dtype=self.col.dtype)
        val = np.empty(crow[-1], dtype=self.val.dtype)
        _gather_rows(self.starts, self.counts, self.col, self.val, crow, col, val)
        return crow, col, val


def fused_step(
    previous: Rows, lhat: SplitLhat, alpha: np.ndarray, threshold: float,
    points: np.ndarray, num_threads: int, sort_columns: bool = True,
    workspace: Workspace | None = None, growth: float | None = None,
    row_target: np.ndarray | None = None, differences: np.ndarray | None = None,
    new_points: np.ndarray | None = None,
) -> tuple[Rows, np.ndarray, np.ndarray]:  # fmt: skip
    """One diffusion step on CPU arrays.

    Args:
        previous: ``F^(k-1)``, ``n`` rows (see :meth:`Rows.from_csr`).
        lhat: ``Lhat``, ``(V, V)`` (see :meth:`SplitLhat.from_csr`).
        alpha: ``(V,)`` scale invariance function.
        threshold: ``lambda``.
        points: ``(V, C)`` positions ``P`` (any number of channels).
        num_threads: threads to use.
        sort_columns: sort the columns within each row (canonical CSR). The steps do not need
            it, so the diffusion loop skips it unless the operators are returned.
        workspace: reuse its buffers (the returned rows then live in them, see
            :class:`Workspace`); ``None`` allocates fresh arrays.
        growth: expected ratio of output to input entries per row (default
            :data:`DEFAULT_GROWTH`); it sizes the first round's output regions. Rows that do
            not fit are redone, so it affects speed and memory, never the result.
        row_target: ``(n,)`` int64 row of ``differences`` and ``new_points`` that each row's
            results go to (default: the same row); lets a run in a renumbered vertex order
            write its results in the caller's order.
        differences, new_points: ``(m,)`` and ``(m, C)`` output arrays to fill (default: new
            arrays with ``m = n``).

    Returns:
        ``(F^(k), D^(k), F^(k) P)``: :class:`Rows` (with ``costs``), the difference map and
        the moved points.
    """
    if numba is None:
        raise RuntimeError("the fused kernel needs numba: pip install numba")
    growth = DEFAULT_GROWTH if growth is None else growth
    # Small steps run on one thread: waking the pool costs more than it saves.
    wanted = 1 if previous.nnz < SERIAL_ENTRIES else num_threads
    numba.set_num_threads(max(1, min(wanted, numba.config.NUMBA_NUM_THREADS)))
    threads = numba.get_num_threads()
    num_rows, num_cols = previous.num_rows, lhat.num_cols
    if workspace is None:
        workspace = Workspace(num_cols, previous.val.dtype, index_dtype=previous.col.dtype)
    acc, weights, marks = workspace.scratch(threads, LANES)
    products = previous.costs
    if products is None:
        products = _products(previous.starts, previous.counts, previous.col, lhat.w_crow)

    dtype = previous.val.dtype
    if row_target is None:
        row_target = np.arange(num_rows, dtype=np.int64)
    if differences is None:
        differences = np.zeros(num_rows, dtype=dtype)
    if new_points is None:
        new_points = np.zeros((num_rows, points.shape[1]), dtype=dtype)
    col, val = workspace.next_output()
    out_start, out_count, costs = workspace.row_arrays(num_rows)  # every row is written
    block_work = np.add.reduceat(products, np.arange(0, num_rows, LANES)) if num_rows else products
    first, last = _block_parts(block_work, 0, num_rows, PARTS_PER_THREAD * threads)
    used = 0
    for attempt in range(_ESTIMATED_ROUNDS + 1):
        factor = growth * 2**attempt if attempt < _ESTIMATED_ROUNDS else -1.0
        start, end = _regions(first, last, previous.counts, products, num_cols, factor, used)
        needed = int(end[-1]) if end.size else used
        col, val = grown(col, used, needed), grown(val, used, needed)
        stopped = np.empty_like(first)
        _run_dynamic(
            _parts, first, last, start, end, products, previous.starts, previous.counts,
            previous.col, previous.val, lhat.diagonal, lhat.w_crow, lhat.w_col, lhat.w_val,
            lhat.row_sums, alpha, threshold, points, sort_columns, acc, weights, marks, col, val,
            out_start, out_count, differences, new_points, row_target, costs, stopped,
        )  # fmt: skip
        used = needed
        unfinished = stopped < last
        if not unfinished.any():
            break
        logger.debug(
            "%d row ranges overflowed their estimated regions (round %d)",
            int(unfinished.sum()), attempt,
        )  # fmt: skip
        first, last = stopped[unfinished], last[unfinished]
    workspace.keep_output(col, val)
    return Rows(out_start, out_count, col, val, costs), differences, new_points


def stream_steps(
    lhat: SplitLhat, alpha: np.ndarray, threshold: float, points: np.ndarray,
    num_threads: int, rows: tuple[int, int], differences: np.ndarray, positions: np.ndarray,
    row_target: np.ndarray | None = None, workspace: Workspace | None = None,
) -> np.ndarray:  # fmt: skip
    """Steps ``2..K`` for the rows ``[rows[0], rows[1])``, each row through every step before
    the next rows start, holding no operator (memory ``O(threads V)`` besides the outputs).

    A row starts from ``F^(1)``, which it takes from ``lhat`` itself.

    Args:
        lhat, alpha, threshold, points, num_threads: as for :func:`fused_step`; ``lhat`` has
            ``n`` rows, and its values' dtype is that of the results.
        rows: the row range; its start must be a multiple of :data:`LANES` (row blocks, and
            so the results, must not depend on how a run is split).
        differences, positions: ``(K, m)`` and ``(K, m, C)`` outputs; ``D^(k)`` and
            ``P^(k)`` of row ``i`` go to row ``row_target[i]`` (default ``i``) of index
            ``k - 1``; index 0 is not written.
        workspace: lends its scratch rows (default: a fresh one).

    Returns:
        ``(K - 1,)`` int64: the stored entries of ``F^(2..K)`` in these rows.
    """
    if numba is None:
        raise RuntimeError("the fused kernel needs numba: pip install numba")
    start, stop = rows
    num_rows = lhat.num_cols
    if not 0 <= start <= stop <= num_rows:
        raise ValueError(f"row range {rows} is not within the {num_rows} rows")
    if start % LANES:
        raise ValueError(f"a row range must start at a multiple of {LANES}, not {start}")
    num_scales = differences.shape[0]
    # Small meshes use one thread: waking the pool costs more than it saves.
    wanted = 1 if num_rows < SERIAL_ROWS else num_threads
    numba.set_num_threads(max(1, min(wanted, numba.config.NUMBA_NUM_THREADS)))
    threads = numba.get_num_threads()
    if workspace is None:
        workspace = Workspace(num_rows, lhat.w_val.dtype, index_dtype=lhat.w_col.dtype)
    acc, weights, marks = workspace.scratch(threads, LANES)
    if row_target is None:
        row_target = np.arange(num_rows, dtype=np.int64)
    # Block starts and ends; the row lengths of F^(1) (W's and the diagonal) stand in for
    # the work of a row through every step.
    blocks = np.arange(start, stop + LANES, LANES)
    blocks[-1] = stop
    block_work = np.diff(lhat.w_crow[blocks] + blocks)
    # A kept entry is at least ``threshold`` of a row summing to one (or the row's maximum).
    longest = int(np.diff(lhat.w_crow[start : stop + 1]).max()) + 1 if stop > start else 0
    width = min(num_rows, max(longest, int(1.0 / threshold) + 1))
    part_first, part_last = _block_parts(block_work, start, stop, PARTS_PER_THREAD * threads)
    entries = np.zeros((part_first.shape[0], num_scales), dtype=np.int64)
    _run_dynamic(
        _stream_parts, part_first, part_last, lhat.diagonal, lhat.w_crow, lhat.w_col,
        lhat.w_val, lhat.row_sums, alpha, threshold, points, width, acc, weights, marks,
        row_target, differences, positions, entries,
    )  # fmt: skip
    return entries.sum(axis=0)[1:]


def _block_parts(
    block_work: np.ndarray, start: int, stop: int, parts: int
) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``[start, stop)`` (``start`` a multiple of :data:`LANES`) in at most ``parts``
    ranges ``[first, last)`` of whole blocks and about equal work (``block_work``, one value
    per block of the range), so that a row's block never depends on the split."""
    first, last = _balanced_parts(block_work, parts)
    return start + first * LANES, np.minimum(start + last * LANES, stop)


def index_dtype(num_cols: int) -> type:
    """``np.int32`` when it can index ``num_cols`` columns, else ``np.int64``.

    The steps read and write every stored column index, so 4-byte indices save a quarter of
    the memory traffic and footprint of ``F`` in float64 (a third in float32).
    """
    return np.int32 if num_cols <= np.iinfo(np.int32).max else np.int64


def _run_dynamic(function, *args):
    """Call a parallel kernel with its ``prange`` iterations handed out one at a time.

    A thread that the OS parks (cores shared with other work) then holds up one small row
    range, not a fixed share of the rows.
    """
    previous = numba.set_parallel_chunksize(1)
    try:
        return function(*args)
    finally:
        numba.set_parallel_chunksize(previous)
