"""Feature files: the one on-disk format of ``stochlap features`` and ``MeshFeatureDataset``
(``cache_dir=``), read by ``sl.load_features``.

Small meshes and the paper variant with two scales keep each run short; the features are
compared with :func:`~stochlap_torch.features.multiscale_features` of the mesh loaded here.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from reference import icosphere, noisy_sphere, open_grid, with_unreferenced_vertex

import stochlap_torch as sl
from stochlap_torch.cli import main
from stochlap_torch.features import multiscale_features
from stochlap_torch.learning import CacheWarning, FeatureFile, MeshFeatureDataset, feature_files

REPO_ROOT = Path(__file__).resolve().parents[1]
FAST = {"variant": "paper", "num_scales": 2}
CLI_FAST = ["--variant", "paper", "-K", "2", "-q"]


def _folder(root: Path) -> Path:
    """Three meshes in three formats, in one folder (the dataset does not search deeper)."""
    root.mkdir(parents=True, exist_ok=True)
    for name, mesh in (("a.obj", icosphere(1)), ("b.ply", noisy_sphere()), ("c.off", open_grid())):
        trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(root / name)
    return root


def _no_computing(monkeypatch) -> None:
    def fail(*args, **kwargs):
        raise AssertionError("features computed although a finished file holds them")

    monkeypatch.setattr("stochlap_torch.features.multiscale_features", fail)


def _mtimes(folder: Path) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in folder.iterdir()}


def test_a_cli_folder_is_a_finished_dataset_and_load_features_reads_it(tmp_path, monkeypatch):
    data, out = _folder(tmp_path / "data"), tmp_path / "out"
    assert main(["features", str(data), "-o", str(out), *CLI_FAST]) == 0
    before = _mtimes(out)
    _no_computing(monkeypatch)
    dataset = MeshFeatureDataset(data, cache_dir=out, dtype=torch.float64, progress=False, **FAST)
    assert _mtimes(out) == before  # nothing rewritten either
    loaded = sl.load_features(out)
    assert list(loaded) == ["a", "b", "c"]
    for sample, (name, stored) in zip(dataset, loaded.items(), strict=True):
        assert isinstance(stored, FeatureFile) and stored.path == out / f"{name}.npz"
        assert Path(sample.path).stem == name
        assert torch.equal(stored.features, sample.features)
        assert torch.equal(stored.vertices, sample.vertices)
        assert torch.equal(stored.faces, sample.faces)
        assert stored.channel_names == tuple(dataset.channel_names())
        assert stored.settings == feature_files.settings_record(dataset.params, "float64", False)
        assert stored.version == sl.__version__
    monkeypatch.undo()
    mesh = sl.load_mesh(data / "b.ply")
    expected = multiscale_features(mesh.vertices, mesh.faces, **FAST)
    torch.testing.assert_close(loaded["b"].features, expected, rtol=0, atol=0)


def test_a_dataset_cache_is_a_finished_cli_folder(tmp_path, capsys):
    data, out = _folder(tmp_path / "data"), tmp_path / "out"
    MeshFeatureDataset(data, cache_dir=out, progress=False, **FAST)
    before = _mtimes(out)
    assert main(["features", str(data), "-o", str(out), "--variant", "paper", "-K", "2"]) == 0
    assert "0 computed, 3 already done" in capsys.readouterr().out
    assert _mtimes(out) == before


def test_load_features_of_a_folder_is_recursive_and_sorted(tmp_path):
    data, out = _folder(tmp_path / "data"), tmp_path / "out"
    (data / "sub").mkdir()
    (data / "c.off").rename(data / "sub" / "0.off")
    assert main(["features", str(data), "-o", str(out), *CLI_FAST]) == 0
    assert list(sl.load_features(out)) == ["a", "b", "sub/0"]
    single = sl.load_features(out / "sub" / "0.npz")
    assert single.features.shape == (len(open_grid().vertices), len(single.channel_names))
    assert single.file_vertices is None  # an indexed mesh: nothing merged


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in vertices.tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces.tolist()]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("variant", ["robust", "paper"])
def test_referenced_marks_exactly_the_vertices_no_face_uses(tmp_path, variant):
    mesh = with_unreferenced_vertex()  # vertex 20 is in no face
    source = _write_obj(tmp_path / "m.obj", mesh.vertices, mesh.faces)
    out = tmp_path / "out"
    assert main(["features", str(source), "-o", str(out), "--variant", variant, "-q"]) == 0
    stored = sl.load_features(out / "m.npz")
    assert stored.referenced.dtype == torch.bool
    assert stored.referenced.nonzero().flatten().tolist() == [i for i in range(43) if i != 20]
    with np.load(out / "m.npz", allow_pickle=False) as arrays:  # a plain member of the file
        assert arrays["referenced"].tolist() == stored.referenced.tolist()
    # The documented placeholder row: not features of the surface, so masked by users.
    row = dict(zip(stored.channel_names, stored.features[20].tolist(), strict=True))
    placeholders = {name: value for name, value in row.items() if value != 0}
    if variant == "paper":
        assert list(placeholders) == ["saliency"]
    else:
        assert all(name.startswith("spread") and name.endswith("_3") for name in placeholders)


def test_a_file_without_referenced_is_recomputed(tmp_path, capsys):
    """Files of earlier versions hold no ``referenced``: not done, recomputed on a rerun."""
    data, out = _folder(tmp_path / "data"), tmp_path / "out"
    assert main(["features", str(data / "a.obj"), "-o", str(out), *CLI_FAST]) == 0
    with np.load(out / "a.npz", allow_pickle=False) as stored:
        older = {name: stored[name] for name in stored.files if name != "referenced"}
    np.savez(out / "a.npz", **older)
    argv = ["features", str(data / "a.obj"), "-o", str(out), "--variant", "paper", "-K", "2"]
    assert main(argv) == 0
    assert "1 computed, 0 already done" in capsys.readouterr().out
    assert bool(sl.load_features(out / "a.npz").referenced.all())


def test_a_file_of_other_numerics_is_recomputed(tmp_path, capsys, monkeypatch):
    data, out = _folder(tmp_path / "data"), tmp_path / "out"
    args = ["features", str(data / "a.obj"), "-o", str(out), "--variant", "paper", "-K", "2"]
    assert main([*args, "-q"]) == 0
    monkeypatch.setattr(feature_files, "numerics_fingerprint", lambda: "0" * 16)
    assert main(args) == 0
    assert "1 computed, 0 already done" in capsys.readouterr().out


def test_a_rerun_of_a_finished_folder_does_not_import_torch(tmp_path):
    data, out = _folder(tmp_path / "data"), tmp_path / "out"
    argv = ["features", str(data), "-o", str(out), *CLI_FAST]
    assert main(argv) == 0
    script = (
        "import sys\nfrom stochlap_torch.cli import main\n"
        f"assert main({argv!r}) == 0\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'numba')))\n"
    )
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, check=True
    )
    assert result.stdout.strip().splitlines()[-1] == "[]"


def _damage(path: Path) -> None:
    whole = path.read_bytes()
    path.write_bytes(whole[: len(whole) // 2])


def test_load_features_names_a_damaged_file(tmp_path):
    data, out = _folder(tmp_path / "data"), tmp_path / "out"
    assert main(["features", str(data), "-o", str(out), *CLI_FAST]) == 0
    _damage(out / "b.npz")
    for target in (out, out / "b.npz"):
        with pytest.raises(
            sl.FileFormatError, match=re.escape(f"{out / 'b.npz'}: not a readable .npz")
        ):
            sl.load_features(target)
    np.savez(out / "b.npz", features=np.zeros((3, 2)))  # some other .npz
    with pytest.raises(sl.FileFormatError, match=r"b\.npz: not a stochlap_torch feature file"):
        sl.load_features(out)
    with pytest.raises(sl.ParameterError, match="no feature files"):
        sl.load_features(data)
    with pytest.raises(FileNotFoundError):
        sl.load_features(out / "missing.npz")


@pytest.mark.parametrize(
    ("member", "value", "problem"),
    [
        ("referenced", lambda a: ~a["referenced"], "referenced is not the"),
        ("faces", lambda a: a["faces"] + len(a["vertices"]), "face indices outside"),
        ("features", lambda a: a["features"][:, :-1], "features of shape"),
        ("features", lambda a: np.full_like(a["features"], np.nan), "NaN"),
        ("settings", lambda a: np.array("[1, 2]"), "not a JSON object"),
        ("version", lambda a: np.array(3), "must be strings"),
    ],
)
def test_members_that_disagree_are_refused_by_name(tmp_path, member, value, problem):
    data, out = _folder(tmp_path / "data"), tmp_path / "out"
    assert main(["features", str(data / "a.obj"), "-o", str(out), *CLI_FAST]) == 0
    with np.load(out / "a.npz", allow_pickle=False) as stored:
        arrays = dict(stored)
    np.savez(out / "a.npz", **{**arrays, member: value(arrays)})
    with pytest.raises(sl.FileFormatError, match=problem):
        sl.load_features(out / "a.npz")


def test_the_dataset_recomputes_a_damaged_or_foreign_file_with_a_warning(tmp_path):
    data, out = _folder(tmp_path / "data"), tmp_path / "out"
    first = MeshFeatureDataset(data, cache_dir=out, progress=False, **FAST)
    _damage(out / "a.npz")
    with pytest.warns(CacheWarning, match=r"a\.npz is unreadable or incomplete; recomputing"):
        again = MeshFeatureDataset(data, cache_dir=out, progress=False, **FAST)
    assert torch.equal(again[0].features, first[0].features)
    assert sl.load_features(out / "a.npz").features.shape == first[0].features.shape
    # Other settings: replaced, and said (two settings need two folders).
    with pytest.warns(CacheWarning, match="holds other settings; recomputing and replacing"):
        MeshFeatureDataset([data / "a.obj"], cache_dir=out, progress=False, variant="paper")
    assert sl.load_features(out / "a.npz").settings["num_scales"] == 6
    # A changed mesh file is recomputed without a word.
    bigger = icosphere(2)
    trimesh.Trimesh(bigger.vertices, bigger.faces, process=False).export(data / "a.obj")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        changed = MeshFeatureDataset(
            [data / "a.obj"], cache_dir=out, progress=False, variant="paper"
        )
    assert changed[0].vertices.shape == (len(bigger.vertices), 3)


def test_the_dataset_refuses_two_meshes_of_one_feature_file(tmp_path):
    first, second = _folder(tmp_path / "one"), _folder(tmp_path / "two")
    paths = [first / "a.obj", second / "a.obj"]
    with pytest.raises(sl.ParameterError, match=r"would share the feature file a\.npz"):
        MeshFeatureDataset(paths, cache_dir=tmp_path / "out", progress=False, **FAST)
    assert not (tmp_path / "out").exists()
    assert len(MeshFeatureDataset(paths, progress=False, **FAST)) == 2  # no files: no conflict


def test_the_settings_record_holds_everything_the_numbers_depend_on():
    params = sl.RobustParams(num_scales=3)
    record = feature_files.settings_record(params, "float32", 1)
    assert record["method"] == "RobustParams" and record["num_scales"] == 3
    assert record["dtype"] == "float32" and record["merge_seams"] is True
    assert record == json.loads(json.dumps(record))  # as a file holds it
