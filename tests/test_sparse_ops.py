"""The custom CSR operators in ``torch.ops.stochlap``: registration checks and dense agreement.

Each operator takes CSR components as plain tensors (``crow`` int64 ``(n + 1,)``, ``col``
int64 ``(nnz,)``, ``val`` float ``(nnz,)``) and is compared with dense torch on random small
matrices, some with empty rows.

``torch.library.opcheck`` runs its four default checks (``test_schema``,
``test_autograd_registration``, ``test_faketensor``, ``test_aot_dispatch_dynamic``) on every
operator, unrestricted. Findings that shaped these tests:

* The data-dependent output sizes of ``csr_matmul`` and ``threshold_rows`` (``nnz`` of the
  result) are declared with ``new_dynamic_size`` in their fake kernels, which is enough for
  ``test_faketensor`` and ``test_aot_dispatch_dynamic`` to pass as they are.
* Only ``spmm`` has an autograd formula. The other operators are meant to run with the
  operators held constant (the library calls them under ``torch.no_grad``), so they are
  opchecked with inputs that do not require grad (with ``val.requires_grad=True``,
  ``test_aot_dispatch_dynamic`` tries to differentiate them, which they do not support).
  ``spmm`` is opchecked with both ``val`` and ``dense`` requiring grad.
* The operators are defined with ``torch.library.Library`` (``sparse/registry.py``), not
  ``custom_op``, so that eager calls do not import ``torch._dynamo``; the last test checks it.
"""

from __future__ import annotations

import pytest
import torch
from torch.library import opcheck

import stochlap_torch.sparse.ops as sparse_ops

ops = torch.ops.stochlap
DTYPES = [torch.float64, torch.float32]


