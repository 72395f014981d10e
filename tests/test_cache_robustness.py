"""The mesh cache refuses values the computation cannot give, survives a folder it
cannot write, and never opens a FIFO or device at an entry's path."""

from __future__ import annotations

import os
import shutil
import signal
import stat
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from reference import noisy_sphere

import stochlap_torch as sl
from stochlap_torch._common.errors import CacheError
from stochlap_torch.features import feature_params, multiscale_features
from stochlap_torch.learning.cache import (
    CacheWarning,
    MeshCache,
    cached_features,
    cached_operators,
    features_key,
    operators_key,
)
from stochlap_torch.params import PaperParams

PARAMS = {"num_scales": 3, "variant": "paper"}


def _mesh():
    mesh = noisy_sphere()
    return torch.tensor(mesh.vertices), torch.tensor(mesh.faces)


def _features_key(vertices, faces, params) -> str:
    return features_key(vertices, faces, feature_params(**params))


def _rewrite(path: Path, change) -> None:
    """Apply ``change`` to the arrays of a cache file (its key fields kept, as a tamperer who
    edits a real entry would)."""
    with np.load(path, allow_pickle=False) as archive:
        arrays = {name: archive[name] for name in archive.files}
    change(arrays)
    with open(path, "wb") as handle:
        np.savez(handle, **arrays)


def _cache_warnings(call):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = call()
    return result, [str(w.message) for w in caught if issubclass(w.category, CacheWarning)]


# ============================================================================================
# Values out of the range the computation gives are refused like other corruption.


def _times_1e300(arrays):
    arrays["features"] = arrays["features"] * 1e300


def _one_1e20(arrays):  # finite in float32, whose largest value is 3.4e38
    arrays["features"] = arrays["features"].copy()
    arrays["features"][7, 2] = 1e20


FEATURE_CASES = {
    "times_1e300": (_times_1e300, torch.float64, PARAMS),
    "one_1e20_float32_robust": (_one_1e20, torch.float32, {}),
}


@pytest.mark.parametrize("case", sorted(FEATURE_CASES))
def test_feature_values_out_of_range_are_recomputed(tmp_path, case):
    """The recomputed entry, reloaded, passes the checks: they refuse no real entry."""
    tamper, dtype, params = FEATURE_CASES[case]
    vertices, faces = _mesh()
    vertices = vertices.to(dtype)
    expected = multiscale_features(vertices, faces, **params)
    cached_features(vertices, faces, tmp_path, **params)
    _rewrite(MeshCache(tmp_path).path(_features_key(vertices, faces, params)), tamper)
    with pytest.warns(CacheWarning, match="invalid data.*magnitude"):
        again = cached_features(vertices, faces, tmp_path, **params)
    assert torch.equal(again, expected)
    reloaded, warned = _cache_warnings(lambda: cached_features(vertices, faces, tmp_path, **params))
    assert warned == [] and torch.equal(reloaded, expected)  # the entry was replaced


OPERATORS = {"num_scales": 8, "threshold": 1e-5}  # long rows: the widest row sums


def _values_times_1e300(arrays):
    arrays["val1"] = arrays["val1"] * 1e300


def _one_value_doubled(arrays):  # still in [0, 1]: only its row's sum shows it
    arrays["val0"] = arrays["val0"].copy()
    arrays["val0"][5] *= 2


def _row_sum_kept_outside_unit_interval(arrays):  # row 0 still sums to 1
    arrays["val0"] = arrays["val0"].copy()
    arrays["val0"][0] += 1.0
    arrays["val0"][1] -= 1.0


def _every_value_zero(arrays):
    arrays["val7"] = np.zeros_like(arrays["val7"])


OPERATOR_CASES = {
    "times_1e300": (_values_times_1e300, torch.float64),
    "one_doubled_float32": (_one_value_doubled, torch.float32),
    "outside_0_1": (_row_sum_kept_outside_unit_interval, torch.float64),
    "zeros_float32": (_every_value_zero, torch.float32),
}


@pytest.mark.parametrize("case", sorted(OPERATOR_CASES))
def test_operators_that_are_not_row_stochastic_are_recomputed(tmp_path, case):
    tamper, dtype = OPERATOR_CASES[case]
    vertices, faces = _mesh()
    vertices = vertices.to(dtype)
    expected = sl.multiscale_representation(
        vertices, faces, return_operators=True, **OPERATORS
    ).operators
    cached_operators(vertices, faces, tmp_path, **OPERATORS)
    key = operators_key(vertices, faces, PaperParams(**OPERATORS))
    _rewrite(MeshCache(tmp_path).path(key), tamper)
    with pytest.warns(CacheWarning, match="invalid data"):
        got = cached_operators(vertices, faces, tmp_path, **OPERATORS)
    for mine, theirs in zip(got, expected, strict=True):
        assert torch.equal(mine.to_dense(), theirs.to_dense())
    _, warned = _cache_warnings(lambda: cached_operators(vertices, faces, tmp_path, **OPERATORS))
    assert warned == []  # replaced, and the real entry passes the checks


# ============================================================================================
# A cache that cannot be written warns once and returns what it computed.


@pytest.fixture
def readonly_folder(tmp_path):
    """A cache folder no file can be created in: read-only mode bits, or, for root (who
    ignores them), the immutable attribute; skips where neither holds."""
    folder = tmp_path / "readonly"
    folder.mkdir()
    folder.chmod(0o555)
    immutable = False
    if _writable(folder) and shutil.which("chattr"):
        immutable = (
            subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode == 0
        )
    try:
        if _writable(folder):
            pytest.skip("no way to make a folder read-only here")
        yield folder
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(folder)], check=True)
        folder.chmod(0o755)


