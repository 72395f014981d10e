"""Write the small intersphinx inventories the documentation builds with offline.

The build reaches no documentation site (CI reaches PyPI only), so each project's
``objects.inv`` is replaced by a local one holding only the names these docs reference, each
with its page on the project's site (the URLs are relative to the site in
``docs/conf.py``'s ``_SITES``). A name the docs start to reference is added to ENTRIES and this
script rerun; the nitpicky build names any name that is missing.

    python docs/_inventories/make_inventories.py
"""

from __future__ import annotations

import zlib
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: project -> [(name, role, uri)], the uri relative to the project's site (``$``: the name).
ENTRIES: dict[str, list[tuple[str, str, str]]] = {
    "python": [
        ("collections.abc.Callable", "py:class", "library/collections.abc.html#$"),
        ("collections.abc.Iterable", "py:class", "library/collections.abc.html#$"),
        ("collections.abc.Mapping", "py:class", "library/collections.abc.html#$"),
        ("collections.abc.Sequence", "py:class", "library/collections.abc.html#$"),
        ("os.PathLike", "py:class", "library/os.html#$"),
        ("pathlib.Path", "py:class", "library/pathlib.html#$"),
        ("ValueError", "py:exception", "library/exceptions.html#$"),
        ("MemoryError", "py:exception", "library/exceptions.html#$"),
        ("RuntimeError", "py:exception", "library/exceptions.html#$"),
        ("TypeError", "py:exception", "library/exceptions.html#$"),
        ("Exception", "py:exception", "library/exceptions.html#$"),
        ("UserWarning", "py:exception", "library/exceptions.html#$"),
        ("NamedTuple", "py:class", "library/typing.html#typing.NamedTuple"),
        ("typing.NamedTuple", "py:class", "library/typing.html#$"),
        ("tuple", "py:class", "library/stdtypes.html#$"),
    ],
    "torch": [
        ("torch.Tensor", "py:class", "tensors.html#$"),
        ("torch.dtype", "py:class", "tensor_attributes.html#$"),
        ("torch.device", "py:class", "tensor_attributes.html#$"),
        ("torch.nn.Module", "py:class", "generated/$.html#$"),
        # autodoc names a base class by its defining module (show-inheritance)
        ("torch.nn.modules.module.Module", "py:class", "generated/torch.nn.Module.html"),
        ("torch.utils.data.Dataset", "py:class", "data.html#$"),
        ("torch.utils.data.dataset.Dataset", "py:class", "data.html#torch.utils.data.Dataset"),
        ("torch.utils.data.DataLoader", "py:class", "data.html#$"),
    ],
    "numpy": [
        ("numpy.ndarray", "py:class", "reference/generated/$.html#$"),
        ("numpy.random.Generator", "py:class", "reference/random/generator.html#$"),
    ],
    "scipy": [
        ("scipy.sparse.csr_matrix", "py:class", "reference/generated/$.html#$"),
        ("scipy.sparse.linalg.eigsh", "py:function", "reference/generated/$.html#$"),
    ],
    "torch_geometric": [
        (
            "torch_geometric.transforms.BaseTransform",
            "py:class",
            "generated/$.html#$",
        ),
        (
            "torch_geometric.transforms.base_transform.BaseTransform",
            "py:class",
            "generated/torch_geometric.transforms.BaseTransform.html",
        ),
        ("torch_geometric.data.Data", "py:class", "generated/$.html#$"),
    ],
    "trimesh": [
        ("trimesh.Trimesh", "py:class", "trimesh.base.html#trimesh.base.Trimesh"),
    ],
}


def inventory(project: str, entries: list[tuple[str, str, str]]) -> bytes:
    """An ``objects.inv`` (version 2) of ``entries``."""
    header = (
        "# Sphinx inventory version 2\n"
        f"# Project: {project}\n"
        "# Version: \n"
        "# The remainder of this file is compressed using zlib.\n"
    )
    lines = "".join(
        f"{name} {role} 1 {uri.replace('$', name)} -\n" for name, role, uri in sorted(entries)
    )
    return header.encode() + zlib.compress(lines.encode())


def main() -> None:
    for project, entries in ENTRIES.items():
        (HERE / f"{project}.inv").write_bytes(inventory(project, entries))


if __name__ == "__main__":
    main()