def random_dense(
    rows: int, cols: int, seed: int, density: float = 0.35, dtype=torch.float64, signed=False
) -> torch.Tensor:
    """Random sparse-ish dense matrix with positive (or signed) entries and an empty row."""
    gen = torch.Generator().manual_seed(seed)
    values = torch.rand(rows, cols, generator=gen, dtype=torch.float64) + 0.05
    if signed:
        values = values * torch.where(torch.rand(rows, cols, generator=gen) < 0.5, -1.0, 1.0)
    mask = torch.rand(rows, cols, generator=gen) < density
    dense = (values * mask).to(dtype)
    dense[rows // 2] = 0  # an empty row
    return dense


def components(dense: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(crow, col, val)`` of a dense matrix, columns sorted within rows."""
    csr = dense.to_sparse_csr()
    return (
        csr.crow_indices().to(torch.int64).clone(),
        csr.col_indices().to(torch.int64).clone(),
        csr.values().clone(),
    )


def to_dense(crow, col, val, num_cols: int) -> torch.Tensor:
    """Dense matrix from CSR components (duplicates would be summed, then caught elsewhere)."""
    rows = torch.repeat_interleave(torch.arange(crow.numel() - 1), crow.diff())
    dense = val.new_zeros(crow.numel() - 1, num_cols)
    return dense.index_put_((rows, col), val, accumulate=True)


def assert_valid_csr(crow, col, val, num_rows: int, num_cols: int) -> None:
    """Row pointers consistent, columns in range and strictly increasing within each row."""
    assert crow.dtype == torch.int64 and col.dtype == torch.int64
    assert crow.shape == (num_rows + 1,)
    assert int(crow[0]) == 0 and int(crow[-1]) == col.numel() == val.numel()
    assert bool((crow.diff() >= 0).all())
    assert bool(((col >= 0) & (col < num_cols)).all())
    for r in range(num_rows):
        row_cols = col[crow[r] : crow[r + 1]]
        assert bool((row_cols.diff() > 0).all()), f"row {r} columns not strictly increasing"


SHAPES = [(5, 6, 4), (7, 7, 7), (1, 3, 2), (12, 9, 11)]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize(("n", "m", "p"), SHAPES)
def test_csr_matmul_matches_dense(n: int, m: int, p: int, dtype: torch.dtype) -> None:
    """``csr_matmul`` equals ``A @ B`` and returns a well-formed CSR with no stored zeros."""
    a, b = random_dense(n, m, 1, dtype=dtype), random_dense(m, p, 2, dtype=dtype)
    crow, col, val = ops.csr_matmul(*components(a), *components(b), p)
    assert_valid_csr(crow, col, val, n, p)
    assert val.dtype == dtype
    expected = a @ b
    torch.testing.assert_close(to_dense(crow, col, val, p), expected)
    assert col.numel() == int((expected != 0).sum())  # positive factors: no cancellation


def test_csr_matmul_in_small_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    """The row-block splitting (tiny ``BLOCK_PRODUCTS``) gives the same product."""
    a, b = random_dense(15, 10, 3, density=0.5), random_dense(10, 8, 4, density=0.5)
    whole = ops.csr_matmul(*components(a), *components(b), 8)
    monkeypatch.setattr(sparse_ops, "BLOCK_PRODUCTS", 3)
    split = ops.csr_matmul(*components(a), *components(b), 8)
    for x, y in zip(whole, split, strict=True):
        torch.testing.assert_close(x, y)
    torch.testing.assert_close(to_dense(*split, 8), a @ b)


def test_csr_matmul_with_zero_matrix() -> None:
    """An all-zero factor gives an empty, well-formed product."""
    a, b = torch.zeros(4, 3, dtype=torch.float64), random_dense(3, 5, 5)
    crow, col, val = ops.csr_matmul(*components(a), *components(b), 5)
    assert_valid_csr(crow, col, val, 4, 5)
    assert col.numel() == 0


def threshold_dense(dense: torch.Tensor, threshold: float) -> torch.Tensor:
    """Dense reference: zero entries ``< threshold`` but keep each nonempty row's maximum."""
    row_max = dense.max(dim=1, keepdim=True).values
    keep = (dense >= threshold) | ((dense == row_max) & (dense != 0))
    return torch.where(keep, dense, torch.zeros_like(dense))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("threshold", [0.2, 0.6, 0.99])
def test_threshold_rows_matches_dense(threshold: float, dtype: torch.dtype) -> None:
    """Entries below the threshold are dropped, each row's largest entry is always kept."""
    dense = random_dense(10, 8, 6, density=0.6, dtype=dtype)
    crow, col, val = ops.threshold_rows(*components(dense), threshold)
    assert_valid_csr(crow, col, val, 10, 8)
    expected = threshold_dense(dense, threshold)
    torch.testing.assert_close(to_dense(crow, col, val, 8), expected)
    assert col.numel() == int((expected != 0).sum())
    nonempty = dense.abs().sum(dim=1) > 0
    assert bool((crow.diff()[nonempty] >= 1).all()), "a nonempty row lost every entry"


@pytest.mark.parametrize("dtype", DTYPES)
def test_normalize_rows_matches_dense(dtype: torch.dtype) -> None:
    """Each row divided by its sum; the pattern is unchanged."""
    dense = random_dense(9, 7, 7, dtype=dtype)
    crow, col, val = components(dense)
    out = ops.normalize_rows(crow, val)
    assert out.shape == val.shape and out.dtype == dtype
    sums = dense.sum(dim=1, keepdim=True)
    expected = torch.where(sums > 0, dense / sums.clamp_min(1e-300), dense)
    torch.testing.assert_close(to_dense(crow, col, out, 7), expected)


@pytest.mark.parametrize("dtype", DTYPES)
def test_scale_columns_matches_dense(dtype: torch.dtype) -> None:
    """Column ``j`` multiplied by ``scale[j]`` (the Schur product with ``alpha``)."""
    dense = random_dense(6, 8, 8, dtype=dtype)
    scale = torch.linspace(1.0, 3.0, 8, dtype=dtype)
    crow, col, val = components(dense)
    out = ops.scale_columns(col, val, scale)
    torch.testing.assert_close(to_dense(crow, col, out, 8), dense * scale[None, :])


@pytest.mark.parametrize("dtype", DTYPES)
def test_row_abs_diff_sum_matches_dense(dtype: torch.dtype) -> None:
    """``sum_j |A - B|(i, j)`` for two matrices with different patterns."""
    a = random_dense(10, 9, 9, dtype=dtype, signed=True)
    b = random_dense(10, 9, 10, dtype=dtype, signed=True)
    out = ops.row_abs_diff_sum(*components(a), *components(b), 9)
    assert out.shape == (10,) and out.dtype == dtype
    torch.testing.assert_close(out, (a - b).abs().sum(dim=1))


def test_row_abs_diff_sum_of_equal_matrices_is_zero() -> None:
    """Identical inputs give exactly zero."""
    a = random_dense(6, 6, 11)
    out = ops.row_abs_diff_sum(*components(a), *components(a), 6)
    assert bool((out == 0).all())


@pytest.mark.parametrize("dtype", DTYPES)
def test_spmm_matches_dense(dtype: torch.dtype) -> None:
    """``CSR @ dense`` for an ``(m, C)`` right-hand side."""
    a = random_dense(8, 6, 12, dtype=dtype, signed=True)
    x = torch.randn(6, 3, generator=torch.Generator().manual_seed(0), dtype=dtype)
    out = ops.spmm(*components(a), x)
    assert out.shape == (8, 3) and out.dtype == dtype
    torch.testing.assert_close(out, a @ x)


def test_spmm_gradients_match_dense() -> None:
    """Gradients w.r.t. ``val`` and ``dense`` equal those of the dense product."""
    a = random_dense(8, 6, 13, signed=True)
    crow, col, val = components(a)
    x = torch.randn(6, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    weight = torch.randn(8, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    val_s, x_s = val.clone().requires_grad_(True), x.clone().requires_grad_(True)
    (ops.spmm(crow, col, val_s, x_s) * weight).sum().backward()
    a_d, x_d = a.clone().requires_grad_(True), x.clone().requires_grad_(True)
    ((a_d @ x_d) * weight).sum().backward()
    rows = torch.repeat_interleave(torch.arange(8), crow.diff())
    torch.testing.assert_close(val_s.grad, a_d.grad[rows, col])
    torch.testing.assert_close(x_s.grad, x_d.grad)


def test_spmm_gradcheck() -> None:
    """Finite-difference check of the gradients w.r.t. ``val`` and ``dense``."""
    a = random_dense(5, 4, 14, signed=True)
    crow, col, val = components(a)
    x = torch.randn(4, 2, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    assert torch.autograd.gradcheck(
        lambda v, d: ops.spmm(crow, col, v, d),
        (val.requires_grad_(True), x.requires_grad_(True)),
    )


def opcheck_samples() -> list[tuple[str, object, tuple]]:
    """``(name, op, args)`` samples for ``opcheck``, float64 and float32."""
    samples = []
    for dtype in DTYPES:
        a = components(random_dense(5, 6, 20, dtype=dtype))
        b = components(random_dense(6, 4, 21, dtype=dtype))
        a2 = components(random_dense(5, 6, 22, dtype=dtype, signed=True))
        scale = torch.linspace(1.0, 2.0, 6, dtype=dtype)
        dense = torch.randn(6, 3, generator=torch.Generator().manual_seed(4), dtype=dtype)
        tag = str(dtype).removeprefix("torch.")
        samples += [
            (f"csr_matmul-{tag}", ops.csr_matmul.default, (*a, *b, 4)),
            (f"threshold_rows-{tag}", ops.threshold_rows.default, (*a, 0.5)),
            (f"normalize_rows-{tag}", ops.normalize_rows.default, (a[0], a[2])),
            (f"scale_columns-{tag}", ops.scale_columns.default, (a[1], a[2], scale)),
            (f"row_abs_diff_sum-{tag}", ops.row_abs_diff_sum.default, (*a, *a2, 6)),
            (
                f"spmm-{tag}",
                ops.spmm.default,
                (a[0], a[1], a[2].clone().requires_grad_(True), dense.requires_grad_(True)),
            ),
        ]
    return samples


@pytest.mark.parametrize(
    ("op", "args"), [s[1:] for s in opcheck_samples()], ids=[s[0] for s in opcheck_samples()]
)
def test_opcheck(op, args) -> None:
    """All default ``opcheck`` utilities pass (see the module docstring for the inputs)."""
    opcheck(op, args)


def test_all_operators_registered() -> None:
    """The six operators exist in the ``stochlap`` namespace."""
    for name in (
        "csr_matmul",
        "threshold_rows",
        "normalize_rows",
        "scale_columns",
        "row_abs_diff_sum",
        "spmm",
    ):
        assert hasattr(torch.ops.stochlap, name), name


# --------------------------------------------------------------------------------------------
# The fused diffusion step ``stochlap::diffusion_step`` (numba kernel on CPU when available)
# --------------------------------------------------------------------------------------------


def step_inputs(num: int, seed: int, dtype=torch.float64):
    """A row-stochastic ``F``, a symmetric positive ``Lhat`` pattern, ``alpha`` and points."""
    gen = torch.Generator().manual_seed(seed)
    f_dense = random_dense(num, num, seed, density=0.3, dtype=dtype)
    f_dense += torch.eye(num, dtype=dtype)  # no empty rows
    f_dense /= f_dense.sum(dim=1, keepdim=True)
    weights = random_dense(num, num, seed + 1, density=0.25, dtype=dtype)
    weights = torch.triu(weights, 1)
    weights = weights + weights.T
    l_dense = weights + torch.diag(weights.sum(dim=1) + (weights.sum(dim=1) == 0).to(dtype))
    alpha = 1.0 + torch.rand(num, generator=gen, dtype=torch.float64).to(dtype)
    points = torch.randn(num, 3, generator=gen, dtype=torch.float64).to(dtype)
    return f_dense, l_dense, alpha, points


def dense_step(f_dense, l_dense, alpha, points, threshold):
    """Dense reference of one step: ``F^(k)``, ``D^(k)`` and ``F^(k) P``."""
    g = f_dense @ l_dense
    g = g / g.sum(dim=1, keepdim=True)
    g = threshold_dense(g, threshold) * alpha[None, :]
    following = g / g.sum(dim=1, keepdim=True)
    return following, (following - f_dense).abs().sum(dim=1), following @ points


def run_step(f_dense, l_dense, alpha, points, threshold):
    """``torch.ops.stochlap.diffusion_step`` on dense inputs converted to CSR components."""
    return ops.diffusion_step(*components(f_dense), *components(l_dense), alpha, threshold, points)


def has_fused_step() -> bool:
    """Whether this build registers ``stochlap::diffusion_step``."""
    return hasattr(torch.ops.stochlap, "diffusion_step")


needs_fused_step = pytest.mark.skipif(
    not has_fused_step(), reason="stochlap::diffusion_step is not registered in this build"
)


@needs_fused_step
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("threshold", [1e-3, 0.08, 0.6])
def test_diffusion_step_matches_dense(threshold: float, dtype: torch.dtype) -> None:
    """One fused step equals the dense composition of the contract."""
    inputs = step_inputs(24, seed=30, dtype=dtype)
    crow, col, val, difference, moved = run_step(*inputs, threshold)
    assert_valid_csr(crow, col, val, 24, 24)
    following, expected_difference, expected_moved = dense_step(*inputs, threshold)
    torch.testing.assert_close(to_dense(crow, col, val, 24), following)
    torch.testing.assert_close(difference, expected_difference)
    torch.testing.assert_close(moved, expected_moved)
    assert col.numel() == int((following != 0).sum())


@needs_fused_step
def test_diffusion_step_with_overflowing_regions(monkeypatch: pytest.MonkeyPatch) -> None:
    """Output regions too small for every row (all redone in later rounds): the same step."""
    from stochlap_torch import _kernels as kernels

    if not kernels.numba_available():
        pytest.skip("numba not available: the op runs the torch composition")
    inputs = step_inputs(30, seed=31)
    whole = run_step(*inputs, 0.01)
    monkeypatch.setattr(kernels.steps, "DEFAULT_GROWTH", 1e-6)  # every row overflows
    split = run_step(*inputs, 0.01)
    for x, y in zip(whole, split, strict=True):
        torch.testing.assert_close(x, y)
    following, _, _ = dense_step(*inputs, 0.01)
    torch.testing.assert_close(to_dense(*split[:3], 30), following)


@needs_fused_step
@pytest.mark.parametrize("dtype", DTYPES)
def test_diffusion_step_opcheck(dtype: torch.dtype) -> None:
    """``opcheck`` with all default utilities (no autograd: inputs do not require grad)."""
    f_dense, l_dense, alpha, points = step_inputs(10, seed=32, dtype=dtype)
    args = (*components(f_dense), *components(l_dense), alpha, 0.05, points)
    opcheck(ops.diffusion_step.default, args)


def test_eager_runs_do_not_import_dynamo(tmp_path) -> None:
    """The operators are registered without ``custom_op``'s dynamo wrapper, so an eager run
    does not pay the ~1 s import of ``torch._dynamo`` (checked in a fresh interpreter)."""
    import subprocess
    import sys

    script = (
        "import sys, stochlap_torch as sl\n"
        "mesh = sl.load_mesh(sl.bundled_mesh_path())\n"
        "sl.saliency(mesh.vertices, mesh.faces, num_scales=3)\n"
        "sl.multiscale_representation(mesh.vertices, mesh.faces, 3, return_operators=True)\n"
        "print('torch._dynamo' in sys.modules)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True, cwd=tmp_path
    )
    assert done.stdout.strip().splitlines()[-1] == "False", done.stdout + done.stderr