def _writable(folder: Path) -> bool:
    probe = folder / "probe"
    try:
        probe.write_bytes(b"")
    except OSError:
        return False
    probe.unlink()
    return True


def _computes_twice_and_warns_once(folder):
    """Two misses (other parameters) in an unwritable cache: both values right, one warning."""
    vertices, faces = _mesh()
    runs = [PARAMS, {"num_scales": 4, "variant": "paper"}]
    got, warned = _cache_warnings(
        lambda: [cached_features(vertices, faces, folder, **params) for params in runs]
    )
    for params, features in zip(runs, got, strict=True):
        assert torch.equal(features, multiscale_features(vertices, faces, **params))
    assert len(warned) == 1 and "cannot be written" in warned[0], warned


def test_readonly_folder_warns_once_and_returns_the_features(readonly_folder):
    _computes_twice_and_warns_once(readonly_folder)
    assert list(readonly_folder.iterdir()) == []


def test_full_disk_warns_once_and_returns_the_features(tmp_path):
    """A write past the file size limit fails as on a full disk (EFBIG instead of ENOSPC)."""
    resource = pytest.importorskip("resource")  # POSIX only
    vertices, faces = _mesh()
    for params in (PARAMS, {"num_scales": 4, "variant": "paper"}):
        multiscale_features(vertices, faces, **params)  # kernels compiled: no write while full
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a failed write, not a kill
    resource.setrlimit(resource.RLIMIT_FSIZE, (1024, hard))
    try:
        _computes_twice_and_warns_once(tmp_path)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, handler)
    assert list(tmp_path.iterdir()) == []  # no temporary file left behind


def test_entry_path_that_is_a_folder_is_left_alone(tmp_path):
    vertices, faces = _mesh()
    entry = MeshCache(tmp_path).path(_features_key(vertices, faces, PARAMS))
    entry.mkdir()
    (entry / "user_file").write_text("mine")
    for _ in range(2):
        with pytest.warns(CacheWarning, match="a directory, not a regular file"):
            features = cached_features(vertices, faces, tmp_path, **PARAMS)
        assert torch.equal(features, multiscale_features(vertices, faces, **PARAMS))
    assert (entry / "user_file").read_text() == "mine"


def test_store_raises_cache_error_naming_the_file(readonly_folder):
    cache = MeshCache(readonly_folder)
    with pytest.raises(CacheError, match=f"{cache.path('ab' * 32)} cannot be written"):
        cache.store("ab" * 32, {"x": np.zeros(3)})


# ============================================================================================
# A FIFO, device or folder at an entry's path is never opened (a FIFO blocked the
# reader for good), is warned about, and is left in place; nothing is cached for it. Each call
# runs under an alarm, so that a regression fails instead of hanging the suite.


def _within(seconds: float, call):
    """``call()``, or ``TimeoutError`` once ``seconds`` have passed (``SIGALRM`` interrupts a
    blocking ``open``; the handler's exception ends it)."""

    def expire(signum, frame):
        raise TimeoutError(f"still blocked after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        return call()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def _fifo(entry: Path) -> str:
    os.mkfifo(entry)
    return "a FIFO"


def _link_to_fifo(entry: Path) -> str:
    os.mkfifo(entry.with_name("user.fifo"))
    entry.symlink_to(entry.with_name("user.fifo"))
    return "a FIFO"


def _link_to_device(entry: Path) -> str:
    entry.symlink_to(os.devnull)
    return "a character device"


SPECIAL_ENTRIES = {
    "fifo": _fifo,
    "link_to_fifo": _link_to_fifo,
    "link_to_dev_null": _link_to_device,
}


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
@pytest.mark.parametrize("special", sorted(SPECIAL_ENTRIES))
def test_special_file_entry_is_not_opened_nor_replaced(tmp_path, special):
    vertices, faces = _mesh()
    expected = multiscale_features(vertices, faces, **PARAMS)  # compiled before the alarm
    entry = MeshCache(tmp_path).path(_features_key(vertices, faces, PARAMS))
    kind = SPECIAL_ENTRIES[special](entry)
    before = (entry.is_symlink(), os.stat(entry).st_mode, sorted(tmp_path.iterdir()))
    for _ in range(2):  # not cached: the second call finds the same entry
        with pytest.warns(CacheWarning, match=f"{kind}, not a regular file"):
            features = _within(20, lambda: cached_features(vertices, faces, tmp_path, **PARAMS))
        assert torch.equal(features, expected)
    assert (entry.is_symlink(), os.stat(entry).st_mode, sorted(tmp_path.iterdir())) == before


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this platform")
def test_store_refuses_to_replace_a_fifo(tmp_path):
    cache = MeshCache(tmp_path)
    os.mkfifo(cache.path("cd" * 32))
    with pytest.raises(CacheError, match="a FIFO, not a regular file; refusing to replace it"):
        _within(20, lambda: cache.store("cd" * 32, {"x": np.zeros(3)}))
    assert stat.S_ISFIFO(os.stat(cache.path("cd" * 32)).st_mode)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")], ids=["nan", "inf"])
def test_non_finite_feature_values_are_recomputed(tmp_path, bad):
    """A NaN compares false with any ceiling: it is refused as non-finite, not by magnitude."""
    vertices, faces = _mesh()
    expected = multiscale_features(vertices, faces, **PARAMS)
    cached_features(vertices, faces, tmp_path, **PARAMS)

    def plant(arrays):
        arrays["features"] = arrays["features"].copy()
        arrays["features"][3, 1] = bad

    _rewrite(MeshCache(tmp_path).path(_features_key(vertices, faces, PARAMS)), plant)
    with pytest.warns(CacheWarning, match="invalid data.*NaN or Inf"):
        again = cached_features(vertices, faces, tmp_path, **PARAMS)
    assert torch.equal(again, expected)
