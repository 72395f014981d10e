"""Feature datasets, DataLoader workers, the PyG transform and trimesh conversion."""

from __future__ import annotations

import re

import pytest
import torch
import trimesh
from reference import icosphere, noisy_sphere, open_grid
from torch.utils.data import DataLoader

import stochlap_torch as sl
from stochlap_torch.features import multiscale_features
from stochlap_torch.learning import MeshFeatureDataset, collate_meshes, find_mesh_files
from stochlap_torch.mesh import from_trimesh, to_trimesh

PARAMS = {"num_scales": 3}


@pytest.fixture(scope="module")
def mesh_folder(tmp_path_factory):
    """Four small meshes in three formats, plus a file that is not a mesh."""
    folder = tmp_path_factory.mktemp("meshes")
    meshes = [icosphere(1), noisy_sphere(), open_grid(), noisy_sphere(seed=3)]
    for position, (mesh, suffix) in enumerate(
        zip(meshes, [".obj", ".ply", ".off", ".obj"], strict=True)
    ):
        tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
        tm.export(folder / f"mesh{position}{suffix}")
    (folder / "notes.txt").write_text("not a mesh")
    return folder


def test_find_mesh_files(mesh_folder, tmp_path):
    paths = find_mesh_files(mesh_folder)
    assert [p.name for p in paths] == ["mesh0.obj", "mesh1.ply", "mesh2.off", "mesh3.obj"]
    with pytest.raises(ValueError, match="no mesh files"):
        find_mesh_files(tmp_path)
    with pytest.raises(FileNotFoundError):
        find_mesh_files([mesh_folder / "missing.obj"])


def test_dataset_items_match_direct_features(mesh_folder):
    dataset = MeshFeatureDataset(mesh_folder, progress=False, dtype=torch.float64, **PARAMS)
    assert len(dataset) == 4
    sample = dataset[2]
    mesh = sl.load_mesh(sample.path)
    expected = multiscale_features(mesh.vertices, mesh.faces, **PARAMS)
    torch.testing.assert_close(sample.features, expected)
    assert sample.features.shape[1] == len(dataset.channel_names())
    assert sample.index == 2 and dataset[-1].index == 3
    with pytest.raises(IndexError):
        dataset[4]


def test_dataset_uses_the_cache(mesh_folder, tmp_path, monkeypatch):
    first = MeshFeatureDataset(mesh_folder, cache_dir=tmp_path, progress=False, **PARAMS)
    assert len(list(tmp_path.glob("*.npz"))) == 4

    def fail(*args, **kwargs):
        raise AssertionError("recomputed although cached")

    monkeypatch.setattr("stochlap_torch.features.multiscale_features", fail)
    second = MeshFeatureDataset(mesh_folder, cache_dir=tmp_path, progress=False, **PARAMS)
    for a, b in zip(first, second, strict=True):
        assert torch.equal(a.features, b.features) and a.features.dtype == torch.float32


def test_progress_logs_without_tqdm(mesh_folder, monkeypatch, caplog):
    import builtins

    real_import = builtins.__import__

    def no_tqdm(name, *args, **kwargs):
        if name.startswith("tqdm"):
            raise ImportError(name)
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_tqdm)
    with caplog.at_level("INFO", logger="stochlap_torch.learning.datasets"):
        MeshFeatureDataset([find_mesh_files(mesh_folder)[0]], **PARAMS)
    assert "multiscale features: 1/1" in caplog.text


@pytest.mark.parametrize("in_memory", [True, False])
def test_dataloader_with_two_workers(mesh_folder, tmp_path, in_memory):
    dataset = MeshFeatureDataset(
        mesh_folder, cache_dir=tmp_path, in_memory=in_memory, progress=False, **PARAMS
    )
    loader = DataLoader(dataset, batch_size=2, num_workers=2, collate_fn=collate_meshes)
    batches = list(loader)
    assert [b.indices.tolist() for b in batches] == [[0, 1], [2, 3]]
    for packed in batches:
        pieces = torch.split(packed.features, packed.ptr.diff().tolist())
        for index, features in zip(packed.indices.tolist(), pieces, strict=True):
            assert torch.equal(features, dataset[index].features)
        assert packed.batch.shape == (packed.vertices.shape[0],)
        assert int(packed.faces.max()) < packed.vertices.shape[0]


def test_dataset_rejects_bad_parameters(mesh_folder):
    with pytest.raises(ValueError):
        MeshFeatureDataset(mesh_folder, normalisation="area", variant="paper")
    with pytest.raises(ValueError, match="cache_dir"):
        MeshFeatureDataset(mesh_folder, in_memory=False, variant="paper")


