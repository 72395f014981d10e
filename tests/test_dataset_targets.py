"""Targets in MeshFeatureDataset and the packed batch.

Every packed quantity is compared with the same packing written as a plain loop here; the
meshes have different vertex and face counts so that a wrong offset shows.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from reference import icosphere, noisy_sphere, open_grid
from torch.utils.data import DataLoader

from stochlap_torch import ParameterError
from stochlap_torch.learning import MeshFeatureDataset, MeshSample, collate_meshes

PARAMS = {"num_scales": 2, "variant": "paper", "progress": False}
MESHES = {"a.obj": icosphere(1), "b.obj": open_grid(4, 5), "c.obj": noisy_sphere()}
CLASSES = {"a.obj": 2, "b.obj": 0, "c.obj": 1}


def vertex_labels(name: str, count: int) -> np.ndarray:
    """``(V,)`` int64 labels that differ between meshes and along each mesh."""
    return (np.arange(count) * 7 + len(name) * ord(name[0])) % 5


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """Three meshes of 42, 20 and 162 vertices, each with a ``.seg`` sidecar of labels."""
    folder = tmp_path_factory.mktemp("targets")
    for name, mesh in MESHES.items():
        trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(folder / name)
        np.savetxt(
            folder / f"{Path(name).stem}.seg", vertex_labels(name, len(mesh.vertices)), fmt="%d"
        )
    return folder


def read_sidecar(path: Path) -> np.ndarray:
    """The sidecar convention of the tests: ``mesh.obj`` -> ``mesh.seg``, one label a line."""
    return np.loadtxt(path.with_suffix(".seg"), dtype=np.int64)


@pytest.fixture(scope="module")
def dataset(folder) -> MeshFeatureDataset:
    return MeshFeatureDataset(
        folder, targets=lambda path: CLASSES[path.name], vertex_targets=read_sidecar, **PARAMS
    )


def plain_pack(samples: list[MeshSample]) -> dict[str, torch.Tensor]:
    """The packing of ``samples`` written as a loop over meshes and vertices."""
    vertices, faces, batch, ptr, face_ptr, labels = [], [], [], [0], [0], []
    for position, sample in enumerate(samples):
        for row in range(sample.vertices.shape[0]):
            vertices.append(sample.vertices[row])
            labels.append(int(sample.vertex_target[row]))
            batch.append(position)
        for face in sample.faces.tolist():
            faces.append([corner + ptr[-1] for corner in face])
        ptr.append(ptr[-1] + sample.vertices.shape[0])
        face_ptr.append(face_ptr[-1] + sample.faces.shape[0])
    return {
        "vertices": torch.stack(vertices),
        "faces": torch.tensor(faces),
        "batch": torch.tensor(batch),
        "ptr": torch.tensor(ptr),
        "face_ptr": torch.tensor(face_ptr),
        "vertex_target": torch.tensor(labels),
        "target": torch.tensor([int(sample.target) for sample in samples]),
    }


def test_samples_carry_their_targets(dataset, folder):
    assert [Path(p).name for p in dataset.paths] == ["a.obj", "b.obj", "c.obj"]
    for sample in dataset:
        name = Path(sample.path).name
        assert int(sample.target) == CLASSES[name] and sample.target.dtype == torch.int64
        expected = vertex_labels(name, len(MESHES[name].vertices))
        assert sample.vertex_target.tolist() == expected.tolist()
        assert sample.vertex_target.dtype == torch.int64


@pytest.mark.parametrize("order", [[0, 1, 2], [2, 0], [1, 2, 0]])
def test_collate_packs_like_a_plain_loop(dataset, order):
    samples = [dataset[i] for i in order]
    packed = collate_meshes(samples)
    expected = plain_pack(samples)
    for name, value in expected.items():
        assert torch.equal(getattr(packed, name), value), name
    assert packed.num_meshes == len(order) and packed.indices.tolist() == order
    assert torch.equal(packed.features, torch.cat([s.features for s in samples]))


def test_unbatch_inverts_collation(dataset):
    samples = [dataset[i] for i in (1, 2, 0)]
    packed = collate_meshes(samples)
    for name in ("vertices", "features", "vertex_target"):
        pieces = packed.unbatch(getattr(packed, name))
        assert len(pieces) == 3
        for piece, sample in zip(pieces, samples, strict=True):
            assert torch.equal(piece, getattr(sample, name)), name
    offsets = packed.ptr[:-1].tolist()
    for piece, sample, offset in zip(
        packed.unbatch_faces(packed.faces), samples, offsets, strict=True
    ):
        assert torch.equal(piece - offset, sample.faces)
    # A per-vertex model output goes back to its mesh: equal to the model run on each mesh.
    weights = torch.randn(packed.features.shape[1], 5, generator=torch.Generator().manual_seed(0))
    outputs = packed.unbatch(packed.features @ weights)
    for output, sample in zip(outputs, samples, strict=True):
        torch.testing.assert_close(output, sample.features @ weights)
    assert packed.mesh_batch.mesh(1).faces.tolist() == samples[1].faces.tolist()


def test_dataloader_batches_sort_back_to_the_samples(dataset):
    loader = DataLoader(
        dataset,
        batch_size=2,
        shuffle=True,
        num_workers=0,
        collate_fn=collate_meshes,
        generator=torch.Generator().manual_seed(3),
    )
    seen = {}
    for packed in loader:
        assert packed.target.shape == (packed.num_meshes,)
        for index, target, labels, features in zip(
            packed.indices.tolist(),
            packed.target,
            packed.unbatch(packed.vertex_target),
            packed.unbatch(packed.features),
            strict=True,
        ):
            seen[index] = (int(target), labels, features)
    assert sorted(seen) == [0, 1, 2]
    for index, (target, labels, features) in seen.items():
        assert target == int(dataset[index].target)
        assert torch.equal(labels, dataset[index].vertex_target)
        assert torch.equal(features, dataset[index].features)


def test_every_kind_of_target_source_gives_the_same_targets(folder, dataset):
    names = ["a.obj", "b.obj", "c.obj"]
    labels = {n: vertex_labels(n, len(MESHES[n].vertices)) for n in names}
    sources = [
        ({n: CLASSES[n] for n in names}, labels),  # mapping by file name
        ({folder / n: CLASSES[n] for n in names}, {str(folder / n): labels[n] for n in names}),
        ([CLASSES[n] for n in names], [labels[n] for n in names]),  # sequences in path order
        (torch.tensor([CLASSES[n] for n in names]), [torch.from_numpy(labels[n]) for n in names]),
    ]
    for targets, vertex_targets in sources:
        other = MeshFeatureDataset(folder, targets=targets, vertex_targets=vertex_targets, **PARAMS)
        for mine, reference in zip(other, dataset, strict=True):
            assert torch.equal(mine.target, reference.target)
            assert torch.equal(mine.vertex_target, reference.vertex_target)


def test_tensor_targets_are_stacked_and_floating_targets_follow_dtype(folder):
    names = ["a.obj", "b.obj", "c.obj"]
    per_mesh = {n: np.arange(4, dtype=np.float64) + i for i, n in enumerate(names)}
    per_vertex = {
        n: np.stack([MESHES[n].vertices[:, 2], -MESHES[n].vertices[:, 0]], 1) for n in names
    }
    for dtype in (torch.float32, torch.float64):
        data = MeshFeatureDataset(
            folder, targets=per_mesh, vertex_targets=per_vertex, dtype=dtype, **PARAMS
        )
        packed = collate_meshes([data[2], data[0]])
        expected = torch.stack([torch.tensor(per_mesh[n], dtype=dtype) for n in ("c.obj", "a.obj")])
        assert torch.equal(packed.target, expected)
        rows = [torch.tensor(per_vertex[n], dtype=dtype) for n in ("c.obj", "a.obj")]
        assert torch.equal(packed.vertex_target, torch.cat(rows))
        assert packed.vertex_target.shape == (162 + 42, 2)


def test_without_targets_they_are_absent(folder):
    data = MeshFeatureDataset(folder, **PARAMS)
    assert data[0].target is None and data[0].vertex_target is None
    packed = next(iter(DataLoader(data, batch_size=3, collate_fn=collate_meshes)))
    assert packed.target is None and packed.vertex_target is None
    assert packed.face_ptr.tolist() == [0, 80, 80 + 24, 80 + 24 + 320]
    only_vertex = MeshFeatureDataset(folder, vertex_targets=read_sidecar, **PARAMS)
    packed = collate_meshes(list(only_vertex))
    assert packed.target is None and packed.vertex_target.shape == (42 + 20 + 162,)


def test_in_memory_false_reads_targets_per_item(folder, tmp_path, dataset):
    lazy = MeshFeatureDataset(
        folder,
        cache_dir=tmp_path,
        in_memory=False,
        targets=[CLASSES[n] for n in ("a.obj", "b.obj", "c.obj")],
        vertex_targets=read_sidecar,
        **PARAMS,
    )
    for mine, reference in zip(lazy, dataset, strict=True):
        assert torch.equal(mine.target, reference.target)
        assert torch.equal(mine.vertex_target, reference.vertex_target)


def test_batch_to_device_moves_every_tensor(dataset):
    packed = collate_meshes(list(dataset))
    moved = packed.to("meta")
    for name, value in zip(packed._fields, moved, strict=True):
        if name == "paths":
            assert value == packed.paths
        else:
            assert value.device.type == "meta" and value.shape == getattr(packed, name).shape
    mesh_batch = packed.mesh_batch.to("meta")
    assert mesh_batch.faces.device.type == "meta" and mesh_batch.face_ptr.device.type == "meta"
    without = collate_meshes(list(MeshFeatureDataset([dataset.paths[0]], **PARAMS))).to("cpu")
    assert without.target is None


def test_unbatch_refuses_a_tensor_of_another_length(dataset):
    packed = collate_meshes([dataset[0], dataset[1]])
    with pytest.raises(ParameterError, match="62 rows"):
        packed.unbatch(torch.zeros(61))
    with pytest.raises(ParameterError, match="per-face tensor with 104 rows"):
        packed.unbatch_faces(packed.features)
    with pytest.raises(ParameterError, match="62 rows"):
        packed.mesh_batch.unbatch(torch.zeros(3))
    with pytest.raises(ParameterError, match="got float"):
        packed.unbatch(0.5)


def test_bad_target_sources_are_refused_naming_the_problem(folder):
    with pytest.raises(ParameterError, match="targets has 2 entries for 3 mesh files"):
        MeshFeatureDataset(folder, targets=[0, 1], **PARAMS)
    with pytest.raises(ParameterError, match="vertex_targets must be a callable"):
        MeshFeatureDataset(folder, vertex_targets=3, **PARAMS)
    with pytest.raises(ParameterError, match=r"no entry for .*b\.obj"):
        MeshFeatureDataset(folder, targets={"a.obj": 0, "c.obj": 1}, **PARAMS)
    with pytest.raises(
        ParameterError,
        match=r"a\.obj has shape \(7,\), not one row per vertex of the mesh \(42 vertices\)",
    ):
        MeshFeatureDataset(folder, vertex_targets=lambda path: np.zeros(7), **PARAMS)
    with pytest.raises(ParameterError, match="not array-like"):
        MeshFeatureDataset(folder, targets=lambda path: object(), **PARAMS)
    with pytest.raises(ParameterError, match=r"share a shape and dtype.*b\.obj"):
        MeshFeatureDataset(
            folder, targets={"a.obj": [0, 1], "b.obj": [0], "c.obj": [1, 1]}, **PARAMS
        )
    with pytest.raises(ParameterError, match=r"dtype.*b\.obj"):
        MeshFeatureDataset(folder, targets={"a.obj": 0, "b.obj": 0.5, "c.obj": 1}, **PARAMS)


def test_collate_refuses_samples_with_and_without_targets(dataset):
    bare = dataset[1]._replace(target=None)
    with pytest.raises(ParameterError, match="target is None in some samples"):
        collate_meshes([dataset[0], bare])
    wrong = dataset[1]._replace(vertex_target=torch.zeros(3, dtype=torch.int64))
    with pytest.raises(ParameterError, match="not one row per vertex"):
        collate_meshes([dataset[0], wrong])
