"""The CUDA kernel of the streamed steps (numba's CUDA target); see :mod:`.cuda_steps`.
Experimental: not yet checked on a GPU (``benchmarks/gpu.py``).

This module imports ``numba.cuda`` and is imported only by :func:`.cuda_steps.stream_steps_cuda`
(the import is slow and not wanted on CPU runs). Under
``NUMBA_ENABLE_CUDASIM=1`` the same functions run in numba's simulator, one Python thread per
CUDA thread, which swaps the ``cuda`` global of this module for its own: the kernels must name
``cuda`` as a module global, and each ``cuda.shared.array`` must stand on its own line.

Every float that the CPU kernel (:func:`~.block._block`) computes in float64 is cast with
``np.float64`` here, in both targets alike (numpy's own promotion would keep float32 in the
simulator), so that a float32 run rounds where the CPU kernel rounds.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import cuda, float64, int32, int64

#: The key of a free slot of the column table.
EMPTY = -1
#: ``owner`` of a slot that no product has claimed yet (above every product position).
_NO_OWNER = 1 << 62
#: Float rows of the block reduction: ``D^(k)`` in two parts and six channels of ``F^(k) P``.
SLOTS = 8
_CHANNELS = SLOTS - 2
#: Scales a kernel can count entries for (``MAX_SCALES`` of the parameters).
MAX_SCALES = 64
#: A multiplier for the hash (2^32 / golden ratio); the table keeps the product's low bits, so
#: columns that differ in their low bits spread out, as a row's neighbouring columns do.
_HASH = 2654435761


@cuda.jit(device=True)
def _sum_scan(buffer, value, tid, threads):
    """``(exclusive prefix sum of value over the threads, total)`` (int64; Hillis-Steele in
    the shared ``buffer`` of ``threads`` entries). Every thread of the block must call it."""
    buffer[tid] = value
    cuda.syncthreads()
    offset = 1
    while offset < threads:
        add = buffer[tid - offset] if tid >= offset else 0
        cuda.syncthreads()
        buffer[tid] += add
        cuda.syncthreads()
        offset *= 2
    inclusive = buffer[tid]
    total = buffer[threads - 1]
    cuda.syncthreads()
    return inclusive - value, total


@cuda.jit(device=True)
def _reduce(buffer, num_slots, num_sums, tid, threads):
    """Tree reduction of the shared ``(SLOTS, threads)`` float64 ``buffer`` into column 0:
    rows ``q < num_sums`` summed, rows ``num_sums <= q < num_slots`` maxed. The order is fixed,
    so results do not depend on timing. Ends with a barrier; read column 0, then barrier again
    before the buffer is written anew."""
    half = threads // 2
    while half > 0:
        cuda.syncthreads()
        if tid < half:
            for q in range(num_slots):
                other = buffer[q, tid + half]
                if q < num_sums:
                    buffer[q, tid] += other
                else:
                    buffer[q, tid] = max(buffer[q, tid], other)
        half //= 2
    cuda.syncthreads()


@cuda.jit(device=True)
def _home(key, mask):
    """The first slot to probe for column ``key`` in a table of ``mask + 1`` slots."""
    return (np.int64(key) * _HASH) & mask


@cuda.jit(device=True)
def _find(keys, mask, key):
    """The slot of column ``key``, or -1 when it is not in the table."""
    slot = _home(key, mask)
    while True:
        found = keys[slot]
        if found == key:
            return slot
        if found == EMPTY:
            return -1
        slot = (slot + 1) & mask


@cuda.jit(device=True)
def _insert(keys, owner, mask, key, position, state, allowed):
    """Put column ``key`` in the table (linear probing) and claim it for ``position`` if that
    comes first; ``state[1]`` counts the columns. False, with ``state[2]`` set, once
    ``allowed`` columns are in: the caller stops, and the table (at least ``allowed`` plus one
    per thread free slots) never fills, so probing always ends."""
    slot = _home(key, mask)
    while True:
        found = keys[slot]
        if found == key:
            break
        if found == EMPTY:
            if cuda.atomic.add(state, 1, 0) >= allowed:  # an atomic read of the count
                state[2] = 1
                return False
            found = cuda.atomic.cas(keys, slot, EMPTY, key)
            if found == EMPTY:
                cuda.atomic.add(state, 1, 1)
                break
            if found == key:
                break
        slot = (slot + 1) & mask
    cuda.atomic.min(owner, slot, position)
    return True


@cuda.jit(device=True)
def _step(k, target, count, rows, table, size, cands, step, out, block):
    """One step of one row: ``F^(k+1)`` (0-based ``k``) from the row's ``count`` entries of
    ``F^(k)`` in ``old_*``, into ``new_*``; ``D`` and ``F P`` to ``differences[k, target]``
    and ``positions[k, target]``. Returns the entries kept, or -1 when the row overflows its
    column table or its row buffer (the launcher redoes it with larger ones).

    The tuples are unpacked first thing (``t_*`` is the transpose of ``W``); the column
    table has ``size`` slots, a power of two. Phases, each ended by a barrier:

    A. every column of ``F^(k)(i, :) Lhat`` goes in the table: the row's own columns (the
       diagonal products, positions ``0..count-1``) and the ``W`` neighbours of each
       (positions ``count + e * max_degree + s``); a column is owned by its first position;
    B. the owned positions, in order, number the candidate columns: entry ``e`` of the row is
       candidate ``e``, new columns follow by first appearance (deterministic, whatever order
       the threads ran in);
    C. each candidate's value is pulled along its column of ``Lhat`` (diagonal first, then the
       transpose's row in order), so no float is summed by atomics; with the row sum ``t`` and
       the largest value;
    D. threshold (the largest value always stays), ``* alpha``; E. normalise, ``D``, ``F P``.
    """
    old_col, old_val, new_col, new_val = rows
    keys, owner, index = table
    cand_col, cand_val = cands
    lhat, alpha, points, threshold, max_degree = step
    differences, positions = out
    red, scan, state, tid, threads = block
    diagonal, w_crow, w_col, _, t_crow, t_col, t_val, row_sums = lhat  # values pulled from t_*
    mask = size - 1
    allowed = min(cand_col.shape[0], size // 2)
    for s in range(tid, size, threads):
        keys[s] = EMPTY
        owner[s] = _NO_OWNER
    if tid == 0:
        state[1] = 0
        state[2] = 0
    cuda.syncthreads()
    # A. The columns of the product.
    for e in range(tid, count, threads):
        j = old_col[e]
        if not _insert(keys, owner, mask, j, e, state, allowed):
            break
        base = count + np.int64(e) * max_degree - w_crow[j]
        for s in range(w_crow[j], w_crow[j + 1]):
            if not _insert(keys, owner, mask, w_col[s], base + s, state, allowed):
                break
    cuda.syncthreads()
    # The count is read before a slot is claimed, so threads racing past ``allowed`` together
    # can leave more columns than the scratch holds without setting ``state[2]``.
    if state[2] != 0 or state[1] > allowed:
        return -1
    # B. Number the candidates: a contiguous chunk of the row per thread, so that a prefix
    # sum over the threads orders them by position.
    chunk = (count + threads - 1) // threads
    first = min(count, tid * chunk)
    last = min(count, first + chunk)
    owned = 0
    for e in range(first, last):
        j = old_col[e]
        base = count + np.int64(e) * max_degree - w_crow[j]
        for s in range(w_crow[j], w_crow[j + 1]):
            owned += owner[_find(keys, mask, w_col[s])] == base + s
    offset, total = _sum_scan(scan, owned, tid, threads)
    num_cands = count + total
    following = count + offset
    for e in range(first, last):
        j = old_col[e]
        index[_find(keys, mask, j)] = e
        cand_col[e] = j
        base = count + np.int64(e) * max_degree - w_crow[j]
        for s in range(w_crow[j], w_crow[j + 1]):
            c = w_col[s]
            slot = _find(keys, mask, c)
            if owner[slot] == base + s:
                index[slot] = following
                cand_col[following] = c
                following += 1
    cuda.syncthreads()
    # C. Candidate values, the row sum of the product (from Lhat's row sums, as the CPU
    # kernel does) and its largest entry.
    row_total = np.float64(0.0)
    for e in range(tid, count, threads):
        row_total += np.float64(old_val[e] * row_sums[old_col[e]])
    largest = np.float64(0.0)
    for q in range(tid, num_cands, threads):
        c = cand_col[q]
        cand_val[q] = 0
        raw = cand_val[q]  # a zero of the value dtype
        if q < count:
            raw = old_val[q] * diagonal[c]
        for s in range(t_crow[c], t_crow[c + 1]):
            slot = _find(keys, mask, t_col[s])
            if slot >= 0 and index[slot] < count:
                raw += old_val[index[slot]] * t_val[s]
        cand_val[q] = raw
        largest = max(largest, np.float64(raw))
    red[0, tid] = row_total
    red[1, tid] = largest
    _reduce(red, 2, 1, tid, threads)
    inverse = 1.0 / red[0, 0]
    largest = red[1, 0]
    cuda.syncthreads()
    # A row's maximum can fall below the threshold only when it holds many entries (after the
    # row is normalised, each is below threshold only if more than 1 / threshold of them); the
    # CPU kernel looks it up past 0.5 / threshold candidates, and so does this one.
    if not num_cands * threshold > 0.5:
        largest = math.inf
    # D. Threshold and scale, over contiguous chunks again (the kept entries keep their order).
    chunk = (num_cands + threads - 1) // threads
    first = min(num_cands, tid * chunk)
    last = min(num_cands, first + chunk)
    kept_here = 0
    scaled_total = np.float64(0.0)
    for q in range(first, last):
        raw = cand_val[q]
        value = np.float64(raw) * inverse
        if value >= threshold or np.float64(raw) == largest:
            scaled = value * np.float64(alpha[cand_col[q]])
            cand_val[q] = scaled
            scaled_total += scaled
            kept_here += 1
        else:
            cand_val[q] = -1  # dropped (kept values are never negative)
    offset, kept = _sum_scan(scan, kept_here, tid, threads)
    red[0, tid] = scaled_total
    _reduce(red, 1, 1, tid, threads)
    inverse = 1.0 / red[0, 0]
    cuda.syncthreads()
    if kept > new_col.shape[0]:
        return -1
    # E. Normalise into the new row; D = sum |new - old| and F P.
    moved = cuda.local.array(_CHANNELS, float64)
    for d in range(_CHANNELS):
        moved[d] = 0.0
    near = min(points.shape[1], _CHANNELS)
    new_sum = np.float64(0.0)
    at = offset
    for q in range(first, last):
        scaled = cand_val[q]
        if scaled >= 0:
            c = cand_col[q]
            value = np.float64(scaled) * inverse
            new_col[at] = c
            new_val[at] = value
            cand_val[q] = value
            at += 1
            new_sum += value
            for d in range(near):
                moved[d] += value * np.float64(points[c, d])
        else:
            cand_val[q] = 0
    cuda.syncthreads()
    change = np.float64(0.0)
    for e in range(tid, count, threads):
        now = cand_val[e]
        change += np.float64(abs(now - old_val[e]) - now)
    red[0, tid] = new_sum
    red[1, tid] = change
    for d in range(_CHANNELS):
        red[2 + d, tid] = moved[d]
    _reduce(red, 2 + near, 2 + near, tid, threads)
    if tid == 0:
        differences[k, target] = red[0, 0] + red[1, 0]
        for d in range(near):
            positions[k, target, d] = red[2 + d, 0]
    cuda.syncthreads()
    # Channels past the sixth (rare): from the stored values, six at a time.
    for low in range(_CHANNELS, points.shape[1], _CHANNELS):
        high = min(points.shape[1], low + _CHANNELS)
        for d in range(low, high):
            total_d = np.float64(0.0)
            for t in range(offset, offset + kept_here):
                total_d += np.float64(new_val[t] * points[new_col[t], d])
            red[d - low, tid] = total_d
        _reduce(red, high - low, high - low, tid, threads)
        if tid == 0:
            for d in range(low, high):
                positions[k, target, d] = red[d - low, 0]
        cuda.syncthreads()
    return kept


@functools.cache
def make_stream_kernel(threads: int, shared_slots: int):
    """The streamed kernel for blocks of ``threads`` threads (a power of two) whose column
    tables of up to ``shared_slots`` slots (a power of two) live in shared memory; larger
    tables use the block's slice of the global scratch. Compiled on first launch, per
    process and per argument types."""

    @cuda.jit
    def stream_kernel(
        rows,
        counter,
        row_target,
        diagonal,
        w_crow,
        w_col,
        w_val,
        t_crow,
        t_col,
        t_val,
        row_sums,
        alpha,
        points,
        threshold,
        max_degree,
        keys_g,
        owner_g,
        index_g,
        cand_col_g,
        cand_val_g,
        rows_col_g,
        rows_val_g,
        differences,
        positions,
        entries,
        failed,
        failed_count,
    ):
        """Rows ``rows[r]`` through every step, one row per thread block at a time (a block
        takes the next ``r`` from ``counter``); rows that overflow their scratch go to
        ``failed[:failed_count]``, the others add their entries per scale to ``entries``."""
        tid = cuda.threadIdx.x
        block = cuda.blockIdx.x
        red = cuda.shared.array((SLOTS, threads), float64)
        scan = cuda.shared.array(threads, int64)
        state = cuda.shared.array(4, int64)
        s_keys = cuda.shared.array(shared_slots, int32)
        s_owner = cuda.shared.array(shared_slots, int64)
        s_index = cuda.shared.array(shared_slots, int32)
        counts = cuda.local.array(MAX_SCALES, int64)
        totals = cuda.local.array(MAX_SCALES, int64)
        lhat = (diagonal, w_crow, w_col, w_val, t_crow, t_col, t_val, row_sums)
        num_scales = differences.shape[0]
        num_vertices = diagonal.shape[0]
        capacity = keys_g.shape[1]
        for k in range(MAX_SCALES):
            totals[k] = 0
        while True:
            if tid == 0:
                state[0] = cuda.atomic.add(counter, 0, 1)
            cuda.syncthreads()
            r = state[0]
            cuda.syncthreads()
            if r >= rows.shape[0]:
                break
            i = rows[r]
            target = row_target[i]
            # F^(1)(i, :): the diagonal, then W's row, over Lhat's row sum.
            count = w_crow[i + 1] - w_crow[i] + 1
            scale = row_sums[i]
            old = 0
            for e in range(tid, count, threads):
                if e == 0:
                    rows_col_g[block, 0, 0] = i
                    rows_val_g[block, 0, 0] = diagonal[i] / scale
                else:
                    s = w_crow[i] + e - 1
                    rows_col_g[block, 0, e] = w_col[s]
                    rows_val_g[block, 0, e] = w_val[s] / scale
            overflowed = False
            for k in range(1, num_scales):
                cuda.syncthreads()
                # The table holds at most min(products, V) columns; half full at most.
                products = 0
                for e in range(tid, count, threads):
                    j = rows_col_g[block, old, e]
                    products += w_crow[j + 1] - w_crow[j] + 1
                _, products = _sum_scan(scan, products, tid, threads)
                size = 2 * threads
                while size < 2 * min(products, num_vertices) and size < capacity:
                    size *= 2
                new = 1 - old
                row_col, row_val = rows_col_g[block], rows_val_g[block]
                table = (s_keys, s_owner, s_index)  # small tables in shared memory
                if size > shared_slots:
                    table = (keys_g[block], owner_g[block], index_g[block])
                kept = _step(
                    k,
                    target,
                    count,
                    (row_col[old], row_val[old], row_col[new], row_val[new]),
                    table,
                    size,
                    (cand_col_g[block], cand_val_g[block]),
                    (lhat, alpha, points, threshold, max_degree),
                    (differences, positions),
                    (red, scan, state, tid, threads),
                )
                if kept < 0:
                    overflowed = True
                    break
                counts[k] = kept
                count = kept
                old = new
            if tid == 0:
                if overflowed:
                    failed[cuda.atomic.add(failed_count, 0, 1)] = i
                else:
                    for k in range(1, num_scales):
                        totals[k] += counts[k]
        if tid == 0:
            for k in range(1, num_scales):
                if totals[k] != 0:
                    cuda.atomic.add(entries, k, totals[k])

    return stream_kernel
