"""The CUDA kernel of the streamed steps (``backend="cuda"``), run in numba's CUDA simulator.

The simulator runs each CUDA thread as a Python thread, on CPU arrays, and must be switched on
before numba is imported: the kernel runs in one subprocess with ``NUMBA_ENABLE_CUDASIM=1`` for
every case (tiny meshes, few scales), and its results are compared here with the CPU kernel
(``backend="numba"``) and the dense float64 reference. The backend resolution is checked in
this process with ``numba.cuda.is_available`` mocked.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import reference as ref
import torch

import stochlap_torch as sl
from stochlap_torch._common.errors import ParameterError
from stochlap_torch.diffusion import parameters

TESTS_DIR = Path(__file__).resolve().parent

#: ``(mesh, K, threshold, dtype)``: small meshes of the reference (with a boundary, a vertex no
#: face uses, two components), the paper's threshold, thresholds that drop entries at every
#: scale, and 0.3, where some rows' largest entry falls below the threshold and is kept by the
#: keep-the-largest rule alone.
CASES = [
    ("icosphere1", 3, 1e-3, "float64"),
    ("open_grid", 4, 0.04, "float64"),
    ("open_grid", 3, 0.3, "float64"),
    ("open_grid", 3, 0.04, "float32"),
    ("unreferenced_vertex", 3, 0.07, "float64"),
    ("two_components", 3, 0.04, "float32"),
]

#: Run in the subprocess: every case through ``backend="cuda"`` on CPU tensors (allowed under
#: the simulator only), results saved as ``.npz`` files.
_SIMULATED_RUNS = """
import json, sys
sys.setswitchinterval(1e-4)  # the simulator's block manager polls its threads: switch often
sys.path[:0] = [{tests!r}, {root!r}]
import numpy as np, torch
import reference as ref
import stochlap_torch as sl
from stochlap_torch import _kernels
assert _kernels.cuda_simulator_enabled()
for number, (name, scales, threshold, dtype) in enumerate(json.loads({cases!r})):
    vertices, faces = ref.SMALL_MESH_BUILDERS[name]().tensors(getattr(torch, dtype))
    result = sl.multiscale_representation(vertices, faces, scales, threshold, backend="cuda")
    np.savez({out!r} + f"/{{number}}.npz", positions=result.positions.numpy(),
             differences=result.differences.numpy(), saliency=result.saliency().numpy(),
             entries=result.entries.numpy())
# The retry rounds: a first round with room for too few columns for most rows.
import logging
redone = []
handler = logging.Handler()
handler.emit = lambda record: redone.append(record.args[0]) if "overflowed" in record.msg else None
logging.getLogger("stochlap_torch._kernels.cuda_steps").addHandler(handler)
logging.getLogger("stochlap_torch._kernels.cuda_steps").setLevel(logging.DEBUG)
_kernels.cuda_steps.FIRST_ROUND_COLUMNS = 1
vertices, faces = ref.open_grid().tensors()
result = sl.multiscale_representation(vertices, faces, 3, 0.3, backend="cuda")
np.savez({out!r} + "/retry.npz", positions=result.positions.numpy(),
         differences=result.differences.numpy(), redone=np.array(redone))
# The budget: scratch for a single block runs one block at a time; less is refused by name.
from stochlap_torch.diffusion.memory import streamed_memory
from stochlap_torch.operators import mesh_operators
_kernels.cuda_steps.FIRST_ROUND_COLUMNS = 1024
grids = []
handler.emit = lambda record: grids.append(record.args[0]) if "blocks" in record.msg else None
vertices, faces = ref.icosphere(1).tensors()
outputs = streamed_memory(mesh_operators(vertices, faces), 3, "cuda")
floor = _kernels.cuda_scratch_floor(len(vertices), 6, 1e-3, 8)
result = sl.multiscale_representation(vertices, faces, 3, 1e-3, backend="cuda",
                                      max_memory=outputs + floor)
try:
    sl.multiscale_representation(vertices, faces, 3, 1e-3, backend="cuda",
                                 max_memory=outputs + floor - 1)
    refused = ""
except sl.MemoryBudgetError as error:
    refused = str(error)
np.savez({out!r} + "/budget.npz", positions=result.positions.numpy(), grids=np.array(grids),
         refused=np.array(refused))
"""


def _simulator_missing() -> str | None:
    """Why the simulator cannot run here, or ``None``."""
    if not sl._kernels.numba_available():
        return "numba is not installed"
    try:
        import numba.cuda.simulator  # noqa: F401
    except ImportError as error:
        return f"numba's CUDA simulator cannot be imported: {error}"
    return None


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> list[dict[str, np.ndarray]]:
    """The CUDA kernel's results for :data:`CASES`, from one simulator subprocess."""
    missing = _simulator_missing()
    if missing:
        pytest.skip(missing)
    out = tmp_path_factory.mktemp("cudasim")
    script = _SIMULATED_RUNS.format(
        tests=str(TESTS_DIR), root=str(TESTS_DIR.parent), cases=json.dumps(CASES), out=str(out)
    )
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1", STOCHLAP_QUIET="1")
    run = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr[-4000:]
    names = [*map(str, range(len(CASES))), "retry", "budget"]
    return [dict(np.load(out / f"{name}.npz")) for name in names]


