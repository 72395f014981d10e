"""On-disk cache: round trip, corruption, mismatch, version, concurrent writers."""

from __future__ import annotations

import multiprocessing
import os
import warnings

import numpy as np
import pytest
import torch
from reference import noisy_sphere

import stochlap_torch as sl
from stochlap_torch.features import feature_params, multiscale_features
from stochlap_torch.learning.cache import (
    CacheWarning,
    MeshCache,
    cached_features,
    cached_operators,
    content_key,
    features_key,
    operators_key,
)
from stochlap_torch.params import PaperParams


def _mesh():
    mesh = noisy_sphere()
    return torch.tensor(mesh.vertices), torch.tensor(mesh.faces)


def _count_calls(monkeypatch):
    import stochlap_torch.learning.cache as features

    calls = []
    original = features.multiscale_features

    def counting(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(features, "multiscale_features", counting)
    return calls


def test_key_depends_on_everything():
    vertices, faces = _mesh()
    base = content_key(vertices, faces, {"num_scales": 4, "threshold": 1e-3})
    moved = vertices.clone()
    moved[5, 1] += 1e-12
    others = [
        content_key(moved, faces, {"num_scales": 4, "threshold": 1e-3}),
        content_key(vertices.float(), faces, {"num_scales": 4, "threshold": 1e-3}),
        content_key(vertices, faces[:, [1, 2, 0]], {"num_scales": 4, "threshold": 1e-3}),
        content_key(vertices, faces, {"num_scales": 5, "threshold": 1e-3}),
        content_key(vertices, faces, {"num_scales": 4, "threshold": 1.0000001e-3}),
        content_key(vertices, faces, {"num_scales": 4, "threshold": 1e-3}, kind="operators"),
    ]
    assert len({base, *others}) == len(others) + 1
    assert content_key(vertices, faces, {"threshold": 1e-3, "num_scales": 4}) == base
    assert content_key(vertices.numpy(), faces.numpy(), {"num_scales": 4, "threshold": 1e-3}) == (
        base
    )


def test_key_follows_the_numerics_not_the_version(monkeypatch):
    """The key changes with the code that computes the numbers, not with the package version."""
    import stochlap_torch.learning.cache as cache_module

    vertices, faces = _mesh()
    before = content_key(vertices, faces, {})
    monkeypatch.setattr(sl, "__version__", "999.0")
    assert content_key(vertices, faces, {}) == before
    monkeypatch.setattr(cache_module, "numerics_fingerprint", lambda: "0" * 16)
    assert content_key(vertices, faces, {}) != before


def test_round_trip_features(tmp_path, monkeypatch):
    vertices, faces = _mesh()
    calls = _count_calls(monkeypatch)
    params = {"num_scales": 3, "rotation_invariant": True, "variant": "paper"}
    first = cached_features(vertices, faces, tmp_path, **params)
    second = cached_features(vertices, faces, tmp_path, **params)
    assert len(calls) == 1
    assert torch.equal(first, second) and second.dtype == torch.float64
    torch.testing.assert_close(second, multiscale_features(vertices, faces, **params))
    assert len(list(tmp_path.glob("*.npz"))) == 1
    assert not list(tmp_path.glob(".tmp-*"))


def test_round_trip_operators(tmp_path):
    vertices, faces = _mesh()
    expected = sl.multiscale_representation(vertices, faces, 3, return_operators=True).operators
    for _ in range(2):
        got = cached_operators(vertices, faces, tmp_path, num_scales=3)
        for mine, theirs in zip(got, expected, strict=True):
            assert torch.equal(mine.to_dense(), theirs.to_dense())


def test_truncated_file_is_recomputed_with_a_warning(tmp_path, monkeypatch):
    vertices, faces = _mesh()
    calls = _count_calls(monkeypatch)
    first = cached_features(vertices, faces, tmp_path, num_scales=3, variant="paper")
    (path,) = tmp_path.glob("*.npz")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.warns(CacheWarning, match="unreadable"):
        again = cached_features(vertices, faces, tmp_path, num_scales=3, variant="paper")
    assert len(calls) == 2 and torch.equal(first, again)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # rewritten: now a clean hit
        cached_features(vertices, faces, tmp_path, num_scales=3, variant="paper")
    assert len(calls) == 2


def test_garbage_file_is_recomputed(tmp_path):
    cache = MeshCache(tmp_path)
    key = "ab" * 32
    cache.path(key).write_bytes(b"not a zip file at all")
    with pytest.warns(CacheWarning):
        assert cache.load(key) is None


def test_pickled_object_array_is_refused(tmp_path):
    cache = MeshCache(tmp_path)
    key = "cd" * 32
    with open(cache.path(key), "wb") as file:
        np.savez(file, x=np.array([{"a": 1}], dtype=object), __cache_key__=np.array(key))
    with pytest.warns(CacheWarning, match="unreadable"):
        assert cache.load(key) is None


def test_file_with_another_key_is_not_trusted(tmp_path, monkeypatch):
    vertices, faces = _mesh()
    cache = MeshCache(tmp_path)
    calls = _count_calls(monkeypatch)
    three = cached_features(vertices, faces, cache, num_scales=3, variant="paper")
    four_key = features_key(vertices, faces, feature_params("paper", num_scales=4))
    three_key = features_key(vertices, faces, feature_params("paper", num_scales=3))
    os.replace(cache.path(three_key), cache.path(four_key))  # a file under the wrong name
    with pytest.warns(CacheWarning, match="another key"):
        four = cached_features(vertices, faces, cache, num_scales=4, variant="paper")
    assert len(calls) == 2 and four.shape[1] > three.shape[1]


def test_file_of_other_numerics_is_not_trusted(tmp_path, monkeypatch):
    import stochlap_torch.learning.cache as cache_module

    cache = MeshCache(tmp_path)
    key = "ef" * 32
    cache.store(key, {"x": np.arange(3.0)})
    assert np.array_equal(cache.load(key)["x"], np.arange(3.0))
    monkeypatch.setattr(cache_module, "numerics_fingerprint", lambda: "f" * 16)
    with pytest.warns(CacheWarning, match="other numerics"):
        assert cache.load(key) is None


def _plant(cache: MeshCache, key: str, arrays: dict) -> None:
    """Write a file the way an attacker who knows the public key function would."""
    import stochlap_torch.learning.cache as cache_module

    payload = dict(arrays)
    payload["__cache_key__"] = np.array(key)
    payload["__cache_numerics__"] = np.array(cache_module.numerics_fingerprint())
    with open(cache.path(key), "wb") as handle:
        np.savez(handle, **payload)


def test_planted_operator_entry_out_of_range_is_recomputed(tmp_path):
    """A planted operator entry with columns >= V (it would crash ``op @ x``) is refused,
    recomputed and replaced."""
    vertices, faces = _mesh()
    cache = MeshCache(tmp_path)
    key = operators_key(vertices, faces, PaperParams(num_scales=2))
    size = vertices.shape[0]
    bad = {
        "crow0": np.arange(size + 1, dtype=np.int64),
        "col0": np.full(size, 10**6, dtype=np.int64),
        "val0": np.ones(size),
        "crow1": np.arange(size + 1, dtype=np.int64),
        "col1": np.arange(size, dtype=np.int64),
        "val1": np.ones(size),
    }
    _plant(cache, key, bad)
    with pytest.warns(CacheWarning, match="invalid data"):
        operators = cached_operators(vertices, faces, cache, num_scales=2)
    expected = sl.multiscale_representation(vertices, faces, 2, return_operators=True).operators
    for got, want in zip(operators, expected, strict=True):
        assert torch.equal(got.to_dense(), want.to_dense())
    assert not any(issubclass(w.category, CacheWarning) for w in _reload(vertices, faces, cache))


def _reload(vertices, faces, cache):
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cached_operators(vertices, faces, cache, num_scales=2)
    return caught


@pytest.mark.parametrize("crow_change", ["decreasing", "short", "nonzero_start"], ids=str)
def test_planted_operator_with_a_broken_row_pointer_is_recomputed(tmp_path, crow_change):
    vertices, faces = _mesh()
    cache = MeshCache(tmp_path)
    key = operators_key(vertices, faces, PaperParams(num_scales=2))
    size = vertices.shape[0]
    crow = np.arange(size + 1, dtype=np.int64)
    if crow_change == "decreasing":
        crow[3], crow[4] = crow[4], crow[3]
    elif crow_change == "short":
        crow = crow[:-1]
    else:
        crow = crow + 1
    arrays = {}
    for k in range(2):
        arrays |= {
            f"crow{k}": crow,
            f"col{k}": np.arange(size, dtype=np.int64),
            f"val{k}": np.ones(size),
        }
    _plant(cache, key, arrays)
    with pytest.warns(CacheWarning, match="invalid data"):
        cached_operators(vertices, faces, cache, num_scales=2)


def test_planted_feature_entry_of_the_wrong_shape_is_recomputed(tmp_path):
    vertices, faces = _mesh()
    cache = MeshCache(tmp_path)
    params = {"num_scales": 3}
    key = features_key(vertices, faces, feature_params(**params))
    _plant(cache, key, {"features": np.zeros((5, 2))})
    with pytest.warns(CacheWarning, match="invalid data"):
        features = cached_features(vertices, faces, cache, **params)
    torch.testing.assert_close(features, multiscale_features(vertices, faces, **params))


@pytest.mark.parametrize("offset", range(-60, 0, 7))
def test_a_corrupted_byte_anywhere_in_the_zip_directory_is_recomputed(tmp_path, offset):
    """One flipped byte in the zip's central directory made NotImplementedError, RuntimeError
    or KeyError escape, and the file stayed broken for good: every outcome must now be a
    warning, a recomputed value, and a replaced file."""
    vertices, faces = _mesh()
    cache = MeshCache(tmp_path)
    first = cached_features(vertices, faces, cache, num_scales=3, variant="paper")
    path = next(tmp_path.glob("*.npz"))
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))
    import warnings

    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        again = cached_features(vertices, faces, cache, num_scales=3, variant="paper")
    assert torch.equal(again, first)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cached_features(vertices, faces, cache, num_scales=3, variant="paper")
    assert not any(issubclass(w.category, CacheWarning) for w in caught)


