"""The interest-point error curves (Fig. 15) as a picture."""

from __future__ import annotations

import struct

import pytest

pytest.importorskip("matplotlib")

from stochlap_torch.viz import plot_error_curves


def test_plot_error_curves(tmp_path):
    radii = [0.0, 0.05, 0.1]
    curves = {
        "a": {"fne": [1.0, 0.5, 0.0], "fpe": [1.0, 0.6, 0.2], "wme": [1.0, 0.4, 0.0]},
        "b": {"fne": [1.0, 0.9, 0.8], "fpe": [1.0, 1.0, 0.9], "wme": [1.0, 0.9, 0.7]},
    }
    path = plot_error_curves(radii, curves, tmp_path / "out" / "fig15.png", title="t", dpi=50)
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert struct.unpack(">II", data[16:24]) == (600, 190)  # 12 x 3.8 inches
    assert [p.name for p in path.parent.iterdir()] == ["fig15.png"]  # no temporary left