def _cpu_kernel(name: str, scales: int, threshold: float, dtype: str):
    vertices, faces = ref.SMALL_MESH_BUILDERS[name]().tensors(getattr(torch, dtype))
    return sl.multiscale_representation(vertices, faces, scales, threshold, backend="numba")


@pytest.mark.parametrize("case", range(len(CASES)), ids=lambda c: "-".join(map(str, CASES[c])))
def test_cuda_kernel_matches_the_cpu_kernel(simulated, case):
    """Positions, difference maps, saliency and entry counts of the CUDA
    kernel equal the CPU kernel's (float64 to 1e-12, float32 to its rounding)."""
    name, scales, threshold, dtype = CASES[case]
    got = simulated[case]
    expected = _cpu_kernel(name, scales, threshold, dtype)
    tolerance = {"atol": 1e-12, "rtol": 0} if dtype == "float64" else {"atol": 2e-6, "rtol": 1e-5}
    assert got["positions"].dtype == np.dtype(dtype)
    np.testing.assert_array_equal(got["entries"], expected.entries.numpy())
    np.testing.assert_allclose(got["positions"], expected.positions.numpy(), **tolerance)
    np.testing.assert_allclose(got["differences"], expected.differences.numpy(), **tolerance)
    np.testing.assert_allclose(got["saliency"], expected.saliency().numpy(), **tolerance)


@pytest.mark.parametrize("case", [0, 1, 2, 4])
def test_cuda_kernel_matches_the_dense_reference(simulated, case):
    """The CUDA kernel against the plain dense float64 method (tests/reference.py)."""
    name, scales, threshold, _ = CASES[case]
    mesh = ref.SMALL_MESH_BUILDERS[name]()
    expected = ref.multiscale(mesh.vertices, mesh.faces, scales, threshold)
    assert expected.threshold_margin > 1e-9  # no entry on the threshold (rounding decides)
    np.testing.assert_allclose(simulated[case]["positions"], expected.positions, atol=1e-12)
    np.testing.assert_allclose(simulated[case]["differences"], expected.differences, atol=1e-12)


@pytest.mark.parametrize("available", [True, False])
@pytest.mark.parametrize("by_default", [False, True])
def test_auto_takes_the_cuda_kernel_only_on_cuda_devices(monkeypatch, available, by_default):
    """``"auto"`` is the CUDA kernel on a CUDA device where numba's CUDA target works once it
    is the default (off until checked on a GPU), the torch ops otherwise there, and the CPU
    kernel on the CPU."""
    numba_cuda = pytest.importorskip("numba.cuda")
    monkeypatch.setattr(numba_cuda, "is_available", lambda: available)
    monkeypatch.setattr(parameters, "CUDA_KERNEL_BY_DEFAULT", by_default)
    cuda = torch.device("cuda")
    expected = "cuda" if available and by_default else "torch"
    assert parameters.resolve_backend("auto", cuda) == expected
    assert parameters.resolve_backend("auto", torch.device("cpu")) == "numba"
    assert parameters.resolve_backend("torch", cuda) == "torch"
    if available:
        assert parameters.resolve_backend("cuda", cuda) == "cuda"
    else:
        with pytest.raises(ParameterError, match="backend='cuda'"):
            parameters.resolve_backend("cuda", cuda)


def test_cuda_backend_on_cpu_tensors_is_a_parameter_error(monkeypatch):
    """Outside the simulator, ``backend="cuda"`` on CPU tensors names the problem (even where
    a GPU is available), in the resolution and through the entry point."""
    numba_cuda = pytest.importorskip("numba.cuda")
    monkeypatch.setattr(numba_cuda, "is_available", lambda: True)
    assert "cuda" in sl.diffusion.BACKENDS
    with pytest.raises(ParameterError, match="CUDA tensors"):
        parameters.resolve_backend("cuda", torch.device("cpu"))
    vertices, faces = ref.icosphere(1).tensors()
    with pytest.raises(ParameterError, match="CUDA tensors"):
        sl.multiscale_representation(vertices, faces, 3, backend="cuda")


def test_rows_that_overflow_their_scratch_are_redone(simulated):
    """A row whose product has more columns than the first round made room
    for is redone with more room, and ends as the CPU kernel's (here with room for a single
    column in the first round, on open_grid at threshold 0.3)."""
    got = simulated[-2]
    assert got["redone"].size and got["redone"][0] > 0
    expected = _cpu_kernel("open_grid", 3, 0.3, "float64")
    np.testing.assert_allclose(got["positions"], expected.positions.numpy(), atol=1e-12, rtol=0)
    np.testing.assert_allclose(got["differences"], expected.differences.numpy(), atol=1e-12, rtol=0)


def test_the_kernel_scratch_fits_the_budget(simulated):
    """The scratch is what the budget leaves after the outputs: room for one block runs the
    rows one block at a time (and gives the CPU kernel's results); a byte less is refused by
    name, before any launch."""
    got = simulated[-1]
    assert got["grids"].size and set(got["grids"].tolist()) == {1}
    expected = _cpu_kernel("icosphere1", 3, 1e-3, "float64")
    np.testing.assert_allclose(got["positions"], expected.positions.numpy(), atol=1e-12, rtol=0)
    assert "scratch" in str(got["refused"]) and "max_memory" in str(got["refused"])