@pytest.mark.parametrize("dtype", ["float32", "float64", torch.int64, torch.float16, None])
def test_dataset_refuses_a_dtype_other_than_float32_or_float64(mesh_folder, dtype):
    """An integer dtype would truncate the features; a string is refused as by load_mesh. The
    check comes before any file is read (the folder does not exist)."""
    expected = r"dtype must be torch\.float32 or torch\.float64, got " + re.escape(repr(dtype))
    for folder in (mesh_folder, mesh_folder / "missing"):
        with pytest.raises(sl.ParameterError, match=expected):
            MeshFeatureDataset(folder, dtype=dtype, progress=False, **PARAMS)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dataset_returns_the_float_dtype_asked_for(mesh_folder, dtype):
    sample = MeshFeatureDataset(
        [find_mesh_files(mesh_folder)[1]], dtype=dtype, progress=False, **PARAMS
    )[0]
    assert sample.vertices.dtype == dtype and sample.features.dtype == dtype


def test_trimesh_round_trip_keeps_order():
    mesh = noisy_sphere()
    original = sl.Mesh(torch.tensor(mesh.vertices), torch.tensor(mesh.faces))
    tm = to_trimesh(original)
    assert isinstance(tm, trimesh.Trimesh)
    back = from_trimesh(tm)
    assert torch.equal(back.vertices, original.vertices) and torch.equal(back.faces, original.faces)
    assert from_trimesh(tm, dtype=torch.float32).vertices.dtype == torch.float32
    assert to_trimesh((original.vertices, original.faces)).vertices.shape == (162, 3)


def test_from_trimesh_validates():
    tm = trimesh.Trimesh(
        vertices=[[0, 0, 0], [1, 0, 0], [0, 1, 0]], faces=[[0, 1, 5]], process=False, validate=False
    )
    with pytest.raises(sl.MeshError):
        from_trimesh(tm)


def test_real_meshes_dataset(meshes_dir, tmp_path):
    files = [meshes_dir / "fandisk.off", meshes_dir / "horse_10k.obj"]
    dataset = MeshFeatureDataset(files, cache_dir=tmp_path, progress=False, **PARAMS)
    for sample in dataset:
        assert torch.isfinite(sample.features).all()
        assert sample.features.shape == (sample.vertices.shape[0], len(dataset.channel_names()))


def test_pyg_transform():
    pytest.importorskip("torch_geometric", reason="torch_geometric is not installed")
    from torch_geometric.data import Batch, Data

    from stochlap_torch.learning import StochasticFeatures

    first, second = noisy_sphere(), open_grid()
    datas = [
        Data(pos=torch.tensor(m.vertices), face=torch.tensor(m.faces).t().contiguous())
        for m in (first, second)
    ]
    import stochlap_torch as sl

    assert sl.StochasticFeatures is StochasticFeatures  # exported at the top level
    for variant in ("robust", "paper"):
        transform = StochasticFeatures(variant=variant, **PARAMS)
        out = transform(datas[0])
        assert "x" not in datas[0]  # BaseTransform works on a copy
        expected = multiscale_features(datas[0].pos, datas[0].face.t(), variant=variant, **PARAMS)
        torch.testing.assert_close(out.x, expected)
        assert out.x.shape[1] == len(transform.channel_names())
        named = StochasticFeatures(attr_name="multiscale", variant=variant, **PARAMS)(datas[1])
        assert named.multiscale.shape[0] == 42 and "x" not in named
        batch = Batch.from_data_list(datas)
        together = transform(batch)
        torch.testing.assert_close(together.x[:162], expected)
        # As PyG's transforms do, the features are concatenated to an existing data.x.
        with_x = datas[1].clone()
        with_x.x = torch.ones(42, 2, dtype=torch.float64)
        stacked = transform(with_x)
        assert stacked.x.shape[0] == 42 and bool((stacked.x[:, :2] == 1).all())
        assert stacked.x.shape[1] == 2 + len(transform.channel_names())
    with pytest.raises(ValueError, match="face"):
        transform(Data(pos=datas[0].pos, face=datas[0].face.t()))
    import pickle

    assert isinstance(pickle.loads(pickle.dumps(transform)), StochasticFeatures)


@pytest.mark.parametrize("samples", [[1, 2], [], 3, [None]], ids=["ints", "empty", "int", "none"])
def test_collate_refuses_what_is_not_samples(samples):
    """``collate_meshes([1, 2])`` raised ``AttributeError: 'int' object has no attribute
    'vertices'``; it names what it takes."""
    with pytest.raises(sl.ParameterError, match="collate_meshes takes"):
        sl.collate_meshes(samples)