def test_bad_keys_and_names(tmp_path):
    cache = MeshCache(tmp_path)
    with pytest.raises(ValueError):
        cache.path("../../etc/passwd")
    with pytest.raises(ValueError):
        cache.store("ab" * 32, {"__cache_key__": np.zeros(1)})


def _writer(directory: str, key: str, seed: int, rounds: int) -> None:
    cache = MeshCache(directory)
    values = np.full(200_000, float(seed))
    for _ in range(rounds):
        cache.store(key, {"x": values, "seed": np.array(seed)})


def test_concurrent_writers_do_not_corrupt(tmp_path):
    key = "12" * 32
    methods = multiprocessing.get_all_start_methods()
    context = multiprocessing.get_context("fork" if "fork" in methods else "spawn")
    workers = [
        context.Process(target=_writer, args=(str(tmp_path), key, seed, 20)) for seed in range(3)
    ]
    for worker in workers:
        worker.start()
    cache = MeshCache(tmp_path)
    reads = 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a torn file would warn: turn that into a failure
        while any(worker.is_alive() for worker in workers):
            arrays = cache.load(key)
            if arrays is not None:
                reads += 1
                assert np.all(arrays["x"] == float(arrays["seed"]))
    for worker in workers:
        worker.join()
        assert worker.exitcode == 0
    arrays = cache.load(key)
    assert np.all(arrays["x"] == float(arrays["seed"]))
    assert reads > 0
    assert [p.name for p in tmp_path.iterdir()] == [cache.path(key).name]


def test_the_numerics_fingerprint_covers_every_part_that_computes_numbers():
    """A new part of the package that computes cached numbers (as ``robust/`` was) must be in
    the fingerprint, or editing it would leave stale entries valid: every part is either a
    source of the fingerprint or one of those known to compute no cached number."""
    from pathlib import Path

    from stochlap_torch.learning import feature_files

    root = Path(feature_files.__file__).resolve().parents[1]
    parts = {p.name for p in root.iterdir() if p.suffix == ".py" or (p / "__init__.py").exists()}
    consumers = {
        "__init__.py",
        "__main__.py",
        "baselines",
        "cli",
        "evaluation",
        "interest.py",
        "learning",
        "nn.py",
        "viz",
        "_warmup.py",
    }
    assert parts - consumers == set(feature_files.NUMERICS_SOURCES)
